"""benchmarks/common.py: a re-measured row on a host of another speed is named, not silently compared."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
from common import host_speed_notes  # noqa: E402


def test_a_row_re_measured_on_a_much_slower_host_is_flagged_with_both_hosts_and_step_counts():
    fast, slow = {"cpu_probe_seconds": 0.2}, {"cpu_probe_seconds": 0.4}
    previous = {"measured_now": ["bottle"], "machine": fast,
                "scenes": {"orchard": {"steps": 3425, "machine": fast},  # the row names its host
                           "bottle": {"steps": 4141},  # measured by the report's own run: the report's host
                           "fern": {"steps": 1263}}}  # measured by an earlier run, host not recorded
    measured = {name: {"steps": 900} for name in ("orchard", "bottle", "fern", "beer")}
    notes = host_speed_notes(previous, measured, slow)
    assert [note.split(":")[0] for note in notes] == ["orchard", "bottle"]
    assert "0.40 s against 0.20 s" in notes[0] and "900 steps now, 3425 then" in notes[0]
    # within the factor (either way) nothing is said
    assert host_speed_notes(previous, measured, {"cpu_probe_seconds": 0.26}) == []
    assert host_speed_notes(previous, measured, {"cpu_probe_seconds": 0.14}) == []
    assert len(host_speed_notes(previous, measured, {"cpu_probe_seconds": 0.12})) == 2
    assert host_speed_notes({}, measured, slow) == []

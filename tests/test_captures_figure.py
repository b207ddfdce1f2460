"""benchmarks/captures.py's figure: a run of some captures replaces their rows and keeps the others'."""

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import captures  # noqa: E402


def _eval_render(results: Path, name: str, value: int, width: int) -> None:
    """An evaluate figure of two rows (render | ... over image | ...) of one grey level."""
    renders = results / name / "eval" / "renders"
    renders.mkdir(parents=True)
    cv2.imwrite(str(renders / "view_000.png"), np.full((240, width, 3), value, np.uint8))


def test_a_run_of_one_capture_keeps_the_other_captures_rows_in_panel_order(tmp_path):
    figure = tmp_path / "captures.png"
    first, second = tmp_path / "first", tmp_path / "second"
    _eval_render(first, "plant", 60, 360)
    _eval_render(first, "orchard", 120, 480)
    captures.montage(first, ["plant", "orchard"], figure)
    _eval_render(second, "orchard", 200, 480)  # the orchard alone, re-measured
    captures.montage(second, ["orchard"], figure)

    stacked = cv2.imread(str(figure))
    assert stacked.shape == (2 * 240, 480 * 2, 3)  # two rows, each the top half scaled to 240 px high
    orchard, plant = stacked[:240], stacked[240:]  # PANEL's order: the orchard first
    assert np.median(orchard[60:, :400]) == 200  # its new render, not the first run's 120
    assert np.median(plant[60:, :300]) == 60  # kept from the first run
    assert not plant[:, 720:].any()  # the narrower row padded with black
    assert sorted(p.name for p in (tmp_path / "captures_rows").iterdir()) == ["orchard.png", "plant.png"]

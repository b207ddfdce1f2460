"""The README stays a newcomer's page: short, no commit hashes, links that resolve, and the test command CI runs."""

import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
SETUP = "bash scripts/bootstrap.sh && . .venv/bin/activate && "
COMMIT_HASH = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
LINK = re.compile(r"\]\(([^)\s]+)\)")


def lines() -> list[str]:
    return README.read_text(encoding="utf-8").splitlines()


def test_readme_is_short():
    text = lines()
    assert len(text) <= 150, f"README.md has {len(text)} lines; move detail to docs/"
    long = [(number, len(line)) for number, line in enumerate(text, 1) if len(line) >= 200]
    assert not long, f"README.md lines of 200 characters or more (line, length): {long}"


def test_readme_quotes_no_commit_hashes():
    hits = [(number, match) for number, line in enumerate(lines(), 1) for match in COMMIT_HASH.findall(line)]
    assert not hits, f"commit hashes in README.md (line, hash): {hits}"


def test_ci_runs_the_readme_test_command():
    commands = [line.strip() for line in lines() if line.startswith(SETUP)]
    assert SETUP + "snakemake --cores 2 results/orchard/occupancy.zarr" in commands
    test_command = SETUP + "python -m pytest -q -n 2 --dist loadfile"
    assert test_command in commands
    ci = [line.strip() for line in (REPO / ".ci" / "run").read_text().splitlines()]
    assert test_command in ci, ".ci/run must run exactly the README's test command"


def test_readme_links_resolve():
    missing = []
    for target in LINK.findall(README.read_text(encoding="utf-8")):
        if "://" in target or target.startswith("#"):
            continue
        path = target.split("#", 1)[0]
        if not (REPO / path).exists():
            missing.append(target)
    assert not missing, f"README.md links to files that do not exist: {missing}"


def test_headline_numbers_are_read_from_the_benchmark_results():
    # the table is written by scripts/readme_numbers.py from benchmarks/results/*.json; a benchmark
    # re-run that changes a number, or a hand edit of the table, leaves the README stale
    check = subprocess.run([sys.executable, str(REPO / "scripts" / "readme_numbers.py"), "--check"],
                           capture_output=True, text=True)
    assert check.returncode == 0, check.stderr

"""Batches of scenes: which scenes a batch builds (every scene file, or a sheet's rows) and the
one-line-per-scene summary printed when a run ends (Snakemake's onsuccess/onerror handlers call it;
`srfpipe summary` prints the same from the files on disk at any time).

A scene's state is read from its artifacts, which every stage writes atomically: an artifact that
exists is finished (a folder holding a stage's output, not an empty folder or a file in its place). The first missing one in the chain is where the scene stopped; the stage logs
written after the last finished artifact say whether it failed there, and how.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
from dataclasses import dataclass
from pathlib import Path

from srfpipe.artifacts import holds_output

# The per-scene artifacts in the order the workflow builds them (workflow/rules/common.smk ARTIFACTS).
DEFAULT_CHAIN = ("poses.zarr", "images.zarr", "labels.zarr", "srf.zarr", "eval", "occupancy.zarr")
# eval/ reads srf.zarr beside occupancy.zarr, not before it: a scene built to occupancy.zarr or sim
# (`snakemake results/orchard/occupancy.zarr`) is done without it, and reported as not evaluated
EVALUATION = "eval"

# A stage that failed: srfpipe's one-line errors ("srfpipe poses: error: ..."), a Python traceback,
# a process killed (out of memory). Words such as "reprojection error" in a progress line do not match.
_ERROR = re.compile(r"(?i:\berror:)|Traceback \(most recent call last\)|\bKilled\b|MemoryError|out of memory")


def read_sheet(path: str | Path, known: list[str] | None = None) -> list[str]:
    """The scenes of a sheet: a TSV or CSV file with a header row holding a `scene` column (other
    columns are free, e.g. notes); blank rows and rows starting with # are skipped. With `known`,
    every name must be one of those (a scene file in scenes_dir). Errors name the file and row."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"sheet {path}: file does not exist")
    try:  # utf-8-sig: a spreadsheet's "CSV UTF-8" starts with a byte order mark
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ValueError(f"sheet {path}: not UTF-8 text ({exc}); save it as UTF-8") from None
    # (line number in the file, line): errors name the row an editor or a spreadsheet shows
    lines = [(number, line) for number, line in enumerate(text.splitlines(), start=1)
             if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"sheet {path}: empty (expected a header row with a 'scene' column)")
    delimiter = "\t" if "\t" in lines[0][1] else ","
    header = [name.strip() for name in (csv.DictReader([lines[0][1]], delimiter=delimiter).fieldnames or [])]
    if "scene" not in header:
        raise ValueError(f"sheet {path}: no 'scene' column in the header {header}")
    scenes: list[str] = []
    for row_number, row in _numbered_rows(lines, delimiter):
        name = (row.get("scene") or "").strip()
        if not re.fullmatch(r"[A-Za-z0-9_.-]+", name):
            raise ValueError(f"sheet {path}: row {row_number}: scene {name!r} is not a scene name")
        if known is not None and name not in known:
            raise ValueError(f"sheet {path}: row {row_number}: no scene file for {name!r} (known: {sorted(known)})")
        if name in scenes:
            raise ValueError(f"sheet {path}: row {row_number}: scene {name!r} is listed twice")
        scenes.append(name)
    if not scenes:
        raise ValueError(f"sheet {path}: lists no scenes")
    return scenes


def _numbered_rows(lines: list[tuple[int, str]], delimiter: str):
    """(line number of its first line, row as a dict) for each row after the header of the kept
    lines (a quoted field may span lines)."""
    consumed = 0

    def feed():
        nonlocal consumed
        for _, line in lines:
            consumed += 1
            yield line

    reader = csv.DictReader(feed(), delimiter=delimiter)
    reader.fieldnames = [name.strip() for name in reader.fieldnames or []]  # reads the header row
    while True:
        start = consumed
        try:
            row = next(reader)
        except StopIteration:
            return
        yield lines[start][0], row


@dataclass
class SceneState:
    """Where one scene stands: `built` the finished artifacts in chain order, `missing` the first
    one not there (None when the final artifact exists), `failed_log` the stage log that reports
    an error after the last finished artifact (None when nothing failed)."""

    scene: str
    built: list[str]
    missing: str | None
    failed_log: Path | None = None
    error: str | None = None
    metrics: dict | None = None
    evaluated: bool = True

    @property
    def status(self) -> str:
        if self.missing is None:
            return "done"
        return "FAILED" if self.failed_log is not None else "incomplete"

    def line(self, width: int = 0) -> str:
        name = self.scene.ljust(width)
        if self.status == "done":
            extra = _metrics_text(self.metrics) if self.evaluated else (
                f"not evaluated: snakemake results/{self.scene}/{EVALUATION} scores it")
            return f"{name}  done        {self.built[-1]}" + (f"  ({extra})" if extra else "")
        reached = f"after {self.built[-1]}" if self.built else "before any artifact"
        if self.status == "FAILED":
            return f"{name}  FAILED      {self.missing} not built: {self.error}  [{self.failed_log}]"
        return f"{name}  incomplete  {self.missing} not built (stopped {reached})"


def _metrics_text(metrics: dict | None) -> str:
    if not metrics:
        return ""
    parts = []
    if isinstance(metrics.get("psnr"), (int, float)):
        parts.append(f"PSNR {metrics['psnr']:.1f} dB")
    if isinstance(metrics.get("miou"), (int, float)):
        parts.append(f"mIoU {metrics['miou']:.2f}")
    if metrics.get("overfit") is True:  # evaluate's generalization check (GENERALIZATION_GAP_DB)
        train, heldout = metrics.get("train_view_psnr"), metrics.get("psnr")
        numbers = (f" (train {train:.1f} dB, held-out {heldout:.1f} dB)"
                   if isinstance(train, (int, float)) and isinstance(heldout, (int, float)) else "")
        if isinstance(metrics.get("appearance_gap_db"), (int, float)):
            numbers += f" ({metrics['appearance_gap_db']:.1f} dB of the gap: each training image's own appearance)"
        if isinstance(metrics.get("overfit_remedy"), str):
            numbers += f": {metrics['overfit_remedy']}"
        parts.append("fits the training views, not new ones" + numbers)
    return ", ".join(parts)


def _error_of(log: Path) -> str | None:
    """None when the log reports no error, else its last line (the error message, or the exception
    closing a traceback); tqdm's carriage-return frames are split off."""
    try:
        text = log.read_text(errors="replace")
    except OSError:
        return None
    if not _ERROR.search(text):
        return None
    lines = [part.strip() for line in text.splitlines() for part in line.split("\r") if part.strip()]
    return lines[-1][:300] if lines else None


def scene_state(scene: str, results: str | Path = "results", logs: str | Path = "logs",
                chain: tuple[str, ...] | list[str] = DEFAULT_CHAIN) -> SceneState:
    """Read one scene's state from results/{scene}/ and logs/{scene}/ (see SceneState)."""
    folder = Path(results) / scene
    built = []
    last_time = 0.0
    missing = None
    evaluated = True
    for artifact in chain:
        path = folder / artifact
        if artifact == EVALUATION and artifact != chain[-1]:
            evaluated = holds_output(path)
            continue
        if not holds_output(path):
            missing = artifact
            break
        built.append(artifact)
        last_time = max(last_time, path.stat().st_mtime)
    state = SceneState(scene, built, missing, evaluated=evaluated)
    if missing is None and not evaluated:
        # the evaluation of a finished scene failed (a batch builds it), or was never asked for
        log = Path(logs, scene, "evaluate.log")
        if error := _error_of(log):
            state.missing, state.failed_log, state.error = EVALUATION, log, error
        return state
    if missing is None:
        metrics = folder / "eval" / "metrics.json"
        if metrics.is_file():
            try:
                state.metrics = json.loads(metrics.read_text())
            except ValueError:
                pass
        return state
    # logs written after the last finished artifact, newest first; the newest reporting an error
    recent = sorted((log for log in Path(logs, scene).glob("*.log") if log.stat().st_mtime >= last_time),
                    key=lambda log: log.stat().st_mtime, reverse=True)
    for log in recent:
        error = _error_of(log)
        if error:
            state.failed_log, state.error = log, error
            break
    return state


def summary_lines(scenes: list[str], results: str | Path = "results", logs: str | Path = "logs",
                  chain: tuple[str, ...] | list[str] = DEFAULT_CHAIN) -> list[str]:
    """One line per scene (done / FAILED / incomplete), then a count line."""
    states = [scene_state(scene, results, logs, chain) for scene in scenes]
    width = max((len(scene) for scene in scenes), default=0)
    counts = {status: sum(state.status == status for state in states) for status in ("done", "FAILED", "incomplete")}
    lines = [state.line(width) for state in states]
    lines.append(f"scenes: {counts['done']} done, {counts['FAILED']} failed, {counts['incomplete']} incomplete "
                 f"(final artifact {chain[-1]})")
    return lines


def print_summary(scenes: list[str], results: str | Path = "results", logs: str | Path = "logs",
                  chain: tuple[str, ...] | list[str] = DEFAULT_CHAIN) -> None:
    if not scenes:
        return
    print("srfpipe summary, one line per scene:", flush=True)
    for line in summary_lines(scenes, results, logs, chain):
        print(f"  {line}", flush=True)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenes", nargs="*", metavar="SCENE",
                        help="scenes to report (default: every folder in --results)")
    parser.add_argument("--sheet", help="report the scenes of this sheet (a TSV/CSV with a 'scene' column)")
    parser.add_argument("--results", default="results", help="the workflow's results_dir")
    parser.add_argument("--logs", default="logs", help="the workflow's log folder")
    parser.add_argument("--final", default=DEFAULT_CHAIN[-1],
                        help="the final artifact (a name in the chain, or 'sim' after occupancy.zarr)")


def run(args: argparse.Namespace) -> int:
    scenes = list(args.scenes)
    if args.sheet:
        scenes += [scene for scene in read_sheet(args.sheet) if scene not in scenes]
    if not scenes:
        results = Path(args.results)
        scenes = sorted(path.name for path in results.iterdir() if path.is_dir()) if results.is_dir() else []
    chain = list(DEFAULT_CHAIN)
    if args.final not in chain:
        chain.append(args.final)
    chain = chain[: chain.index(args.final) + 1]
    print_summary(scenes, args.results, args.logs, chain)
    states = [scene_state(scene, args.results, args.logs, chain) for scene in scenes]
    return 0 if all(state.status == "done" for state in states) else 1

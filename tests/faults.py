"""Fault injection for tests/test_faults.py and benchmarks/reliability.py: kill a Snakemake rule's
job halfway with SIGKILL, find what a killed run left behind, mount a small or read-only tmpfs,
and compare two builds array by array.

Only processes this module started (and their children) are ever signalled.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from tests.conftest import CORES, REPO, snakemake_env

# What "halfway" looks like for each stage: the hidden partial artifact of create_artifact exists
# (the stage is writing), or, for training, a checkpoint has been written.
HALFWAY = {
    "downscale": ("images.zarr",),
    "segment": ("masks/apple.zarr", "masks/branch.zarr", "masks/leaf.zarr"),
    "composite": ("labels.zarr",),
    "train": ("srf.ckpt",),
    "evaluate": ("eval",),
    "distill": ("occupancy.zarr",),
    "package": ("sim",),
}


def snakemake_command(root: Path, *targets: str) -> list[str]:
    return [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(root),
            "--cores", CORES, *targets]


def _children(pid: int) -> list[int]:
    """All descendants of `pid` (from /proc)."""
    parents: dict[int, list[int]] = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            fields = Path(f"/proc/{entry.name}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        parents.setdefault(int(fields[1]), []).append(int(entry.name))
    found, todo = [], [pid]
    while todo:
        for child in parents.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def _cmdline(pid: int) -> list[str]:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace").split("\0")
    except OSError:
        return []


def stage_processes(snakemake_pid: int, stage: str) -> list[int]:
    """The `srfpipe <stage>` processes among the descendants of a Snakemake run."""
    pids = []
    for pid in _children(snakemake_pid):
        args = _cmdline(pid)
        if any(Path(a).name == "srfpipe" for a in args[:2]) and stage in args[1:3]:
            pids.append(pid)
    return pids


def is_halfway(scene_dir: Path, stage: str, min_step: int = 0) -> bool:
    """The stage is writing its artifact; for training, a checkpoint exists and the training log
    (logs/SCENE/train_metrics.jsonl) has reached step `min_step` (put it between checkpoints)."""
    for name in HALFWAY[stage]:
        path = scene_dir / name
        if stage == "train":
            if path.is_dir() and any(path.glob("step-*.pt")):
                metrics = scene_dir.parent.parent / "logs" / scene_dir.name / "train_metrics.jsonl"
                return (last_logged_step(metrics) or 0) >= min_step
        elif path.parent.is_dir() and any(path.parent.glob(f".{path.name}.partial-*")):
            return True
    return False


def kill_stage_halfway(root: Path, targets: list[str], scene: str, stage: str, timeout: float = 900,
                       min_step: int = 0) -> dict:
    """Run Snakemake on `targets`; when `stage` of `scene` is halfway, SIGKILL its job's process
    (training: once a checkpoint exists and the log has reached step `min_step`).

    Returns {"killed": bool, "returncode", "stage", "seconds", "train_step" (last step logged
    before the kill, for training)}. The Snakemake process itself sees its job die and exits.
    """
    scene_dir = root / "results" / scene
    process = subprocess.Popen(snakemake_command(root, *targets), cwd=root, env=snakemake_env(),
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               start_new_session=True)
    start = time.monotonic()
    killed, train_step = False, None
    try:
        while process.poll() is None and time.monotonic() - start < timeout:
            if is_halfway(scene_dir, stage, min_step):
                for pid in stage_processes(process.pid, stage):
                    if stage == "train":
                        train_step = last_logged_step(root / "logs" / scene / "train_metrics.jsonl")
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGKILL)
                        killed = True
                if killed:
                    break
            time.sleep(0.002)
        output, _ = process.communicate(timeout=timeout)
    finally:
        if process.poll() is None:  # a hung run: end the process group this function started
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    return {"killed": killed, "returncode": process.returncode, "stage": stage,
            "seconds": round(time.monotonic() - start, 2), "train_step": train_step, "output": output[-3000:]}


def last_logged_step(metrics_log: Path) -> int | None:
    import json

    if not metrics_log.exists():
        return None
    # only whole lines: the trainer may be writing the last one while this reads the file
    whole = metrics_log.read_text().split("\n")[:-1]
    steps = [json.loads(line).get("step") for line in whole if line.strip()]
    steps = [s for s in steps if isinstance(s, int)]
    return max(steps) if steps else None


def leftovers(results: Path) -> list[Path]:
    """What an interrupted stage may leave: hidden partial/old artifacts, checkpoint temp files."""
    found = [p for p in results.rglob(".*") if ".partial-" in p.name or ".old-" in p.name]
    found += list(results.rglob("*.pt.tmp"))
    return sorted(found)


@contextlib.contextmanager
def tmpfs(path: Path, size: str = "1m", read_only: bool = False):
    """Mount a tmpfs of `size` at `path` (read-only when asked); needs root. Unmounted after."""
    path.mkdir(parents=True, exist_ok=True)
    result = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                            capture_output=True, text=True)
    if result.returncode != 0:
        raise PermissionError(f"cannot mount a tmpfs at {path}: {result.stderr.strip()}")
    try:
        if read_only:
            subprocess.run(["mount", "-o", "remount,ro", str(path)], check=True, capture_output=True)
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def compare_artifacts(a: Path, b: Path) -> dict[str, dict]:
    """Every array of two Zarr artifacts: {"relative/path": {"bitwise": bool, "max_abs_diff": float}}."""
    import zarr

    out: dict[str, dict] = {}

    def walk(ga, gb, prefix):
        for name, item in ga.members():
            key = f"{prefix}{name}"
            if isinstance(item, zarr.Group):
                walk(item, gb[name], key + "/")
                continue
            x, y = np.asarray(item[...]), np.asarray(gb[name][...])
            equal = x.shape == y.shape and x.dtype == y.dtype and x.tobytes() == y.tobytes()
            diff = 0.0
            if not equal and x.shape == y.shape and x.size:
                diff = float(np.nanmax(np.abs(x.astype(np.float64) - y.astype(np.float64))))
            out[key] = {"bitwise": equal, "max_abs_diff": diff if x.shape == y.shape else float("inf")}

    walk(zarr.open_group(str(a), mode="r"), zarr.open_group(str(b), mode="r"), "")
    return out

"""What every benchmark does: build scenes through the Snakemake workflow in a work directory,
read the rules' run times, describe the machine and write benchmarks/results/NAME.json.

The scripts import this as `common` (`python benchmarks/NAME.py` puts benchmarks/ on sys.path).
"""

from __future__ import annotations

import copy
import csv
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"


def write_workdir(workdir: Path, scenes: dict[str, dict], final_artifact: str) -> None:
    """config/config.yaml listing `scenes` (name -> scene config) and config/scenes/NAME.yaml."""
    folder = workdir / "config" / "scenes"
    folder.mkdir(parents=True, exist_ok=True)
    for name, scene in scenes.items():
        (folder / f"{name}.yaml").write_text(yaml.safe_dump(scene, sort_keys=False))
    (workdir / "config" / "config.yaml").write_text(yaml.safe_dump(
        {"scenes_dir": "config/scenes", "scenes": list(scenes), "results_dir": "results",
         "final_artifact": final_artifact}, sort_keys=False))


def merge(base: dict, overrides: dict) -> dict:
    """A copy of the scene config `base` with `overrides` (section by section) on top."""
    scene = copy.deepcopy(base)
    for key, value in overrides.items():
        if isinstance(value, dict):
            scene[key] = {**scene.get(key, {}), **value}
        else:
            scene[key] = value
    return scene


def renamed_paths(value, old: str, new: str):
    """The scene with paths into its own results (the plant's imported ground-truth masks) moved
    to another scene's results folder, which is where that scene's capture is generated."""
    if isinstance(value, dict):
        return {k: renamed_paths(v, old, new) for k, v in value.items()}
    if isinstance(value, list):
        return [renamed_paths(v, old, new) for v in value]
    if isinstance(value, str) and value.startswith(old):
        return new + value[len(old):]
    return value


def holdout_every(scene: dict) -> int:
    """The scene's evaluate.holdout_every, or the schema's default when the scene file does not set it."""
    from srfpipe.config import section_defaults

    return int((scene.get("evaluate") or {}).get("holdout_every", section_defaults("evaluate")["holdout_every"]))


def snakemake_env() -> dict:
    """The environment for Snakemake: this interpreter's `srfpipe` script first on PATH."""
    return dict(os.environ, PATH=str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""))


def run_workflow(workdir: Path, targets: list[str], cores: int = 2, log: Path | None = None,
                 extra: tuple[str, ...] = ()) -> float:
    """Build `targets` (paths relative to the work directory) with the repo's Snakefile; wall seconds.
    With `log`, Snakemake's output is appended there instead of the terminal; `extra` are more
    Snakemake arguments."""
    # targets first: options such as --quiet take a variable number of values
    command = [sys.executable, "-m", "snakemake", *targets, "-s", str(REPO / "Snakefile"), "-d", str(workdir),
               "--cores", str(cores), *extra]
    return run_command(command, log)


def run_command(command: list[str], log: Path | None = None) -> float:
    """Run `command` (echoed) with `snakemake_env()`, output appended to `log` if given; wall seconds."""
    print("$", " ".join(command), flush=True)
    started = time.perf_counter()
    if log is None:
        subprocess.run(command, check=True, env=snakemake_env())
    else:
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "a") as handle:
            subprocess.run(command, check=True, env=snakemake_env(), stdout=handle, stderr=subprocess.STDOUT)
    return time.perf_counter() - started


def rule_seconds(workdir: Path, scene: str, job: str) -> float | None:
    """Wall seconds of the jobs whose Snakemake benchmark file is benchmarks/runs/SCENE/JOB.tsv
    (`job` may be a glob, e.g. "segment_*": the jobs' times are summed); None if none ran."""
    total, found = 0.0, False
    for path in sorted((workdir / "benchmarks" / "runs" / scene).glob(f"{job}.tsv")):
        with path.open() as handle:
            total += float(next(csv.DictReader(handle, delimiter="\t"))["s"])
        found = True
    return total if found else None


def cpu_probe_seconds(repeats: int = 5) -> float:
    """Seconds this machine's CPU takes for a fixed piece of a training step: a gather of 2^18 rows
    of 16 channels (what the dense grid's trilinear read does) through a small MLP, forward and
    backward, best of `repeats`. Machines that report the same name and core count differ (one
    here ran the fox's COLMAP refinement 1.9x slower than another, and its 10 minutes of training
    held 31-84 % of the other's steps); two results' probes say how far their machines compare."""
    import torch

    generator = torch.Generator().manual_seed(0)
    table = torch.randn(1 << 16, 16, generator=generator, requires_grad=True)
    rows = torch.randint(0, 1 << 16, (1 << 18,), generator=generator)
    with torch.random.fork_rng():  # the layers' initial draws leave the caller's random stream as it was
        layers = [torch.nn.Linear(16, 64), torch.nn.Linear(64, 64), torch.nn.Linear(64, 4)]

    def once() -> float:
        started = time.perf_counter()
        x = table[rows]
        for layer in layers[:-1]:
            x = torch.relu(layer(x))
        layers[-1](x).square().mean().backward()
        return time.perf_counter() - started

    once()  # allocations and lazy initialisation
    return min(once() for _ in range(repeats))


def machine_info(**extra) -> dict:
    """Where a number was measured: platform, CPU, its speed (`cpu_probe_seconds`), Python and torch
    versions, plus `extra`."""
    import torch

    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(), "cpu_probe_seconds": round(cpu_probe_seconds(), 4),
            "python": platform.python_version(), "torch": torch.__version__, **extra}


def result_path(name: str, quick: bool) -> Path:
    """benchmarks/results/NAME.json, or NAME_quick.json for a short run (never the committed numbers)."""
    return RESULTS / f"{name}{'_quick' if quick else ''}.json"


def measured_steps(name: str, quick: bool = False) -> int:
    """The training steps the defaults' build of capture `name` reached in its 10 minutes (captures.json)."""
    path = result_path("captures", quick)
    steps = (json.loads(path.read_text())["scenes"].get(name) or {}).get("steps")
    if not steps:
        raise SystemExit(f"{path} has no steps for {name}: run benchmarks/captures.py --scenes {name} first")
    return int(steps)


def earlier_measurements(previous: dict[str, dict], measured_now) -> dict[str, dict]:
    """The per-scene entries of a previous result file that this run did not measure, marked
    `measured_in_an_earlier_run` (a run of some scenes keeps the others' last measurement)."""
    return {name: dict(entry, measured_in_an_earlier_run=True)
            for name, entry in previous.items() if name not in measured_now}


# Hosts whose CPU probes differ by more than this factor train visibly different step counts in one
# time budget (2026-12-01: a probe of 0.40 s against the panel's 0.17-0.26 s trained 25-30 % of the
# rows' steps in 10 minutes, the code's own speed unchanged)
HOST_SPEED_FACTOR = 1.5


def host_speed_notes(previous: dict, measured: dict[str, dict], machine: dict) -> list[str]:
    """One line per re-measured scene whose earlier entry in the `previous` report was measured on a
    host whose `cpu_probe_seconds` differs from `machine`'s by more than HOST_SPEED_FACTOR: its new
    time-budgeted row compares the hosts as much as the code. An entry's host is its own `machine`,
    else the report's when that report measured it; otherwise it is not known and nothing is said."""
    notes = []
    now = machine.get("cpu_probe_seconds")
    for name, entry in measured.items():
        before = previous.get("scenes", {}).get(name)
        if not before or not now:
            continue
        host = before.get("machine") or (previous.get("machine") if name in previous.get("measured_now", []) else None)
        then = (host or {}).get("cpu_probe_seconds")
        if not then or max(now / then, then / now) <= HOST_SPEED_FACTOR:
            continue
        notes.append(f"{name}: this host's CPU probe reads {now:.2f} s against {then:.2f} s where its previous entry "
                     f"was measured ({entry.get('steps')} steps now, {before.get('steps')} then): a time-budgeted row "
                     "compares the hosts as much as the code (--equal-steps compares step for step)")
    return notes


def write_result(path: Path, report: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {path}")
    if path.resolve().parent == RESULTS.resolve():
        refresh_readme()
    return path


def refresh_readme() -> None:
    """Re-write the README's headline table from the results (scripts/readme_numbers.py), so a
    benchmark's new numbers reach it; a failure there is reported, not fatal to the benchmark."""
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "readme_numbers.py")], capture_output=True, text=True)
    if done.returncode != 0:
        print(f"README.md's headline table not refreshed: {done.stderr.strip()}", file=sys.stderr)

"""Reliability: inject faults into real Snakemake builds and count what the pipeline came through;
run the bad-input corpus; check determinism. Writes benchmarks/results/reliability.json (the table
in docs/reliability.md).

    python benchmarks/reliability.py [--quick] [--workdir DIR]

Faults (each on a tiny orchard, the scene of tests/test_faults.py with more iterations):
* every stage's job SIGKILLed halfway (downscale, segment, composite, train, evaluate, distill,
  package): the same command is run again and again, each run killed at its next stage, then once
  more without a kill. Survived when the final run finishes, every artifact opens as complete,
  nothing partial is left, and training lost at most one checkpoint interval;
* Snakemake itself SIGKILLed with its job (pre-emption of the whole run): recovery needs
  `snakemake --unlock` first when Snakemake left its lock (recorded);
* a full disk (a 384 kB tmpfs as results_dir) and a read-only results folder: survived when the
  build fails with a clear error naming the folder and leaves no partial artifact;
* two scenes built at once (--cores 2): survived when both finish and share no file;
* determinism: the same scene built twice; every array of every artifact compared.
* integrity: seconds per GB that open_artifact spends verifying an artifact's files against its
  manifest (`integrity_check_seconds_per_gb`, a ~512 MB artifact, files in the page cache).

`artifacts_lost` counts artifacts complete before a fault and missing or incomplete after it;
`partial_artifacts_left` counts hidden partial/old artifacts and checkpoint temp files after the
recovery (or after the failed run, for the disk faults). Needs root for the tmpfs mounts.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import common  # noqa: E402
from tests.faults import (  # noqa: E402
    compare_artifacts,
    is_halfway,
    kill_stage_halfway,
    leftovers,
    snakemake_command,
    tmpfs,
)
from tests.test_faults import FAULT_SCENE  # noqa: E402

from srfpipe.artifacts import open_artifact, read_provenance  # noqa: E402

STAGES = ["downscale", "segment", "composite", "train", "evaluate", "distill", "package"]
TARGETS = ["results/{scene}/sim", "results/{scene}/eval"]


def scene_config(quick: bool) -> dict:
    scene = copy.deepcopy(FAULT_SCENE)
    scene["train"].update(iterations=48 if quick else 160, checkpoint_every=8 if quick else 20)
    scene["occupancy"]["voxels_across"] = 64  # distillation long enough to be caught halfway
    return scene


def halfway_step(quick: bool) -> int:
    """Training is killed here: past half the steps, half an interval after a checkpoint."""
    train = scene_config(quick)["train"]
    return train["iterations"] // 2 + train["checkpoint_every"] // 2


def targets(scene: str) -> list[str]:
    return [t.format(scene=scene) for t in TARGETS]


def complete_artifacts(results: Path) -> set[Path]:
    found = set()
    for path in list(results.rglob("*.zarr")) + list(results.rglob("eval")) + list(results.rglob("sim")):
        if any(part.startswith(".") for part in path.relative_to(results).parts):
            continue
        try:
            if path.name in ("eval", "sim"):
                if any(path.iterdir()):
                    found.add(path)
            else:
                open_artifact(path)
                found.add(path)
        except Exception:
            pass
    return found


def lost(before: set[Path], results: Path) -> list[str]:
    after = complete_artifacts(results)
    return [str(p) for p in sorted(before - after)]


def run(root: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(snakemake_command(root, *args), cwd=root, env=common.snakemake_env(),
                          capture_output=True, text=True)


def new_workdir(parent: Path, name: str, scenes: dict[str, dict]) -> Path:
    root = parent / name
    if root.exists():
        shutil.rmtree(root)
    common.write_workdir(root, scenes, "occupancy")
    return root


def kill_every_stage(parent: Path, quick: bool) -> list[dict]:
    """One build of the full targets, run again and again with the same command: each run's
    next stage is SIGKILLed halfway, and the following run must get past it. The final run,
    without a kill, must finish."""
    root = new_workdir(parent, "kill_stages", {"tiny": scene_config(quick)})
    results = root / "results"
    interval = scene_config(quick)["train"]["checkpoint_every"]
    outputs = {"downscale": "images.zarr", "segment": "masks/apple.zarr", "composite": "labels.zarr",
               "train": "srf.zarr", "evaluate": "eval", "distill": "occupancy.zarr", "package": "sim"}
    records = []
    for stage in STAGES:
        # Snakemake may have run this stage already, beside the one killed last (evaluate and
        # distill both follow train): remove its output so that this run has it to do
        shutil.rmtree(results / "tiny" / outputs[stage], ignore_errors=True)
        before = complete_artifacts(results) if results.exists() else set()
        outcome = kill_stage_halfway(root, targets("tiny"), "tiny", stage,
                                     min_step=halfway_step(quick))
        record = {"fault": f"sigkill_{stage}", "injected": outcome["killed"], "seconds_to_kill": outcome["seconds"],
                  "lost": lost(before, results)}
        if stage == "train":
            record["train_step_at_kill"] = outcome["train_step"]
        records.append(record)
        print(json.dumps(record), flush=True)
    final = run(root, *targets("tiny"))
    complete = complete_artifacts(results)
    left = [str(p) for p in leftovers(results)]
    for record, stage in zip(records, STAGES):
        record["rerun_ok"] = final.returncode == 0 and (results / "tiny" / outputs[stage]) in complete
        record["leftovers"] = left if stage == STAGES[-1] else []  # counted once, after the last run
        if stage == "train" and final.returncode == 0:
            srf = read_provenance(results / "tiny" / "srf.zarr")
            record["resumed_from_step"] = srf["resumed_from_step"]
            record["steps_lost"] = (record["train_step_at_kill"] or 0) - srf["resumed_from_step"]
            record["lost_at_most_one_interval"] = srf["resumed_from_step"] > 0 and record["steps_lost"] <= interval
        record["survived"] = bool(record["injected"] and record["rerun_ok"] and not left and not record["lost"]
                                  and record.get("lost_at_most_one_interval", True))
    print(json.dumps({"final_run_ok": final.returncode == 0, "leftovers": left}), flush=True)
    return records


def kill_snakemake_too(parent: Path, quick: bool) -> dict:
    """Pre-emption of the whole run: Snakemake and the training job SIGKILLed together."""
    root = new_workdir(parent, "kill_all", {"tiny": scene_config(quick)})
    results = root / "results"
    run(root, "results/tiny/labels.zarr")
    before = complete_artifacts(results)
    process = subprocess.Popen(snakemake_command(root, *targets("tiny")), cwd=root, env=common.snakemake_env(),
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    injected = False
    deadline = time.monotonic() + 900
    while process.poll() is None and time.monotonic() < deadline:
        if is_halfway(results / "tiny", "train"):
            os.killpg(process.pid, signal.SIGKILL)  # the group this function started
            injected = True
            break
        time.sleep(0.01)
    process.wait()
    time.sleep(1)
    record = {"fault": "sigkill_snakemake_and_train", "injected": injected, "lost": lost(before, results)}
    first = run(root, *targets("tiny"))
    record["same_command_ok"] = first.returncode == 0
    record["needed_unlock"] = False
    if first.returncode != 0 and "LockException" in first.stdout + first.stderr:
        record["needed_unlock"] = True
        run(root, "--unlock", *targets("tiny"))
        first = run(root, *targets("tiny"))
    record["rerun_ok"] = first.returncode == 0
    record["leftovers"] = [str(p) for p in leftovers(results)]
    if first.returncode == 0:
        record["resumed_from_step"] = read_provenance(results / "tiny" / "srf.zarr")["resumed_from_step"]
    record["survived"] = bool(injected and record["rerun_ok"] and not record["leftovers"] and not record["lost"])
    print(json.dumps(record), flush=True)
    return record


def disk_faults(parent: Path, quick: bool) -> list[dict]:
    """results_dir on a 2 MB tmpfs, and on a read-only one holding a finished poses.zarr."""
    records = []
    for kind in ("disk_full", "read_only"):
        root = new_workdir(parent, kind, {"tiny": scene_config(quick)})
        mount = root / "results"
        try:
            with tmpfs(mount, size="384k" if kind == "disk_full" else "64m"):
                if kind == "read_only":
                    run(root, "results/tiny/poses.zarr")
                    subprocess.run(["mount", "-o", "remount,ro", str(mount)], check=True)
                before = complete_artifacts(mount)
                result = run(root, "results/tiny/images.zarr")
                logs = "\n".join(p.read_text() for p in (root / "logs").rglob("*.log")) if (root / "logs").exists() else ""
                text = result.stdout + result.stderr + logs
                problem = "No space left on device" if kind == "disk_full" else "Read-only file system"
                # a disk that did not fill up injected nothing
                record = {"fault": kind, "injected": result.returncode != 0 or kind == "read_only",
                          "failed": result.returncode != 0,
                          "clear_error": problem in text and "results" in text,
                          "leftovers": [str(p) for p in leftovers(mount)], "lost": lost(before, mount)}
        except PermissionError as exc:
            record = {"fault": kind, "injected": False, "skipped": str(exc), "leftovers": [], "lost": []}
        record["survived"] = bool(record["injected"] and record.get("failed") and record.get("clear_error")
                                  and not record["leftovers"] and not record["lost"])
        records.append(record)
        print(json.dumps(record), flush=True)
    return records


def concurrent_and_determinism(parent: Path, quick: bool) -> tuple[dict, dict]:
    """Two identical scenes (same config and seed) built at once: they must not touch each
    other's files, and must come out the same; array by array, which are bitwise equal."""
    scene = scene_config(quick)
    root = new_workdir(parent, "concurrent", {"left": scene, "right": scene})
    started = time.perf_counter()
    result = run(root, *targets("left"), *targets("right"))
    results = root / "results"
    files = {name: {p.relative_to(results / name) for p in (results / name).rglob("*")} for name in ("left", "right")}
    concurrent = {"fault": "two_scenes_at_once", "injected": True, "ok": result.returncode == 0,
                  "seconds": round(time.perf_counter() - started, 1),
                  "same_file_layout": files["left"] == files["right"],
                  "leftovers": [str(p) for p in leftovers(results)], "lost": []}
    concurrent["survived"] = bool(concurrent["ok"] and concurrent["same_file_layout"] and not concurrent["leftovers"])
    bitwise, tolerance = [], {}
    for artifact in ("poses.zarr", "images.zarr", "masks/apple.zarr", "masks/branch.zarr", "masks/leaf.zarr",
                     "labels.zarr", "srf.zarr", "occupancy.zarr"):
        if not (results / "left" / artifact).exists():
            continue
        for key, value in compare_artifacts(results / "left" / artifact, results / "right" / artifact).items():
            if value["bitwise"]:
                bitwise.append(f"{artifact}/{key}")
            else:
                tolerance[f"{artifact}/{key}"] = value["max_abs_diff"]
    left, right = (json.loads((results / s / "eval" / "metrics.json").read_text()) for s in ("left", "right"))
    determinism = {"arrays_compared": len(bitwise) + len(tolerance), "bitwise_equal": len(bitwise),
                   "bitwise_equal_arrays": sorted(bitwise), "within_tolerance": tolerance,
                   "eval_psnr": [left.get("psnr"), right.get("psnr")]}
    print(json.dumps(concurrent), json.dumps({k: v for k, v in determinism.items() if k != "bitwise_equal_arrays"}),
          flush=True)
    return concurrent, determinism


def bad_input_corpus(parent: Path) -> dict:
    """Every `bad_input` test case (tests/test_bad_inputs.py and the marked cases elsewhere)."""
    report = parent / "bad_inputs.xml"
    subprocess.run([sys.executable, "-m", "pytest", "-q", "-m", "bad_input", "-p", "no:cacheprovider",
                    f"--junitxml={report}", str(common.REPO / "tests")], cwd=common.REPO, env=common.snakemake_env())
    cases = list(ET.parse(report).getroot().iter("testcase"))
    failed = [f"{c.get('classname')}::{c.get('name')}" for c in cases
              if c.find("failure") is not None or c.find("error") is not None]
    skipped = [c for c in cases if c.find("skipped") is not None]
    per_file: dict[str, int] = {}
    for case in cases:
        per_file[case.get("classname")] = per_file.get(case.get("classname"), 0) + 1
    return {"tried": len(cases) - len(skipped), "clear_error": len(cases) - len(skipped) - len(failed),
            "failed": failed, "per_file": per_file}


def integrity_check_seconds_per_gb(megabytes: int = 512, parent: Path | None = None, repeats: int = 3) -> dict:
    """How long `open_artifact`'s integrity check takes: a ~512 MB artifact (incompressible
    uint8 data in 4 MB chunks, like images and weights) written with create_artifact, then opened
    `repeats` times with its files in the page cache (the usual case: the previous stage has
    just written them) and once after evicting them (posix_fadvise DONTNEED: read from disk).
    Seconds per GB of stored bytes; the best warm run, the cold run."""
    import numpy as np

    from srfpipe.artifacts import create_artifact, read_provenance

    folder = Path(tempfile.mkdtemp(prefix="srfpipe-integrity-", dir=parent))
    try:
        path = folder / "big.zarr"
        rows = max(1, megabytes * (1 << 20) // (1 << 22))  # 4 MB chunks
        rng = np.random.default_rng(0)
        started = time.perf_counter()
        with create_artifact(path, "integrity-benchmark") as group:
            array = group.create_array("data", shape=(rows, 1 << 22), chunks=(1, 1 << 22), dtype=np.uint8)
            for row in range(rows):
                array[row] = rng.integers(0, 256, 1 << 22, dtype=np.uint8)
        write_seconds = time.perf_counter() - started
        integrity = read_provenance(path)["integrity"]
        gigabytes = integrity["bytes"] / 1e9

        def timed(verify: bool = True) -> float:
            t0 = time.perf_counter()
            open_artifact(path, stage="integrity-benchmark", verify=verify)
            return time.perf_counter() - t0

        warm = [timed() for _ in range(repeats)]
        cold = None
        if hasattr(os, "posix_fadvise"):
            for file in path.rglob("*"):
                if file.is_file():
                    fd = os.open(file, os.O_RDONLY)
                    try:
                        os.fsync(fd)
                        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
                    finally:
                        os.close(fd)
            cold = timed()
        unverified = min(timed(verify=False) for _ in range(repeats))
        result = {
            "seconds_per_gb": round(min(warm) / gigabytes, 3),
            "cold_seconds_per_gb": round(cold / gigabytes, 3) if cold is not None else None,
            "open_without_check_seconds": round(unverified, 4),
            "gigabytes": round(gigabytes, 3),
            "files": integrity["files"],
            "algorithm": integrity["algorithm"],
            "write_seconds": round(write_seconds, 2),
            "warm_seconds": [round(s, 3) for s in warm],
            "cold_seconds": round(cold, 3) if cold is not None else None,
            "cpus": os.cpu_count(),
        }
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    print(json.dumps({"integrity_check": result}), flush=True)
    return result


# The hostile-input corpus (`pytest -m hostile`): each case's class, from its test's name.
HOSTILE_CLASSES = {
    "injection": ("substitution", "escape_results", "injection"),
    "corruption": ("corrupt", "damaged", "flipped", "deleted", "truncated", "stray", "missing_chunk"),
}


def hostile_corpus(parent: Path) -> dict:
    """Every `hostile` test case: tried, handled (a clear error or correct handling), and per class."""
    report = parent / "hostile.xml"
    subprocess.run([sys.executable, "-m", "pytest", "-q", "-m", "hostile", "-p", "no:cacheprovider",
                    f"--junitxml={report}", str(common.REPO / "tests")], cwd=common.REPO, env=common.snakemake_env())
    cases = [c for c in ET.parse(report).getroot().iter("testcase") if c.find("skipped") is None]
    failed = {f"{c.get('classname')}::{c.get('name')}" for c in cases
              if c.find("failure") is not None or c.find("error") is not None}
    names = [f"{c.get('classname')}::{c.get('name')}" for c in cases]
    per_class = {}
    for kind, words in HOSTILE_CLASSES.items():
        members = [n for n in names if any(w in n.split("::")[-1] for w in words)]
        per_class[kind] = {"tried": len(members), "handled": sum(1 for n in members if n not in failed)}
    return {"tried": len(cases), "clear_error": len(cases) - len(failed), "failed": sorted(failed),
            "per_class": per_class, "cases": names}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer training steps (writes reliability_quick.json)")
    parser.add_argument("--workdir", type=Path, default=None, help="work folder (default: a temporary one)")
    parser.add_argument("--skip-corpus", action="store_true", help="do not run the bad-input corpus")
    parser.add_argument("--corpus-only", action="store_true",
                        help="run the bad-input and hostile corpora only; keep the last run's fault results")
    args = parser.parse_args()
    parent = args.workdir or Path(tempfile.mkdtemp(prefix="srfpipe-reliability-"))
    parent.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()

    previous_file = common.result_path("reliability", args.quick)
    if args.corpus_only:  # the fault runs take most of an hour: keep the last ones
        previous = json.loads(previous_file.read_text())
        faults, determinism = previous["faults"], previous["determinism"]
    else:
        faults = kill_every_stage(parent, args.quick)
        faults.append(kill_snakemake_too(parent, args.quick))
        faults += disk_faults(parent, args.quick)
        concurrent, determinism = concurrent_and_determinism(parent, args.quick)
        faults.append(concurrent)
    corpus = bad_input_corpus(parent) if not args.skip_corpus else {"tried": 0, "clear_error": 0}
    hostile = hostile_corpus(parent) if not args.skip_corpus else {"tried": 0, "clear_error": 0, "per_class": {}}
    injection = hostile["per_class"].get("injection", {"tried": 0, "handled": 0})
    corruption = hostile["per_class"].get("corruption", {"tried": 0, "handled": 0})
    integrity = integrity_check_seconds_per_gb(parent=parent)

    injected = [f for f in faults if f["injected"]]
    report = {
        "faults_injected": len(injected),
        "faults_survived": sum(1 for f in injected if f["survived"]),
        "bad_inputs_tried": corpus["tried"],
        "bad_inputs_clear_error": corpus["clear_error"],
        "hostile_inputs_tried": hostile["tried"],
        "hostile_inputs_clear_error": hostile["clear_error"],
        "injections_tried": injection["tried"],
        "injections_blocked": injection["handled"],
        "corruptions_tried": corruption["tried"],
        "corruptions_detected": corruption["handled"],
        "artifacts_lost": sum(len(f.get("lost", [])) for f in faults),
        "partial_artifacts_left": sum(len(f.get("leftovers", [])) for f in faults),
        "integrity_check_seconds_per_gb": integrity["seconds_per_gb"],
        "integrity_check": integrity,
        "faults": faults,
        "determinism": determinism,
        "bad_inputs": corpus,
        "hostile_inputs": hostile,
        "faults_from_an_earlier_run": bool(args.corpus_only),
        "seconds": round(time.perf_counter() - started, 1),
        "machine": common.machine_info(),
        "reproduce": "python benchmarks/reliability.py" + (" --quick" if args.quick else ""),
    }
    common.write_result(common.result_path("reliability", args.quick), report)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark: a batch through a real SLURM cluster, and what a config change re-runs.

Starts the single-node SLURM cluster of the CI step (tests/slurm_cluster.py: munged, slurmctld and
slurmd from Debian's packages, started by hand, stopped by PID), builds the CI's two tiny scenes
(tests/test_slurm.py) with `snakemake batch --workflow-profile workflow/profiles/slurm` through
snakemake-executor-plugin-slurm: `tiny` (the tiny orchard through every stage to its simulator
package) and `broken` (a nerfstudio capture whose images are missing: its poses job fails, and the
profile's `retries: 1` submits it twice). Then, on the built scene, two dry runs (`snakemake -n`,
its job table): after changing a training key (train.iterations 20 -> 25) and after changing one
prompt's threshold (segmentation.thresholds.leaf 0.6).

Writes benchmarks/results/cluster.json. Needs root and slurm-wlm + munge (scripts/ci_slurm.sh
installs them); a few minutes.

    python benchmarks/cluster.py [--workdir DIR]
"""

from __future__ import annotations

import argparse
import copy
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from importlib.metadata import version
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from common import machine_info, result_path, rule_seconds, write_result  # noqa: E402
from tests.slurm_cluster import (  # noqa: E402
    SlurmCluster,
    dry_run_jobs,
    missing_requirements,
    run_batch,
    slurm_command,
    write_batch,
)
from tests.test_batch import TINY_FULL, write_broken_capture  # noqa: E402

STAGES = ["orchard_capture", "poses", "downscale", "segment_*", "composite", "train", "evaluate", "distill",
          "package"]


def _seconds(job: dict) -> float | None:
    try:
        start, end = (datetime.fromisoformat(job[key]) for key in ("StartTime", "EndTime"))
    except (KeyError, ValueError):
        return None
    return (end - start).total_seconds()


def rerun_counts(workdir: Path, scene: dict, targets: list[str]) -> dict:
    """Jobs a dry run lists after a training-key change and after one prompt's change (each from
    the built state; the scene file is restored after each)."""
    path = workdir / "config" / "scenes" / "tiny.yaml"
    original = path.read_text()
    report = {"before_any_change": dry_run_jobs(workdir, *targets)}
    train = copy.deepcopy(scene)
    train["train"]["iterations"] = scene["train"]["iterations"] + 5
    prompt = copy.deepcopy(scene)
    prompt["segmentation"]["thresholds"] = {"leaf": 0.6}
    for name, changed in (("train", train), ("prompt", prompt)):
        path.write_text(yaml.safe_dump(changed, sort_keys=False))
        try:
            report[name] = dry_run_jobs(workdir, *targets)
        finally:
            path.write_text(original)
    return report


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--workdir", type=Path, default=None, help="scratch folder (default: a temporary one)")
    parser.add_argument("--timeout", type=int, default=900, help="seconds before the run is interrupted (SIGINT)")
    parser.add_argument("--out", type=Path, help="result file (default: benchmarks/results/cluster.json)")
    args = parser.parse_args(argv)
    reason = missing_requirements()
    if reason:
        print(f"cannot start the SLURM cluster: {reason}; run `bash scripts/ci_slurm.sh` once to install it")
        return 2

    with tempfile.TemporaryDirectory(prefix="srfpipe-bench-cluster-") as tmp:
        root = (args.workdir or Path(tmp)).resolve()
        work = root / "work"
        scenes = {"tiny": copy.deepcopy(TINY_FULL),
                  "broken": {"source": {"format": "nerfstudio",
                                        "path": str(write_broken_capture(work / "captures" / "broken"))}}}
        write_batch(work, scenes, final_artifact="sim")
        started = time.perf_counter()
        cluster = SlurmCluster(root / "slurm")
        with cluster:
            start_seconds = time.perf_counter() - started
            run = run_batch(cluster, work, timeout=args.timeout, log=root / "snakemake.log")
            slurm_version = subprocess.run(["sinfo", "--version"], capture_output=True, text=True,
                                           env=cluster.env()).stdout.strip()
            node = {"name": cluster.node, "cpus": cluster.cpus, "real_memory_mb": cluster.memory_mb}
        print(run.stdout[-3000:])
        targets = ["results/tiny/sim", "results/tiny/eval"]
        reruns = rerun_counts(work, scenes["tiny"], targets)

        finished = {job["JobId"]: job for job in run.finished}
        jobs = [{"slurm_jobid": job_id, "rule": rule, "state": finished.get(job_id, {}).get("JobState"),
                 "seconds": _seconds(finished.get(job_id, {}))} for job_id, rule in run.submitted.items()]
        rule_times = {stage.rstrip("_*"): rule_seconds(work, "tiny", stage) for stage in STAGES}
        in_jobs = sum(job["seconds"] or 0 for job in jobs)
        report = {
            "slurm_jobs_submitted": len(run.submitted),
            "slurm_jobs_succeeded": len(run.succeeded),
            "scenes_ok": sum(status == "done" for status in run.summary.values()),
            "scenes_failed": sum(status == "FAILED" for status in run.summary.values()),
            "seconds": round(run.seconds, 1),
            "rerun_jobs_after_train_change": sum(reruns["train"].values()),
            "rerun_jobs_after_prompt_change": sum(reruns["prompt"].values()),
            "rerun_rules_after_train_change": reruns["train"],
            "rerun_rules_after_prompt_change": reruns["prompt"],
            "rerun_jobs_before_any_change": sum(reruns["before_any_change"].values()),
            "snakemake_returncode": run.returncode,
            "summary": run.summary,
            "cluster_start_seconds": round(start_seconds, 1),
            "jobs": jobs,
            "seconds_inside_slurm_jobs": round(in_jobs, 1),
            "tiny_rule_seconds": rule_times,
            "config": {
                "scenes": scenes | {"broken": {"source": {"format": "nerfstudio",
                                                          "path": "<a capture whose 3 images are missing>"}}},
                "final_artifact": "sim",
                "command": " ".join(slurm_command(Path("WORK"), "batch", timeout=args.timeout)).replace(
                    sys.executable, "python"),
                "train_change": "train.iterations 20 -> 25",
                "prompt_change": "segmentation.thresholds.leaf 0.6 (default 0.5)",
                "dry_run_targets": targets,
                "node": node,
            },
            "machine": machine_info(slurm=slurm_version, snakemake=version("snakemake"),
                                    slurm_plugin=version("snakemake-executor-plugin-slurm")),
        }
    out = write_result(args.out or result_path("cluster", False), report)

    print(f"{'':34}{'value':>10}")
    for key in ("slurm_jobs_submitted", "slurm_jobs_succeeded", "scenes_ok", "scenes_failed", "seconds",
                "seconds_inside_slurm_jobs", "cluster_start_seconds", "rerun_jobs_after_train_change",
                "rerun_jobs_after_prompt_change"):
        print(f"{key:34}{report[key]:>10}")
    print(f"{'rule':18}{'state':>12}{'s in SLURM':>12}")
    for job in jobs:
        seconds = f"{job['seconds']:.0f}" if job["seconds"] is not None else "-"
        print(f"{job['rule']:18}{str(job['state']):>12}{seconds:>12}")
    print(f"-> {out}")
    good = (report["scenes_ok"] == 1 and report["scenes_failed"] == 1
            and report["slurm_jobs_succeeded"] == report["slurm_jobs_submitted"] - 2)
    return 0 if good else 1


if __name__ == "__main__":
    sys.exit(main())

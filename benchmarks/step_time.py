"""Benchmark: how long one training step takes on each panel capture, and what a variant does to it.

A speed change that keeps the arithmetic moves every capture's 10 minutes by the steps it adds, so
it is measured per capture as the time of a step, not as a PSNR: each capture is built up to
labels.zarr through the workflow (the panel's scene files and generated variants, as
benchmarks/captures.py builds them, in the same work folder by default), then trained in a fresh
interpreter per run, the way `srfpipe train` starts (its scene's train settings, glibc keeping freed
memory, 2 threads, time budget off): `--warmup` steps, then `--repeats` times `--steps` steps timed.

`--variant VAR=VALUE` (repeatable) runs each capture again with that environment variable set, the
runs of default and variants alternating, and compares their loss and parameter sum after the last
step: equal means the same arithmetic, so the change is speed alone. The default runs get none of
the variables the variants set. A host's speed drifts between runs (the same default run took 25 %
longer a step in one interpreter than in the next), so each variant runs between two default runs
and both enter the default's median.

    python benchmarks/step_time.py [--quick] [--workdir DIR] [--scenes NAME ...]
                                   [--variant THP_MEM_ALLOC_ENABLE=1] [--warmup N] [--steps N] [--repeats N]

Writes benchmarks/results/step_time.json: per capture `ms_per_step` (the median of the repeats) of the
default and each variant, `variant_over_default` (their ratio), `same_arithmetic`, and the peak
resident memory (`peak_rss_mb`) of each run; `--quick`: the orchard only, 10 + 5 steps.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from captures import PANEL, prepare_variants, scene_configs
from common import REPO, machine_info, result_path, run_workflow, write_result, write_workdir

THREADS = 2  # the rule's `threads`


def time_steps(workdir: Path, name: str, warmup: int, steps: int, repeats: int) -> dict:
    """In this interpreter: train `name` as `srfpipe train` would and time its steps."""
    import resource
    import time

    import torch

    from srfpipe.config import load_scene
    from srfpipe.device import keep_freed_memory
    from srfpipe.srf.trainer import TrainSettings, start_run, training_step

    torch.set_num_threads(THREADS)
    keep_freed_memory()
    scene = load_scene(workdir / "config" / "scenes" / f"{name}.yaml")
    settings = TrainSettings.from_options({**scene["train"], "time_budget": 0})
    results, scratch = workdir / "results" / name, workdir / "step_time" / name
    run = start_run(results / "images.zarr", results / "labels.zarr", scratch / f"srf-{os.getpid()}.zarr", settings,
                    scene["evaluate"]["holdout_every"], scratch / f"ckpt-{os.getpid()}")
    for step in range(warmup):
        training_step(run, step)
    timed = []
    for repeat in range(repeats):
        started = time.perf_counter()
        for step in range(warmup + repeat * steps, warmup + (repeat + 1) * steps):
            _, loss, _ = training_step(run, step)
        timed.append(1000.0 * (time.perf_counter() - started) / steps)
    return {"ms_per_step": timed, "loss": float(loss),
            "parameter_sum": float(sum(p.detach().double().sum() for p in run.model.parameters())),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "steps": warmup + repeats * steps}


def child_run(workdir: Path, name: str, args, environment: dict, unset: set) -> dict:
    """`time_steps` in a fresh interpreter (an allocator reads its settings once per process), with
    the variables `unset` removed from this environment and `environment` added."""
    env = {key: value for key, value in os.environ.items() if key not in unset}
    command = [sys.executable, __file__, "--child", name, "--workdir", str(workdir), "--warmup", str(args.warmup),
               "--steps", str(args.steps), "--repeats", str(args.repeats)]
    done = subprocess.run(command, env={**env, **environment}, capture_output=True, text=True, check=False)
    if done.returncode:
        raise SystemExit(f"{name} {environment or 'default'}: the timing run failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def parse_variants(assignments: list[str]) -> dict[str, dict]:
    variants = {}
    for assignment in assignments:
        key, sep, value = assignment.partition("=")
        if not (sep and key):
            raise SystemExit(f"--variant {assignment!r}: expected VARIABLE=VALUE, e.g. THP_MEM_ALLOC_ENABLE=0")
        variants[assignment] = {key: value}
    return variants


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the orchard only, 10 warm-up steps and 5 timed")
    parser.add_argument("--workdir", type=Path, default=REPO / "benchmarks" / "work" / "captures")
    parser.add_argument("--scenes", nargs="+", default=list(PANEL), choices=PANEL)
    parser.add_argument("--variant", action="append", default=[], metavar="VAR=VALUE",
                        help="an environment variable to compare with the default (repeatable), e.g. "
                             "THP_MEM_ALLOC_ENABLE=1: PyTorch's CPU tensors of 2 MB and more on huge pages")
    parser.add_argument("--warmup", type=int, default=100, help="steps before the timing (the grids prune)")
    parser.add_argument("--steps", type=int, default=20, help="steps a repeat times")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--child", metavar="SCENE", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(time_steps(args.workdir, args.child, args.warmup, args.steps, args.repeats)))
        return 0
    if args.quick:
        args.scenes, args.warmup, args.steps = ["orchard"], 10, 5
    variants = parse_variants(args.variant)
    unset = {key for environment in variants.values() for key in environment}

    scenes = scene_configs(args.scenes, quick=False)
    write_workdir(args.workdir, scenes, "occupancy")
    prepare_variants(args.workdir, scenes, ())
    run_workflow(args.workdir, [f"results/{name}/labels.zarr" for name in scenes], log=args.workdir / "snakemake.log")

    report = {"machine": machine_info(threads=THREADS),
              "config": {"warmup": args.warmup, "steps": args.steps, "repeats": args.repeats, "variants": variants},
              "scenes": {}}
    print(f"{'capture':14} {'default ms':>10} " + " ".join(f"{v + ' ms':>28} {'ratio':>6} {'same':>5}" for v in variants))
    for name in scenes:
        default = child_run(args.workdir, name, args, {}, unset)
        entry = {"default": default, "ms_per_step": statistics.median(default["ms_per_step"])}
        for label, environment in variants.items():
            run = child_run(args.workdir, name, args, environment, unset)
            again = child_run(args.workdir, name, args, {}, unset)  # alternate, so a host's drift hits both
            default["ms_per_step"] += again["ms_per_step"]
            entry["ms_per_step"] = statistics.median(default["ms_per_step"])
            ms = statistics.median(run["ms_per_step"])
            entry[label] = {**run, "ms_per_step_median": ms, "variant_over_default": ms / entry["ms_per_step"],
                            "same_arithmetic": run["loss"] == default["loss"]
                            and run["parameter_sum"] == default["parameter_sum"]}
        report["scenes"][name] = entry
        print(f"{name:14} {entry['ms_per_step']:10.0f} " + " ".join(
            f"{entry[v]['ms_per_step_median']:28.0f} {entry[v]['variant_over_default']:6.2f} "
            f"{str(entry[v]['same_arithmetic']):>5}" for v in variants), flush=True)
    write_result(result_path("step_time", args.quick), report)
    return 0


if __name__ == "__main__":
    sys.exit(main())

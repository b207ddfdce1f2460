"""Benchmark: training speed and quality against time on the device torch picks (CUDA when present).

For each scene (orchard, fox, plant by default), images.zarr and labels.zarr are built through the
Snakemake workflow with the shipped scene file (captures.py's configuration: the fox read from
../shared/data/fox), then `srfpipe train` runs on them with the scene's settings and `device: auto`:

1. throughput: a short run at 4096 and at 65536 rays a step (`train.rays_per_batch`), steps/s and
   rays/s from srf.zarr's `iterations_done` / `train_seconds` (training steps only);
2. quality against time: one run per budget (15, 30, 60, 120 s of training; the learning rate
   follows each run's own budget), scored by `srfpipe evaluate` on the held-out views: PSNR,
   object-pixel PSNR, mIoU against ground truth (the orchard, the plant) or the masks;
3. `preset: paper` (the hash grid, 500k iterations): its steps/s over a short run and the hours
   its 500k iterations would take at that rate;
4. `profile` (`--profile-steps`, 300 by default on CUDA): torch.profiler over that many orchard steps after the
   first `--profile-after` (2000: the CUDA graph's capacities have settled), the
   operations and kernels that take the most time a step, and the host's waits and copies a step;
5. `interpolation_ms` (`--kernel-repeats`, 20 by default on CUDA): one forward and backward of each way to
   read the grids (`embedding_bag`, `grid_sample`, the gather) at the orchard's and the paper preset's sizes.

`orchard_seconds_to_28_5_db` is the first budget whose held-out PSNR reaches 28.5 dB, linearly
interpolated between budgets (null when none does).

    python benchmarks/gpu.py [--quick] [--scenes orchard fox plant] [--workdir DIR]
                             [--budgets 15 30 60 120] [--throughput-seconds 30] [--build-only | --no-build]

How it is run on a GPU machine: the project installed with `pip install -e .` over the CUDA torch the
machine has (zarr and the other wheels carried where missing), then `python benchmarks/gpu.py`
from the repository root with ../shared beside it. A GPU machine without Snakemake (or without
../shared) takes the artifacts from another machine: `python benchmarks/gpu.py --build-only` there
builds images.zarr and labels.zarr through the workflow into the work directory, which travels with
the repository, and `--no-build` on the GPU machine trains on them. The committed gpu.json was run
that way (see its `machine.command`). `--quick` (the orchard only, budgets 15 and 30 s, throughput
runs of 10 s, paper preset 10 s) is what runs on a CPU to check the script.

Before the curves, `cuda_vs_cpu` checks that CUDA is correct: the orchard trained for `--agreement-steps` fixed
steps (seed 0) and evaluated; that srf.zarr distilled, baked and rendered on CUDA and on the CPU and compared;
`--cpu-reference` on a CPU machine trains and evaluates the same run on the CPU, and `heldout_psnr_gap_db` is
the difference (the tolerance is 0.5 dB).

`benchmarks/gpu_lease.sh` does all of this for one lease: `prepare` here (inputs and wheels into
benchmarks/work/gpu-lease), `run SECONDS` there. On this project's lent GPU machines (no Snakemake, no network) the missing wheels (zarr, numcodecs, donfig,
google-crc32c, jsonschema and its three dependencies) were installed with `pip install --no-deps --target`, the
repository put on PYTHONPATH, and an `srfpipe` script that runs `python3 -m srfpipe.cli` put on PATH.

A run of some scenes keeps the other scenes' entries of an earlier gpu.json, marked
`measured_in_an_earlier_run`; the headline keys come from the orchard's run (and the first scene's
throughput) when this run measured them.

Writes benchmarks/results/gpu.json (`gpu_quick.json`): device, the per-scene curves, steps_per_s_4096,
steps_per_s_65536, rays_per_s_best, paper_preset_steps_per_s, paper_preset_hours,
orchard_seconds_to_28_5_db, and the machine and configuration used.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import yaml

from captures import scene_configs
import sys

from common import (REPO, earlier_measurements, machine_info, result_path, run_command, run_workflow, write_result,
                    write_workdir)

BUDGETS = (15, 30, 60, 120)
QUICK_BUDGETS = (15, 30)
THROUGHPUT_RAYS = (4096, 65536)
PAPER_ITERATIONS = 500_000
TARGET_PSNR = 28.5


def device_name() -> str:
    import torch

    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"


def train(workdir: Path, scene: str, name: str, options: dict) -> dict:
    """`srfpipe train` on the scene's images and labels with `options` over its train section; what srf.zarr says,
    and the command's wall seconds (`process_seconds`: start-up, data loading and the training loop), which show
    whether the training clock counted the device's work (2026-11-28: a 30-s budget's loop took 42 s)."""
    from srfpipe.artifacts import read_provenance

    results = workdir / "results" / scene
    out = workdir / "runs" / scene / f"{name}.zarr"
    if out.exists():
        shutil.rmtree(out)
    shutil.rmtree(out.with_name(f"{name}.ckpt"), ignore_errors=True)
    wall = run_command(["srfpipe", "train", "--images", str(results / "images.zarr"), "--labels", str(results / "labels.zarr"),
                 "--out", str(out), "--scene", str(workdir / "config" / "scenes" / f"{scene}.yaml"),
                 "--options", json.dumps({"device": "auto", **options})],
                log=workdir / "logs" / scene / f"gpu-{name}.log")
    info = read_provenance(out)
    steps, seconds = int(info["iterations_done"]), float(info["train_seconds"])
    return {"path": out, "steps": steps, "train_seconds": seconds, "steps_per_s": steps / max(seconds, 1e-9),
            "device": info.get("device"), "process_seconds": wall}


def evaluate(workdir: Path, scene: str, run: dict) -> dict:
    results = workdir / "results" / scene
    out = run["path"].with_suffix(".eval")
    shutil.rmtree(out, ignore_errors=True)
    run_command(["srfpipe", "evaluate", "--images", str(results / "images.zarr"), "--labels",
                 str(results / "labels.zarr"), "--srf", str(run["path"]), "--out", str(out),
                 "--scene", str(workdir / "config" / "scenes" / f"{scene}.yaml")],
                log=workdir / "logs" / scene / "gpu-evaluate.log")
    metrics = json.loads((out / "metrics.json").read_text())
    return {"psnr": metrics.get("psnr"), "psnr_object": metrics.get("psnr_object"),
            "miou": metrics.get("miou_gt", metrics.get("miou")), "ssim": metrics.get("ssim")}


def agreement(workdir: Path, steps: int, device: str, reference_only: bool = False) -> dict:
    """The same orchard run (seed 0, `steps` fixed steps) trained and evaluated on `device`; then that
    srf.zarr distilled, baked (srfpipe.sim.baked) and rendered on `device` and on the CPU, compared.
    With `reference_only`: train and evaluate only (the CPU reference, on a CPU machine)."""
    import time

    import numpy as np
    import zarr

    result: dict = {"device": device, "steps": steps}
    start = time.perf_counter()
    run = train(workdir, "orchard", f"agree-{device}-{steps}", {"device": device, "iterations": steps, "time_budget": 0,
                                                               "eval_every": 0, "snapshot_seconds": [], "checkpoint_every": 0})
    result["train"] = {k: v for k, v in run.items() if k != "path"}
    result["heldout"] = evaluate(workdir, "orchard", run)
    result["train_evaluate_wall_seconds"] = time.perf_counter() - start
    if reference_only:
        return result

    from srfpipe.artifacts import meta
    from srfpipe.cameras import look_at
    from srfpipe.occupancy.grid import VoxelGrid
    from srfpipe.sim.baked import bake
    from srfpipe.srf.metrics import psnr
    from srfpipe.srf.query import SemanticRadianceField

    devices = (device, "cpu")
    caches, fields, baked, renders, walls = {}, {}, {}, {}, {}
    for dev in devices:
        cache = run["path"].with_name(f"occupancy-{dev}.zarr")
        shutil.rmtree(cache, ignore_errors=True)
        start = time.perf_counter()
        run_command(["srfpipe", "distill", "--srf", str(run["path"]), "--out", str(cache), "--no-progress",
                     "--scene", str(workdir / "config" / "scenes" / "orchard.yaml"), "--options", json.dumps({"device": dev})],
                    log=workdir / "logs" / "orchard" / f"gpu-distill-{dev}.log")
        walls[f"distill_{dev}"] = time.perf_counter() - start
        caches[dev] = zarr.open_group(str(cache), mode="r")
    grid = VoxelGrid.from_attrs(meta(caches[device])["grid"])
    probability = np.asarray(caches[device]["probability"][...])
    for dev in devices:
        fields[dev] = SemanticRadianceField.load(run["path"], device=dev)
        start = time.perf_counter()
        baked[dev] = bake(fields[dev], grid, probability)
        walls[f"bake_{dev}"] = time.perf_counter() - start
    lo, hi = fields["cpu"].bounds_world
    centre, extent = (lo + hi) / 2, float(np.max(hi - lo))
    pose = look_at(centre + np.array([1.2, 0.8, 0.6]) * extent, centre)
    for dev in devices:
        start = time.perf_counter()
        renders[dev] = fields[dev].render(pose, np.array([120.0, 120.0, 80.0, 60.0]), 160, 120)
        walls[f"render_{dev}"] = time.perf_counter() - start

    result["distill_compare"] = {}
    for key in ("occupancy", "class_occupancy", "probability"):
        on_device, on_cpu = np.asarray(caches[device][key][...]), np.asarray(caches["cpu"][key][...])
        result["distill_compare"][key] = {"differ_fraction": float(np.mean(on_device != on_cpu)),
                                          "count_device": int(np.count_nonzero(on_device)),
                                          "count_cpu": int(np.count_nonzero(on_cpu))}
    dense_d, dense_c = baked[device]["density"], baked["cpu"]["density"]
    result["bake_compare"] = {
        "density_rel_err_p99": float(np.quantile(np.abs(dense_d - dense_c) / np.maximum(dense_c, 1e-3), 0.99)),
        "occupied_device": int((dense_d > 0).sum()), "occupied_cpu": int((dense_c > 0).sum()),
        "rgb_max_abs": int(np.abs(baked[device]["rgb"].astype(int) - baked["cpu"]["rgb"].astype(int)).max())}
    result["render_compare"] = {
        "rgb_psnr_device_vs_cpu": psnr(renders[device]["rgb"], renders["cpu"]["rgb"]),
        "semantic_max_abs": float(np.abs(renders[device]["semantic"] - renders["cpu"]["semantic"]).max())}
    result["wall_seconds"] = walls
    return result


def profile_training(workdir: Path, steps: int, after: int = 0) -> dict:
    """torch.profiler over `srfpipe train` of the orchard, in this process: `steps` steps after the
    first `after` (the first steps are not the run's: on CUDA the graph's capacities start at 128
    samples a ray and shrink as the occupancy grid empties, so a profile of steps 0-300 weighed the
    start four times over). The operations and kernels that take the most time a step (device time
    on CUDA, else CPU time) and how often the host waits for the device or copies to or from it."""
    import time

    import torch
    from torch.profiler import ProfilerActivity, profile, schedule

    from srfpipe import cli
    from srfpipe.srf import trainer

    results, out = workdir / "results" / "orchard", workdir / "runs" / "orchard" / "profile.zarr"
    shutil.rmtree(out, ignore_errors=True)
    shutil.rmtree(out.with_name("profile.ckpt"), ignore_errors=True)
    cuda = torch.cuda.is_available()
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    start = time.perf_counter()
    # the profiler's schedule advances once a training step: the loop's own step function, wrapped
    step_function = trainer.training_step
    with profile(activities=activities, schedule=schedule(wait=after, warmup=min(after, 5), active=steps, repeat=1)) as prof:
        def profiled_step(run, step):
            result = step_function(run, step)
            prof.step()
            return result

        trainer.training_step = profiled_step
        try:
            cli.main(["train", "--images", str(results / "images.zarr"), "--labels", str(results / "labels.zarr"),
                      "--out", str(out), "--scene", str(workdir / "config" / "scenes" / "orchard.yaml"),
                      "--options", json.dumps({"device": "auto", "iterations": after + min(after, 5) + steps + 1,
                                               "time_budget": 0, "eval_every": 0, "snapshot_seconds": [],
                                               "checkpoint_every": 0})])
        finally:
            trainer.training_step = step_function
    wall = time.perf_counter() - start
    events = prof.key_averages()
    own = (lambda e: e.self_device_time_total) if cuda else (lambda e: e.self_cpu_time_total)
    top = sorted(events, key=own, reverse=True)[:10]
    calls = {e.key: e.count for e in events}
    return {"steps": steps, "after_steps": after, "wall_seconds_profiled": wall, "time": "device" if cuda else "cpu",
            "per_step_ms": {e.key[:80]: own(e) / 1000.0 / steps for e in top},
            "calls_per_step": {e.key[:80]: e.count / steps for e in top},
            "total_ms_per_step": sum(own(e) for e in events) / 1000.0 / steps,
            "host_waits_per_step": calls.get("cudaStreamSynchronize", 0) / steps,
            "host_copies_per_step": calls.get("cudaMemcpyAsync", 0) / steps}


def interpolation_timings(repeats: int, rays: int = 4096, samples: int = 32) -> dict:
    """Milliseconds of one forward and backward of each way to read the grids, on the device torch picks, at
    `samples` points along each of `rays` rays (as a training batch has them: a ray's points share cells, so
    the backward's atomic adds collide; uniformly random points would hide that). The dense grids of the
    orchard's default field (96^3 x 16 colour features and 96^3 x 1 log-density): the corner sum by
    `embedding_bag`, by `grid_sample` with the corner sum's backward (`index_add_`; srfpipe's path on CUDA), and
    by `grid_sample` with its own backward; the paper preset's hash grid (16 levels x 2 features, 2^19 rows a
    level): its forward by the row gather and batched product and by `embedding_bag`, and a whole pass."""
    import time

    import torch

    from srfpipe.device import choose_device
    from srfpipe.srf import encodings

    device = choose_device("auto")
    generator = torch.Generator().manual_seed(0)

    def timed(function) -> float:
        for _ in range(3):
            function()
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        for _ in range(repeats):
            function()
        if device.type == "cuda":
            torch.cuda.synchronize()
        return (time.perf_counter() - start) / repeats * 1000.0

    # rays from a sphere of radius 0.9 towards points near the centre, sampled a cell apart (1/48 of [-1, 1])
    start = torch.nn.functional.normalize(torch.randn(rays, 3, generator=generator), dim=-1) * 0.9
    target = (torch.rand(rays, 3, generator=generator) - 0.5) * 0.6
    direction = torch.nn.functional.normalize(target - start, dim=-1)
    t = 0.6 + torch.arange(samples) / 48.0
    u = (start[:, None, :] + t[None, :, None] * direction[:, None, :]).reshape(-1, 3).clamp(-1, 1).to(device)
    result: dict = {"device": device_name(), "rays": rays, "samples_per_ray": samples, "repeats": repeats}
    for features in (16, 1):
        grid = encodings.DenseGrid((96, 96, 96), features).to(device)
        pos = (u + 1.0) * 0.5 * (grid._res - 1.0)
        origin = torch.minimum(pos.floor(), grid._res - 2.0)
        index = (origin.long() * grid._strides).sum(-1, keepdim=True) + grid._corner_offsets
        weights = encodings._axis_weights(pos - origin)
        volume = (grid.resolution, u)
        result[f"dense_96_f{features}"] = {
            "embedding_bag": timed(lambda: encodings.interpolated_gather(grid.table, index, weights).sum().backward()),
            "grid_sample_forward": timed(
                lambda: encodings.interpolated_gather(grid.table, index, weights, volume).sum().backward()),
            "grid_sample": timed(lambda: encodings.sampled_volume(grid.table, grid.resolution, u).sum().backward())}
    hashed = encodings.HashGrid(levels=16, features_per_level=2, log2_table_size=19).to(device)
    index = torch.randint(0, hashed.table.shape[0], (u.shape[0] * 16, 8), generator=generator).to(device)
    weights = torch.rand(u.shape[0] * 16, 8, generator=generator).to(device)
    result["hash_16x2_forward"] = {
        "gather": timed(lambda: encodings.weighted_rows(hashed.table, index, weights, fused=False)),
        "embedding_bag": timed(lambda: encodings.weighted_rows(hashed.table, index, weights, fused=True))}
    result["hash_16x2"] = {"embedding_bag": timed(lambda: hashed(u).sum().backward())}
    return result


def with_agreement_gap(report: dict) -> dict:
    """`cuda_vs_cpu.heldout_psnr_gap_db`: |CUDA - CPU| held-out PSNR of the agreement run, when both
    ran the same number of steps (the issue's tolerance: 0.5 dB)."""
    check = report.get("cuda_vs_cpu", {})
    reference = check.get("cpu_reference")
    if reference and check.get("heldout") and reference.get("steps") == check.get("steps"):
        check["heldout_psnr_gap_db"] = abs(check["heldout"]["psnr"] - reference["heldout"]["psnr"])
    return report


def seconds_to(curve: list[dict], target: float) -> float | None:
    """First budget at which the PSNR curve reaches `target`, interpolated linearly between budgets."""
    previous = None
    for point in curve:
        if point["psnr"] is not None and point["psnr"] >= target:
            if previous is None or previous["psnr"] is None:
                return float(point["budget_seconds"])
            fraction = (target - previous["psnr"]) / (point["psnr"] - previous["psnr"])
            return float(previous["budget_seconds"] + fraction * (point["budget_seconds"] - previous["budget_seconds"]))
        previous = point
    return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the orchard only, budgets 15 and 30 s, short throughput runs")
    parser.add_argument("--scenes", nargs="+", default=None, choices=["orchard", "fox", "plant"])
    parser.add_argument("--workdir", type=Path, default=REPO / "benchmarks" / "work" / "gpu")
    parser.add_argument("--budgets", nargs="+", type=int, default=None, help="training budgets in seconds (default 15 30 60 120)")
    parser.add_argument("--throughput-seconds", type=int, default=None,
                        help="length of each throughput run (default 30, quick 10; 0: none)")
    parser.add_argument("--agreement-steps", type=int, default=1500,
                        help="steps of the CUDA-against-CPU check on the orchard (0: none)")
    parser.add_argument("--profile-steps", type=int, default=None,
                        help="profile this many orchard training steps (default 300 on CUDA, none on the CPU; 0: none)")
    parser.add_argument("--profile-after", type=int, default=2000,
                        help="steps before the profiled ones (default 2000: the capacities have settled)")
    parser.add_argument("--kernel-repeats", type=int, default=None,
                        help="time each way to read the grids over this many passes (default 20 on CUDA, none on the CPU; 0: none)")
    parser.add_argument("--cpu-reference", action="store_true",
                        help="on a CPU machine: train and evaluate the agreement run on the CPU and add it to gpu.json")
    build = parser.add_mutually_exclusive_group()
    build.add_argument("--build-only", action="store_true", help="build images.zarr and labels.zarr through the workflow, then stop")
    build.add_argument("--no-build", action="store_true", help="train on the work directory's artifacts (built elsewhere with --build-only)")
    args = parser.parse_args()
    names = args.scenes or (["orchard"] if args.quick else ["orchard", "fox", "plant"])
    budgets = tuple(args.budgets or (QUICK_BUDGETS if args.quick else BUDGETS))
    short = args.throughput_seconds if args.throughput_seconds is not None else (10 if args.quick else 30)

    scenes = scene_configs(names, quick=False)
    if args.no_build:
        missing = [str(args.workdir / "results" / n / a) for n in names for a in ("images.zarr", "labels.zarr")
                   if not (args.workdir / "results" / n / a).is_dir()]
        if missing:
            parser.error("--no-build: not built (run --build-only first): " + ", ".join(missing))
    else:
        write_workdir(args.workdir, scenes, "labels")
        run_workflow(args.workdir, [f"results/{name}/labels.zarr" for name in names], log=args.workdir / "snakemake.log")
        if args.build_only:
            return 0

    path = result_path("gpu", args.quick)
    previous = json.loads(path.read_text()) if path.exists() else {}
    if args.cpu_reference:
        reference = agreement(args.workdir, args.agreement_steps, "cpu", reference_only=True)
        reference["machine"] = machine_info(quick=args.quick, command=" ".join(sys.argv))
        previous.setdefault("cuda_vs_cpu", {})["cpu_reference"] = reference
        write_result(path, with_agreement_gap(previous))
        return 0
    reference = previous.get("cuda_vs_cpu", {}).get("cpu_reference")
    if previous.get("device") != device_name():
        # another device's speeds and curves are not merged; its correctness check is kept, named by its device
        check = previous.get("cuda_vs_cpu")
        previous = {"cuda_vs_cpu": {"measured_on": previous.get("device"), **check}} if check else {}
    report: dict = {"device": device_name(), "budgets_seconds": list(budgets), "scenes": {}}
    repeats = args.kernel_repeats if args.kernel_repeats is not None else (20 if device_name() != "cpu" else 0)
    if repeats:
        report["interpolation_ms"] = interpolation_timings(repeats)
        print(f"reading the grids (ms a forward and backward): {json.dumps(report['interpolation_ms'])}", flush=True)
    elif previous.get("interpolation_ms"):
        report["interpolation_ms"] = dict(previous["interpolation_ms"], measured_in_an_earlier_run=True)
    if args.agreement_steps and "orchard" in names and device_name() != "cpu":
        report["cuda_vs_cpu"] = agreement(args.workdir, args.agreement_steps, "cuda")
        print(f"CUDA against the CPU: {json.dumps(report['cuda_vs_cpu'], default=str)}", flush=True)
    elif previous.get("cuda_vs_cpu"):
        report["cuda_vs_cpu"] = previous["cuda_vs_cpu"]
    if reference is not None and "cuda_vs_cpu" in report:
        report["cuda_vs_cpu"]["cpu_reference"] = reference
    for name in names:
        entry: dict = {"throughput": {}, "curve": []}
        earlier = previous.get("scenes", {}).get(name, {})
        for rays in THROUGHPUT_RAYS if short > 0 else ():
            run = train(args.workdir, name, f"rays-{rays}", {"rays_per_batch": rays, "time_budget": short,
                                                            "eval_every": 0, "snapshot_seconds": []})
            entry["throughput"][str(rays)] = {"steps_per_s": run["steps_per_s"], "rays_per_s": run["steps_per_s"] * rays,
                                              "steps": run["steps"], "device": run["device"],
                                              "process_seconds": run["process_seconds"]}
            print(f"{name}: {rays} rays a step: {run['steps_per_s']:.1f} steps/s on {run['device']}", flush=True)
        for budget in budgets:
            run = train(args.workdir, name, f"budget-{budget}", {"time_budget": budget})
            point = {"budget_seconds": budget, "steps": run["steps"], "process_seconds": run["process_seconds"],
                     **evaluate(args.workdir, name, run)}
            entry["curve"].append(point)
            print(f"{name}: {budget} s: {point}", flush=True)
            # a run cut short (a lease ending) keeps what it measured
            write_result(result_path("gpu_partial", args.quick), {**report, "scenes": {**report["scenes"], name: entry}})
        # an earlier run on this device keeps the budgets (and throughputs) this run did not measure
        entry["curve"] = sorted(entry["curve"] + [dict(p, measured_in_an_earlier_run=True) for p in earlier.get("curve", [])
                                                  if p["budget_seconds"] not in budgets], key=lambda p: p["budget_seconds"])
        for rays, value in earlier.get("throughput", {}).items():
            entry["throughput"].setdefault(rays, dict(value, measured_in_an_earlier_run=True))
        report["scenes"][name] = entry

    report["rays_per_s_best"] = max((t["rays_per_s"] for s in report["scenes"].values() for t in s["throughput"].values()),
                                    default=None)
    if "orchard" in report["scenes"]:
        orchard = report["scenes"]["orchard"]
        presets = yaml.safe_load((REPO / "workflow" / "schemas" / "presets.yaml").read_text())
        paper = train(args.workdir, "orchard", "paper", {**presets["paper"].get("train", {}), "time_budget": short or 10,
                                                         "eval_every": 0, "snapshot_seconds": []})
        report.update({
            "steps_per_s_4096": orchard["throughput"]["4096"]["steps_per_s"],
            "steps_per_s_65536": orchard["throughput"]["65536"]["steps_per_s"],
            "paper_preset_steps_per_s": paper["steps_per_s"],
            "paper_preset_hours": PAPER_ITERATIONS / max(paper["steps_per_s"], 1e-9) / 3600.0,
            "paper_preset_process_seconds": paper["process_seconds"],
            "orchard_seconds_to_28_5_db": seconds_to(orchard["curve"], TARGET_PSNR),
        })
    elif previous:
        # the orchard's headline keys from an earlier run on the same device
        for key in ("orchard_seconds_to_28_5_db", "steps_per_s_4096", "steps_per_s_65536", "paper_preset_steps_per_s",
                    "paper_preset_hours"):
            report[key] = previous.get(key)
        report["rays_per_s_best"] = max(report["rays_per_s_best"] or 0.0, previous.get("rays_per_s_best") or 0.0)
    if previous:
        report["scenes"].update(earlier_measurements(previous.get("scenes", {}), report["scenes"]))
    report["budgets_seconds"] = sorted({p["budget_seconds"] for s in report["scenes"].values() for p in s["curve"]})
    profile_steps = args.profile_steps if args.profile_steps is not None else (300 if device_name() != "cpu" else 0)
    if profile_steps and "orchard" in names:
        report["profile"] = profile_training(args.workdir, profile_steps, args.profile_after)
    elif previous.get("profile"):
        report["profile"] = dict(previous["profile"], measured_in_an_earlier_run=True)
    report.update({"machine": machine_info(quick=args.quick, device=device_name(), command=" ".join(sys.argv)),
                   "scene_configs": scenes})
    write_result(path, with_agreement_gap(report))

    print(f"device: {report['device']}")
    print(f"{'scene':8} " + " ".join(f"{b:>5d} s" for b in report["budgets_seconds"]) + "   (held-out PSNR)")
    for name, entry in report["scenes"].items():
        print(f"{name:8} " + " ".join(f"{p['psnr']:7.2f}" for p in entry["curve"]))
    if report.get("steps_per_s_4096") is not None:
        print(f"steps/s at 4096 rays {report['steps_per_s_4096']:.1f}, at 65536 {report['steps_per_s_65536']:.1f}; "
              f"best {report['rays_per_s_best'] / 1e6:.2f} M rays/s; paper preset {report['paper_preset_hours']:.1f} h")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

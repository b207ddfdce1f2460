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
   its 500k iterations would take at that rate.

`orchard_seconds_to_28_5_db` is the first budget whose held-out PSNR reaches 28.5 dB, linearly
interpolated between budgets (null when none does).

    python benchmarks/gpu.py [--quick] [--scenes orchard fox plant] [--workdir DIR]

How it is run on a GPU machine: the project installed with `pip install -e .` over the CUDA torch the
machine has (zarr and the other wheels carried where missing), then `python benchmarks/gpu.py`
from the repository root with ../shared beside it. `--quick` (the orchard only, budgets 15 and 30 s,
throughput runs of 10 s, paper preset 10 s) is what runs on a CPU to check the script.

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
from common import REPO, machine_info, result_path, run_command, run_workflow, write_result, write_workdir

BUDGETS = (15, 30, 60, 120)
QUICK_BUDGETS = (15, 30)
THROUGHPUT_RAYS = (4096, 65536)
PAPER_ITERATIONS = 500_000
TARGET_PSNR = 28.5


def device_name() -> str:
    import torch

    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu"


def train(workdir: Path, scene: str, name: str, options: dict) -> dict:
    """`srfpipe train` on the scene's images and labels with `options` over its train section; what srf.zarr says."""
    from srfpipe.artifacts import read_provenance

    results = workdir / "results" / scene
    out = workdir / "runs" / scene / f"{name}.zarr"
    if out.exists():
        shutil.rmtree(out)
    shutil.rmtree(out.with_name(f"{name}.ckpt"), ignore_errors=True)
    run_command(["srfpipe", "train", "--images", str(results / "images.zarr"), "--labels", str(results / "labels.zarr"),
                 "--out", str(out), "--scene", str(workdir / "config" / "scenes" / f"{scene}.yaml"),
                 "--options", json.dumps({"device": "auto", **options})],
                log=workdir / "logs" / scene / f"gpu-{name}.log")
    info = read_provenance(out)
    steps, seconds = int(info["iterations_done"]), float(info["train_seconds"])
    return {"path": out, "steps": steps, "train_seconds": seconds, "steps_per_s": steps / max(seconds, 1e-9),
            "device": info.get("device")}


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
    args = parser.parse_args()
    names = args.scenes or (["orchard"] if args.quick else ["orchard", "fox", "plant"])
    budgets = QUICK_BUDGETS if args.quick else BUDGETS
    short = 10 if args.quick else 30  # seconds of each throughput run

    scenes = scene_configs(names, quick=False)
    write_workdir(args.workdir, scenes, "labels")
    run_workflow(args.workdir, [f"results/{name}/labels.zarr" for name in names], log=args.workdir / "snakemake.log")

    report: dict = {"device": device_name(), "budgets_seconds": list(budgets), "scenes": {}}
    for name in names:
        entry: dict = {"throughput": {}, "curve": []}
        for rays in THROUGHPUT_RAYS:
            run = train(args.workdir, name, f"rays-{rays}", {"rays_per_batch": rays, "time_budget": short,
                                                            "eval_every": 0, "snapshot_seconds": []})
            entry["throughput"][str(rays)] = {"steps_per_s": run["steps_per_s"], "rays_per_s": run["steps_per_s"] * rays,
                                              "steps": run["steps"], "device": run["device"]}
            print(f"{name}: {rays} rays a step: {run['steps_per_s']:.1f} steps/s on {run['device']}")
        for budget in budgets:
            run = train(args.workdir, name, f"budget-{budget}", {"time_budget": budget})
            point = {"budget_seconds": budget, "steps": run["steps"], **evaluate(args.workdir, name, run)}
            entry["curve"].append(point)
            print(f"{name}: {budget} s: {point}")
        report["scenes"][name] = entry

    presets = yaml.safe_load((REPO / "workflow" / "schemas" / "presets.yaml").read_text())
    paper = train(args.workdir, names[0], "paper", {**presets["paper"].get("train", {}), "time_budget": short,
                                                    "eval_every": 0, "snapshot_seconds": []})
    throughput = [t for s in report["scenes"].values() for t in s["throughput"].values()]
    orchard = report["scenes"].get("orchard", {})
    report.update({
        "steps_per_s_4096": report["scenes"][names[0]]["throughput"]["4096"]["steps_per_s"],
        "steps_per_s_65536": report["scenes"][names[0]]["throughput"]["65536"]["steps_per_s"],
        "rays_per_s_best": max(t["rays_per_s"] for t in throughput),
        "paper_preset_steps_per_s": paper["steps_per_s"],
        "paper_preset_hours": PAPER_ITERATIONS / max(paper["steps_per_s"], 1e-9) / 3600.0,
        "orchard_seconds_to_28_5_db": seconds_to(orchard.get("curve", []), TARGET_PSNR) if orchard else None,
        "machine": machine_info(quick=args.quick, device=device_name()),
        "scene_configs": scenes,
    })
    write_result(result_path("gpu", args.quick), report)

    print(f"device: {report['device']}")
    print(f"{'scene':8} " + " ".join(f"{b:>5d} s" for b in budgets) + "   (held-out PSNR)")
    for name, entry in report["scenes"].items():
        print(f"{name:8} " + " ".join(f"{p['psnr']:7.2f}" for p in entry["curve"]))
    print(f"steps/s at 4096 rays {report['steps_per_s_4096']:.1f}, at 65536 {report['steps_per_s_65536']:.1f}; "
          f"best {report['rays_per_s_best'] / 1e6:.2f} M rays/s; paper preset {report['paper_preset_hours']:.1f} h")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

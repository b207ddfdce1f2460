"""Benchmark: the pipeline's defaults on captures unlike the orchard (issue "any capture").

Three scenes, each built through the Snakemake workflow with the shipped scene file and otherwise
default settings (10 minutes of training on 2 cores, every 8th view held out):

* fox     config/scenes/fox.yaml: a real phone capture (../shared/data/fox), zero classes;
* plant   config/scenes/plant.yaml: the built-in thin plant, millimetres, 18 far narrow views;
* orchard config/scenes/orchard.yaml: the built-in orchard, which must not get worse.

    python benchmarks/captures.py [--quick] [--workdir DIR] [--scenes fox plant orchard]

A scene whose images shrink by another factor than 4 (images.downscale null keeps the plant's 18
views at 256 px) is also measured on its held-out views at factor 4, the resolution earlier runs
measured at: `reference` in its entry; the plant's thin_* keys are those.

Writes benchmarks/results/captures.json and captures.png (per scene, the first held-out view:
render | semantics | depth). `--quick`: 60 s of training and no COLMAP refinement of the fox.
"""

from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

import numpy as np
import yaml

from common import (REPO, earlier_measurements, machine_info, merge, renamed_paths, result_path, rule_seconds, run_command,
                    run_workflow, write_result, write_workdir)

FOX = (REPO / ".." / "shared" / "data" / "fox").resolve()
# The factor every captures.json measured at before images.downscale came from the capture: a scene
# whose images now shrink by another factor is measured again on the same held-out views at this
# one, since PSNR depends on the pixel size (the same field scores lower on finer pixels).
REFERENCE_DOWNSCALE = 4
REFERENCE_KEYS = ("psnr", "psnr_object", "ssim", "miou_gt_classes", "floater_fraction", "views")


def scene_configs(names: list[str], quick: bool) -> dict[str, dict]:
    scenes = {}
    for name in names:
        scene = yaml.safe_load((REPO / "config" / "scenes" / f"{name}.yaml").read_text()) or {}
        if name == "fox":
            scene["source"]["path"] = str(FOX)
            if quick:
                scene.setdefault("poses", {})["refine"] = "none"
        if quick:
            scene.setdefault("train", {})["time_budget"] = 60
        scenes[name] = scene
    return scenes


def box_volume(box) -> float:
    box = np.asarray(box, dtype=np.float64)
    return float(np.prod(box[1] - box[0]))


def scene_report(results: Path, workdir: Path, name: str) -> dict:
    """What the issue asks about one scene, read from its artifacts."""
    from srfpipe.artifacts import read_provenance

    report: dict = {}
    metrics_file = results / name / "eval" / "metrics.json"
    if metrics_file.exists():
        metrics = json.loads(metrics_file.read_text())
        for key in ("psnr", "psnr_object", "ssim", "miou", "miou_gt", "miou_gt_classes", "iou_gt",
                    "floater_fraction", "significant_samples_per_ray", "views"):
            if key in metrics:
                report[key] = metrics[key]
    labels = results / name / "labels.zarr"
    if labels.exists():
        info = read_provenance(labels)
        report["bounds"] = {"box": info.get("bounds_world"), "source": info.get("bounds_source"),
                            "poses_box": info.get("bounds_poses"), "hull": info.get("bounds_hull")}
        truth_file = results / name / "capture" / "ground_truth" / "scene.json"
        # a generated capture that knows its object's box (the plant): how tight the model box is
        truth = json.loads(truth_file.read_text()).get("object_bounds_world") if truth_file.exists() else None
        if truth and report["bounds"]["box"]:
            report["bounds"]["ratio_to_object"] = box_volume(report["bounds"]["box"]) / box_volume(truth)
            if report["bounds"]["poses_box"]:
                report["bounds"]["poses_ratio_to_object"] = box_volume(report["bounds"]["poses_box"]) / box_volume(truth)
    srf = results / name / "srf.zarr"
    if srf.exists():
        info = read_provenance(srf)
        report["train_seconds"] = info.get("train_seconds")
        report["steps"] = info.get("iterations_done")
        report["appearance_dim"] = info.get("config", {}).get("appearance_dim")
        report["grid_resolution"] = info.get("model_config", {}).get("inner", {}).get("resolution")
    occupancy = results / name / "occupancy.zarr"
    report["distill_ok"] = occupancy.exists()
    if occupancy.exists():
        info = read_provenance(occupancy)
        report["occupancy"] = {"grid": info.get("grid"), "resolution": info.get("resolution"),
                               "occupied_voxels": (info.get("counts") or {}).get("occupied_voxels")}
    report["rule_seconds"] = {rule: rule_seconds(workdir, name, rule)
                              for rule in ("poses", "downscale", "segment_*", "composite", "train", "evaluate", "distill")}
    return report


def reference_scenes(results: Path, scenes: dict[str, dict]) -> dict[str, dict]:
    """`<name>-reference`: each scene whose images.zarr has another factor than REFERENCE_DOWNSCALE,
    at that factor (its own capture and labels: paths into its results folder follow the name)."""
    from srfpipe.artifacts import read_provenance

    references = {}
    for name, scene in scenes.items():
        images = results / name / "images.zarr"
        if images.exists() and read_provenance(images).get("downscale") != REFERENCE_DOWNSCALE:
            reference = merge(scene, {"images": {"downscale": REFERENCE_DOWNSCALE}})
            references[f"{name}-reference"] = renamed_paths(reference, f"results/{name}/", f"results/{name}-reference/")
    return references


def reference_report(workdir: Path, name: str) -> dict:
    """The scene's field on its reference scene's held-out views (`srfpipe evaluate`, the rule's
    stage, into results/<name>/eval-reference)."""
    results, reference = workdir / "results" / name, workdir / "results" / f"{name}-reference"
    out = results / "eval-reference"
    run_command(["srfpipe", "evaluate", "--images", str(reference / "images.zarr"), "--labels",
                 str(reference / "labels.zarr"), "--srf", str(results / "srf.zarr"), "--out", str(out),
                 "--scene", str(workdir / "config" / "scenes" / f"{name}.yaml")],
                log=workdir / "logs" / name / "evaluate-reference.log")
    metrics = json.loads((out / "metrics.json").read_text())
    return {"downscale": REFERENCE_DOWNSCALE, **{k: metrics[k] for k in REFERENCE_KEYS if k in metrics}}


def montage(results: Path, names: list[str], path: Path) -> None:
    """First held-out render of each scene, top row only (render | semantics | depth), stacked."""
    import cv2

    rows = []
    for name in names:
        renders = sorted((results / name / "eval" / "renders").glob("*.png"))
        if not renders:
            continue
        figure = cv2.imread(str(renders[0]))
        top = figure[: figure.shape[0] // 2]
        scale = 240 / top.shape[0]
        top = cv2.resize(top, (int(top.shape[1] * scale), 240), interpolation=cv2.INTER_AREA)
        cv2.putText(top, name, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
        rows.append(top)
    if not rows:
        return
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
    cv2.imwrite(str(path), np.concatenate(rows, axis=0))
    print(f"wrote {path}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="60 s of training, no COLMAP refinement")
    parser.add_argument("--workdir", type=Path, default=REPO / "benchmarks" / "work" / "captures")
    parser.add_argument("--scenes", nargs="+", default=["fox", "plant", "orchard"])
    parser.add_argument("--snakemake-args", nargs=argparse.REMAINDER, default=[],
                        help="more Snakemake arguments (last), e.g. --rerun-triggers mtime to keep a "
                             "finished COLMAP refinement after a schema default changed")
    args = parser.parse_args()
    if "fox" in args.scenes and not (FOX / "transforms.json").exists():
        parser.error(f"{FOX}: the fox capture is not there (../shared/data/fox beside the repository)")

    scenes = scene_configs(args.scenes, args.quick)
    write_workdir(args.workdir, scenes, "occupancy")
    targets = [f"results/{name}/{artifact}" for name in scenes for artifact in ("eval", "occupancy.zarr")]
    try:  # --keep-going: one failing scene must not hide the others' numbers
        seconds = run_workflow(args.workdir, targets, log=args.workdir / "snakemake.log", extra=("--keep-going", *args.snakemake_args))
    except subprocess.CalledProcessError:
        seconds = None
        print(f"some jobs failed: see {args.workdir / 'snakemake.log'} and {args.workdir / 'logs'}")

    results = args.workdir / "results"
    per_scene = {name: scene_report(results, args.workdir, name) for name in scenes}
    if references := reference_scenes(results, scenes):
        write_workdir(args.workdir, {**scenes, **references}, "occupancy")
        run_workflow(args.workdir, [f"results/{name}/labels.zarr" for name in references],
                     log=args.workdir / "snakemake.log", extra=tuple(args.snakemake_args))
        for name in scenes:
            if f"{name}-reference" in references and (results / name / "srf.zarr").exists():
                per_scene[name]["reference"] = reference_report(args.workdir, name)
    previous_file = result_path("captures", args.quick)
    measured_now = sorted(per_scene)
    if previous_file.exists():  # a run of some scenes keeps the others' last measurement
        previous = json.loads(previous_file.read_text()).get("scenes", {})
        per_scene = {**earlier_measurements(previous, per_scene), **per_scene}
    report: dict = {"scenes": per_scene, "measured_now": measured_now, "workflow_seconds": seconds,
                    "machine": machine_info(quick=args.quick), "scene_configs": scenes}
    fox, plant, orchard = (per_scene.get(n, {}) for n in ("fox", "plant", "orchard"))
    report.update({
        "fox_psnr": fox.get("psnr"), "fox_ssim": fox.get("ssim"),
        "fox_floater_fraction": fox.get("floater_fraction"), "fox_bounds": fox.get("bounds"),
        # the plant at the reference factor when its own differs (see REFERENCE_DOWNSCALE)
        "thin_psnr_object": (plant.get("reference") or plant).get("psnr_object"),
        "thin_miou_classes": (plant.get("reference") or plant).get("miou_gt_classes"),
        "thin_psnr_object_own_resolution": plant.get("psnr_object"),
        "thin_miou_classes_own_resolution": plant.get("miou_gt_classes"),
        "orchard_psnr": orchard.get("psnr"), "orchard_miou": orchard.get("miou_gt"),
        "distill_ok": {name: s.get("distill_ok") for name, s in per_scene.items()},
        # from the plant's entry, which an earlier run's measurement keeps
        "thin_bounds_ratio": (plant.get("bounds") or {}).get("ratio_to_object"),
        "thin_bounds_ratio_poses": (plant.get("bounds") or {}).get("poses_ratio_to_object"),
    })
    # every scene in the report whose renders are in the work directory, measured now or earlier
    montage(results, list(per_scene), REPO / "benchmarks" / "results" / f"captures{'_quick' if args.quick else ''}.png")
    write_result(result_path("captures", args.quick), report)

    print(f"{'scene':8} {'psnr':>6} {'obj':>6} {'ssim':>6} {'mIoU':>6} {'floaters':>8} {'bounds':>10} distill")
    for name, s in per_scene.items():
        cells = [s.get("psnr"), s.get("psnr_object"), s.get("ssim"), s.get("miou_gt_classes") or s.get("miou_gt"),
                 s.get("floater_fraction")]
        text = " ".join(f"{v:6.3f}" if isinstance(v, float) else f"{'-':>6}" for v in cells)
        print(f"{name:8} {text} {str((s.get('bounds') or {}).get('source')):>10} {s.get('distill_ok')}")
    if report["thin_bounds_ratio"] is not None:
        print(f"thin_bounds_ratio: {report['thin_bounds_ratio']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

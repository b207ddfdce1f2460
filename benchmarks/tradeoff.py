"""Speed against accuracy: the presets and the knobs that matter, each built through the workflow.

Every setting is its own scene in the work directory (`<scene>-<setting>`: the scene's config plus
the setting's overrides), built to `eval` and `occupancy.zarr` by Snakemake, one training at a time
on the machine's cores. For each setting the report holds held-out PSNR (whole image and object
pixels), SSIM, mIoU against ground truth, training seconds and steps, the peak memory of the
training job (Snakemake's benchmark file), and the milliseconds to render a 64 x 64 frame
(RGB + semantics) from the trained field. Where the capture has ground truth, also from the setting's
occupancy.zarr:

* occupancy_iou: the mean over the cache's classes with a ground-truth mesh of their occupancy IoU
  (benchmarks/occupancy.py's voxelization and counts; per class in occupancy_iou_classes);
* fruit_count / fruit_count_gt / fruit_count_error (|count - gt|), fruit_matched, fruit_centroid_err:
  the simulator package's fruit instances (srfpipe.sim.package's find_instances on the reach
  classes, matched to apples.json / berries.json as `srfpipe package` does), without building sim/.

    python benchmarks/tradeoff.py            # presets and knobs on the orchard and the plant
    python benchmarks/tradeoff.py --quick    # a 60-second budget per setting, orchard only (< 15 min)
    python benchmarks/tradeoff.py --backfill # only the ground-truth columns of the settings already built

Writes benchmarks/results/tradeoff.json and tradeoff.png (quality against training time).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import time
from pathlib import Path

import numpy as np
import yaml

from common import REPO, machine_info, merge, renamed_paths, result_path, rule_seconds, run_command, run_workflow, write_result, write_workdir
from occupancy import MESH_CLASSES, class_accuracy

# name -> (scene overrides). Presets first, then one knob at a time against `balanced`.
SETTINGS = {
    "fast": {"preset": "fast"},
    "balanced": {"preset": "balanced"},
    "accurate": {"preset": "accurate"},
    "rays-1024": {"train": {"rays_per_batch": 1024}},
    "rays-8192": {"train": {"rays_per_batch": 8192}},
    "cells-64": {"train": {"default_cells": 64}},
    "cells-128": {"train": {"default_cells": 128}},
    "levels-3": {"train": {"grid_levels": 3, "default_cells": 192}},
    "step-0.5": {"train": {"step_ratio": 0.5}},
    "occupancy-0.001": {"train": {"occupancy_threshold": 0.001}},
    "downscale-2": {"images": {"downscale": 2}},
    "voxels-68": {"occupancy": {"voxels_across": 68}},
    "voxels-272": {"occupancy": {"voxels_across": 272}},
}
PRESETS = ("fast", "balanced", "accurate", "paper")
# a knob of the cache alone (only the occupancy section) trains nothing: it distills this setting's
# field again, so the sweep spends no training minutes on a setting whose field would be the same
CACHE_KNOB_FIELD = "balanced"
QUICK_SETTINGS = ["fast", "balanced", "rays-1024", "cells-64", "levels-3"]
QUICK_BUDGET = 60
# ground-truth meshes voxelized with the interior filled (closed) or as a surface: the orchard's as in
# benchmarks/occupancy.py, the plant's stem (capsules, like the branches) and berries closed; any other
# class as a surface
CLOSED_CLASSES = {**MESH_CLASSES, "stem": True, "berry": True}


def is_cache_knob(setting: str) -> bool:
    return set(SETTINGS.get(setting, {})) == {"occupancy"}


def setting_scenes(scenes: list[str], settings: list[str], quick: bool) -> dict[str, dict]:
    out = {}
    for scene_name in scenes:
        base = yaml.safe_load((REPO / "config" / "scenes" / f"{scene_name}.yaml").read_text()) or {}
        for setting in settings:
            scene = merge(base, SETTINGS[setting])
            if quick:  # every setting gets the same short budget
                scene.setdefault("train", {})["time_budget"] = QUICK_BUDGET
            name = f"{scene_name}-{setting}"
            out[name] = renamed_paths(scene, f"results/{scene_name}/", f"results/{name}/")
    return out


def scene_and_setting(name: str) -> tuple[str, str]:
    """`<scene>-<setting>` split at a known setting's name (a scene's name may hold hyphens too);
    a setting no longer in SETTINGS (an earlier run's, kept in the report) at the first hyphen."""
    for setting in sorted(SETTINGS, key=len, reverse=True):
        if name.endswith(f"-{setting}") and len(name) > len(setting) + 1:
            return name[: -len(setting) - 1], setting
    scene, _, setting = name.partition("-")
    return scene, setting


def built(settings: dict[str, dict]) -> dict[str, dict]:
    """The settings that have numbers: one that was not built has nothing to report or keep (a
    cache knob's numbers are its cache's)."""
    return {name: report for name, report in settings.items()
            if report.get("psnr") is not None or (report.get("field") and report.get("distill_ok"))}


def peak_memory_mb(workdir: Path, scene: str, job: str) -> float | None:
    path = workdir / "benchmarks" / "runs" / scene / f"{job}.tsv"
    if not path.exists():
        return None
    with path.open() as handle:
        row = next(csv.DictReader(handle, delimiter="\t"))
    try:
        return float(row["max_rss"])
    except (KeyError, ValueError):
        return None


def render_ms(srf: Path, size: int = 64, repeats: int = 5) -> float | None:
    """Milliseconds to render a size x size frame (RGB, semantics, depth) from a training camera."""
    import torch

    from srfpipe.srf.data import load_posed_images
    from srfpipe.srf.query import SemanticRadianceField
    from srfpipe.cameras import transform_poses

    if not srf.exists():
        return None
    field = SemanticRadianceField.load(srf, "cpu")
    data = load_posed_images(srf.parent / "images.zarr")
    pose = transform_poses(data.world_from_scene, data.poses_scene[1].numpy().astype(np.float64))
    scale = size / max(data.width, data.height)
    intrinsics = data.intrinsics[1].numpy() * scale
    torch.set_num_threads(2)
    field.render(pose, intrinsics, size, size)  # warm-up
    started = time.perf_counter()
    for _ in range(repeats):
        field.render(pose, intrinsics, size, size)
    return (time.perf_counter() - started) / repeats * 1000.0


def ground_truth_folder(results: Path) -> Path | None:
    """The capture's ground_truth/ that `srfpipe package` reads (recorded in images.zarr), else
    results/<scene>/capture/ground_truth; None without one."""
    from srfpipe.sim.package import read_ground_truth

    folder = read_ground_truth(results / "images.zarr")[0] if (results / "images.zarr").exists() else None
    fallback = results / "capture" / "ground_truth"
    return folder or (fallback if (fallback / "scene.json").exists() else None)


def occupancy_iou(results: Path, folder: Path | None) -> dict:
    """occupancy_iou (mean) and occupancy_iou_classes: per class of occupancy.zarr that has a
    ground-truth mesh (ground_truth/meshes/<class>.ply), the IoU of benchmarks/occupancy.py's
    class_accuracy against the ground truth in `folder`; {} without a cache, ground truth or such a class."""
    from srfpipe.occupancy import OccupancyCache

    if folder is None or not (results / "occupancy.zarr").exists():
        return {}
    cache = OccupancyCache.load(results / "occupancy.zarr")
    classes = {name: CLOSED_CLASSES.get(name, False) for name in cache.classes
               if (folder / "meshes" / f"{name}.ply").exists()}
    if not classes:
        return {}
    metrics, _ = class_accuracy(cache, folder, classes)
    per_class = {name: metrics[f"iou_{name}"] for name in classes}
    return {"occupancy_iou": round(float(np.mean(list(per_class.values()))), 4), "occupancy_iou_classes": per_class}


def scene_options(workdir: Path, name: str, section: str) -> dict:
    """The validated `section` of the setting's scene file in the work directory (what the workflow
    passes the stage), else the section's defaults."""
    from srfpipe.config import load_scene, section_defaults

    path = workdir / "config" / "scenes" / f"{name}.yaml"
    return load_scene(path)[section] if path.exists() else section_defaults(section)


def fruit_counts(results: Path, folder: Path | None, options: dict) -> dict:
    """The simulator package's fruit instances against the ground truth, without building sim/: as
    `srfpipe package` (srfpipe.sim.package.package) does for scene.json's ground_truth, each reach
    class of occupancy.zarr goes through find_instances and match_ground_truth (`options`: the scene's
    sim section) against its ground-truth file (apples.json, berries.json). Summed over the reach
    classes that have one; {} when none does."""
    from srfpipe.artifacts import meta, open_artifact
    from srfpipe.occupancy.grid import VoxelGrid
    from srfpipe.sim.package import reach_instances

    if folder is None or not (results / "occupancy.zarr").exists():
        return {}
    group = open_artifact(results / "occupancy.zarr", stage="distill")
    attrs = meta(group)
    grid = VoxelGrid.from_attrs(attrs["grid"])
    reach = [c for c, role in zip(attrs["distance"]["classes"], attrs["distance"]["roles"]) if role == "reach"]
    _, truth = reach_instances(group["class_occupancy"], list(attrs["classes"]), reach, grid.origin,
                               grid.voxel_size, options, folder)
    matches = list(truth.values())
    if not matches:
        return {}
    count, count_gt = sum(m["count"] for m in matches), sum(m["count_gt"] for m in matches)
    matched = sum(m["matched"] for m in matches)
    error = sum(m["centroid_err_mean"] * m["matched"] for m in matches if m["matched"])
    return {"fruit_count": count, "fruit_count_gt": count_gt, "fruit_count_error": abs(count - count_gt),
            "fruit_matched": matched, "fruit_centroid_err": error / matched if matched else None}


def ground_truth_columns(workdir: Path, name: str, field: str | None = None) -> dict:
    """The columns measured against the capture's ground truth from the setting's occupancy.zarr;
    the capture and the sim options are those of the setting that trained the field (`field`, by
    default the setting itself: a cache knob's results hold only its occupancy.zarr)."""
    results, field = workdir / "results" / name, field or name
    folder = ground_truth_folder(workdir / "results" / field)
    options = scene_options(workdir, field, "sim")
    return {**occupancy_iou(results, folder), **fruit_counts(results, folder, options)}


def setting_report(workdir: Path, name: str) -> dict:
    from srfpipe.artifacts import read_provenance

    results = workdir / "results" / name
    report: dict = {}
    metrics_file = results / "eval" / "metrics.json"
    if metrics_file.exists():
        metrics = json.loads(metrics_file.read_text())
        for key in ("psnr", "psnr_object", "ssim", "miou_gt", "miou_gt_classes", "floater_fraction"):
            if key in metrics:
                report[key] = metrics[key]
    srf = results / "srf.zarr"
    if srf.exists():
        info = read_provenance(srf)
        report["train_seconds"] = info.get("train_seconds")
        report["steps"] = info.get("iterations_done")
        report["train_config"] = info.get("config")
        # a partial run merges its rows into an earlier run's: each row says when, and by which code
        report["trained_at"] = info.get("created")
        report["srfpipe_commit"] = (info.get("versions") or {}).get("srfpipe_commit")
    report["train_wall_seconds"] = rule_seconds(workdir, name, "train")
    report["train_peak_memory_mb"] = peak_memory_mb(workdir, name, "train")
    report["render_64_ms"] = render_ms(srf)
    report["distill_seconds"] = rule_seconds(workdir, name, "distill")
    report.update(cache_columns(workdir, name))
    return report


def cache_columns(workdir: Path, name: str, field: str | None = None) -> dict:
    """distill_ok; with a cache, its bytes on disk against the dense grid's, its voxels and the
    columns measured against the capture's ground truth (ground_truth_columns)."""
    from srfpipe.artifacts import read_provenance

    cache = workdir / "results" / name / "occupancy.zarr"
    if not cache.exists():
        return {"distill_ok": False}
    info = read_provenance(cache)
    return {"distill_ok": True, "cache_bytes": info.get("bytes_on_disk"), "dense_bytes": info.get("dense_bytes"),
            "voxels_across": info.get("resolution", {}).get("voxels_across"),
            "voxel_size": info.get("grid", {}).get("voxel_size"), **ground_truth_columns(workdir, name, field)}


def distill_cache_knob(workdir: Path, scene: str, setting: str) -> dict:
    """A cache knob: `srfpipe distill` of the scene's CACHE_KNOB_FIELD field with the knob's occupancy
    overrides (the same stage the workflow's distill rule runs), timed; its report names the field,
    whose quality columns are the field's. {} when that field was not built."""
    field = f"{scene}-{CACHE_KNOB_FIELD}"
    source, results = workdir / "results" / field, workdir / "results" / f"{scene}-{setting}"
    if not (source / "srf.zarr").exists():
        return {}
    results.mkdir(parents=True, exist_ok=True)
    log = workdir / "logs" / f"{scene}-{setting}" / "distill.log"
    log.unlink(missing_ok=True)  # run_command appends
    command = ["srfpipe", "distill", "--srf", str(source / "srf.zarr"), "--no-progress",
               "--scene", str(workdir / "config" / "scenes" / f"{field}.yaml"),
               "--options", json.dumps(SETTINGS[setting]["occupancy"]), "--out", str(results / "occupancy.zarr")]
    try:
        seconds = run_command(command, log)
    except subprocess.CalledProcessError:
        print(f"{scene}-{setting}: distill failed, see {log}")
        return {}
    return {"field": field, "distill_seconds": seconds, **cache_columns(workdir, f"{scene}-{setting}", field)}


def backfill(workdir: Path) -> int:
    """Only the ground-truth columns (ground_truth_columns) of the settings built in `workdir`, merged
    into tradeoff.json and/or tradeoff_quick.json: into an entry only when the setting's srf.zarr was
    trained by that run (its train config and train_seconds equal the entry's) and its occupancy.zarr
    was distilled from that srf.zarr after it was written."""
    from srfpipe.artifacts import read_provenance

    paths = {quick: result_path("tradeoff", quick) for quick in (False, True)}
    reports = {quick: json.loads(path.read_text()) for quick, path in paths.items() if path.exists()}
    changed = set()
    for results in sorted(p for p in (workdir / "results").iterdir() if p.is_dir()):
        name, srf, cache = results.name, results / "srf.zarr", results / "occupancy.zarr"
        if not (srf.exists() and cache.exists()):
            print(f"{name}: no srf.zarr and occupancy.zarr, skipped")
            continue
        trained, distilled = read_provenance(srf), read_provenance(cache)
        sources = [Path(i["path"]) for i in distilled.get("inputs", []) if i.get("stage") == "train"]
        from_srf = any((workdir / p).resolve() == srf.resolve() for p in sources)
        if not from_srf or distilled["created"] < trained["created"]:
            print(f"{name}: occupancy.zarr was not distilled from this srf.zarr ({sources}), skipped")
            continue
        owners = [quick for quick, report in reports.items()
                  if (entry := report["settings"].get(name)) is not None
                  and entry.get("train_config") == trained.get("config")
                  and entry.get("train_seconds") == trained.get("train_seconds")]
        if not owners:
            print(f"{name}: srf.zarr (train_seconds {trained.get('train_seconds')}) matches no entry of "
                  f"{', '.join(paths[q].name for q in reports)}, skipped")
            continue
        columns = ground_truth_columns(workdir, name)
        for quick in owners:
            print(f"{name}: -> {paths[quick].name}: {columns}")
            reports[quick]["settings"][name].update(columns)
            if "presets" in reports[quick]:
                reports[quick]["presets"] = preset_summary(reports[quick]["settings"])
            changed.add(quick)
    for quick in sorted(changed):
        write_result(paths[quick], reports[quick])
        print_table(reports[quick]["settings"])
    return 0


def preset_summary(per_setting: dict) -> dict:
    """Each preset on the orchard: the issue's keys; `paper`, a GPU run, with its CPU time estimated."""
    summary = {}
    for name, r in per_setting.items():
        scene, setting = scene_and_setting(name)
        if scene == "orchard" and setting in PRESETS:
            summary[setting] = {"psnr": r.get("psnr"), "psnr_object": r.get("psnr_object"), "miou": r.get("miou_gt"),
                                "train_seconds": r.get("train_seconds"), "occupancy_iou": r.get("occupancy_iou"),
                                "fruit_count_error": r.get("fruit_count_error")}
    if "paper" not in summary and (estimate := paper_cpu_estimate()):
        summary["paper"] = estimate
    return summary


def paper_cpu_estimate() -> dict | None:
    """Why `paper` has no measurement here: its iterations of the hash grid at the speed that
    benchmarks/train.py measured for the hash grid on the orchard, on this machine (4096 rays, as
    the paper); None when train.json or its hash curve is missing."""
    from srfpipe.config import load_schema

    train_file = REPO / "benchmarks" / "results" / "train.json"
    iterations = load_schema("presets.yaml")["paper"]["train"]["iterations"]
    try:
        curve = json.loads(train_file.read_text())["curves"]["hash"]
        steps, seconds = float(curve["step"][-1]), float(curve["seconds"][-1])
    except (OSError, KeyError, IndexError, ValueError):
        return None
    hours = iterations / (steps / seconds) / 3600.0
    return {"measured": False, "iterations": iterations, "cpu_hours_estimate": hours,
            "why": f"a GPU setting: {iterations} steps of the hash grid at {steps / seconds:.2f} steps/s "
                   f"(train.json: {steps:.0f} steps in {seconds:.0f} s on the orchard, these 2 cores) "
                   f"would train for about {hours / 24:.1f} days"}


def print_table(per_setting: dict) -> None:
    print(f"{'setting':28} {'psnr':>6} {'obj':>6} {'ssim':>6} {'mIoU':>6} {'train s':>8} {'steps':>6} {'64px ms':>8} "
          f"{'MB':>7} {'occIoU':>6} {'fruit/gt':>8} {'cache MB':>8}")
    for name, s in per_setting.items():
        cells = [s.get(k) for k in ("psnr", "psnr_object", "ssim", "miou_gt", "train_seconds")]
        text = " ".join(f"{v:6.2f}" if isinstance(v, float) else f"{'-':>6}" for v in cells)
        fruit = f"{s['fruit_count']}/{s['fruit_count_gt']}" if "fruit_count" in s else "-"
        occupancy = f"{s['occupancy_iou']:6.3f}" if s.get("occupancy_iou") is not None else f"{'-':>6}"
        print(f"{name:28} {text} {s.get('steps') or '-':>6} {s.get('render_64_ms') or float('nan'):8.1f} "
              f"{s.get('train_peak_memory_mb') or float('nan'):7.0f} {occupancy} {fruit:>8} "
              f"{(s.get('cache_bytes') or float('nan')) / 1e6:8.1f}")


def pareto_front(points: list[tuple[str, float, float]]) -> list[str]:
    """Names of the settings no other setting beats on both axes (less time, more quality),
    in order of time."""
    front, best = [], -np.inf
    for name, seconds, quality in sorted(points, key=lambda p: (p[1], -p[2])):
        if quality > best:
            front.append(name)
            best = quality
    return front


def scene_points(per_setting: dict, key: str) -> dict[str, list[tuple[str, float, float]]]:
    """(setting, training seconds, metric) per scene, for the settings that have both."""
    points: dict[str, list] = {}
    for name, s in per_setting.items():
        if s.get("train_seconds") is not None and s.get(key) is not None:
            scene, setting = scene_and_setting(name)
            points.setdefault(scene, []).append((setting, float(s["train_seconds"]), float(s[key])))
    return points


def pareto_fronts(per_setting: dict) -> dict:
    """Per scene and metric, the settings on the Pareto front of quality against training time."""
    fronts: dict[str, dict] = {}
    for key in ("psnr", "psnr_object", "miou_gt"):
        for scene, points in scene_points(per_setting, key).items():
            fronts.setdefault(scene, {})[key] = pareto_front(points)
    return fronts


PLOT_METRICS = (("psnr", "held-out PSNR (dB)"), ("psnr_object", "object-pixel PSNR (dB)"),
                ("miou_gt", "mIoU (ground truth)"))


def pareto_plot(per_setting: dict, path: Path, panel_size=(360, 300)) -> None:
    """Quality against training seconds: one row per scene, one panel per metric; presets in
    red, single knobs in blue, the Pareto front as a line. Drawn with OpenCV (no plotting
    library among the project's dependencies)."""
    import cv2

    width, height = panel_size
    per_metric = {key: scene_points(per_setting, key) for key, _ in PLOT_METRICS}
    scenes = sorted({scene for points in per_metric.values() for scene in points})
    font = cv2.FONT_HERSHEY_SIMPLEX
    rows = []
    for scene in scenes:
        panels = []
        for key, label in PLOT_METRICS:
            panel = np.full((height, width, 3), 255, np.uint8)
            cv2.putText(panel, f"{scene}: {label}", (10, 18), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
            points = per_metric[key].get(scene, [])
            if points:
                xs, ys = np.array([p[1] for p in points]), np.array([p[2] for p in points])
                x0, x1 = 0.0, float(xs.max()) * 1.15 or 1.0
                # a lone point (a scene with one setting) gets a readable axis: 2 % of its value
                pad = 0.08 * np.ptp(ys) or 0.02 * max(abs(float(ys.max())), 1e-3)
                y0, y1 = float(ys.min()) - pad, float(ys.max()) + pad
                left, bottom, w, h = 48, height - 36, width - 60, height - 66

                def at(x, y):
                    return int(left + (x - x0) / (x1 - x0) * w), int(bottom - (y - y0) / (y1 - y0) * h)

                cv2.rectangle(panel, (left, bottom - h), (left + w, bottom), (0, 0, 0), 1)
                front = pareto_front(points)
                by_name = {p[0]: p for p in points}
                line = np.array([at(by_name[n][1], by_name[n][2]) for n in front], np.int32)
                cv2.polylines(panel, [line], False, (160, 160, 160), 1, cv2.LINE_AA)
                for name, x, y in points:
                    colour = (40, 40, 210) if name in PRESETS else (200, 90, 0)  # BGR: presets red, knobs blue
                    cv2.circle(panel, at(x, y), 4 if name in front else 3, colour, -1, cv2.LINE_AA)
                    cv2.putText(panel, name, (at(x, y)[0] + 5, at(x, y)[1] - 4), font, 0.3, colour, 1, cv2.LINE_AA)
                decimals = max(0, 1 - int(np.floor(np.log10(y1 - y0))))  # ticks that differ
                for value in np.linspace(y0, y1, 5):
                    cv2.putText(panel, f"{value:.{decimals}f}", (2, at(x0, value)[1] + 4), font, 0.3, (0, 0, 0), 1, cv2.LINE_AA)
                for value in np.linspace(x0, x1, 5):
                    cv2.putText(panel, f"{value:.0f}", (at(value, y0)[0] - 8, bottom + 13), font, 0.3, (0, 0, 0), 1,
                                cv2.LINE_AA)
            else:
                cv2.putText(panel, "no setting measured", (60, height // 2), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
            cv2.putText(panel, "training seconds (2 CPU cores)", (width // 2 - 90, height - 6), font, 0.38,
                        (0, 0, 0), 1, cv2.LINE_AA)
            panels.append(panel)
        rows.append(np.concatenate(panels, axis=1))
    if not rows:
        return
    cv2.imwrite(str(path), np.concatenate(rows, axis=0))
    print(f"wrote {path}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help=f"{QUICK_BUDGET} s of training per setting, settings {QUICK_SETTINGS}, orchard only")
    parser.add_argument("--scenes", nargs="+", default=None, help="scene files of config/scenes (default orchard plant)")
    parser.add_argument("--settings", nargs="+", default=None, choices=sorted(SETTINGS))
    parser.add_argument("--workdir", type=Path, default=REPO / "benchmarks" / "work" / "tradeoff")
    parser.add_argument("--backfill", action="store_true",
                        help="build nothing: add the ground-truth columns (occupancy IoU, fruit count) of the settings "
                             "already built in --workdir to the result file of the run that trained them")
    args = parser.parse_args()
    if args.backfill:
        return backfill(args.workdir)
    scenes = args.scenes or (["orchard"] if args.quick else ["orchard", "plant"])
    settings = args.settings or (QUICK_SETTINGS if args.quick else list(SETTINGS))

    trained = [s for s in settings if not is_cache_knob(s)]
    cache_knobs = [s for s in settings if is_cache_knob(s)]
    if cache_knobs and CACHE_KNOB_FIELD not in trained:
        trained.append(CACHE_KNOB_FIELD)
    configs = setting_scenes(scenes, trained, args.quick)
    write_workdir(args.workdir, configs, "occupancy")
    targets = [f"results/{name}/{artifact}" for name in configs for artifact in ("eval", "occupancy.zarr")]
    try:
        seconds = run_workflow(args.workdir, targets, log=args.workdir / "snakemake.log", extra=("--keep-going",))
    except subprocess.CalledProcessError:
        seconds = None
        print(f"some jobs failed: see {args.workdir / 'snakemake.log'} and {args.workdir / 'logs'}")

    measured = {name: setting_report(args.workdir, name) for name in configs}
    for scene in scenes:
        for setting in cache_knobs:
            measured[f"{scene}-{setting}"] = distill_cache_knob(args.workdir, scene, setting)
    per_setting = built(measured)  # a failed setting keeps an earlier run's numbers, if any
    if failed := sorted(set(measured) - set(per_setting)):
        print(f"not built, left out of the report: {', '.join(failed)}")
    overrides = {s: SETTINGS[s] for s in settings}
    path = result_path("tradeoff", args.quick)
    if path.exists() and (args.settings or args.scenes):
        # a partial run (some settings or scenes) updates those entries and keeps the others
        earlier = json.loads(path.read_text())
        per_setting = {**built(earlier.get("settings", {})), **per_setting}
        overrides = {**earlier.get("overrides", {}), **overrides}
        scenes = sorted(set(earlier.get("scenes", [])) | set(scenes))
    report = {"settings": per_setting, "overrides": overrides, "workflow_seconds": seconds,
              "machine": machine_info(quick=args.quick), "scenes": scenes,
              "presets": preset_summary(per_setting), "pareto": pareto_fronts(per_setting)}
    suffix = "_quick" if args.quick else ""
    pareto_plot(per_setting, REPO / "benchmarks" / "results" / f"tradeoff{suffix}.png")
    write_result(path, report)
    print_table(per_setting)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

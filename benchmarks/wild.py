"""Benchmark: captures from the wild (issue 34): unposed photos or a video, and labels on a few frames.

Everything is built through the workflow, as a user builds it.

* orchard_video  the built-in orchard walked round in one turn and written as a video by the
                 generator (`orchard.video: true`), built as a scene of `source.format: video`:
                 frames chosen by the `video_frames` rule (source.max_frames), posed by structure
                 from motion in the `poses` rule, compared with the generator's poses; then (full
                 run) the rest of the pipeline with the defaults: held-out PSNR and mIoU against the
                 built-in segmenter's masks (no ground truth comes with a video).
* fox_sfm        the photos of ../shared/data/fox as `source.format: images` (its transforms.json
                 ignored), poses compared with that file's (COLMAP's, from ns-process-data); then the
                 fox's scene file from the recovered poses, trained for the steps the posed fox reached
                 in its 10 minutes (captures.json; time budget off, so any machine compares): held-out PSNR.
* sparse         the sparse-label curve: the orchard and the plant with their masks imported for
                 100 %, 25 %, 10 %, 5 % of the training frames and for exactly 3 frames (evenly spaced;
                 the generator's ground-truth label images stand in for a person's masks), each run
                 trained with preset fast (5 minutes); mIoU against ground truth on every view of the
                 capture (labelled, unlabelled and held-out), and evaluate's own held-out and
                 unlabelled-view mIoU. One scene name is re-built per share: Snakemake re-runs the
                 masks, composite, train and evaluate jobs only.

Pose comparisons are after a similarity alignment (`srfpipe.poses.align.pose_errors`): SfM's world
frame and scale are its own. Keys of benchmarks/results/wild.json: orchard_video_registered,
orchard_video_rot_err_deg, orchard_video_trans_err_pct (of the tree's bounding-box size),
orchard_video_psnr, orchard_video_miou, fox_sfm_registered, fox_sfm_rot_err_deg, fox_sfm_psnr,
sfm_seconds (wall time of the stages up to poses.zarr, per capture), {orchard,plant}_sparse_miou_{100,
25,10,5}pct and _3frames (with background, as the issue's mIoU; `sparse` holds the per-class and
classes-only numbers; with several `--seeds`, each share's point is their mean and `_sd` their spread), and `posed_reference`: the posed builds' numbers from captures.json.

    python benchmarks/wild.py [--quick] [--only orchard_video|fox_sfm|sparse] [--sparse-scenes orchard plant]
                              [--fractions 100pct 10pct] [--seeds 0 1 2]

A run of some parts keeps the other parts' last numbers in the JSON. `--quick`
(results/wild_quick.json): a 72-view turn at 320 x 240 with every frame kept, no pipeline after the
poses, no fox, and the orchard's curve at 24 views for 100 %, 10 % and 3 frames, 40 s each. The full
run renders 300 views of 640 x 480 and keeps the default 150 frames; the fox's 50 photos of
1080 x 1920 take several minutes to pose on 2 cores; the curve is 10 runs of 5 minutes' training.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import yaml

from common import (REPO, holdout_every, machine_info, measured_steps, merge, result_path, rule_seconds, run_workflow,
                    write_result, write_workdir)

SHARED = (REPO / ".." / "shared" / "data").resolve()
FOX = SHARED / "fox"
FULL_ORBIT = {"seed": 0, "views": 300, "width": 640, "height": 480, "video": True}
QUICK_ORBIT = {"seed": 0, "views": 72, "width": 320, "height": 240, "video": True}


def _frame_number(name: str) -> int:
    return int(name.rsplit("_", 1)[1])


def pose_artifact(results: Path) -> tuple[dict, np.ndarray]:
    from srfpipe.artifacts import meta, open_artifact

    group = open_artifact(results / "poses.zarr", stage="poses")
    return meta(group), group["camera_to_world"][:]


def pipeline_metrics(workdir: Path, name: str) -> dict:
    """The rest of the pipeline from the recovered poses, with the scene's defaults: held-out metrics."""
    run_workflow(workdir, [f"results/{name}/eval"], log=workdir / "snakemake.log")
    metrics = json.loads((workdir / "results" / name / "eval" / "metrics.json").read_text())
    return {k: metrics.get(k) for k in ("psnr", "ssim", "psnr_object", "miou", "miou_classes", "train_view_psnr",
                                         "train_seconds", "views")}


def orchard_video(workdir: Path, quick: bool) -> dict:
    """The orchard walked round as a video: frames, SfM poses and (full run) the whole pipeline,
    through the workflow as a user builds it (`source.format: video`)."""
    from srfpipe.poses.align import pose_errors
    from srfpipe.scenes.orchard import generate_orchard

    options = QUICK_ORBIT if quick else FULL_ORBIT
    capture = generate_orchard(workdir / "generated" / "orchard_video", progress=False, **options)
    scene = json.loads((capture / "ground_truth" / "scene.json").read_text())
    truth = np.array(scene["camera_to_world"])
    bounds = np.array(scene["bounds_world"])
    source = {"format": "video", "path": str(capture / "video.avi")}
    if quick:
        source["max_frames"] = options["views"]
    name = "orchard-video"
    write_workdir(workdir, {name: {"source": source}}, "eval")
    started = time.perf_counter()
    run_workflow(workdir, [f"results/{name}/poses.zarr"], log=workdir / "snakemake.log")
    seconds = time.perf_counter() - started
    info, poses = pose_artifact(workdir / "results" / name)
    registered = [_frame_number(n) for n in info["names"]]
    errors = pose_errors(poses, truth[registered], float(np.max(bounds[1] - bounds[0])))
    entry = {
        "orchard_video_registered": info["sfm"]["registered_fraction"],
        "orchard_video_rot_err_deg": errors["rot_err_deg"],
        "orchard_video_trans_err_pct": 100.0 * errors["trans_err"],
        "seconds": seconds,
        "frames_seconds": rule_seconds(workdir, name, "video_frames"),
        "poses_seconds": rule_seconds(workdir, name, "poses"),
        "orbit": options,
        "frames_chosen": info["sfm"]["n_images"],
        "errors": errors,
        "sfm": info["sfm"],
    }
    if not quick:
        built = pipeline_metrics(workdir, name)
        entry.update(orchard_video_psnr=built["psnr"], orchard_video_miou=built["miou"], pipeline=built)
    return entry


def fox_sfm(workdir: Path) -> dict:
    """The fox's photos with transforms.json ignored (`source.format: images`), through the
    workflow; the poses compared with that file's, then the pipeline from the recovered poses."""
    from srfpipe.poses import load_capture
    from srfpipe.poses.align import pose_errors

    known = load_capture({"format": "nerfstudio", "path": str(FOX)})
    name = "fox-sfm"
    scene = yaml.safe_load((REPO / "config" / "scenes" / "fox.yaml").read_text())
    scene = merge(scene, {"source": {"format": "images", "path": str(FOX)}, "poses": {}})
    scene["poses"].pop("refine", None)  # SfM's own bundle adjustment replaces the refinement
    # the posed fox's steps (captures.json), time budget off: the two PSNRs compare on any machine
    steps = measured_steps("fox")
    scene["train"] = {**scene.get("train", {}), "iterations": steps, "time_budget": 0}
    write_workdir(workdir, {name: scene}, "eval")
    started = time.perf_counter()
    run_workflow(workdir, [f"results/{name}/poses.zarr"], log=workdir / "snakemake.log")
    seconds = time.perf_counter() - started
    info, poses = pose_artifact(workdir / "results" / name)
    index = {path: i for i, path in enumerate(known.image_paths)}
    matched = [k for k, path in enumerate(info["image_paths"]) if path in index]
    reference = known.camera_to_world[[index[info["image_paths"][k]] for k in matched]]
    scene_size = float(np.max(np.ptp(reference[:, :3, 3], axis=0)))
    errors = pose_errors(poses[matched], reference, scene_size)
    built = pipeline_metrics(workdir, name)
    return {
        "fox_sfm_registered": info["sfm"]["registered_fraction"],
        "fox_sfm_rot_err_deg": errors["rot_err_deg"],
        "fox_sfm_trans_err_pct_of_camera_spread": 100.0 * errors["trans_err"],
        "fox_sfm_psnr": built["psnr"],
        "steps": steps,
        "seconds": seconds,
        "poses_seconds": rule_seconds(workdir, name, "poses"),
        "errors": errors,
        "sfm": info["sfm"],
        "pipeline": built,
    }


# issue 34 part 2: the labelled share of the training frames (or a count of frames)
SPARSE_FRACTIONS = {"100pct": 1.0, "25pct": 0.25, "10pct": 0.10, "5pct": 0.05, "3frames": 3}
# every run of the curve: preset fast (2048 rays a step; its 5 minutes for the full run)
SPARSE_PRESET = "fast"
SPARSE_BUDGET = {False: 300.0, True: 40.0}  # train.time_budget, seconds
QUICK_FRACTIONS = ("100pct", "10pct", "3frames")
# the ground-truth label values of the generated captures (ground_truth/scene.json classes, in order)
SPARSE_SCENES = {"orchard": {"apple": 1, "branch": 2, "leaf": 3}, "plant": {"stem": 1, "leaf": 2, "berry": 3}}
QUICK_SPARSE_ORCHARD = {"views": 24, "width": 320, "height": 240}


def labelled_count(share: float, training_frames: int) -> int:
    """Frames to label: a count as it is (3), a share of the training frames rounded, at least one."""
    if share > 1:
        return min(int(share), training_frames)
    return max(1, min(training_frames, round(share * training_frames)))


def sparse_scene(name: str, folder: str, quick: bool) -> dict:
    """The scene file as the README builds it, its masks imported from `folder` (a human's labels:
    the generator's ground-truth label images of the chosen frames), trained for the curve's budget."""
    scene = yaml.safe_load((REPO / "config" / "scenes" / f"{name}.yaml").read_text())
    overrides = {"segmentation": {"prompts": list(SPARSE_SCENES[name]), "backend": "import",
                                  "import": {"path": folder, "format": "labels", "values": SPARSE_SCENES[name]}},
                 "train": {"time_budget": SPARSE_BUDGET[quick]}, "evaluate": {"unlabelled_views": 4},
                 "preset": SPARSE_PRESET}
    if quick and name == "orchard":
        overrides["orchard"] = {**scene.get("orchard", {}), **QUICK_SPARSE_ORCHARD}
    return merge(scene, overrides)


def all_views_miou(results: Path) -> dict:
    """mIoU of the trained field's labels against the generator's ground truth on every view of
    the capture (labelled, unlabelled and held-out), one ray per pixel (evaluate supersamples its
    few held-out views; here every view is rendered, at a quarter of the cost)."""
    from srfpipe.evaluate import world_from_scene_pose
    from srfpipe.srf import metrics
    from srfpipe.srf.data import load_posed_images, remap_ground_truth
    from srfpipe.srf.query import SemanticRadianceField

    data = load_posed_images(results / "images.zarr", results / "labels.zarr")
    field = SemanticRadianceField.load(results / "srf.zarr")
    classes = len(data.classes)
    confusion = np.zeros((classes + 1, classes + 1), np.int64)
    for index in range(data.count):
        pose = world_from_scene_pose(data.world_from_scene, data.poses_scene[index].numpy())
        rendered = field.render(pose, data.intrinsics[index].numpy(), data.width, data.height)
        reference = remap_ground_truth(data.gt_label[index], data.gt_classes, data.classes)
        confusion += metrics.confusion(metrics.label_from_probabilities(rendered["semantic"]), reference, classes + 1)
    iou = metrics.iou_from_confusion(confusion)
    return {"miou": float(np.nanmean(iou)), "miou_classes": float(np.nanmean(iou[1:])),
            "iou": dict(zip(["background", *data.classes], map(float, iou))), "views": data.count}


def seed_result(run: dict) -> dict:
    """What one training seed of a share measured (a run's fields as `sparse_labels` writes them)."""
    return {"miou": run["all_views"]["miou"], "miou_classes": run["all_views"]["miou_classes"],
            **{k: run.get(k) for k in ("psnr", "psnr_object", "miou_unlabelled_gt", "train_seconds")}}


def with_seeds(earlier: dict | None, measured: dict) -> dict:
    """One share's run with the seeds of an earlier run of it kept (a run without `seeds` was trained at
    the default seed 0), and their mean: the curve's point, since one 5-minute run of the plant moves
    by about 0.03 from build to build."""
    seeds = dict((earlier or {}).get("seeds") or ({"0": seed_result(earlier)} if earlier else {}))
    if earlier and earlier.get("labelled_frames") != measured["labelled_frames"]:
        seeds = {}  # other frames labelled: not the same point
    seeds.update(measured["seeds"])
    def lowest(run: dict) -> int:
        return min(int(seed) for seed in run.get("seeds") or {"0": None})

    first = earlier if earlier and lowest(earlier) < lowest(measured) else measured  # its fields: the lowest seed's
    values = np.array([seed["miou"] for seed in seeds.values()])
    classes = np.array([seed["miou_classes"] for seed in seeds.values()])
    return {**first, "seed": first.get("seed", 0), "seeds": seeds, "mean": {"miou": float(values.mean()), "miou_classes": float(classes.mean()),
                                             "miou_sd": float(values.std(ddof=1)) if len(values) > 1 else None,
                                             "seeds": len(values)}}


def curve_point(run: dict) -> dict:
    """The all-view mIoU of a share: the mean over its seeds where it has several."""
    return run.get("mean") or run["all_views"]


def sparse_labels(workdir: Path, quick: bool, scenes: list[str], fractions: list[str], seeds=(0,)) -> dict:
    """The sparse-label curve: each scene built once per labelled share and training seed, one scene
    name re-built after a change of its mask folder or seed (Snakemake re-runs masks, composite, train
    and evaluate, or train and evaluate only)."""
    import shutil

    from srfpipe.evaluate import train_view_choice
    from srfpipe.srf.data import split_views

    report = {}
    for name in scenes:
        write_workdir(workdir, {name: sparse_scene(name, f"prepared/{name}/100pct", quick)}, "eval")
        run_workflow(workdir, [f"results/{name}/capture"], log=workdir / "snakemake.log")
        truth = sorted((workdir / "results" / name / "capture" / "ground_truth" / "labels").glob("*.png"))
        holdout = holdout_every(sparse_scene(name, "", quick))
        train, _ = split_views(len(truth), holdout)
        entry = {"training_frames": len(train), "budget_seconds": SPARSE_BUDGET[quick], "preset": SPARSE_PRESET,
                 "runs": {}}
        for tag, share in SPARSE_FRACTIONS.items():
            if tag not in fractions or (quick and tag not in QUICK_FRACTIONS):
                continue
            chosen = train_view_choice(train, labelled_count(share, len(train)))
            folder = workdir / "prepared" / name / tag
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir(parents=True)
            for index in chosen:
                shutil.copy2(truth[index], folder / truth[index].name)
            run = None
            for seed in seeds:
                scene = merge(sparse_scene(name, f"prepared/{name}/{tag}", quick), {"train": {"seed": seed}})
                write_workdir(workdir, {name: scene}, "eval")
                print(f"=== {name}: {len(chosen)} of {len(train)} training frames labelled ({tag}), seed {seed}", flush=True)
                run_workflow(workdir, [f"results/{name}/eval"], log=workdir / "snakemake.log")
                results = workdir / "results" / name
                evaluated = json.loads((results / "eval" / "metrics.json").read_text())
                everywhere = all_views_miou(results)
                measured = {
                    "labelled_frames": [truth[i].stem for i in chosen], "all_views": everywhere, "seed": seed,
                    **{k: evaluated.get(k) for k in ("psnr", "psnr_object", "miou_gt", "miou_gt_classes",
                                                     "miou_unlabelled_gt", "miou_unlabelled_gt_classes", "train_seconds")},
                }
                measured["seeds"] = {str(seed): seed_result(measured)}
                run = measured if run is None else with_seeds(run, measured)
                print(f"{name:8} {tag:8} seed {seed} all-view mIoU {everywhere['miou']:.3f} (classes "
                      f"{everywhere['miou_classes']:.3f}), held-out {evaluated.get('miou_gt', float('nan')):.3f}", flush=True)
            entry["runs"][tag] = run
        report[name] = entry
    return report


def plot_sparse(sparse: dict, path: Path, size=(520, 360)) -> None:
    """mIoU on all views against the number of labelled training frames (log scale), one line per
    scene (OpenCV drawing: no plotting library needed)."""
    import cv2

    colours = {"orchard": (40, 150, 40), "plant": (180, 60, 160)}
    width, height = size
    panel = np.full((height, width, 3), 255, np.uint8)
    left, bottom, w, h = 50, height - 45, width - 80, height - 90
    points = {name: sorted((len(run["labelled_frames"]), curve_point(run)["miou"]) for run in entry["runs"].values())
              for name, entry in sparse.items()}
    most = max(n for curve in points.values() for n, _ in curve)

    def at(frames, miou):
        return int(left + np.log(frames) / np.log(most) * w), int(bottom - miou * h)

    cv2.rectangle(panel, (left, bottom - h), (left + w, bottom), (0, 0, 0), 1)
    for value in np.linspace(0, 1, 6):
        cv2.putText(panel, f"{value:.1f}", (12, at(1, value)[1] + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
    for frames in sorted({n for curve in points.values() for n, _ in curve}):
        cv2.putText(panel, str(frames), (at(frames, 0)[0] - 6, bottom + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    (0, 0, 0), 1)
    for row, (name, curve) in enumerate(points.items()):
        colour = colours.get(name, (0, 0, 0))
        pixels = [at(n, m) for n, m in curve]
        for a, b in zip(pixels, pixels[1:]):
            cv2.line(panel, a, b, colour, 2, cv2.LINE_AA)
        for pixel in pixels:
            cv2.circle(panel, pixel, 3, colour, -1)
        cv2.putText(panel, name, (left + 10 + 90 * row, 38), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1)
    cv2.putText(panel, "mIoU on every view vs ground truth (with background)", (left, 18), cv2.FONT_HERSHEY_SIMPLEX,
                0.45, (0, 0, 0), 1)
    cv2.putText(panel, "training frames labelled (log scale)", (left, height - 10), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                (0, 0, 0), 1)
    cv2.imwrite(str(path), panel)
    print(f"wrote {path}")


def print_sparse(sparse: dict) -> None:
    print(f"{'scene':8} {'labelled':>12} | {'all views':>9} {'classes':>7} {'seeds':>5} {'sd':>5} | {'held-out':>8} "
          f"{'unlabelled':>10}   (all views: the seeds' mean; held-out, unlabelled: one seed)")
    for name, entry in sparse.items():
        for tag, run in entry["runs"].items():
            held, unlabelled, point = run.get("miou_gt"), run.get("miou_unlabelled_gt"), curve_point(run)
            sd = point.get("miou_sd")
            print(f"{name:8} {tag + ' (' + str(len(run['labelled_frames'])) + ')':>12} | {point['miou']:9.3f} "
                  f"{point['miou_classes']:7.3f} {point.get('seeds', 1):5d} {sd if sd is not None else float('nan'):5.3f} | "
                  f"{held if held is not None else float('nan'):8.3f} {unlabelled if unlabelled is not None else float('nan'):10.3f}")


def posed_reference() -> dict:
    """The posed builds the recovered poses are compared with: the panel's orchard and fox
    (benchmarks/captures.py, the same defaults), with their steps and the masks' mIoU (`miou`, what
    the video's `orchard_video_miou` is) beside the truth's."""
    results = json.loads((REPO / "benchmarks" / "results" / "captures.json").read_text())
    panel, scenes = results.get("panel", {}), results.get("scenes", {})
    return {name: {**{k: panel.get(name, {}).get(k) for k in ("psnr", "miou_classes", "steps")},
                   "miou": scenes.get(name, {}).get("miou")}
            for name in ("orchard", "fox")}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a small turn, every frame kept, no fox")
    parser.add_argument("--only", choices=["orchard_video", "fox_sfm", "sparse"], default=None)
    parser.add_argument("--sparse-scenes", nargs="+", default=list(SPARSE_SCENES), choices=list(SPARSE_SCENES))
    parser.add_argument("--fractions", nargs="+", default=list(SPARSE_FRACTIONS), choices=list(SPARSE_FRACTIONS),
                        help="the labelled shares of the curve to measure (default: all)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0],
                        help="train.seed of each run of a share (several: the curve's point is their mean; the seeds "
                             "of an earlier run of the same share are kept)")
    parser.add_argument("--workdir", type=Path, default=REPO / "benchmarks" / "work" / "wild")
    args = parser.parse_args()

    path = result_path("wild", args.quick)
    # a run of some parts keeps the other parts' last measurement
    report: dict = json.loads(path.read_text()) if path.exists() else {}
    report.update({"machine": machine_info(cores=2), "quick": args.quick})
    report.setdefault("sfm_seconds", {})
    # before any part writes the file: a run of one part compares it with today's posed builds too
    report["posed_reference"] = posed_reference()
    if args.only in (None, "orchard_video"):
        entry = orchard_video(args.workdir, args.quick)
        report.update({k: v for k, v in entry.items() if k.startswith("orchard_video_")})
        report["sfm_seconds"]["orchard_video"] = entry["seconds"]
        report["orchard_video"] = entry
        write_result(path, report)
    if args.only in (None, "fox_sfm") and not args.quick:
        entry = fox_sfm(args.workdir)
        report.update({k: v for k, v in entry.items() if k.startswith("fox_sfm_")})
        report["sfm_seconds"]["fox"] = entry["seconds"]
        report["fox_sfm"] = entry
        write_result(path, report)
    if args.only in (None, "sparse"):
        sparse = report.setdefault("sparse", {})
        for name in args.sparse_scenes:
            measured = sparse_labels(args.workdir / "sparse", args.quick, [name], args.fractions, args.seeds)[name]
            earlier = sparse.get(name, {})  # a run of some shares keeps the others' runs, and their other seeds
            runs = {**earlier.get("runs", {}),
                    **{tag: with_seeds(earlier.get("runs", {}).get(tag), run) for tag, run in measured["runs"].items()}}
            sparse[name] = {**earlier, **measured, "runs": runs}
            for tag, run in runs.items():
                point = curve_point(run)
                sparse[name][f"sparse_miou_{tag}"], sparse[name][f"sparse_miou_classes_{tag}"] = point["miou"], point["miou_classes"]
                if point.get("miou_sd") is not None:
                    sparse[name][f"sparse_miou_{tag}_sd"] = point["miou_sd"]
            report.update({f"{name}_{k}": v for k, v in sparse[name].items() if k.startswith("sparse_miou")})
            write_result(path, report)
        plot_sparse(sparse, path.with_name(path.stem + "_sparse.png"))
        print_sparse(sparse)
    print(json.dumps({k: v for k, v in report.items()
                      if k.endswith(("_registered", "_deg", "_pct", "seconds", "frames"))}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

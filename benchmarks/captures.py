"""Benchmark: the pipeline's defaults on a panel of captures nobody tuned for (issue "captures nobody tuned for").

Every default is a claim about every capture, so each panel capture is built through the Snakemake
workflow with its scene file and otherwise default settings (10 minutes of training on 2 cores,
every 8th view held out):

* orchard       config/scenes/orchard.yaml: the built-in orchard, which must not get worse;
* plant         config/scenes/plant.yaml: the built-in thin plant, millimetres, 18 far narrow views;
* fox           config/scenes/fox.yaml: a real phone capture (../shared/data/fox), zero classes;
* bottle        config/scenes/bottle.yaml: real photos of one object in a living room, masks of that
                object only (../shared/data/bottle);
* fern          config/scenes/fern.yaml: a real forward-facing plant in LLFF's format (../shared/data/fern);
* beer          config/scenes/beer.yaml: phone-video frames with a COLMAP binary model (../shared/data/beer);
* plant-small   generated variant: the plant small in the frame (a wide lens: under 1 % of the
                pixels), its masks soft (blurred edges) and with the parts thinner than 5 px
                missing from every third view's masks (as a segmenter drops a stalk);
* orchard-apple generated variant: the orchard with only `apple` prompted (masks cover a few percent);
* plant-berry   generated variant: the plant with only `berry` prompted (masks cover 0.35 % of the
                pixels, the issue's thin plant whose organ masks carved its stem away);
* orchard-lens  generated variant: the orchard rendered through an OpenCV lens with a phone's strong
                tangential calibration (k1 -0.0024, k2 -0.021, p1 0.011, p2 0.0096) at 605 x 806;
* orchard-front generated variant: the orchard's 80 views taken from one side, their rings spread
                over 30 degrees of azimuth (a forward-facing capture like the fern's, with ground truth).

    python benchmarks/captures.py [--quick] [--workdir DIR] [--scenes NAME ...] [--panel-only] [--masks-only]
                                  [--mask-blur-sweep]

A scene whose images shrink by another factor than 4 (images.downscale null keeps the plant's 18
views at 256 px) is also measured on its held-out views at factor 4, the resolution earlier runs
measured at: `reference` in its entry; the plant's thin_* keys are those.

Writes benchmarks/results/captures.json (per scene, and the `panel` table the issue names: psnr,
ssim, psnr_object, miou_classes, train_view_psnr, bounds_source, steps, masks_miou_classes (the masks'
own class mIoU against ground truth on the training views: the ceiling a field that learns from
them rarely passes; `--masks-only` measures it without training, and also composited at
`segmentation.threshold` 0.25 to 0.5: miou_masks_gt_classes_by_threshold), and nerfacto's and
srfpipe's peers.json numbers where that file has the capture) and captures.png (per scene, the
first held-out view: render | semantics | depth; each scene's row in captures_rows/). `--quick`: 60 s of
training and no COLMAP refinement of the fox. A run of some scenes keeps the others' last measurement.
"""

from __future__ import annotations

import argparse
import json
import subprocess
from pathlib import Path

import numpy as np
import yaml

from common import (REPO, earlier_measurements, holdout_every, host_speed_notes, machine_info, measured_steps, merge,
                    renamed_paths, result_path, rule_seconds, run_workflow, write_result, write_workdir)

SHARED = (REPO / ".." / "shared" / "data").resolve()
FOX = SHARED / "fox"
# The factor every captures.json measured at before images.downscale came from the capture: a scene
# whose images now shrink by another factor is measured again on the same held-out views at this
# one, since PSNR depends on the pixel size (the same field scores lower on finer pixels).
REFERENCE_DOWNSCALE = 4
REFERENCE_KEYS = ("psnr", "psnr_object", "ssim", "miou_gt_classes", "floater_fraction", "views")

PANEL = ("orchard", "plant", "fox", "bottle", "fern", "beer", "plant-small", "orchard-apple", "orchard-lens",
         "orchard-front", "plant-berry")
# a phone's COLMAP calibration with large tangential terms (the fruit capture of the issue)
PHONE_LENS = [-0.0024, -0.021, 0.011, 0.0096]
# orchard-front: the azimuth its cameras span (the fern's 20 views span 18 degrees round their focus)
FRONT_ARC_DEG = 30.0
# generated variants: (scene file they start from, overrides)
VARIANTS = {
    "plant-small": ("plant", {"plant": {"fov_deg": 40},
                              "segmentation": {"import": {"path": "prepared/plant-small/masks", "format": "masks",
                                                          "pattern": "{prompt}/{stem}.png"}}}),
    "orchard-apple": ("orchard", {"segmentation": {"prompts": ["apple"]}}),
    "plant-berry": ("plant", {"segmentation": {"prompts": ["berry"]}, "occupancy": {"avoid": []}}),
    "orchard-lens": ("orchard", {"orchard": {"width": 605, "height": 806, "distortion": PHONE_LENS}}),
    "orchard-front": ("orchard", {"orchard": {"arc_deg": FRONT_ARC_DEG}}),
}
# Variants whose images are another capture's: only the prompts differ, and nerfacto never sees the
# masks, so it trains on the same images.zarr with the same split and its numbers are that capture's
SAME_IMAGES = {"orchard-apple": "orchard", "plant-berry": "plant"}
FIVE_MINUTES = 300.0
NERFACTO_MINUTES = (1, 2, 5, 10)  # the panel's nerfacto_psnr_{1,2,5,10}min (peers.py --panel)
THIN_PART_PX = 5  # plant-small: parts thinner than this vanish from every third view's masks
MASK_BLUR_PX = 1.5  # plant-small: Gaussian sigma of the masks' soft edges


def shared_paths(value):
    """Paths of a scene file that lead into ../shared/data, made absolute (the work directory is elsewhere)."""
    if isinstance(value, dict):
        return {k: shared_paths(v) for k, v in value.items()}
    if isinstance(value, list):
        return [shared_paths(v) for v in value]
    if isinstance(value, str) and value.startswith("../shared/data/"):
        return str(SHARED / value[len("../shared/data/"):])
    return value


def parse_overrides(assignments: list[str]) -> dict:
    """`--set section.key=value` (YAML values) as nested scene sections: a candidate default."""
    overrides: dict = {}
    for assignment in assignments:
        key, sep, value = assignment.partition("=")
        section, dot, name = key.partition(".")
        if not (sep and dot and section and name):
            raise SystemExit(f"--set {assignment!r}: expected SECTION.KEY=VALUE, e.g. train.distortion=0.002")
        overrides.setdefault(section, {})[name] = yaml.safe_load(value)
    return overrides


def scene_configs(names: list[str], quick: bool, candidate: dict | None = None) -> dict[str, dict]:
    scenes = {}
    for name in names:
        base, overrides = VARIANTS.get(name, (name, {}))
        scene = yaml.safe_load((REPO / "config" / "scenes" / f"{base}.yaml").read_text()) or {}
        scene = shared_paths(renamed_paths(merge(scene, overrides), f"results/{base}/", f"results/{name}/"))
        for key, value in overrides.items():  # nested overrides replace whole sub-sections
            if isinstance(value, dict):
                for sub, inner in value.items():
                    scene[key][sub] = inner
        if name == "fox" and quick:
            scene.setdefault("poses", {})["refine"] = "none"
        if quick:
            scene.setdefault("train", {})["time_budget"] = 60
        else:  # the field's weights at 5 minutes: the panel's srfpipe_psnr_5min, from the same run
            scene.setdefault("train", {})["snapshot_seconds"] = [FIVE_MINUTES]
        for section, values in (candidate or {}).items():
            scene[section] = {**scene.get(section, {}), **values}
        scenes[name] = scene
    return scenes


def prepare_soft_partial_masks(workdir: Path, name: str, scene: dict) -> Path:
    """plant-small's masks from its generated ground-truth labels: soft edges everywhere, and the
    parts thinner than THIN_PART_PX gone from every third view (a morphological opening), as a
    segmenter's masks of a thin plant look. One PNG per prompt and frame, 0-255."""
    capture = workdir / "results" / name / "capture" / "ground_truth"
    values = scene["segmentation"]["import"].get("values") or {}
    if not values:  # the plant's label values, from its own scene file
        values = yaml.safe_load((REPO / "config" / "scenes" / "plant.yaml").read_text())["segmentation"]["import"]["values"]
    return write_soft_partial_masks(capture / "labels", values, workdir / "prepared" / name / "masks", MASK_BLUR_PX)


def write_soft_partial_masks(labels: Path, values: dict, out: Path, blur_px: float) -> Path:
    """{prompt}/{frame}.png under `out` from the truth's label images in `labels`: each prompt's
    pixels (`values`: prompt -> label value(s)), parts thinner than THIN_PART_PX opened away in
    every third view, then a Gaussian blur of sigma `blur_px`, 0-255."""
    import cv2

    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (THIN_PART_PX, THIN_PART_PX))
    for index, path in enumerate(sorted(labels.glob("*.png"))):
        label = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        for prompt, value in values.items():
            mask = np.isin(label, np.atleast_1d(value)).astype(np.uint8)
            if index % 3 == 1:
                mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel)
            soft = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), blur_px)
            (out / prompt).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(out / prompt / path.name), np.round(255 * np.clip(soft, 0, 1)).astype(np.uint8))
    return out


MASK_BLUR_SWEEP = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0)


def mask_blur_sweep(workdir: Path, extra: tuple) -> int:
    """`--mask-blur-sweep`: plant-small's masks made at each blur of MASK_BLUR_SWEEP (its own is
    MASK_BLUR_PX), imported and composited by the stages' own functions as given and on each class's
    own scale (`labels.rescale_soft_masks`), scored against the truth on the labelled training views
    (every prompt's class kept, so a class its masks lose scores 0). Writes captures_mask_blur_sweep.json."""
    import shutil
    import tempfile

    from srfpipe.artifacts import meta, open_artifact
    from srfpipe.config import validate_scene
    from srfpipe.evaluate import mask_agreement
    from srfpipe.segment.composite import composite_masks, read_frames
    from srfpipe.segment.run import prompt_options, segment_images
    from srfpipe.srf.data import load_posed_images, split_views

    name = "plant-small"
    scenes = scene_configs([name], quick=False)
    write_workdir(workdir, scenes, "occupancy")
    prepare_variants(workdir, scenes, extra)
    run_workflow(workdir, [f"results/{name}/labels.zarr"], log=workdir / "snakemake.log", extra=extra)
    results = workdir / "results" / name
    scene = validate_scene(scenes[name])
    prompts = scene["segmentation"]["prompts"]
    values = yaml.safe_load((REPO / "config" / "scenes" / "plant.yaml").read_text())["segmentation"]["import"]["values"]
    train, _ = split_views(read_frames(results / "images.zarr").count, holdout_every(scenes[name]))
    rows = {}
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        for blur in MASK_BLUR_SWEEP:
            folder = Path(tmp) / f"blur-{blur:g}"
            write_soft_partial_masks(results / "capture" / "ground_truth" / "labels", {p: values[p] for p in prompts},
                                     folder / "png", blur)
            section = {**scene["segmentation"], "import": {**scene["segmentation"]["import"], "path": str(folder / "png")}}
            masks = [segment_images(results / "images.zarr", prompt, prompt_options(section, prompt),
                                    folder / f"{prompt}.zarr", progress=False) for prompt in prompts]
            row = {}
            for mode, rescale in (("as_given", False), ("own_scale", True)):
                labels = composite_masks(results / "images.zarr", masks,
                                         {**scene["labels"], "rescale_soft_masks": rescale, "keep_empty_classes": True},
                                         folder / f"labels-{mode}.zarr", progress=False)
                data = load_posed_images(results / "images.zarr", labels)
                agreement = mask_agreement(data, train)
                row[mode] = {"miou_classes": agreement["miou_masks_gt_classes"],
                             "iou": {c: agreement["iou_masks_gt"][c] for c in prompts},
                             "object_iou": agreement["object_iou_masks_gt"]}
            row["highest_probability"] = meta(open_artifact(labels))["highest_probability"]  # either reading's
            rows[f"{blur:g}"] = row
            shutil.rmtree(folder)
            print(f"blur {blur:g} px: highest {', '.join(f'{p} {h:.2f}' for p, h in row['highest_probability'].items())}; "
                  f"class mIoU as given {row['as_given']['miou_classes']:.3f}, own scale {row['own_scale']['miou_classes']:.3f}")
    path = result_path("captures_mask_blur_sweep", False)
    write_result(path, {"what": mask_blur_sweep.__doc__.split("Writes")[0].strip(), "scene": name,
                        "panel_blur_px": MASK_BLUR_PX, "thin_part_px": THIN_PART_PX, "threshold": 0.5,
                        "blur_px": rows, "machine": machine_info()})
    return 0


def prepare_variants(workdir: Path, scenes: dict[str, dict], extra: tuple) -> None:
    """What a generated variant needs before the workflow builds it: plant-small's masks are made
    from its own generated capture."""
    if "plant-small" in scenes:
        run_workflow(workdir, ["results/plant-small/capture"], log=workdir / "snakemake.log", extra=extra)
        prepare_soft_partial_masks(workdir, "plant-small", scenes["plant-small"])


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
                    "floater_fraction", "significant_samples_per_ray", "views", "miou_classes",
                    "train_view_psnr", "generalization_gap_db", "overfit", "miou_masks_gt", "miou_masks_gt_classes",
                    "iou_masks_gt", "train_view_psnr_borrowed_appearance", "appearance_gap_db", "object_iou_gt",
                    "miou_gt_classes_on_object", "object_iou_masks_gt"):
            if key in metrics:
                report[key] = metrics[key]
    labels = results / name / "labels.zarr"
    if labels.exists():
        info = read_provenance(labels)
        report["bounds"] = {"box": info.get("bounds_world"), "source": info.get("bounds_source"),
                            "poses_box": info.get("bounds_poses"), "hull": info.get("bounds_hull"),
                            "semantic_box": info.get("semantic_bounds_world"),
                            "background": info.get("background")}
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
        report.update(five_minute_metrics(results / name, info))
    occupancy = results / name / "occupancy.zarr"
    report["distill_ok"] = occupancy.exists()
    if occupancy.exists():
        info = read_provenance(occupancy)
        report["occupancy"] = {"grid": info.get("grid"), "resolution": info.get("resolution"),
                               "occupied_voxels": (info.get("counts") or {}).get("occupied_voxels")}
    report["rule_seconds"] = {rule: rule_seconds(workdir, name, rule)
                              for rule in ("poses", "downscale", "segment_*", "composite", "train", "evaluate", "distill")}
    return report


def stale_fields(results: Path, scenes: dict[str, dict]) -> list[str]:
    """Scenes whose srf.zarr records train settings other than their scene file's (a build that
    did not retrain after the candidate or the step count changed)."""
    from srfpipe.artifacts import read_provenance
    from srfpipe.settings import TrainSettings

    defaults = TrainSettings.from_options({}).as_dict()  # what a field recorded before a key existed
    stale = []
    for name, scene in scenes.items():
        srf = results / name / "srf.zarr"
        if not srf.exists():
            continue
        trained = {**defaults, **read_provenance(srf).get("config", {})}
        # values the trainer resolves from the data (auto, null) are recorded resolved: not compared
        asked = {k: v for k, v in scene.get("train", {}).items()
                 if k != "snapshot_seconds" and v is not None and v != "auto"}
        if any(trained.get(k) != v for k, v in asked.items()):
            stale.append(name)
    return stale


def five_minute_metrics(results: Path, info: dict) -> dict:
    """Held-out PSNR and SSIM of the run's snapshot at FIVE_MINUTES of training (what one 10-minute
    run had reached by then), rendered by the same code as peers.py's; empty without that snapshot."""
    from peers import SrfRenderer, read_views, srf_snapshots

    snapshots = srf_snapshots(results / "srf.ckpt", info.get("fingerprint"))
    if not snapshots:
        return {}
    path = min(snapshots, key=lambda p: abs(snapshots[p] - FIVE_MINUTES))
    views = read_views(results / "images.zarr")
    metrics = SrfRenderer(results / "srf.zarr", views, np.asarray(info["heldout_views"])).metrics(Path(path))
    return {"psnr_5min": metrics["psnr"], "ssim_5min": metrics["ssim"], "snapshot_5min_seconds": snapshots[path]}


def reference_scenes(results: Path, scenes: dict[str, dict]) -> dict[str, dict]:
    """`<name>-reference`: each scene whose images.zarr has another factor than REFERENCE_DOWNSCALE,
    at that factor (its own capture and labels: paths into its results folder follow the name)."""
    from srfpipe.artifacts import read_provenance

    references = {}
    for name, scene in scenes.items():
        if name in VARIANTS:  # the earlier runs' resolution matters for the captures they measured only
            continue
        images = results / name / "images.zarr"
        if images.exists() and read_provenance(images).get("downscale") != REFERENCE_DOWNSCALE:
            reference = merge(scene, {"images": {"downscale": REFERENCE_DOWNSCALE}})
            references[f"{name}-reference"] = renamed_paths(reference, f"results/{name}/", f"results/{name}-reference/")
    return references


def reference_report(workdir: Path, name: str) -> dict:
    """The scene's field on its reference scene's held-out views (the evaluate stage's
    `evaluate_field`, into results/<name>/eval-reference)."""
    from srfpipe.evaluate import evaluate_field
    from srfpipe.srf.data import load_posed_images
    from srfpipe.srf.query import SemanticRadianceField

    results, reference = workdir / "results" / name, workdir / "results" / f"{name}-reference"
    out = results / "eval-reference"
    # in process, not `srfpipe evaluate`: that refuses images the field was not trained on, and these are
    # deliberately the same capture at the reference resolution (evaluate_field renders any build's views)
    options = yaml.safe_load((workdir / "config" / "scenes" / f"{name}.yaml").read_text()).get("evaluate") or {}
    field = SemanticRadianceField.load(results / "srf.zarr", "auto")
    data = load_posed_images(reference / "images.zarr", reference / "labels.zarr")
    metrics = evaluate_field(field, data, out, options, reference / "labels.zarr", results / "srf.zarr")
    return {"downscale": REFERENCE_DOWNSCALE, **{k: metrics[k] for k in REFERENCE_KEYS if k in metrics}}


def montage(results: Path, names: list[str], path: Path) -> None:
    """First held-out render of each scene, top row only (render | semantics | depth), stacked.

    Each scene's row is kept beside the figure (`<figure>_rows/NAME.png`) and the figure is stacked
    from those rows in PANEL's order: a run of some scenes replaces their rows and keeps the others'."""
    import cv2

    rows_dir = path.with_name(path.stem + "_rows")
    rows_dir.mkdir(exist_ok=True)
    for name in names:
        renders = sorted((results / name / "eval" / "renders").glob("*.png"))
        if not renders:
            continue
        figure = cv2.imread(str(renders[0]))
        top = figure[: figure.shape[0] // 2]
        scale = 240 / top.shape[0]
        top = cv2.resize(top, (int(top.shape[1] * scale), 240), interpolation=cv2.INTER_AREA)
        cv2.putText(top, name, (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
        cv2.imwrite(str(rows_dir / f"{name}.png"), top)
    order = list(PANEL) + sorted(p.stem for p in rows_dir.glob("*.png") if p.stem not in PANEL)
    rows = [cv2.imread(str(rows_dir / f"{name}.png")) for name in order if (rows_dir / f"{name}.png").exists()]
    if not rows:
        return
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
    cv2.imwrite(str(path), np.concatenate(rows, axis=0))
    print(f"wrote {path}")


def panel_entry(scene: dict, peers: dict) -> dict:
    """The issue's panel keys for one capture, from its entry (and peers.json's, when it has the capture)."""
    bounds = scene.get("bounds") or {}
    budgets = peers.get("budgets") or {}
    return {
        "psnr": scene.get("psnr"), "ssim": scene.get("ssim"), "psnr_object": scene.get("psnr_object"),
        "miou_classes": scene.get("miou_gt_classes", scene.get("miou_classes")),
        # the masks the field learned from, against the truth on the training views: their ceiling
        "masks_miou_classes": scene.get("miou_masks_gt_classes"),
        "train_view_psnr": scene.get("train_view_psnr"), "generalization_gap_db": scene.get("generalization_gap_db"),
        **{f"nerfacto_psnr_{minutes}min": ((budgets.get(str(60 * minutes)) or {}).get("nerfacto") or {}).get("psnr")
           for minutes in NERFACTO_MINUTES},
        # from this run's own 5-minute snapshot (peers.json's srfpipe runs used other presets and images)
        "srfpipe_psnr_5min": scene.get("psnr_5min"),
        "bounds_source": bounds.get("source"), "steps": scene.get("steps"),
        **({"nerfacto_same_images_as": peers["same_images_as"]} if "same_images_as" in peers else {}),
        # nerfacto's own gap on the same training views (own embedding) at 10 minutes, where measured
        **({f"nerfacto_{key}": peers["training_views"].get(key) for key in
            ("train_view_psnr", "train_view_psnr_average_appearance", "generalization_gap_db")}
           if peers.get("training_views") else {}),
    }


def peers_by_scene() -> dict:
    """peers.json's entry of each scene it measured (empty when the file is absent)."""
    path = REPO / "benchmarks" / "results" / "peers.json"
    if not path.exists():
        return {}
    report = json.loads(path.read_text())
    side_by_side = {name: report[name] for name in report.get("scenes", []) if isinstance(report.get(name), dict)}
    nerfacto_alone = report.get("panel") or {}  # measured on the panel's own builds: these win
    peers = {name: {"budgets": {b: {**((side_by_side.get(name) or {}).get("budgets", {}).get(b) or {}),
                                    **((nerfacto_alone.get(name) or {}).get("budgets", {}).get(b) or {})}
                                for b in (str(60 * minutes) for minutes in NERFACTO_MINUTES)}}
             for name in {*side_by_side, *nerfacto_alone}}
    for name, entry in nerfacto_alone.items():
        if entry.get("training_views"):
            peers[name]["training_views"] = entry["training_views"]
    for name, same in SAME_IMAGES.items():
        if name not in peers and same in peers:
            peers[name] = {**peers[same], "same_images_as": same}
    return peers


MASK_THRESHOLDS = (0.25, 0.3, 0.35, 0.4, 0.45, 0.5)


def mask_ceiling(results: Path, scene: dict) -> dict:
    """The composited masks of a capture with ground truth against that truth on its labelled training
    views (`srfpipe.evaluate.mask_agreement`, as evaluate reports it), from labels.zarr alone, and the
    same mIoU of the classes had they been composited at each of MASK_THRESHOLDS
    (`segmentation.threshold`) instead of the built one (`miou_masks_gt_classes_by_threshold`)."""
    from srfpipe.evaluate import mask_agreement
    from srfpipe.srf.data import load_posed_images, split_views

    data = load_posed_images(results / "images.zarr", results / "labels.zarr")
    if data.gt_label is None or not data.classes:
        return {}
    train, _ = split_views(data.count, holdout_every(scene))
    return {**mask_agreement(data, train), **mask_ceiling_by_threshold(data, results / "masks", train)}


def mask_ceiling_by_threshold(data, masks_dir: Path, train: np.ndarray) -> dict:
    """mIoU of the classes against the truth on the labelled training views `train` of `data` (with
    ground truth), the per-prompt masks in `masks_dir` composited at each of MASK_THRESHOLDS as given
    (`labels.rescale_soft_masks` false: the thresholds apply to the masks' own values)."""
    import zarr

    from srfpipe.segment.composite import label_image
    from srfpipe.srf import metrics
    from srfpipe.srf.data import remap_ground_truth

    views = train if data.labelled is None else train[data.labelled[train]]
    masks = [zarr.open_group(masks_dir / f"{prompt}.zarr", mode="r")["probability"] for prompt in data.classes]
    values = list(range(1, len(data.classes) + 1))
    confusion = {t: np.zeros((len(values) + 1,) * 2, np.int64) for t in MASK_THRESHOLDS}
    for index in views:
        probability = np.stack([np.asarray(m[int(index)]) for m in masks]).astype(np.float32) / 255.0
        truth = remap_ground_truth(data.gt_label[index], data.gt_classes, data.classes)
        for t in MASK_THRESHOLDS:
            confusion[t] += metrics.confusion(label_image(probability, [t] * len(values), values), truth, len(values) + 1)
    return {"miou_masks_gt_classes_by_threshold": {
        f"{t:g}": float(np.nanmean(metrics.iou_from_confusion(c)[1:])) for t, c in confusion.items()}}


def measure_masks_only(workdir: Path, names: list[str], path: Path, extra: tuple) -> int:
    """`--masks-only`: build each capture up to labels.zarr (no training) and add the masks' ceiling
    (miou_masks_gt...) to its entry in captures.json, keeping everything else."""
    scenes = scene_configs(names, quick=False)
    write_workdir(workdir, scenes, "occupancy")
    prepare_variants(workdir, scenes, extra)
    run_workflow(workdir, [f"results/{name}/labels.zarr" for name in scenes], log=workdir / "snakemake.log", extra=extra)
    report = json.loads(path.read_text())
    for name, scene in scenes.items():
        ceiling = mask_ceiling(workdir / "results" / name, scene)
        report["scenes"].setdefault(name, {}).update(ceiling)
        if ceiling:
            print(f"{name:14} masks against the truth: mIoU of the classes {ceiling['miou_masks_gt_classes']:.3f} "
                  f"({', '.join(f'{k} {v:.2f}' for k, v in ceiling['iou_masks_gt'].items() if v is not None)}); "
                  "composited at " + ", ".join(f"{t} {v:.3f}" for t, v in
                                              ceiling["miou_masks_gt_classes_by_threshold"].items()))
    write_result(path, report)
    return refresh_panel(path)


def refresh_panel(path: Path) -> int:
    """Rebuild captures.json's `panel` from its scenes and the current peers.json, building nothing:
    nerfacto's numbers (peers.py --panel) are measured once, apart from srfpipe's runs."""
    report = json.loads(path.read_text())
    peers = peers_by_scene()
    report["panel"] = {name: panel_entry(report["scenes"][name], peers.get(name, {}))
                       for name in PANEL if name in report["scenes"]}
    write_result(path, report)
    return 0


def candidate_slug(overrides: dict) -> str:
    """The candidate's file-name part: train.distortion-0.01 (and -equal-steps), one file per candidate."""
    parts = [f"{section}.{key}-{value}" for section, values in overrides.items() if isinstance(values, dict)
             for key, value in values.items()]
    parts += ["equal-steps"] if overrides.get("equal_steps") else []
    return "_".join(parts).replace("/", "-").replace(" ", "")


def equal_steps(scenes: dict[str, dict], quick: bool) -> None:
    """Each scene trains for the steps its defaults reached (captures.json `steps`), time budget off:
    a slower or faster machine than the one that measured the defaults compares step for step."""
    for name, scene in scenes.items():
        scene["train"] = {**scene.get("train", {}), "iterations": measured_steps(name, quick), "time_budget": 0}
        scene["train"].pop("snapshot_seconds", None)


CHANGE_KEYS = ("psnr", "ssim", "psnr_object", "miou_classes", "train_view_psnr", "generalization_gap_db")
# issue "captures nobody tuned for": a change that costs any capture more than this is a scene option
DEFAULT_TOLERANCE_DB = 0.3


def candidate_change(panel: dict, baseline_files: list[Path]) -> tuple[dict, dict]:
    """Each capture's candidate numbers minus the defaults' panel entry from the first of
    `baseline_files` that has the capture at the candidate's steps (else the first that has it: the
    equal-steps baseline may hold an older panel's steps); and which file that was, per capture."""
    baselines = [(path, json.loads(path.read_text()).get("panel", {})) for path in baseline_files if path.exists()]
    change, used = {}, {}
    for name, entry in panel.items():
        having = [(path, b[name]) for path, b in baselines if name in b]
        same_steps = [(path, base) for path, base in having if base.get("steps") == entry.get("steps")]
        path, base = (same_steps or having or [(None, {})])[0]
        used[name] = path.name if path else None
        change[name] = {key: entry[key] - base[key] for key in CHANGE_KEYS
                        if isinstance(entry.get(key), float) and isinstance(base.get(key), float)}
    return change, used


def print_change(overrides: dict, change: dict, baselines: dict) -> None:
    print(f"candidate {overrides} against the defaults:")
    print(f"{'capture':14} " + " ".join(f"{k[:12]:>12}" for k in CHANGE_KEYS) + "  baseline")
    for name, delta in change.items():
        print(f"{name:14} " + " ".join(f"{delta[k]:+12.2f}" if k in delta else f"{'-':>12}" for k in CHANGE_KEYS)
              + f"  {baselines.get(name)}")
    worst = min((d["psnr"] for d in change.values() if "psnr" in d), default=None)
    if worst is not None:
        print(f"worst held-out PSNR change {worst:+.2f} dB: "
              f"{'within' if worst >= -DEFAULT_TOLERANCE_DB else 'beyond'} the {DEFAULT_TOLERANCE_DB} dB a default may cost")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="60 s of training, no COLMAP refinement")
    parser.add_argument("--workdir", type=Path, default=REPO / "benchmarks" / "work" / "captures")
    parser.add_argument("--scenes", nargs="+", default=list(PANEL), choices=PANEL)
    parser.add_argument("--panel-only", action="store_true",
                        help="rebuild captures.json's panel from its scenes and peers.json (after peers.py --panel), build nothing")
    parser.add_argument("--snakemake-args", nargs=argparse.REMAINDER, default=[],
                        help="more Snakemake arguments (last), e.g. --rerun-triggers mtime to keep a "
                             "finished COLMAP refinement after a schema default changed")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="a candidate default, set in every scene (repeatable): the run writes "
                             "captures_candidate_<candidate>.json with each capture's change against captures.json's panel, "
                             "in its own work directory (captures-candidate)")
    parser.add_argument("--equal-steps", action="store_true",
                        help="train each capture for the steps its captures.json entry reached in its 10 minutes "
                             "(time budget off), so a candidate (--set) compares with the defaults on any machine; "
                             "alone, it measures the defaults so (captures_candidate_equal-steps.json), the baseline "
                             "that equal-steps candidates are then compared with: the same code and schedule, so "
                             "a difference is the candidate's, not the machine's or the code's since captures.json")
    parser.add_argument("--masks-only", action="store_true",
                        help="build the scenes up to labels.zarr (no training) and add the masks' own mIoU against "
                             "ground truth (masks_miou_classes) to captures.json")
    parser.add_argument("--mask-blur-sweep", action="store_true",
                        help="plant-small's masks at blurs of 0.5 to 3 px, composited as given and on each class's own "
                             "scale, against the truth (no training): captures_mask_blur_sweep.json")
    args = parser.parse_args()
    if args.mask_blur_sweep:
        return mask_blur_sweep(args.workdir, tuple(args.snakemake_args))
    if args.masks_only:
        return measure_masks_only(args.workdir, args.scenes, result_path("captures", args.quick), tuple(args.snakemake_args))
    if args.panel_only:
        return refresh_panel(result_path("captures", args.quick))
    for name in args.scenes:
        source = (yaml.safe_load((REPO / "config" / "scenes" / f"{VARIANTS.get(name, (name,))[0]}.yaml").read_text())
                  .get("source", {}))
        path = shared_paths(source.get("path", ""))
        if path.startswith(str(SHARED)) and not Path(path).exists():
            parser.error(f"{path}: the {name} capture is not there (../shared/data beside the repository)")

    overrides = parse_overrides(args.overrides)
    if overrides and args.workdir == parser.get_default("workdir"):
        args.workdir = args.workdir.with_name("captures-candidate")
    scenes = scene_configs(args.scenes, args.quick, overrides)
    if args.equal_steps:
        equal_steps(scenes, args.quick)
        if args.workdir == parser.get_default("workdir"):
            args.workdir = args.workdir.with_name("captures-candidate")
        overrides = {**overrides, "equal_steps": True}
    write_workdir(args.workdir, scenes, "occupancy")
    prepare_variants(args.workdir, scenes, tuple(args.snakemake_args))
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
    previous_file = result_path(f"captures_candidate_{candidate_slug(overrides)}" if overrides else "captures", args.quick)
    # a capture whose build stopped before its held-out metrics (a failed job, --until) measured nothing:
    # its earlier measurement stays, never an empty row in its place; nor does a field that an earlier
    # build trained with other settings (Snakemake under --rerun-triggers mtime did not retrain it)
    for name in stale_fields(results, scenes):
        print(f"{name}: srf.zarr was not trained with this run's train settings (stale; add --forcerun train)")
        per_scene[name]["psnr"] = None
    unmeasured = sorted(name for name, entry in per_scene.items() if entry.get("psnr") is None)
    if unmeasured:
        print(f"no held-out metrics for {', '.join(unmeasured)}: their earlier entries are kept")
    per_scene = {name: entry for name, entry in per_scene.items() if name not in unmeasured}
    if not per_scene:
        print(f"nothing measured: {previous_file} is left as it was")
        return 1
    measured_now = sorted(per_scene)
    machine = machine_info(quick=args.quick)
    for entry in per_scene.values():  # each row names its host: a run of some captures keeps the others' rows
        entry["machine"] = machine
    previous_configs = {}
    previous_report = json.loads(previous_file.read_text()) if previous_file.exists() else {}
    for note in host_speed_notes(previous_report, per_scene, machine):
        print(f"warning: {note}")
    if previous_report and previous_report.get("overrides", {}) == overrides:
        # a run of some scenes keeps the others' last measurement (of the same candidate)
        previous_configs = previous_report.get("scene_configs", {})
        per_scene = {**earlier_measurements(previous_report.get("scenes", {}), per_scene), **per_scene}
    peers = peers_by_scene()
    panel = {name: panel_entry(per_scene[name], peers.get(name, {})) for name in PANEL if name in per_scene}
    report: dict = {"overrides": overrides, "scenes": per_scene, "panel": panel, "measured_now": measured_now,
                    "workflow_seconds": seconds,
                    "machine": machine,
                    "scene_configs": {**{k: v for k, v in previous_configs.items() if k in per_scene},
                                      **{k: v for k, v in scenes.items() if k in measured_now}}}
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
    if overrides:
        # an equal-steps candidate against the defaults at equal steps where measured, else captures.json
        baselines = [result_path("captures", args.quick)]
        if overrides.get("equal_steps") and set(overrides) != {"equal_steps"}:
            baselines.insert(0, result_path("captures_candidate_equal-steps", args.quick))
        report["change"], report["change_baseline"] = candidate_change(panel, baselines)
        write_result(previous_file, report)
        print_change(overrides, report["change"], report["change_baseline"])
        return 0
    # every scene in the report whose renders are in the work directory, measured now or earlier
    montage(results, list(per_scene), REPO / "benchmarks" / "results" / f"captures{'_quick' if args.quick else ''}.png")
    write_result(result_path("captures", args.quick), report)

    columns = ("psnr", "ssim", "psnr_object", "miou_classes", "train_view_psnr", "nerfacto_psnr_10min")
    print(f"{'capture':14} " + " ".join(f"{c[:12]:>12}" for c in columns) + f" {'bounds':>12} {'steps':>6} distill")
    for name, entry in panel.items():
        cells = " ".join(f"{entry[c]:12.3f}" if isinstance(entry[c], float) else f"{'-':>12}" for c in columns)
        print(f"{name:14} {cells} {str(entry['bounds_source']):>12} {str(entry['steps']):>6} "
              f"{per_scene[name].get('distill_ok')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Evaluate a trained SRF on its held-out views: PSNR, SSIM, per-class IoU and mIoU -> eval/.

The held-out views are the ones the trainer excluded (recorded in srf.zarr; `split_views`).
Writes `metrics.json` (and the same as an HTML table, `metrics.html`), one PNG per view (top:
render | semantic blend | depth; bottom: the captured image | its reference labels | render
opacity), like the paper's figure 1, and the training curve (`training_curve.svg`) for the report.
IoU is computed on label images: a pixel takes the most probable class whose probability
is >= 0.5, background otherwise; `miou` averages over the trained classes and background.

A generalization check: a few training views (`evaluate.train_views`, evenly spaced) are rendered
the same way and scored (`train_view_psnr`, no renders written); `generalization_gap_db` is that
minus the held-out `psnr`, and a gap above GENERALIZATION_GAP_DB sets `overfit` and logs a warning,
with the setting that narrowed such gaps on the panel where it applies (`overfit_remedy`).
A field with per-image appearance embeddings renders those views once more with the appearance a
new view at their pose borrows (`train_view_psnr_borrowed_appearance`): `appearance_gap_db`, the
part of the gap that is each training image's own embedding rather than the geometry.
Sparse labels: when some training frames had no masks and the capture has ground truth, a few of
them (`evaluate.unlabelled_views`) are scored against it too (`miou_unlabelled_gt`).
The masks' own ceiling: on a capture with ground truth, the composited labels of the labelled
training views are scored against it (`miou_masks_gt`, `iou_masks_gt`): a field that learns from
masks rarely beats them, so a low held-out `miou_gt` beside a low `miou_masks_gt` says the masks,
not the field, limit it.

A field with zero classes (a capture without masks) has nothing to segment and no reference
labels to say which pixels are objects: its metrics are `psnr` and `ssim` only (no `psnr_object`,
no IoU keys; accumulation is no stand-in for objects, since with a contracted background every
pixel is opaque), and its renders drop the semantic panels (render | depth over image | opacity).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from srfpipe import cameras
from srfpipe.srf.trainer import SURROUNDING_SCENE_DISTORTION, round_a_subject_in_a_scene

log = logging.getLogger("srfpipe.evaluate")

# RGB colours for the default class table (apple, branch, leaf) and a fallback palette.
DEFAULT_COLOURS = {"apple": (220, 30, 30), "branch": (140, 90, 40), "leaf": (40, 200, 60)}
PALETTE = [(230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48), (145, 30, 180)]


def add_arguments(parser) -> None:
    from srfpipe.config import add_options_arguments

    parser.add_argument("--images", required=True, metavar="ZARR", help="images.zarr (stage downscale)")
    parser.add_argument("--labels", required=True, metavar="ZARR", help="labels.zarr (stage composite)")
    parser.add_argument("--srf", required=True, metavar="ZARR", help="srf.zarr (stage train)")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (metrics.json, renders/)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    parser.add_argument("--device", default="auto", help="auto | cpu | cuda")
    add_options_arguments(parser, "evaluate")


def run(args) -> int:
    from srfpipe.config import stage_options

    options = stage_options(args, "evaluate")
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    metrics = evaluate(args.images, args.labels, args.srf, args.out, options, device=args.device)
    summary = {k: metrics[k] for k in ("psnr", "psnr_object", "ssim", "miou", "miou_gt", "miou_masks_gt", "miou_unlabelled_gt",
                                       "floater_fraction", "train_view_psnr", "generalization_gap_db", "overfit")
               if k in metrics}
    print(json.dumps(summary))
    return 0


def class_colours(classes: list[str], label_attrs: dict | None = None) -> np.ndarray:
    """(C + 1, 3) uint8 colours: background black, then one per class (NGFF table when given)."""
    colours = np.zeros((len(classes) + 1, 3), dtype=np.uint8)
    table = {}
    for entry in ((label_attrs or {}).get("image-label") or {}).get("colors", []) or []:
        if isinstance(entry, dict) and "label-value" in entry and "rgba" in entry:
            table[int(entry["label-value"])] = entry["rgba"][:3]
    for i, name in enumerate(classes):
        colours[i + 1] = table.get(i + 1, DEFAULT_COLOURS.get(name, PALETTE[i % len(PALETTE)]))
    return colours


def class_rgba(classes: list[str]) -> dict[str, list[float]]:
    """Each class's colour in the evaluation renders (class_colours, default table) as opaque RGBA in
    [0, 1], by class name: the colours of the simulator package's class meshes (srfpipe.sim.package)."""
    colours = class_colours(classes)
    return {name: [float(c) / 255 for c in colours[classes.index(name) + 1]] + [1.0] for name in classes}


def semantic_blend(rgb: np.ndarray, label: np.ndarray, colours: np.ndarray, alpha: float = 0.6) -> np.ndarray:
    """rgb (H, W, 3) float in [0, 1] blended with class colours where label > 0 -> uint8."""
    base = (np.clip(rgb, 0, 1) * 255).astype(np.float32)
    tint = colours[label].astype(np.float32)
    out = np.where((label > 0)[..., None], (1 - alpha) * base + alpha * tint, base * 0.5)
    return out.astype(np.uint8)


def depth_image(depth: np.ndarray, near: float, far: float) -> np.ndarray:
    """Colour-mapped inverse depth (turbo: near red, far blue), black where there is no depth.

    Inverse depth, as mip-NeRF 360 shows unbounded scenes: linear depth spends the whole colour
    range on the background (the orchard's sky lies 100x farther than its tree), which leaves the
    object and the ground it stands on one colour."""
    import cv2

    valid = np.isfinite(depth) & (depth > 0)
    near = max(near, 1e-9)
    far = max(far, near * (1 + 1e-6))
    disparity = 1.0 / np.maximum(np.where(valid, depth, far), 1e-9)
    norm = np.clip((disparity - 1.0 / far) / (1.0 / near - 1.0 / far), 0, 1)
    coloured = cv2.applyColorMap((255 * norm).astype(np.uint8), cv2.COLORMAP_TURBO)[..., ::-1]
    return np.where(valid[..., None], coloured, 0).astype(np.uint8)


def evaluate(images, labels, srf, out, options: dict, device="auto") -> dict:
    """Compute the metrics and renders; write them to `out` atomically; return the metrics.

    The images and labels must be the ones srf.zarr was trained on (their fingerprints, recorded in
    srf.zarr's inputs): a field scored against another scene's capture is refused, not measured."""
    from srfpipe.artifacts import check_inputs_match
    from srfpipe.srf.data import load_posed_images
    from srfpipe.srf.query import SemanticRadianceField

    from srfpipe.srf.io import read_curve

    check_inputs_match(srf, {"downscale": images, "composite": labels})
    field = SemanticRadianceField.load(srf, device)
    data = load_posed_images(images, labels)
    curves = (read_curve(srf, "curve"), read_curve(srf, "eval_curve"))
    return evaluate_field(field, data, out, options, labels, srf, curves, images=images)


# a held-out view rendered with supersampling stays within this many rays: views of up to 256 x 256
# pixels, where a pixel's footprint is large against thin structure (the plant: +0.56 dB held out at
# 256 px); the fox's 270 x 480 gained nothing for 4x the evaluation time (see the schema)
SUPERSAMPLE_MAX_RAYS = 262144


def default_supersample(width: int, height: int, asked: int | None) -> int:
    """The s of evaluate.supersample: the scene's value, else 2 while s*s*W*H <= SUPERSAMPLE_MAX_RAYS, else 1."""
    if asked is not None:
        return int(asked)
    return 2 if 4 * width * height <= SUPERSAMPLE_MAX_RAYS else 1


# A field that scores this much higher on views it trained on than on held-out ones fits the
# training views with floaters / fog in front of the cameras rather than the scene's surfaces
# (the views it was fitted to look right, a new viewpoint does not): issue 30's threshold.
GENERALIZATION_GAP_DB = 6.0
# What narrowed such a gap where the cameras stand round the subject in a scene (docs/benchmarks.md,
# captures): mip-NeRF 360's distortion loss, the default there (train.distortion null); advice for
# a field trained with it switched off.
DISTORTION_REMEDY = SURROUNDING_SCENE_DISTORTION


def overfit_remedy(train_config: dict, poses_scene, background_empty: bool) -> str | None:
    """The setting to try when a field fits its training views only, or None: `train.distortion`
    when it was off, the background is a scene (not an empty backdrop) and the cameras stand round
    their focus point (`cameras.cameras_surround`)."""
    if train_config.get("distortion") or not round_a_subject_in_a_scene(poses_scene, background_empty):
        return None
    return f"try train.distortion: {DISTORTION_REMEDY} (mip-NeRF 360's distortion loss, against floaters)"


def train_view_choice(train: np.ndarray, count: int) -> np.ndarray:
    """`count` of the training views `train`, evenly spaced (the centres of `count` equal parts of
    the list, so neither end is favoured); all of them when there are no more; none for 0."""
    train = np.asarray(train)
    count = max(0, min(int(count), len(train)))
    if count == 0:
        return train[:0]
    return train[((np.arange(count) + 0.5) * len(train) / count).astype(int)]


def pooled_psnr(renders: list[np.ndarray], targets: list[np.ndarray]) -> float:
    """PSNR over all pixels of all `renders` against their `targets` (one mean squared error, like
    the held-out `psnr`, with the same floor), via srfpipe.srf.metrics.psnr."""
    from srfpipe.srf import metrics

    return metrics.psnr(np.concatenate([r.reshape(-1, 3) for r in renders]),
                        np.concatenate([t.reshape(-1, 3) for t in targets]))


def evaluate_field(field, data, out, options: dict, labels, srf, curves=None, images=None) -> dict:
    """Metrics and renders of `field` on the held-out views of `data` (`PosedImages`), into `out`.

    `field` needs `classes`, `attrs` (holdout_every, train_seconds) and
    `render(camera_to_world, intrinsics, width, height)` like `SemanticRadianceField` (the views go
    to the world through `data`'s own scene frame, so a field of another build measures them too); `labels`
    and `srf` are the paths the data and the field came from (for messages and the record).
    `curves`, srf.zarr's (curve, eval_curve), adds the training curve (`training_curve.svg`).
    metrics.json records its provenance under `srfpipe` (stage evaluate, the options used, the
    inputs `images` (the images.zarr path, when given), `labels` and `srf` with their fingerprints,
    versions), as every artifact does.
    `options` is the `evaluate` section (holdout_every: the field's when not given).
    `evaluate.train_views` training views are rendered the same way
    for `train_view_psnr`, `generalization_gap_db` and `overfit` (see GENERALIZATION_GAP_DB).
    When some training frames had no masks (sparse labels) and the capture has ground truth,
    `evaluate.unlabelled_views` of them are scored against it:
    `iou_unlabelled_gt`, `miou_unlabelled_gt` (how far the field spread the labels it was given).
    """
    from srfpipe.figures import metrics_html, training_curve_svg

    import cv2

    from srfpipe.artifacts import atomic_directory, meta, open_artifact, provenance
    from srfpipe.srf.data import split_views

    out = Path(out)
    if data.label is None:
        raise ValueError(f"{labels}: missing array 'label' (the composited label image)")
    if list(data.classes) != list(field.classes):
        raise ValueError(f"{labels}: classes {data.classes} differ from the SRF's {field.classes} ({srf})")
    from srfpipe.settings import EvaluateSettings

    settings = EvaluateSettings.from_options(
        {"holdout_every": field.attrs.get("holdout_every", EvaluateSettings.holdout_every), **options})
    holdout = settings.holdout_every
    if holdout != int(field.attrs.get("holdout_every", holdout)):
        raise ValueError(
            f"{srf}: trained with holdout_every={field.attrs.get('holdout_every')}, evaluate asks for {holdout}"
        )
    train, heldout = split_views(data.count, holdout)
    supersample = default_supersample(data.width, data.height, settings.supersample)

    def render_view(index, training=False, **render_options):
        """The render of view `index` and its captured image (float64 in [0, 1]); a `training` view
        through its camera as the field refined it (train.camera_refinement)."""
        # the views' own frame: a field trained on other labels of the same capture has another
        pose_world = world_from_scene_pose(data.world_from_scene, data.poses_scene[index].numpy())
        if training and hasattr(field, "training_pose"):
            pose_world = field.training_pose(index, pose_world)
        if training and getattr(field, "has_appearance", False) and "exclude_view" not in render_options:
            # its own appearance, as it trained (not what a new view there would borrow)
            render_options["appearance_view"] = int(index)
        rendered = field.render(pose_world, data.intrinsics[index].numpy(), data.width, data.height, supersample,
                                **render_options)
        return rendered, data.images[index].numpy().astype(np.float64) / 255.0

    semantic = len(data.classes) > 0
    colours = class_colours(data.classes, meta(open_artifact(labels, stage="composite")))
    scores = HeldoutScores(data)
    with atomic_directory(out) as tmp:
        (tmp / "renders").mkdir()
        for index in heldout:
            rendered, target = render_view(index)
            pred_label, reference = scores.add(index, rendered, target)
            _write_figure(tmp / "renders" / f"{data.names[index]}.png", rendered, target, pred_label, reference,
                          colours, cv2)
        result = {"views": len(heldout), "holdout_every": holdout, "supersample": supersample,
                  "classes": list(data.classes), **scores.colour_metrics()}
        result.update(generalization_check(field, data, render_view, train_view_choice(train, settings.train_views),
                                           result["psnr"]))
        result.update(scores.sample_metrics())
        if semantic:
            result.update(scores.semantic_metrics())
            if data.gt_label is not None:
                result.update(mask_agreement(data, train))
            result["labelled_frames"] = int(data.count if data.labelled is None else data.labelled.sum())
            result.update(unlabelled_view_scores(data, render_view, train, settings.unlabelled_views))
        result.update({"label_source": str(labels), "srf": str(srf), "train_seconds": field.attrs.get("train_seconds"),
                       "per_view": scores.per_view})
        record = provenance("evaluate", {**settings.as_dict(), "supersample": supersample},
                            [p for p in (images, labels, srf) if p is not None], complete=True)
        (tmp / "metrics.json").write_text(json.dumps(_clean({**result, "srfpipe": record}), indent=2))
        (tmp / "metrics.html").write_text(metrics_html(_clean(result), title=f"held-out views of {srf}"))
        if curves is not None and len(curves[0].get("step", [])):
            (tmp / "training_curve.svg").write_text(training_curve_svg(*curves))
    _log_result(result, srf, semantic)
    return result


class HeldoutScores:
    """Sums over the held-out views of `data` (`PosedImages`), one `add` a view: squared error over
    all pixels and over the object pixels, the samples' statistics, and the confusion of the
    predicted labels against the composited labels and against the ground truth."""

    def __init__(self, data):
        self.data = data
        self.labels = len(data.classes) + 1
        self.per_view = []
        self.pixels = 0
        self.sq_err, self.sq_err_object, self.object_pixels = 0.0, 0.0, 0
        self.significant, self.floaters = 0.0, 0.0  # samples with weight > 0.03, and those off the ray's surface
        self.candidates, self.kept = 0.0, 0.0  # intervals placed along the rays, and those not skipped as empty
        self.confusion = np.zeros((self.labels, self.labels), np.int64)
        self.confusion_gt = np.zeros_like(self.confusion) if data.gt_label is not None else None
        # the true object's pixels each labelled with its most likely class, against the truth
        self.confusion_gt_on_object = np.zeros_like(self.confusion) if data.gt_label is not None else None

    def add(self, index: int, rendered: dict, target: np.ndarray):
        """Score view `index`'s render against its image; the predicted and reference label images
        for its figure (None, None without classes)."""
        from srfpipe.srf import metrics
        from srfpipe.srf.data import remap_ground_truth

        data = self.data
        err = (rendered["rgb"].astype(np.float64) - target) ** 2
        self.sq_err += float(err.sum())
        self.pixels += err.shape[0] * err.shape[1]
        if "floater_samples" in rendered:
            self.significant += float(rendered["significant_samples"].sum())
            self.floaters += float(rendered["floater_samples"].sum())
        if "candidate_samples" in rendered:
            self.candidates += float(rendered["candidate_samples"].sum())
            self.kept += float(rendered["kept_samples"].sum())
        view = {"name": data.names[index], "index": int(index), "psnr": metrics.psnr(rendered["rgb"], target),
                "ssim": metrics.ssim(rendered["rgb"], target)}
        self.per_view.append(view)
        if self.labels == 1:
            return None, None
        pred_label = metrics.label_from_probabilities(rendered["semantic"])
        reference = data.label[index]
        if data.labelled is None or data.labelled[index]:  # a frame without masks has no reference
            self.confusion += metrics.confusion(pred_label, reference, self.labels)
        if self.confusion_gt is not None:
            reference = remap_ground_truth(data.gt_label[index], data.gt_classes, data.classes)
            self.confusion_gt += metrics.confusion(pred_label, reference, self.labels)
            on_object = np.where(reference > 0, rendered["semantic"].argmax(axis=-1) + 1, 0)
            self.confusion_gt_on_object += metrics.confusion(on_object, reference, self.labels)
        objects = reference > 0
        self.sq_err_object += float(err[objects].sum())
        self.object_pixels += int(objects.sum())
        view["psnr_object"] = metrics.psnr(rendered["rgb"], target, objects)
        return pred_label, reference

    def colour_metrics(self) -> dict:
        """psnr (one mean squared error over every held-out pixel) and ssim (the views' mean)."""
        from srfpipe.srf import metrics

        return {"psnr": metrics.psnr_from_mse(self.sq_err / (self.pixels * 3)),
                "ssim": float(np.mean([v["ssim"] for v in self.per_view]))}

    def sample_metrics(self) -> dict:
        result = {}
        if self.significant:
            # fog and floaters: of the samples that carry weight (> 0.03), the share that lies
            # off the surface each ray sees (srfpipe.srf.model.FLOATER_CELLS from its median depth)
            result["floater_fraction"] = self.floaters / self.significant
            result["significant_samples_per_ray"] = self.significant / self.pixels
        if self.candidates:
            # empty space costs no samples: the share of the intervals placed along the held-out
            # rays that the occupancy grid skipped (the field is never evaluated there)
            result["samples_skipped_fraction"] = 1.0 - self.kept / self.candidates
            result["samples_per_ray"] = self.kept / self.pixels
            result["candidate_samples_per_ray"] = self.candidates / self.pixels
        return result

    def semantic_metrics(self) -> dict:
        """psnr_object and the IoU keys against the composited labels (and `_gt`, the ground truth)."""
        from srfpipe.srf import metrics

        names = ["background"] + list(self.data.classes)
        result = {"psnr_object": metrics.psnr_from_mse(self.sq_err_object / (self.object_pixels * 3))
                  if self.object_pixels else None}
        result.update(_iou_metrics(self.confusion, names, ""))
        if self.confusion_gt is not None:
            result.update(_iou_metrics(self.confusion_gt, names, "_gt"))
            result.update(where_and_which(self.confusion_gt, self.confusion_gt_on_object))
        return result


def where_and_which(confusion_gt: np.ndarray, confusion_on_object: np.ndarray) -> dict:
    """The class mIoU against the truth split in two: `object_iou_gt`, the IoU of the pixels the
    field gives any class with the truth's object pixels (where the object is), and
    `miou_gt_classes_on_object`, the class mIoU over the truth's object pixels alone, each taking
    the field's most likely class (which class it is). A capture whose thin parts span a pixel or
    less loses its mIoU to the first; labels that bleed between classes, to the second."""
    from srfpipe.srf import metrics

    return {"object_iou_gt": object_iou(confusion_gt),
            "miou_gt_classes_on_object": _finite(np.nanmean(metrics.iou_from_confusion(confusion_on_object)[1:]))}


def object_iou(confusion: np.ndarray) -> float | None:
    """IoU of the pixels labelled with any class against the reference's object pixels, from a
    [reference, predicted] confusion whose label 0 is the background."""
    hit = float(confusion[1:, 1:].sum())
    union = hit + float(confusion[0, 1:].sum()) + float(confusion[1:, 0].sum())
    return hit / union if union else None


def generalization_check(field, data, render_view, views, heldout_psnr: float) -> dict:
    """The training views `views` rendered like the held-out ones (through the cameras the field
    was trained with): train_view_psnr, generalization_gap_db, overfit (and overfit_remedy where
    one applies); for a field with per-image appearance, the part of the gap that is each training
    image's own embedding (appearance_gap_db)."""
    rendered, targets = [], []
    for index in views:
        image, target = render_view(index, training=True)
        rendered.append(image["rgb"])
        targets.append(target)
    train_psnr = pooled_psnr(rendered, targets) if rendered else None
    gap = train_psnr - heldout_psnr if train_psnr is not None else None
    result = {"train_view_names": [data.names[i] for i in views], "train_view_psnr": train_psnr,
              "generalization_gap_db": gap, "overfit": bool(gap is not None and gap > GENERALIZATION_GAP_DB)}
    if result["overfit"] and (remedy := overfit_remedy(field.attrs.get("config", {}), data.poses_scene.numpy(),
                                                    data.background_empty)):
        result["overfit_remedy"] = remedy
    if rendered and getattr(field, "has_appearance", False):
        # the same training views with the appearance a new view at their pose gets (the nearest
        # *other* training image's): the part of the gap that is each image's own embedding
        # (exposure, white balance, and whatever else it absorbed), apart from the geometry's
        borrowed = [render_view(index, training=True, exclude_view=int(index))[0]["rgb"] for index in views]
        result["train_view_psnr_borrowed_appearance"] = pooled_psnr(borrowed, targets)
        result["appearance_gap_db"] = train_psnr - result["train_view_psnr_borrowed_appearance"]
    return result


def unlabelled_view_scores(data, render_view, train, count: int) -> dict:
    """Sparse labels: `count` of the training views that had no masks, against the capture's ground
    truth (unlabelled_view_names and the `_unlabelled_gt` IoU keys); {} when every view had masks
    or the capture has no ground truth."""
    from srfpipe.srf import metrics
    from srfpipe.srf.data import remap_ground_truth

    unlabelled = train[:0] if data.labelled is None else train[~data.labelled[train]]
    chosen = train_view_choice(unlabelled, count)
    if not len(chosen):
        return {}
    if data.gt_label is None:
        log.info("%d training views had no masks; the capture has no ground truth to score them on", len(unlabelled))
        return {}
    labels = len(data.classes) + 1
    confusion = np.zeros((labels, labels), np.int64)
    for index in chosen:
        rendered, _ = render_view(index)
        reference = remap_ground_truth(data.gt_label[index], data.gt_classes, data.classes)
        confusion += metrics.confusion(metrics.label_from_probabilities(rendered["semantic"]), reference, labels)
    return {"unlabelled_view_names": [data.names[i] for i in chosen],
            **_iou_metrics(confusion, ["background"] + list(data.classes), "_unlabelled_gt")}


def _log_result(result: dict, srf, semantic: bool) -> None:
    log.info("psnr %.2f ssim %.3f%s", result["psnr"], result["ssim"],
             f" miou {result['miou']:.3f}" if semantic else " (no classes: no IoU)")
    if result.get("object_iou_gt") is not None and result.get("miou_gt_classes_on_object") is not None:
        log.info("class mIoU against the truth %.3f: where the object is (its IoU) %.3f, which class it is "
                 "(on the true object's pixels) %.3f", result["miou_gt_classes"], result["object_iou_gt"],
                 result["miou_gt_classes_on_object"])
    if result["overfit"]:
        notes = [f"{result['appearance_gap_db']:.1f} dB of it is the training images' own appearance embeddings"
                 ] if "appearance_gap_db" in result else []
        notes += [result["overfit_remedy"]] if "overfit_remedy" in result else []
        log.warning("%s: fits the training views, not new ones: training views %.1f dB, held-out %.1f dB "
                    "(gap %.1f dB > %g)%s", srf, result["train_view_psnr"], result["psnr"],
                    result["generalization_gap_db"], GENERALIZATION_GAP_DB, "".join(f"; {n}" for n in notes))


def mask_agreement(data, train) -> dict:
    """The composited labels of the training views `train` that had masks against the capture's
    ground truth (`PosedImages` with gt_label): iou_masks_gt, miou_masks_gt and
    miou_masks_gt_classes, the ceiling the masks set, and object_iou_masks_gt (where they put the object)."""
    from srfpipe.srf import metrics
    from srfpipe.srf.data import remap_ground_truth

    views = train if data.labelled is None else train[data.labelled[train]]
    labels = len(data.classes) + 1
    conf = np.zeros((labels, labels), np.int64)
    for index in views:
        truth = remap_ground_truth(data.gt_label[index], data.gt_classes, data.classes)
        conf += metrics.confusion(data.label[index], truth, labels)
    return {**_iou_metrics(conf, ["background"] + list(data.classes), "_masks_gt"),
            "object_iou_masks_gt": object_iou(conf)}


def _iou_metrics(confusion: np.ndarray, names: list[str], suffix: str) -> dict:
    """iou{suffix} per label, miou{suffix} (with background) and miou{suffix}_classes (without)."""
    from srfpipe.srf import metrics

    iou = metrics.iou_from_confusion(confusion)
    return {f"iou{suffix}": {name: _finite(v) for name, v in zip(names, iou)},
            f"miou{suffix}": float(np.nanmean(iou)),
            f"miou{suffix}_classes": float(np.nanmean(iou[1:]))}


def world_from_scene_pose(world_from_scene: np.ndarray, pose_scene: np.ndarray) -> np.ndarray:
    return cameras.transform_poses(world_from_scene, pose_scene.astype(np.float64))


def _finite(value):
    return None if not np.isfinite(value) else float(value)


def _clean(value):
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_clean(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


def _write_figure(path, result, target, pred_label, reference, colours, cv2) -> None:
    """Top: render | semantic blend | depth; bottom: captured image | reference labels | opacity.
    Without classes (`pred_label` None) the semantic panels are left out."""
    depth = result["depth"]
    valid = result["accumulation"] > 0.5
    finite = depth[valid] if valid.any() else np.array([0.0, 1.0])
    near, far = float(np.percentile(finite, 2)), float(np.percentile(finite, 98))
    opacity = np.repeat((np.clip(result["accumulation"], 0, 1) * 255).astype(np.uint8)[..., None], 3, axis=-1)
    top = [(np.clip(result["rgb"], 0, 1) * 255).astype(np.uint8), depth_image(np.where(valid, depth, 0), near, far)]
    bottom = [(target * 255).astype(np.uint8), opacity]
    if pred_label is not None:
        top.insert(1, semantic_blend(result["rgb"], pred_label, colours))
        bottom.insert(1, semantic_blend(target, reference, colours))
    figure = np.concatenate([np.concatenate(top, axis=1), np.concatenate(bottom, axis=1)], axis=0)
    if not cv2.imwrite(str(path), figure[..., ::-1]):
        raise RuntimeError(f"{path}: could not write PNG")

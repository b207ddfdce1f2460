"""The evaluate stage on a field with known answers: the synthetic sphere scene rendered exactly."""

from __future__ import annotations

import dataclasses
import json
import logging

import cv2
import numpy as np
import pytest
import torch

from srfpipe.artifacts import read_provenance
from srfpipe.batch import summary_lines
from srfpipe.cameras import pixel_rays
from srfpipe.evaluate import GENERALIZATION_GAP_DB, default_supersample, evaluate_field
from srfpipe.segment.composite import composite_masks
from srfpipe.srf import synthetic
from srfpipe.srf.data import load_posed_images

WIDTH, HEIGHT, VIEWS, HOLDOUT = 32, 24, 8, 4
CENTRES = {"supersample": 1}  # synthetic.write_scene's images are pixel-centre renders
IOU_KEYS = ("iou", "miou", "miou_classes", "iou_gt", "miou_gt", "miou_gt_classes")


class ExactField:
    """Stands in for a trained SRF: renders the synthetic scene by ray casting, with `classes`
    semantic channels (one-hot of the scene's labels 1..len(classes))."""

    def __init__(self, images_path, classes: list[str]):
        attrs = read_provenance(images_path)
        self.classes = list(classes)
        self.world_from_scene = np.asarray(attrs["world_from_scene"], dtype=np.float64)
        self.attrs = {"holdout_every": HOLDOUT, "train_seconds": 0.0}

    def render(self, camera_to_world, intrinsics, width, height, supersample=1) -> dict:
        s = supersample  # the mean of the s x s pixels of the s times finer image
        origins, directions = pixel_rays(camera_to_world, np.asarray(intrinsics) * s, width * s, height * s)
        rgb, label, depth = synthetic.render(origins, directions)
        hit = np.isfinite(depth)
        semantic = label[..., None] == np.arange(1, len(self.classes) + 1)  # (H, W, C), C may be 0
        out = {"rgb": rgb, "semantic": semantic, "depth": np.where(hit, depth, 0), "accumulation": hit}
        return {key: value.astype(np.float32).reshape(height, s, width, s, *value.shape[2:]).mean((1, 3))
                for key, value in out.items()}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = tmp_path_factory.mktemp("synthetic")
    images, labels = synthetic.write_scene(folder, views=VIEWS, width=WIDTH, height=HEIGHT)
    return folder, images, labels


def test_zero_classes_give_colour_metrics_and_two_panel_renders(scene):
    folder, images, _ = scene
    labels = composite_masks(images, [], {}, folder / "no_classes.zarr", progress=False)  # a capture without masks
    data = load_posed_images(images, labels)
    assert data.classes == []
    out = folder / "eval_no_classes"
    returned = evaluate_field(ExactField(images, []), data, out, CENTRES, labels, "exact")
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["classes"] == [] and saved["views"] == VIEWS // HOLDOUT
    assert saved["psnr"] > 45 and saved["ssim"] > 0.98  # exact renders: only the 8-bit rounding differs
    assert returned["psnr"] == pytest.approx(saved["psnr"])
    for key in IOU_KEYS + ("psnr_object",):
        assert key not in saved, key
    assert all(set(view) == {"name", "index", "psnr", "ssim"} for view in saved["per_view"])
    figure = cv2.imread(str(out / "renders" / "frame_00000.png"))
    assert figure.shape == (2 * HEIGHT, 2 * WIDTH, 3)  # render | depth over image | opacity
    np.testing.assert_allclose(figure[:HEIGHT, :WIDTH], figure[HEIGHT:, :WIDTH], atol=2)


def test_classes_give_iou_and_three_panel_renders(scene):
    folder, images, labels = scene
    data = load_posed_images(images, labels)
    out = folder / "eval_classes"
    saved = evaluate_field(ExactField(images, data.classes), data, out, CENTRES, labels, "exact")
    assert saved["classes"] == ["apple", "branch", "leaf"]
    for key in IOU_KEYS + ("psnr_object",):
        assert key in saved, key
    # poses make a float32 round trip through the scene frame: a few edge pixels may flip
    assert saved["miou"] > 0.9 and saved["miou_gt"] > 0.9 and saved["psnr_object"] > 40
    figure = cv2.imread(str(out / "renders" / "frame_00000.png"))
    assert figure.shape == (2 * HEIGHT, 3 * WIDTH, 3)


class FatField(ExactField):
    """The exact field with every class grown by a pixel into the background (thin parts rendered fat)."""

    def render(self, *args, **kwargs) -> dict:
        out = super().render(*args, **kwargs)
        grown = np.stack([cv2.dilate(channel, np.ones((3, 3), np.uint8)) for channel in np.moveaxis(out["semantic"], -1, 0)], -1)
        return {**out, "semantic": np.where(out["semantic"].max(-1, keepdims=True) > 0, out["semantic"], grown)}


class SwappedField(ExactField):
    """The exact field with its first and last class exchanged (the object in place, its labels wrong)."""

    def render(self, *args, **kwargs) -> dict:
        out = super().render(*args, **kwargs)
        return {**out, "semantic": out["semantic"][..., ::-1].copy()}


def test_the_class_miou_splits_into_where_the_object_is_and_which_class_it_is(scene):
    folder, images, labels = scene
    data = load_posed_images(images, labels)
    scores = {name: evaluate_field(field(images, data.classes), data, folder / f"eval_{name}", CENTRES, labels, name)
              for name, field in (("exact", ExactField), ("fat", FatField), ("swapped", SwappedField))}
    exact, fat, swapped = scores["exact"], scores["fat"], scores["swapped"]
    assert exact["object_iou_gt"] > 0.95 and exact["miou_gt_classes_on_object"] > 0.9
    assert exact["object_iou_masks_gt"] > 0.9  # the synthetic scene's masks are its labels
    # a silhouette a pixel too wide costs the object's IoU, not its classes
    assert fat["object_iou_gt"] < exact["object_iou_gt"] - 0.1 and fat["miou_gt_classes"] < exact["miou_gt_classes"] - 0.05
    assert fat["miou_gt_classes_on_object"] == pytest.approx(exact["miou_gt_classes_on_object"], abs=0.02)
    # wrong classes in the right place: the other way round
    assert swapped["object_iou_gt"] == pytest.approx(exact["object_iou_gt"])
    assert swapped["miou_gt_classes_on_object"] < 0.5


@pytest.mark.bad_input
def test_classes_that_differ_from_the_fields_name_both(scene):
    folder, images, labels = scene
    data = load_posed_images(images, labels)
    with pytest.raises(ValueError, match=r"labels.zarr: classes \['apple', 'branch', 'leaf'\] differ from the SRF's "
                                         r"\[\] \(exact\)"):
        evaluate_field(ExactField(images, []), data, folder / "eval_bad", {}, labels, "exact")
    assert not (folder / "eval_bad").exists()


def test_supersampling_is_on_for_small_views_and_measurably_changes_the_render(scene):
    # the default: 2 x 2 rays per pixel while a view stays within SUPERSAMPLE_MAX_RAYS rays
    assert default_supersample(128, 128, None) == 2 and default_supersample(160, 120, None) == 2
    assert default_supersample(256, 256, None) == 2  # the plant at the resolution its 18 views keep
    assert default_supersample(270, 480, None) == 1 and default_supersample(270, 480, 3) == 3
    folder, images, labels = scene
    data = load_posed_images(images, labels)
    out = folder / "eval_supersampled"
    saved = evaluate_field(ExactField(images, data.classes), data, out, {}, labels, "exact")
    assert saved["supersample"] == 2
    # against centre-rendered images the area mean differs at the sphere's edges only
    assert 25 < saved["psnr"] < 45


def test_a_field_from_other_labels_of_the_same_capture_sees_the_views_where_they_are(scene):
    """The views' poses go to the world through their own scene frame, not the field's: a field
    trained on other labels of the capture (another mask hull, another normalization; or another
    image size, as benchmarks/captures.py's reference views) still renders the same cameras."""
    folder, images, labels = scene
    data = load_posed_images(images, labels)
    field = ExactField(images, data.classes)
    other_frame = np.diag([2.0, 2.0, 2.0, 1.0])
    other_frame[:3, 3] = (0.3, -0.2, 0.5)
    field.world_from_scene = other_frame @ field.world_from_scene  # the field's own frame differs
    saved = evaluate_field(field, data, folder / "eval_other_frame", CENTRES, labels, "exact")
    assert saved["psnr"] > 45 and saved["miou_gt"] > 0.9


def test_training_views_are_scored_like_the_held_out_ones_and_give_the_gap(scene):
    """A few evenly spaced training views go through the same render; only numbers are kept."""
    folder, images, labels = scene
    data = load_posed_images(images, labels)
    out = folder / "eval_train_views"
    returned = evaluate_field(ExactField(images, data.classes), data, out, CENTRES, labels, "exact")
    saved = json.loads((out / "metrics.json").read_text())
    # 8 views, every 4th held out: training views 1 2 3 5 6 7, three evenly spaced of them
    assert saved["train_view_names"] == ["frame_00002", "frame_00005", "frame_00007"]
    for key in ("psnr", "train_view_psnr", "generalization_gap_db"):
        assert isinstance(saved[key], float) and np.isfinite(saved[key]), key
    assert saved["generalization_gap_db"] == pytest.approx(saved["train_view_psnr"] - saved["psnr"])
    assert returned["train_view_psnr"] == pytest.approx(saved["train_view_psnr"])
    # exact renders of every view: both only 8-bit rounding off, no gap
    assert saved["train_view_psnr"] > 45 and abs(saved["generalization_gap_db"]) < 3
    assert saved["overfit"] is False
    assert sorted(path.name for path in (out / "renders").iterdir()) == ["frame_00000.png", "frame_00004.png"]

    assert "appearance_gap_db" not in saved  # no appearance embeddings: nothing to borrow

    off = evaluate_field(ExactField(images, data.classes), data, folder / "eval_train_views_off",
                         {**CENTRES, "train_views": 0}, labels, "exact")
    assert off["train_view_names"] == [] and off["train_view_psnr"] is None
    assert off["generalization_gap_db"] is None and off["overfit"] is False
    assert off["psnr"] == pytest.approx(saved["psnr"])


class ExposedField(ExactField):
    """The exact field with a per-image exposure, as an appearance embedding learns it: each
    training image rendered with its own is exact; with another image's, 20 % darker."""

    has_appearance = True

    def render(self, camera_to_world, intrinsics, width, height, supersample=1, exclude_view=None,
               appearance_view=None) -> dict:
        out = super().render(camera_to_world, intrinsics, width, height, supersample)
        if exclude_view is not None:
            out["rgb"] = out["rgb"] * 0.8
        return out


def test_the_gap_that_is_the_training_images_own_appearance_is_told_apart(scene):
    folder, images, labels = scene
    data = load_posed_images(images, labels)
    saved = evaluate_field(ExposedField(images, data.classes), data, folder / "eval_exposed", CENTRES, labels,
                           "exposed")
    assert saved["train_view_psnr"] > 45 and saved["overfit"] is False
    assert saved["train_view_psnr_borrowed_appearance"] < 25
    assert saved["appearance_gap_db"] == pytest.approx(saved["train_view_psnr"]
                                                       - saved["train_view_psnr_borrowed_appearance"])


def test_a_field_that_matches_only_the_training_views_is_flagged_and_the_summary_says_so(scene, tmp_path, caplog):
    """Held-out images replaced by noise: the field still renders the training views exactly but
    none of the held-out ones, so the gap is far above GENERALIZATION_GAP_DB."""
    folder, images, labels = scene
    data = load_posed_images(images, labels)
    noisy = data.images.clone()
    generator = torch.Generator().manual_seed(0)
    for index in range(0, VIEWS, HOLDOUT):
        noisy[index] = torch.randint(0, 256, noisy[index].shape, generator=generator, dtype=torch.uint8)
    results = tmp_path / "results"
    field = ExactField(images, data.classes)
    with caplog.at_level(logging.WARNING, logger="srfpipe.evaluate"):
        overfit = evaluate_field(field, dataclasses.replace(data, images=noisy), results / "noisy" / "eval",
                                 CENTRES, labels, "exact")
    assert overfit["overfit"] is True
    assert overfit["generalization_gap_db"] > GENERALIZATION_GAP_DB and overfit["train_view_psnr"] > 45
    warning = (f"fits the training views, not new ones: training views {overfit['train_view_psnr']:.1f} dB, "
               f"held-out {overfit['psnr']:.1f} dB (gap {overfit['generalization_gap_db']:.1f} dB > 6)")
    assert any(warning in record.getMessage() for record in caplog.records if record.levelno == logging.WARNING)
    # the cameras stand round the scene and the field had no distortion loss: the flag says what to try
    assert overfit["overfit_remedy"].startswith("try train.distortion: 0.01")
    assert any(overfit["overfit_remedy"] in record.getMessage() for record in caplog.records)

    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="srfpipe.evaluate"):
        fine = evaluate_field(field, data, results / "exact" / "eval", CENTRES, labels, "exact")
    assert fine["overfit"] is False
    assert not [record for record in caplog.records if "fits the training views" in record.getMessage()]

    lines = summary_lines(["noisy", "exact"], results, tmp_path / "logs", chain=("eval",))
    assert lines[0].startswith("noisy  done") and lines[1].startswith("exact  done")
    assert (f"fits the training views, not new ones (train {overfit['train_view_psnr']:.1f} dB, "
            f"held-out {overfit['psnr']:.1f} dB): try train.distortion: 0.01") in lines[0]
    assert "fits the training views" not in lines[1]


def test_the_distortion_remedy_is_offered_only_where_it_helped():
    """Advice for an overfit field: the distortion loss for cameras standing round their subject
    in a scene (the panel's 360-degree captures gained), never for forward-facing ones (the fern
    lost), an empty backdrop (the small plant lost) or a field that had it already."""
    from srfpipe.cameras import look_at
    from srfpipe.evaluate import overfit_remedy

    def looking_at_origin(angles_deg):
        return np.stack([look_at(3.0 * np.array([np.cos(a), np.sin(a), 0.5]), np.zeros(3))
                         for a in np.radians(angles_deg)])

    orbit, facing = looking_at_origin(np.arange(0, 360, 30)), looking_at_origin(np.linspace(0, 20, 12))
    assert "train.distortion" in overfit_remedy({"distortion": 0.0}, orbit, background_empty=False)
    assert overfit_remedy({"distortion": 0.01}, orbit, background_empty=False) is None
    assert overfit_remedy({"distortion": 0.0}, facing, background_empty=False) is None
    assert overfit_remedy({"distortion": 0.0}, orbit, background_empty=True) is None


def test_depth_image_orders_near_to_far_and_blanks_missing_depth():
    """Inverse depth: near red, far blue, and the object 10x nearer than a far background still gets
    most of the colour range (linear depth gave the whole object one colour)."""
    from srfpipe.evaluate import depth_image

    depth = np.array([[1.0, 1.5, 2.0, 10.0, 100.0, 0.0, np.nan, np.inf]])
    image = depth_image(depth, near=1.0, far=100.0)[0].astype(int)
    turbo = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1].astype(int)
    index = [int(np.argmin(((turbo - pixel) ** 2).sum(axis=1))) for pixel in image[:5]]
    assert index == sorted(index, reverse=True) and index[0] == 255 and index[-1] == 0
    assert index[0] - index[2] > 100  # depths 1 and 2 are far apart in colour
    assert (image[5:] == 0).all()


class LabelsOnlyWhereLabelled(ExactField):
    """A field that learnt its classes on the labelled frames only: exact there, no class anywhere else."""

    def __init__(self, images_path, classes, labelled_poses):
        super().__init__(images_path, classes)
        self.labelled_poses = labelled_poses

    def render(self, camera_to_world, intrinsics, width, height, supersample=1) -> dict:
        out = super().render(camera_to_world, intrinsics, width, height, supersample)
        if not any(np.allclose(camera_to_world, pose, atol=1e-4) for pose in self.labelled_poses):
            out["semantic"] = np.zeros_like(out["semantic"])
        return out


def test_sparse_labels_are_scored_on_the_training_views_that_had_no_mask(scene):
    """Frames 1 and 2 had no masks: evaluate renders them and scores their classes against the
    capture's ground truth, so a field that did not spread the labels to them scores low there."""
    from srfpipe.evaluate import world_from_scene_pose

    folder, images, labels = scene
    data = load_posed_images(images, labels)
    sparse = dataclasses.replace(data, labelled=np.array([i not in (1, 2) for i in range(VIEWS)]))
    spread = evaluate_field(ExactField(images, data.classes), sparse, folder / "eval_sparse", CENTRES, labels, "exact")
    assert spread["unlabelled_view_names"] == ["frame_00001", "frame_00002"]
    assert spread["labelled_frames"] == VIEWS - 2
    assert spread["miou_unlabelled_gt"] > 0.9 and set(spread["iou_unlabelled_gt"]) == {"background", *data.classes}

    poses = [world_from_scene_pose(data.world_from_scene, data.poses_scene[i].numpy())
             for i in range(VIEWS) if i not in (1, 2)]
    kept = evaluate_field(LabelsOnlyWhereLabelled(images, data.classes, poses), sparse, folder / "eval_not_spread",
                          CENTRES, labels, "exact")
    assert kept["miou_unlabelled_gt"] < 0.5 and kept["miou_gt"] > 0.9  # held-out views 0 and 4 were labelled

    every = evaluate_field(ExactField(images, data.classes), data, folder / "eval_every", CENTRES, labels, "exact")
    assert "miou_unlabelled_gt" not in every and every["labelled_frames"] == VIEWS


def test_the_masks_own_agreement_with_the_truth_is_reported_apart_from_the_fields(scene):
    """`miou_masks_gt` scores the masks the field learned from (labelled training views) against
    the capture's truth: masks that miss a class lower it, while the field's own score does not move."""
    folder, images, labels = scene
    data = load_posed_images(images, labels)
    exact = evaluate_field(ExactField(images, data.classes), data, folder / "eval_masks", CENTRES, labels, "exact")
    assert exact["miou_masks_gt"] > 0.95 and set(exact["iou_masks_gt"]) == {"background", *data.classes}
    present = np.bincount(data.label.ravel(), minlength=len(data.classes) + 1)
    missed = int(np.argmax(present[1:])) + 1  # the class with the most pixels
    label = np.where(data.label == missed, 0, data.label).astype(data.label.dtype)
    damaged = evaluate_field(ExactField(images, data.classes), dataclasses.replace(data, label=label),
                             folder / "eval_masks_missing", CENTRES, labels, "exact")
    assert damaged["iou_masks_gt"][data.classes[missed - 1]] == 0
    assert damaged["miou_masks_gt_classes"] < exact["miou_masks_gt_classes"] - 0.3
    assert damaged["miou_gt"] == pytest.approx(exact["miou_gt"])


def test_metrics_json_records_its_provenance(scene):
    """eval/ is an artifact like the others: metrics.json records the stage, the options it used,
    its inputs with their fingerprints and the versions (it recorded none)."""
    from srfpipe.artifacts import fingerprint

    folder, images, labels = scene
    out = folder / "eval_provenance"
    evaluate_field(ExactField(images, synthetic.CLASSES), load_posed_images(images, labels), out, CENTRES, labels,
                   "exact", images=images)
    record = json.loads((out / "metrics.json").read_text())["srfpipe"]
    assert record["stage"] == "evaluate" and record["complete"] and record["schema_version"] == 1
    assert record["config"]["holdout_every"] == HOLDOUT and record["config"]["supersample"] >= 1
    assert record["versions"]["srfpipe"] and record["versions"]["numpy"]
    recorded = {entry["path"]: entry for entry in record["inputs"]}
    assert recorded[str(images)]["manifest_sha256"] == fingerprint(images)
    assert recorded[str(labels)]["stage"] == "composite" and "exact" in recorded

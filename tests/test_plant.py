"""The built-in plant generator: a thin sapling in millimetres, few far views, dark backdrop.

Checks the capture itself (views, units, thin stem, labels against depth, far cameras) and the way
it enters the workflow (its own capture rule, poses without ground-truth bounds, class names carried
into images.zarr and read back by the SRF data loader, masks imported from its labels).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from srfpipe.artifacts import open_artifact, read_provenance
from srfpipe.cameras import pixel_rays, project_points
from srfpipe.scenes.plant import generate_plant
from tests.conftest import REPO
from tests.test_orchard import read_capture

CLASSES = ["background", "stem", "leaf", "berry"]
SMALL = {"views": 16, "width": 128, "height": 128, "seed": 2}


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    folder = generate_plant(tmp_path_factory.mktemp("plant") / "capture", progress=False, **SMALL)
    return folder, read_capture(folder)


@pytest.fixture(scope="module")
def full_size(tmp_path_factory):
    """Two views at the default size (512x512), where the stem's width in pixels is what users get."""
    folder = generate_plant(tmp_path_factory.mktemp("plant_full") / "capture", progress=False, views=2)
    return read_capture(folder)


def mean_width(mask: np.ndarray) -> float:
    """Mean width in pixels of the shapes in a binary mask: 2 * area / perimeter (a strip's width)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    perimeter = sum(cv2.arcLength(c, True) for c in contours)
    return 2.0 * float(mask.sum()) / max(perimeter, 1.0)


def test_capture_has_the_requested_views_classes_and_units(small):
    folder, cap = small
    assert sorted(p.name for p in folder.parent.iterdir()) == ["capture"], "temp folder left behind"
    assert len(cap["transforms"]["frames"]) == SMALL["views"] == len(cap["images"]) == len(cap["depth"])
    for image, label, depth in zip(cap["images"], cap["labels"], cap["depth"]):
        assert image.shape == (128, 128, 3) and label.shape == (128, 128) and depth.dtype == np.float32
    scene = cap["scene"]
    assert scene["classes"] == CLASSES
    assert scene["units"] == "millimetre"
    assert "bounds_world" not in scene, "the poses stage would take it as the scene bounds"
    lo, hi = np.array(scene["object_bounds_world"])
    assert hi[2] == pytest.approx(300.0, rel=1e-4), "the plant is plant_height millimetres tall"
    assert np.all(hi - lo > 50) and np.all(hi - lo < 305.0)  # the tilted stem base dips a little below 0
    assert len(cap["berries"]) == scene["plant"]["n_berries"] == 9
    for name in ("stem", "leaf", "berry"):
        assert (folder / "ground_truth" / "meshes" / f"{name}.ply").stat().st_size > 1000


def test_labels_agree_with_depth_and_the_true_geometry(small):
    """Foreground pixels have depth and back-project into the plant's box; background has none.

    Berry pixels back-project onto a berry's surface: depth and labels are in millimetres and agree.
    """
    _, cap = small
    lo, hi = (np.array(b) for b in cap["scene"]["object_bounds_world"])
    centres = np.array([b["centre"] for b in cap["berries"]])
    radius = cap["berries"][0]["radius"]
    present = set()
    for pose, label, depth in zip(cap["poses"], cap["labels"], cap["depth"]):
        assert np.all(np.isfinite(depth))
        np.testing.assert_array_equal(label > 0, depth > 0)
        present |= set(np.unique(label).tolist())
        origins, directions = pixel_rays(pose, cap["intrinsics"], 128, 128)
        points = origins + (depth / (directions @ pose[:3, 2]))[..., None] * directions
        plant = points[label > 0]
        assert np.all((plant >= lo - 0.05) & (plant <= hi + 0.05))
        berry = points[label == 3]
        if len(berry):
            distance = np.linalg.norm(berry[:, None] - centres[None], axis=-1).min(1)
            assert np.all(np.abs(distance - radius) < 0.07 * radius)  # facets of a 12-sided UV sphere
    assert present == {0, 1, 2, 3}


def test_stem_is_thin_at_the_default_size(full_size):
    """The stem class (stem, twigs, stalks) is a few pixels wide; leaves and berries are much wider."""
    assert full_size["images"][0].shape == (512, 512, 3)
    for label in full_size["labels"]:
        stem, leaf, berry = (label == value for value in (1, 2, 3))
        assert stem.sum() > 500, "the stem must be visible in every view"
        assert mean_width(stem) < 3.0
        assert mean_width(leaf) > 1.8 * mean_width(stem) and mean_width(berry) > 1.8 * mean_width(stem)
        # nowhere wider than the stem's base (about 8 px): the largest inscribed half-widths stay small
        half_width = cv2.distanceTransform(stem.astype(np.uint8), cv2.DIST_L2, 5)[stem]
        assert np.percentile(half_width, 99) <= 5.0


def test_cameras_are_far_and_the_plant_still_fills_the_frame(full_size, small):
    _, cap = small
    lo, hi = (np.array(b) for b in cap["scene"]["object_bounds_world"])
    target = np.array(cap["scene"]["look_at_target"])
    np.testing.assert_allclose(target, (lo + hi) / 2)
    size = float(np.max(hi - lo))
    distances = np.linalg.norm(cap["poses"][:, :3, 3] - target, axis=1)
    assert np.all(distances > 6 * size) and np.all(distances < 10 * size)
    elevations = np.degrees(np.arcsin((cap["poses"][:, 2, 3] - target[2]) / distances))
    assert np.sum(np.abs(elevations - 10) < 3) == 8 and np.sum(np.abs(elevations - 40) < 3) == 8
    for pose in cap["poses"]:
        uv, z = project_points(target[None], pose, cap["intrinsics"])
        assert z[0] > 0 and np.allclose(uv[0], 64.0, atol=0.5), "every camera looks at the plant"
    for label in full_size["labels"]:
        rows = np.nonzero(label.any(axis=1))[0]
        assert (rows.max() - rows.min()) / label.shape[0] > 0.45


def test_backdrop_is_dark_and_noisy_and_the_plant_stands_out(small):
    _, cap = small
    rgb = np.concatenate([image[..., ::-1].reshape(-1, 3) for image in cap["images"]]).astype(float)
    label = np.concatenate([label.ravel() for label in cap["labels"]])
    background = rgb[label == 0]
    assert background.mean() < 25 and background.std() > 0.5
    leaf, berry = rgb[label == 2].mean(0), rgb[label == 3].mean(0)
    assert leaf[1] > leaf[0] and leaf[1] > leaf[2] and leaf.mean() > background.mean() + 20
    assert berry[0] > berry[1] + 40 and berry[0] > berry[2] + 40


def test_deterministic_by_seed(small, tmp_path):
    _, cap = small
    again = read_capture(generate_plant(tmp_path / "same", progress=False, **SMALL))
    for a, b in zip(cap["images"] + cap["labels"], again["images"] + again["labels"]):
        np.testing.assert_array_equal(a, b)
    other = read_capture(generate_plant(tmp_path / "other", progress=False, **{**SMALL, "seed": 3}))
    assert other["berries"] != cap["berries"]
    assert np.mean(other["labels"][0] != cap["labels"][0]) > 0.01


def test_bare_plant_and_bad_options(tmp_path, capsys):
    from srfpipe.cli import main

    bare = read_capture(generate_plant(tmp_path / "bare", progress=False, views=2, width=64, height=64,
                                        n_twigs=0, n_berries=0))
    assert bare["berries"] == []
    assert set(np.unique(np.concatenate([label.ravel() for label in bare["labels"]])).tolist()) <= {0, 1, 2}
    out = tmp_path / "bad"
    assert main(["plant", "--options", '{"views": 1}', "--out", str(out)]) == 1
    assert "plant.views: 1 is less than the minimum of 2" in capsys.readouterr().err
    assert main(["plant", "--options", '{"n_apples": 3}', "--out", str(out)]) == 1
    assert "n_apples" in capsys.readouterr().err
    assert not out.exists()


# ----------------------------------------------------------------------------- in the workflow


def _plant_scene(**plant) -> dict:
    """config/scenes/plant.yaml as shipped, with a tiny capture and working resolution = capture."""
    scene = yaml.safe_load((REPO / "config" / "scenes" / "plant.yaml").read_text())
    scene["plant"] = {"views": 16, "width": 48, "height": 48, **plant}
    scene["images"] = {"downscale": 1}
    return scene


@pytest.mark.workflow
def test_plant_and_orchard_scenes_each_get_their_own_capture_rule(workflow):
    from tests.conftest import TINY_ORCHARD

    workflow.write_scene("plant", _plant_scene())
    workflow.write_scene("tiny", TINY_ORCHARD)
    jobs = workflow.dry_run_jobs("results/plant/images.zarr", "results/tiny/images.zarr")
    rules = ("plant_capture", "orchard_capture", "poses", "downscale")
    assert {rule: jobs.get(rule) for rule in rules} == {"plant_capture": 1, "orchard_capture": 1, "poses": 2,
                                                         "downscale": 2}


@pytest.mark.workflow
def test_shipped_plant_scene_to_labels(workflow):
    """The shipped scene file builds: bounds from the data, class names carried, masks from the labels."""
    from srfpipe.segment.composite import composite_masks
    from srfpipe.srf.data import load_posed_images

    workflow.write_scene("plant", _plant_scene())
    workflow.run("results/plant/labels.zarr")
    results = workflow.root / "results" / "plant"
    poses = read_provenance(results / "poses.zarr")
    assert poses["source_format"] == "plant" and poses["bounds_source"] == "frusta"
    images = open_artifact(results / "images.zarr", stage="downscale")
    assert images["images"].shape == (16, 48, 48, 3)
    assert read_provenance(results / "images.zarr")["ground_truth_classes"] == CLASSES
    data = load_posed_images(results / "images.zarr", results / "labels.zarr")
    assert data.gt_classes == CLASSES
    # imported from the ground-truth labels at the capture's size: the composite is the ground truth
    truth = np.asarray(images["ground_truth/labels"][:])
    lookup = np.zeros(256, np.uint8)
    for name in data.classes:
        lookup[CLASSES.index(name)] = data.classes.index(name) + 1
    np.testing.assert_array_equal(data.label, lookup[truth])
    assert set(data.classes) >= {"leaf", "berry"}
    assert (workflow.root / "logs" / "plant" / "plant_capture.log").exists()
    # its near-black backdrop is seen to be empty (labels.background auto): the model's box is the
    # masks' hull, around the plant (the frusta's box is many times larger)
    truth_scene = json.loads((results / "capture" / "ground_truth" / "scene.json").read_text())
    obj_lo, obj_hi = (np.array(b) for b in truth_scene["object_bounds_world"])
    info = read_provenance(results / "labels.zarr")
    assert info["background"] == "empty" and info["background_from"] == "images" and info["background_spread"] < 12
    assert data.bounds_source == "mask_hull" and data.background_empty
    # the trainer empties the rays whose pixel has the backdrop's near-black colour
    colour, level = data.backdrop
    assert max(colour) < 30 and 12 <= level < 30
    images_rgb = np.asarray(images["images"][:]).astype(int)
    shows = (np.abs(images_rgb - np.array(colour)).max(axis=-1) <= level)
    assert 0.5 < shows.mean() < 0.999 and shows[data.label > 0].mean() < 0.2
    # masks of the whole plant: every unmasked ray is emptied; the berries' masks alone miss the rest
    # of the plant, so only the rays that show the backdrop are
    from srfpipe.srf.trainer import background_rays, mask_coverage

    assert mask_coverage(data) > 0.8 and background_rays(data) == "unmasked"
    composite_masks(results / "images.zarr", [str(results / "masks" / "berry.zarr")], {},
                    workflow.root / "berries.zarr", progress=False)
    berries = load_posed_images(results / "images.zarr", workflow.root / "berries.zarr")
    assert berries.background_empty and mask_coverage(berries) < 0.3 and background_rays(berries) == "backdrop"
    # the berries' masks alone carve a box round the berries; the silhouettes keep the stem and leaves
    # in the model's box (issue 30: a thin plant's organ masks carved its stem away)
    assert berries.bounds_source == "mask_hull"
    assert np.all(berries.bounds_world[0] <= obj_lo + 1.0) and np.all(berries.bounds_world[1] >= obj_hi - 1.0), \
        (berries.bounds_world, obj_lo, obj_hi)
    region = data.semantic_bounds_world
    np.testing.assert_allclose(data.bounds_world, region)
    assert np.all(region[0] <= obj_lo + 1.0) and np.all(region[1] >= obj_hi - 1.0), (region, obj_lo, obj_hi)
    # a scene whose background is not empty keeps the cameras' box; the hull stays its semantic region
    masks = sorted(str(m) for m in (results / "masks").glob("*.zarr"))
    order = [str(results / "masks" / f"{name}.zarr") for name in _plant_scene()["segmentation"]["prompts"]]
    composite_masks(results / "images.zarr", [m for m in order if m in masks], {"background": "scene"},
                    workflow.root / "scene.zarr", progress=False)
    scene = load_posed_images(results / "images.zarr", workflow.root / "scene.zarr")
    assert scene.bounds_source == "frusta" and not scene.background_empty
    np.testing.assert_allclose(scene.semantic_bounds_world, region)
    assert np.prod(region[1] - region[0]) < 0.5 * np.prod(scene.bounds_world[1] - scene.bounds_world[0])
    # masks on 2 of the 16 frames: the other frames' silhouettes against the empty backdrop carve the
    # hull too, so the box stays around the plant instead of the cone two views leave behind it
    import shutil

    import zarr

    from srfpipe.artifacts import reseal_artifact

    two = [i in (0, 8) for i in range(16)]
    sparse = []
    for path in [m for m in order if m in masks]:
        copy = workflow.root / "sparse" / Path(path).name
        shutil.copytree(path, copy)
        group = zarr.open_group(str(copy), mode="r+")
        group.attrs["srfpipe"] = {**group.attrs["srfpipe"], "labelled": two}
        reseal_artifact(copy)  # a deliberate edit: these masks now cover frames 0 and 8 only
        sparse.append(str(copy))
    composite_masks(results / "images.zarr", sparse, {}, workflow.root / "two.zarr", progress=False)
    few = load_posed_images(results / "images.zarr", workflow.root / "two.zarr")
    assert few.labelled.tolist() == two and few.bounds_source == "mask_hull"
    assert read_provenance(workflow.root / "two.zarr")["hull_silhouettes"]["frames_without_masks"] == 14
    box = few.bounds_world
    assert np.all(box[0] <= obj_lo + 1.0) and np.all(box[1] >= obj_hi - 1.0), (box, obj_lo, obj_hi)
    assert np.prod(box[1] - box[0]) < 2.0 * np.prod(region[1] - region[0])


def test_images_zarr_without_class_names_reads_as_an_orchard(tmp_path):
    """images.zarr written before ground_truth_classes existed: the loader falls back to the orchard's names."""
    import zarr

    from srfpipe.artifacts import create_artifact, update_attrs
    from srfpipe.srf.data import ORCHARD_GT_CLASSES, load_posed_images

    path = tmp_path / "images.zarr"
    with create_artifact(path, "downscale", config={}, inputs=[]) as group:
        group.create_array("images", data=np.zeros((2, 4, 4, 3), np.uint8))
        group.create_array("intrinsics", data=np.tile([4.0, 4.0, 2.0, 2.0], (2, 1)))
        group.create_array("camera_to_world", data=np.tile(np.eye(4), (2, 1, 1)))
        group.create_group("ground_truth").create_array("labels", data=np.zeros((2, 4, 4), np.uint8))
        update_attrs(group, scene_from_world=np.eye(4), bounds_world=[[-1, -1, -1], [1, 1, 1]])
    assert load_posed_images(path).gt_classes == ORCHARD_GT_CLASSES
    update_attrs(zarr.open_group(str(path), mode="r+"), ground_truth_classes=CLASSES)
    assert load_posed_images(path).gt_classes == CLASSES


@pytest.mark.bad_input
@pytest.mark.parametrize("options, key", [
    ({"distance": 1e-9}, "distance"),  # every camera at the plant's centre: refused by the poses stage
    ({"fov_deg": 175}, "fov_deg"),
])
def test_cameras_the_poses_stage_would_refuse_are_refused_naming_the_key(tmp_path, options, key):
    from srfpipe.config import ConfigError

    out = tmp_path / "capture"
    with pytest.raises(ConfigError, match=f"plant .*{key}"):
        generate_plant(out, progress=False, views=2, width=32, height=24, **options)
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.bad_input
def test_a_capture_in_which_no_view_shows_the_plant_is_refused(tmp_path):
    out = tmp_path / "capture"
    with pytest.raises(ValueError, match=r"no pixel of the 2 views shows the subject .*plant.plant_height"):
        generate_plant(out, progress=False, views=2, width=32, height=24, plant_height=1e-9)
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.bad_input
def test_more_berries_than_the_plant_holds_stop_when_it_is_full(monkeypatch):
    # n_berries 1e6 tried 60 places per berry asked for (6e7 tries) on a plant holding ~150
    from srfpipe.scenes import sapling

    monkeypatch.setattr(sapling, "BERRY_TRY_BUDGET", 2000)
    monkeypatch.setattr(sapling, "BERRY_MAX_MISSES", 500)
    tries = []
    distance = sapling.point_segment_distance

    def counted(*args):
        tries.append(1)
        if len(tries) > 100_000:
            raise AssertionError("still trying after 100 000 places")
        return distance(*args)

    monkeypatch.setattr(sapling, "point_segment_distance", counted)
    built = sapling.build_sapling(0, 300, 8, 0, 10**6)
    assert 0 < built.info["n_berries"] < 1000

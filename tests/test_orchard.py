"""The built-in orchard generator: determinism, ground-truth consistency, nerfstudio layout, CLI."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from srfpipe.cameras import opengl_to_opencv, pixel_rays, project_points
from srfpipe.scenes.orchard import generate_orchard

TINY = {"views": 12, "width": 128, "height": 96, "n_apples": 10, "seed": 3}


def read_capture(folder):
    """A generated capture in memory: images (BGR), labels, depth, poses, and every ground-truth
    JSON file by name (scene, apples or berries)."""
    transforms = json.loads((folder / "transforms.json").read_text())
    gt = folder / "ground_truth"
    frames = transforms["frames"]
    stems = [f["file_path"].split("/")[-1].rsplit(".", 1)[0] for f in frames]
    return {
        "transforms": transforms,
        "poses": np.array([opengl_to_opencv(np.array(f["transform_matrix"])) for f in frames]),
        "intrinsics": np.array([transforms[k] for k in ("fl_x", "fl_y", "cx", "cy")]),
        "images": [cv2.imread(str(folder / f["file_path"]), cv2.IMREAD_COLOR) for f in frames],
        "labels": [cv2.imread(str(gt / "labels" / f"{s}.png"), cv2.IMREAD_UNCHANGED) for s in stems],
        "depth": [np.load(gt / "depth" / f"{s}.npy") for s in stems],
        **{path.stem: json.loads(path.read_text()) for path in sorted(gt.glob("*.json"))},
    }


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    folder = generate_orchard(tmp_path_factory.mktemp("orchard") / "capture", progress=False, **TINY)
    return folder, read_capture(folder)


def test_layout_and_atomic_write(tiny):
    folder, cap = tiny
    assert sorted(p.name for p in folder.parent.iterdir()) == ["capture"], "temp folder left behind"
    assert len(cap["images"]) == TINY["views"]
    for image, label, depth in zip(cap["images"], cap["labels"], cap["depth"]):
        assert image.shape == (96, 128, 3) and image.dtype == np.uint8
        assert label.shape == (96, 128) and label.dtype == np.uint8
        assert depth.shape == (96, 128) and depth.dtype == np.float32
    for name in ("apple", "branch", "leaf", "ground"):
        assert (folder / "ground_truth" / "meshes" / f"{name}.ply").stat().st_size > 0
    assert cap["scene"]["classes"] == ["background", "apple", "branch", "leaf"]
    assert len(cap["apples"]) == TINY["n_apples"]
    assert all(a["radius"] == pytest.approx(0.04) for a in cap["apples"])


def test_transforms_json_is_nerfstudio_and_looks_at_the_tree(tiny):
    _, cap = tiny
    t = cap["transforms"]
    assert t["camera_model"] == "OPENCV"
    assert (t["w"], t["h"]) == (128, 96)
    assert t["cx"] == 64.0 and t["cy"] == 48.0
    assert all(t[k] == 0.0 for k in ("k1", "k2", "p1", "p2"))
    assert t["frames"][0]["file_path"] == "images/frame_00000.png"
    # nerfstudio/OpenGL: the camera looks down its -z axis, with +y up
    gl = np.array(t["frames"][0]["transform_matrix"])
    to_tree = np.array([0.0, 0.0, 1.2]) - gl[:3, 3]
    assert np.dot(-gl[:3, 2], to_tree / np.linalg.norm(to_tree)) > 0.95
    assert gl[2, 1] > 0.8, "camera +y should point roughly up in the world"
    # the trunk at mid height projects near the image centre
    uv, z = project_points(np.array([[0.0, 0.0, 1.2]]), cap["poses"][0], cap["intrinsics"])
    assert z[0] > 0 and abs(uv[0, 0] - 64) < 10 and abs(uv[0, 1] - 48) < 30


def test_labels_cover_all_classes(tiny):
    _, cap = tiny
    present = set(np.unique(np.concatenate([label.ravel() for label in cap["labels"]])).tolist())
    assert present == {0, 1, 2, 3}


def test_depth_back_projects_onto_the_apples(tiny):
    """Every apple pixel, lifted to 3D with its depth and pose, lies on the surface of an apple."""
    _, cap = tiny
    centres = np.array([a["centre"] for a in cap["apples"]])
    radius = cap["apples"][0]["radius"]
    lo, hi = (np.array(b) for b in cap["scene"]["bounds_world"])
    n_apple_pixels = 0
    for pose, label, depth in zip(cap["poses"], cap["labels"], cap["depth"]):
        origins, directions = pixel_rays(pose, cap["intrinsics"], 128, 96)
        t = depth / (directions @ pose[:3, 2])  # z-depth -> distance along the unit ray
        points = origins + t[..., None] * directions
        apple = label == 1
        n_apple_pixels += apple.sum()
        dist = np.linalg.norm(points[apple][:, None] - centres[None], axis=-1).min(1)
        assert np.all(np.abs(dist - radius) < 0.004)
        tree_pixels = label >= 1
        assert np.all((points[tree_pixels] >= lo) & (points[tree_pixels] <= hi))
        assert np.all(depth[tree_pixels] > 0) and np.all(np.isfinite(depth))
        sky = depth == 0
        assert np.all(label[sky] == 0)
        assert np.all(directions[sky][:, 2] > -0.02), "rays that miss everything must point at the sky"
    assert n_apple_pixels > 50


def test_most_apples_are_visible_somewhere(tiny):
    _, cap = tiny
    seen = np.zeros(len(cap["apples"]), bool)
    centres = np.array([a["centre"] for a in cap["apples"]])
    for pose, label in zip(cap["poses"], cap["labels"]):
        uv, z = project_points(centres, pose, cap["intrinsics"])
        ij = np.floor(uv).astype(int)
        inside = (z > 0) & (ij[:, 0] >= 0) & (ij[:, 0] < 128) & (ij[:, 1] >= 0) & (ij[:, 1] < 96)
        hits = np.zeros(len(centres), bool)
        hits[inside] = label[ij[inside, 1], ij[inside, 0]] == 1
        seen |= hits
    assert seen.mean() >= 0.7, f"only {seen.sum()} of {len(seen)} apples visible in any view"


def test_deterministic_by_seed(tiny, tmp_path):
    folder, cap = tiny
    again = read_capture(generate_orchard(tmp_path / "same", progress=False, **TINY))
    for a, b in zip(cap["images"], again["images"]):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(cap["labels"], again["labels"]):
        np.testing.assert_array_equal(a, b)
    assert cap["apples"] == again["apples"]
    other = read_capture(generate_orchard(tmp_path / "other", progress=False, **{**TINY, "seed": 4}))
    assert other["apples"] != cap["apples"]
    assert np.mean(np.abs(other["images"][0].astype(int) - cap["images"][0].astype(int))) > 5


def test_render_has_enough_sift_features(tmp_path):
    """COLMAP refinement needs texture: a full-size render must give SIFT plenty of keypoints."""
    folder = generate_orchard(tmp_path / "full", progress=False, views=2, n_apples=8)
    gray = cv2.imread(str(folder / "images" / "frame_00000.png"), cv2.IMREAD_GRAYSCALE)
    assert gray.shape == (480, 640)
    keypoints = cv2.SIFT_create().detect(gray, None)
    assert len(keypoints) > 100


def test_cli_help():
    result = subprocess.run([sys.executable, "-m", "srfpipe.cli", "orchard", "--help"],
                            capture_output=True, text=True, check=True)
    assert "--options" in result.stdout and "--out" in result.stdout and "n_apples" in result.stdout


def test_cli_bad_option_gives_clear_error(tmp_path, capsys):
    from srfpipe.cli import main

    out = tmp_path / "bad"
    assert main(["orchard", "--options", '{"views": 1}', "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "orchard.views: 1 is less than the minimum of 2" in err
    assert main(["orchard", "--options", '{"n_trees": 3}', "--out", str(out)]) == 1
    assert "n_trees" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(ValueError, match="n_apples"):
        generate_orchard(out, n_apples=-1)


def test_class_colours_are_plausible(tiny):
    """Apples red/yellow, leaves green, sky blue: what a colour-based segmenter would rely on."""
    _, cap = tiny
    rgb = np.concatenate([image[..., ::-1].reshape(-1, 3) for image in cap["images"]]).astype(float)
    label = np.concatenate([label.ravel() for label in cap["labels"]])
    sky = np.concatenate([depth.ravel() == 0 for depth in cap["depth"]])
    apple, leaf, sky_rgb = rgb[label == 1].mean(0), rgb[label == 3].mean(0), rgb[sky].mean(0)
    assert apple[0] > apple[2] + 40 and apple[0] > leaf[0] + 40
    assert leaf[1] > leaf[0] and leaf[1] > leaf[2]
    assert sky_rgb[2] > sky_rgb[0] + 30


def test_views_on_rings_look_at_the_tree():
    from srfpipe.cameras import look_at
    from srfpipe.scenes.orchard import ring_poses

    target = np.array([0.0, 0.0, 1.4])
    poses = ring_poses(7, [0.9, 2.2], 3.5, target, np.random.default_rng(0))
    assert poses.shape == (7, 4, 4)
    heights = poses[:, 2, 3]
    assert np.sum(np.abs(heights - 0.9) < 0.15) == 4 and np.sum(np.abs(heights - 2.2) < 0.15) == 3
    assert np.allclose(np.linalg.norm(poses[:, :2, 3], axis=1), 3.5, rtol=0.1)
    for pose in poses:
        assert np.allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-9)
        assert np.linalg.det(pose[:3, :3]) > 0
        to_target = (target - pose[:3, 3]) / np.linalg.norm(target - pose[:3, 3])
        assert np.allclose(pose[:3, 2], to_target)  # OpenCV: +z forward
        assert pose[2, 1] < 0  # OpenCV: +y down, so image rows run down the world z axis
    with pytest.raises(ValueError, match="parallel"):
        look_at([0, 0, 5], [0, 0, 0])


def test_views_on_an_arc_face_the_tree_from_one_side():
    """orchard.arc_deg: a forward-facing capture (the panel's orchard-front), which the trainer's
    defaults must tell from an orbit (`cameras_surround`)."""
    from srfpipe.cameras import cameras_surround
    from srfpipe.scenes.orchard import ring_poses

    target = np.array([0.0, 0.0, 1.4])
    poses = ring_poses(80, [0.9, 2.2], 3.5, target, np.random.default_rng(0), arc_deg=30.0)
    azimuth = np.degrees(np.arctan2(poses[:, 1, 3], poses[:, 0, 3]))
    assert azimuth.min() > -16 and azimuth.max() < 16 and azimuth.max() - azimuth.min() > 25
    assert not cameras_surround(poses, target)
    assert cameras_surround(ring_poses(80, [0.9, 2.2], 3.5, target, np.random.default_rng(0)), target)


def test_scene_without_apples_or_leaves(tmp_path):
    import open3d as o3d

    folder = generate_orchard(tmp_path / "bare", progress=False, views=2, width=32, height=24,
                              n_apples=0, leaf_density=0)
    assert json.loads((folder / "ground_truth" / "apples.json").read_text()) == []
    for name in ("apple", "leaf"):
        mesh = o3d.io.read_triangle_mesh(str(folder / "ground_truth" / "meshes" / f"{name}.ply"))
        assert len(mesh.triangles) == 0
    labels = cv2.imread(str(folder / "ground_truth" / "labels" / "frame_00000.png"), cv2.IMREAD_UNCHANGED)
    assert set(np.unique(labels).tolist()) <= {0, 2}


def test_chunked_rendering_matches_whole_image(monkeypatch):
    from srfpipe.scenes import raycast
    from srfpipe.cameras import look_at
    from srfpipe.scenes.orchard import intrinsics_for, sun_direction
    from srfpipe.scenes.tree import build_tree

    sun = sun_direction(np.random.default_rng(1))
    renderer = raycast.OrchardRenderer(build_tree(1, 6, 3, 1.0, 2.5), 1, sun)
    pose = look_at([3.0, -1.5, 1.5], [0.0, 0.0, 1.3])
    whole = renderer.render(pose, intrinsics_for(48, 36, 60), 48, 36)
    monkeypatch.setattr(raycast, "RAYS_PER_CHUNK", 777)
    chunked = renderer.render(pose, intrinsics_for(48, 36, 60), 48, 36)
    for a, b in zip((whole.rgb, whole.label, whole.depth), (chunked.rgb, chunked.label, chunked.depth)):
        np.testing.assert_array_equal(a, b)
    assert set(np.unique(whole.label).tolist()) >= {0, 2, 3}


def test_failed_run_leaves_old_output_untouched(tmp_path, monkeypatch):
    from srfpipe.scenes import raycast

    small = {"views": 2, "width": 32, "height": 24}
    out = generate_orchard(tmp_path / "capture", progress=False, seed=1, **small)
    before = (out / "ground_truth" / "apples.json").read_text()

    def broken(self, *args, **kwargs):
        raise RuntimeError("renderer crashed")

    monkeypatch.setattr(raycast.OrchardRenderer, "render", broken)
    with pytest.raises(RuntimeError, match="renderer crashed"):
        generate_orchard(out, progress=False, seed=2, **small)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture"], "temp folder left behind"
    assert (out / "ground_truth" / "apples.json").read_text() == before
    monkeypatch.undo()
    generate_orchard(out, progress=False, seed=2, **small)  # a rerun replaces the old capture
    assert (out / "ground_truth" / "apples.json").read_text() != before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture"]


def test_python_dash_m_srfpipe_is_the_srfpipe_command():
    """`python -m srfpipe` (no console script on PATH, a checkout on PYTHONPATH) ran nothing: the
    package had no __main__."""
    result = subprocess.run([sys.executable, "-m", "srfpipe", "summary", "--help"],
                            capture_output=True, text=True, check=True)
    assert "usage: srfpipe summary" in result.stdout


def test_ctrl_c_stops_a_stage_with_one_line_and_leaves_no_output(tmp_path):
    """Ctrl-C while the orchard renders: exit status 130, one line saying so (no traceback), and
    neither the capture folder nor its hidden partial left behind."""
    import os
    import signal
    import time

    out = tmp_path / "capture"
    stage = subprocess.Popen([sys.executable, "-m", "srfpipe", "orchard", "--out", str(out), "--no-progress"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not any(p.name.startswith(".capture.partial-") for p in tmp_path.iterdir()):
        assert stage.poll() is None and time.monotonic() < deadline, "the stage ended before it was interrupted"
        time.sleep(0.1)
    stage.send_signal(signal.SIGINT)
    _, stderr = stage.communicate(timeout=120)
    assert stage.returncode == 130, stderr
    assert "Traceback" not in stderr and stderr.strip().splitlines()[-1] == (
        "srfpipe orchard: interrupted: its output was not written")
    assert os.listdir(tmp_path) == []


@pytest.mark.bad_input
@pytest.mark.parametrize("options, key", [
    ({"fov_deg": 179.9999999}, "fov_deg"),  # fx ~1e-8 px: the poses stage refused the capture written
    ({"fov_deg": 1e-9}, "fov_deg"),  # fx ~2e12 px
    ({"distortion": [50, 50, 0, 0]}, "distortion"),  # a lens mapping most of the frame outside it
    ({"ring_radius": 1e-12}, "ring_radius"),  # every camera straight below the canopy centre
    ({"ring_radius": 1e300}, "ring_radius"),
])
def test_cameras_the_poses_stage_would_refuse_are_refused_naming_the_key(tmp_path, options, key):
    from srfpipe.config import ConfigError

    out = tmp_path / "capture"
    with pytest.raises(ConfigError, match=f"orchard .*{key}"):
        generate_orchard(out, progress=False, views=2, width=32, height=24, **options)
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.bad_input
def test_a_capture_in_which_no_view_shows_the_tree_is_refused(tmp_path):
    # a 1 nm tree covers no pixel: every view was all background, written as a capture like any other
    out = tmp_path / "capture"
    with pytest.raises(ValueError, match=r"no pixel of the 2 views shows the subject .*orchard.tree_height"):
        generate_orchard(out, progress=False, views=2, width=32, height=24, tree_height=1e-9)
    assert not out.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.bad_input
def test_more_apples_than_the_tree_holds_stop_when_it_is_full(monkeypatch):
    # n_apples 1e6 tried 200 places per apple asked for (2e8 tries, hours) on a tree holding ~230
    from srfpipe.scenes import tree

    monkeypatch.setattr(tree, "APPLE_TRY_BUDGET", 2000)
    monkeypatch.setattr(tree, "APPLE_MAX_MISSES", 500)
    tries = []
    distance = tree.point_segment_distance

    def counted(*args):
        tries.append(1)
        if len(tries) > 100_000:
            raise AssertionError("still trying after 100 000 places")
        return distance(*args)

    monkeypatch.setattr(tree, "point_segment_distance", counted)
    built = tree.build_tree(0, 10**6, 2, 0.0, 2.5)
    assert 0 < built.info["n_apples"] < 1000

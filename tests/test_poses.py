"""Pose import (nerfstudio, Blender, COLMAP, LLFF, orchard), validation errors, bounds, normalization, refinement."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from srfpipe import cameras
from srfpipe.artifacts import meta, open_artifact
from srfpipe.poses import (
    align_poses,
    bounds_from_frusta,
    bounds_from_points,
    colmap_camera_parameters,
    import_poses,
    load_capture,
    perturb_poses,
    pose_errors,
    read_blender,
    read_colmap,
    read_llff,
    read_nerfstudio,
)
from srfpipe.poses.colmap_refine import pairs_from_poses

# ----------------------------------------------------------------------------- synthetic captures


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV camera_to_world at `eye` looking at `target`."""
    eye = np.asarray(eye, float)
    forward = np.asarray(target, float) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, np.cross(forward, right), forward, eye
    return pose


def ring(n: int, radius: float = 3.0, height: float = 1.0, target=(0.0, 0.0, 1.0)) -> np.ndarray:
    angles = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([look_at([radius * np.cos(a), radius * np.sin(a), height], target) for a in angles])


def write_noise_images(folder: Path, names, width: int, height: int, seed: int = 0, channels: int = 3) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    for name in names:
        image = rng.integers(0, 256, size=(height, width, channels), dtype=np.uint8)
        assert cv2.imwrite(str(folder / name), image)


def write_nerfstudio(root: Path, poses_cv: np.ndarray, width=32, height=24, intrinsics=(30.0, 31.0, 16.0, 12.0),
                     distortion=(0.0, 0.0, 0.0, 0.0), **extra) -> Path:
    """A nerfstudio capture with noise images; poses given in OpenCV convention, stored as OpenGL."""
    names = [f"frame_{i:05d}.png" for i in range(len(poses_cv))]
    write_noise_images(root / "images", names, width, height)
    fx, fy, cx, cy = intrinsics
    k1, k2, p1, p2 = distortion
    meta_json = {
        "camera_model": "OPENCV", "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": width, "h": height,
        "k1": k1, "k2": k2, "p1": p1, "p2": p2,
        "frames": [{"file_path": f"images/{n}", "transform_matrix": cameras.opencv_to_opengl(p).tolist()}
                   for n, p in zip(names, poses_cv)],
        **extra,
    }
    (root / "transforms.json").write_text(json.dumps(meta_json))
    return root


def edit_transforms(root: Path, edit) -> Path:
    path = root / "transforms.json"
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    return path


def write_colmap_model(root: Path, text: bool, n_images: int = 4):
    """A COLMAP model written by pycolmap (two cameras: OPENCV and SIMPLE_RADIAL) plus noise images."""
    import pycolmap

    poses = ring(n_images)
    reconstruction = pycolmap.Reconstruction()
    cam1 = pycolmap.Camera.create_from_model_name(1, "OPENCV", 30.0, 32, 24)
    cam1.params = [30.0, 31.0, 16.5, 12.25, 0.05, -0.01, 0.001, -0.002]
    cam2 = pycolmap.Camera.create_from_model_name(2, "SIMPLE_RADIAL", 28.0, 32, 24)
    cam2.params = [28.0, 16.0, 12.0, -0.03]
    for camera in (cam1, cam2):
        reconstruction.add_camera_with_trivial_rig(camera)
    names = [f"im_{i}.jpg" for i in range(n_images)]
    for i, (name, pose) in enumerate(zip(names, poses)):
        w2c = np.linalg.inv(pose)
        image = pycolmap.Image(name=name, camera_id=1 + i % 2, image_id=i + 1)
        reconstruction.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3]))
    rng = np.random.default_rng(1)
    points = rng.uniform(-0.5, 0.5, size=(50, 3)) + [0, 0, 1]
    for p in points:
        reconstruction.add_point3D(p, pycolmap.Track(), np.zeros(3, np.uint8))
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (reconstruction.write_text if text else reconstruction.write_binary)(str(model))
    write_noise_images(root / "images", names, 32, 24)
    return poses, points, names


# ----------------------------------------------------------------------------- importers


def test_nerfstudio_import_converts_opengl_to_opencv(tmp_path):
    poses = ring(5)
    write_nerfstudio(tmp_path, poses)
    capture = read_nerfstudio(tmp_path)
    np.testing.assert_allclose(capture.camera_to_world, poses, atol=1e-12)
    np.testing.assert_allclose(capture.intrinsics, [[30.0, 31.0, 16.0, 12.0]] * 5)
    assert capture.image_size.tolist() == [[32, 24]] * 5
    assert capture.image_paths[0] == "images/frame_00000.png"
    assert capture.names[0] == "frame_00000"
    # the camera really looks at its target: the ring's centre projects to the principal point
    uv, depth = cameras.project_points(np.array([[0.0, 0.0, 1.0]]), capture.camera_to_world[0], capture.intrinsics[0])
    np.testing.assert_allclose(uv[0], [16.0, 12.0], atol=1e-9)
    assert depth[0] > 0


def test_nerfstudio_camera_angle_and_per_frame_intrinsics(tmp_path):
    write_nerfstudio(tmp_path, ring(3))

    def edit(data):
        for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
            del data[key]
        data["camera_angle_x"] = np.radians(60.0)
        data["frames"][1].update({"fl_x": 50.0, "fl_y": 52.0, "cx": 15.0, "cy": 11.0, "k1": 0.1})

    edit_transforms(tmp_path, edit)
    capture = read_nerfstudio(tmp_path / "transforms.json")
    focal = 0.5 * 32 / np.tan(np.radians(30.0))  # image width read from the PNG
    np.testing.assert_allclose(capture.intrinsics[0], [focal, focal, 16.0, 12.0])
    np.testing.assert_allclose(capture.intrinsics[1], [50.0, 52.0, 15.0, 11.0])
    np.testing.assert_allclose(capture.distortion[1], [0.1, 0.0, 0.0, 0.0])
    assert capture.image_size.tolist() == [[32, 24]] * 3


def test_nerfstudio_applied_transform_is_undone(tmp_path):
    original = ring(4)
    # nerfstudio's COLMAP converter: swap y and z, negate the new z, then store applied @ pose
    applied = np.eye(4)[[0, 2, 1, 3]]
    applied[2, :] *= -1
    write_nerfstudio(tmp_path, cameras.transform_poses(applied, original), applied_transform=applied[:3].tolist())
    capture = read_nerfstudio(tmp_path)
    np.testing.assert_allclose(capture.camera_to_world, original, atol=1e-12)
    assert capture.extra["applied_transform_undone"] == applied[:3].tolist()


@pytest.mark.bad_input
def test_nerfstudio_unsupported_camera_model_names_file(tmp_path):
    write_nerfstudio(tmp_path, ring(2))
    path = edit_transforms(tmp_path, lambda d: d.update(camera_model="OPENCV_FISHEYE"))
    with pytest.raises(ValueError, match=f"{path}.*OPENCV_FISHEYE"):
        read_nerfstudio(tmp_path)


def write_blender(root: Path, poses: np.ndarray, angle: float, n_train: int) -> None:
    """A Blender NeRF capture: the first `n_train` poses in the train split, the rest in test."""
    for split, frames in (("train", range(0, n_train)), ("test", range(n_train, len(poses)))):
        names = [f"r_{i}.png" for i in frames]
        write_noise_images(root / split, names, 40, 30, channels=4)  # Blender renders are RGBA
        data = {"camera_angle_x": angle, "frames": [
            {"file_path": f"./{split}/r_{i}", "rotation": 0.0,
             "transform_matrix": cameras.opencv_to_opengl(poses[i]).tolist()} for i in frames]}
        (root / f"transforms_{split}.json").write_text(json.dumps(data))


def test_blender_import_reads_size_from_images_and_adds_png(tmp_path):
    poses = ring(4)
    angle = 0.6911
    write_blender(tmp_path, poses, angle, n_train=3)
    capture = read_blender(tmp_path)
    assert capture.image_paths == ["train/r_0.png", "train/r_1.png", "train/r_2.png", "test/r_3.png"]
    np.testing.assert_allclose(capture.camera_to_world, poses, atol=1e-12)
    focal = 0.5 * 40 / np.tan(0.5 * angle)
    np.testing.assert_allclose(capture.intrinsics, [[focal, focal, 20.0, 15.0]] * 4)
    assert capture.image_size.tolist() == [[40, 30]] * 4
    assert capture.extra["splits"] == ["train", "train", "train", "test"]


@pytest.mark.parametrize("text", [False, True], ids=["binary", "text"])
def test_colmap_import(tmp_path, text):
    poses, points, names = write_colmap_model(tmp_path, text)
    capture = read_colmap(tmp_path)
    assert capture.image_paths == [f"images/{n}" for n in names]
    np.testing.assert_allclose(capture.camera_to_world, poses, atol=1e-9)
    np.testing.assert_allclose(capture.intrinsics[0], [30.0, 31.0, 16.5, 12.25])
    np.testing.assert_allclose(capture.distortion[0], [0.05, -0.01, 0.001, -0.002])
    np.testing.assert_allclose(capture.intrinsics[1], [28.0, 28.0, 16.0, 12.0])
    np.testing.assert_allclose(capture.distortion[1], [-0.03, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(np.sort(capture.points_world, axis=0), np.sort(points, axis=0), atol=1e-9)


def test_colmap_camera_models():
    import pycolmap

    def camera(model, params):
        cam = pycolmap.Camera.create_from_model_name(1, model, 10.0, 20, 10)
        cam.params = params
        return cam

    assert colmap_camera_parameters(camera("SIMPLE_PINHOLE", [9, 10, 5]), "x") == ([9, 9, 10, 5], [0, 0, 0, 0])
    assert colmap_camera_parameters(camera("PINHOLE", [9, 8, 10, 5]), "x") == ([9, 8, 10, 5], [0, 0, 0, 0])
    assert colmap_camera_parameters(camera("RADIAL", [9, 10, 5, 0.1, 0.2]), "x") == ([9, 9, 10, 5], [0.1, 0.2, 0, 0])
    with pytest.raises(ValueError, match="cam.txt.*OPENCV_FISHEYE is not supported"):
        colmap_camera_parameters(camera("OPENCV_FISHEYE", [9, 8, 10, 5, 0, 0, 0, 0]), "cam.txt")


def test_import_poses_writes_artifact_with_points_bounds(tmp_path):
    _, points, _ = write_colmap_model(tmp_path / "cap", text=False)
    out = import_poses({"format": "colmap", "path": str(tmp_path / "cap")}, None, {}, tmp_path / "poses.zarr")
    group = open_artifact(out, stage="poses")
    info = meta(group)
    assert group["camera_to_world"].shape == (4, 4, 4)
    assert group["points_world"].shape == (50, 3)
    assert info["bounds_source"] == "points"
    assert info["source_format"] == "colmap"
    assert info["refinement"] is None
    bounds = np.array(info["bounds_world"])
    assert np.all(bounds[0] <= points.min(0) + 0.02) and np.all(bounds[1] >= points.max(0) - 0.02)
    assert info["image_paths"][0] == "images/im_0.jpg"
    assert info["config"]["poses"]["refine"] == "none"


# ----------------------------------------------------------------------------- bounds and normalization


def test_normalization_round_trip(tmp_path):
    write_nerfstudio(tmp_path / "cap", ring(6))
    bounds = [[-1.0, -2.0, 0.0], [3.0, 2.0, 1.0]]
    out = import_poses({"format": "nerfstudio"}, tmp_path / "cap", {"bounds": bounds}, tmp_path / "p.zarr")
    info = meta(open_artifact(out))
    assert info["bounds_source"] == "config"
    scene_from_world = np.array(info["scene_from_world"])
    world_from_scene = np.array(info["world_from_scene"])
    np.testing.assert_allclose(scene_from_world @ world_from_scene, np.eye(4), atol=1e-12)
    corners = np.array(np.meshgrid(*zip(*bounds), indexing="ij")).reshape(3, -1).T
    scene = cameras.transform_points(scene_from_world, corners)
    assert np.abs(scene).max() == pytest.approx(1.0)  # the longest side spans [-1, 1]
    assert np.all(np.abs(scene) <= 1.0 + 1e-12)
    points = np.random.default_rng(0).uniform(-5, 5, size=(100, 3))
    back = cameras.transform_points(world_from_scene, cameras.transform_points(scene_from_world, points))
    np.testing.assert_allclose(back, points, atol=1e-12)
    poses = open_artifact(out)["camera_to_world"][:]
    round_trip = cameras.transform_poses(world_from_scene, cameras.transform_poses(scene_from_world, poses))
    np.testing.assert_allclose(round_trip, poses, atol=1e-12)


def test_bounds_from_points_ignores_outliers():
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-1, 1, size=(2000, 3)), [[100.0, 100.0, 100.0], [-80.0, 0.0, 0.0]]])
    bounds = bounds_from_points(points)
    assert np.all(bounds[0] > -1.2) and np.all(bounds[1] < 1.2)
    assert np.all(bounds[0] < -0.9) and np.all(bounds[1] > 0.9)


def test_points_near_cameras_leave_the_background_to_the_shell():
    from srfpipe.poses.bounds import near_cameras

    rng = np.random.default_rng(0)
    # a ring 3.5 from a tree, 1.5 up, looking at it; points on the tree and on the ground 15 round it
    poses = ring(24, radius=3.5, height=1.5, target=(0.0, 0.0, 1.2))
    tree = rng.uniform([-1, -1, 0], [1, 1, 2.5], size=(3000, 3))
    ground = np.column_stack([rng.uniform(-15, 15, size=(3000, 2)), np.zeros(3000)])
    box = bounds_from_points(np.concatenate([tree, ground]))
    assert np.all(box[1, :2] - box[0, :2] > 25)
    clipped = near_cameras(box, poses)
    # within the cameras' distance of what they look at: the tree and the ground under the ring
    assert np.all(clipped[1, :2] - clipped[0, :2] < 8) and np.all(clipped[1, :2] - clipped[0, :2] > 6)
    assert np.all(clipped[0] <= tree.min(0)) and np.all(clipped[1] >= tree.max(0))
    # forward-facing cameras (all on one side of what they see): the points' box as it is
    forward = np.stack([cameras.look_at([x, -5.0, 1.0], [x, 0.0, 1.0]) for x in np.linspace(-0.5, 0.5, 8)])
    np.testing.assert_array_equal(near_cameras(box, forward), box)


def test_bounds_from_frusta_ring_gives_box_around_target():
    poses = ring(16, radius=3.5, height=1.5, target=(0.5, -0.3, 1.2))
    intrinsics = np.tile([200.0, 200.0, 160.0, 120.0], (16, 1))  # ~77 deg horizontal field of view
    sizes = np.tile([320, 240], (16, 1))
    bounds = bounds_from_frusta(poses, intrinsics, sizes)
    centre = bounds.mean(0)
    np.testing.assert_allclose(centre[:2], [0.5, -0.3], atol=0.2)
    extent = bounds[1] - bounds[0]
    assert np.all(extent > 1.0) and np.all(extent < 7.0)  # around the object, inside the ring
    assert np.all(bounds[0] < [0.5, -0.3, 1.2]) and np.all(bounds[1] > [0.5, -0.3, 1.2])


# ----------------------------------------------------------------------------- bad inputs


@pytest.mark.bad_input
def test_missing_images_are_skipped_listed_and_recorded(tmp_path, caplog):
    write_nerfstudio(tmp_path / "cap", ring(6))
    for i in (1, 4):
        (tmp_path / "cap" / "images" / f"frame_{i:05d}.png").unlink()
    out = import_poses({"format": "nerfstudio", "path": str(tmp_path / "cap")}, None, {}, tmp_path / "poses.zarr")
    info = meta(open_artifact(out, stage="poses"))
    assert info["n_images"] == 4 and info["n_frames_listed"] == 6
    assert info["missing_images"] == ["images/frame_00001.png", "images/frame_00004.png"]
    assert "skipped 2 of 6 frames" in caplog.text and "frame_00004.png" in caplog.text


@pytest.mark.bad_input
def test_too_few_images_left_is_an_error_naming_the_file(tmp_path):
    write_nerfstudio(tmp_path, ring(4))
    for i in (0, 1, 2):
        (tmp_path / "images" / f"frame_{i:05d}.png").unlink()
    with pytest.raises(ValueError, match=r"transforms.json: only 1 of 4 frames have an image \(3 missing\)"):
        import_poses({"format": "nerfstudio", "path": str(tmp_path)}, None, {}, tmp_path / "poses.zarr")
    assert not (tmp_path / "poses.zarr").exists()
    for name in (tmp_path / "images").iterdir():
        name.unlink()
    with pytest.raises(FileNotFoundError, match="none of the 4 frames has an image"):
        load_capture({"format": "nerfstudio", "path": str(tmp_path)})


@pytest.mark.parametrize(
    "bad, message",
    [(np.full((4, 4), np.nan), "NaN"),
     (np.diag([2.0, 1.0, 1.0, 1.0]), "not orthonormal"),
     (np.diag([-1.0, 1.0, 1.0, 1.0]), "reflection")],
    ids=["nan", "scaled", "reflection"],
)
@pytest.mark.bad_input
def test_bad_pose_names_file_and_frame(tmp_path, bad, message):
    write_nerfstudio(tmp_path, ring(3))
    # Python's json writes NaN as a bare NaN literal, as many capture tools do
    path = edit_transforms(tmp_path, lambda d: d["frames"][2].update(transform_matrix=bad.tolist()))
    with pytest.raises(ValueError, match=rf"{path}: frames\[2\].*{message}"):
        read_nerfstudio(tmp_path)


@pytest.mark.bad_input
@pytest.mark.parametrize("file_path", ["../outside.png", "images/../../outside.png", "/etc/hostname"])
def test_file_path_escaping_dataset_folder(tmp_path, file_path):
    capture = tmp_path / "capture"
    write_nerfstudio(capture, ring(2))
    write_noise_images(tmp_path, ["outside.png"], 32, 24)
    path = edit_transforms(capture, lambda d: d["frames"][0].update(file_path=file_path))
    with pytest.raises(ValueError, match=rf"{path}: frames\[0\].*points outside the dataset folder"):
        read_nerfstudio(capture)


def test_absolute_path_inside_capture_is_accepted(tmp_path):
    write_nerfstudio(tmp_path, ring(2))
    edit_transforms(tmp_path, lambda d: d["frames"][0].update(file_path=str(tmp_path / "images" / "frame_00000.png")))
    assert read_nerfstudio(tmp_path).image_paths[0] == "images/frame_00000.png"


def test_min_images_is_the_configured_minimum(tmp_path):
    write_nerfstudio(tmp_path, ring(4))
    (tmp_path / "images" / "frame_00002.png").unlink()
    source = {"format": "nerfstudio", "path": str(tmp_path)}
    message = r"transforms.json: only 3 of 4 frames have an image \(1 missing\), fewer than poses.min_images=4"
    with pytest.raises(ValueError, match=message + ".*images/frame_00002.png"):
        import_poses(source, None, {"min_images": 4}, tmp_path / "poses.zarr")
    assert not (tmp_path / "poses.zarr").exists()
    out = import_poses(source, None, {"min_images": 3}, tmp_path / "poses.zarr")
    assert meta(open_artifact(out, stage="poses"))["n_images"] == 3


def test_blender_frames_without_image_are_skipped(tmp_path, caplog):
    poses = ring(5)
    write_blender(tmp_path, poses, 0.6911, n_train=3)
    for missing in ("train/r_1.png", "test/r_4.png"):
        (tmp_path / missing).unlink()
    capture = read_blender(tmp_path)
    assert capture.image_paths == ["train/r_0.png", "train/r_2.png", "test/r_3.png"]
    np.testing.assert_allclose(capture.camera_to_world, poses[[0, 2, 3]], atol=1e-12)
    assert capture.extra["splits"] == ["train", "train", "test"]
    assert capture.extra["n_frames_listed"] == 5
    assert capture.extra["missing_images"] == ["train/r_1.png", "test/r_4.png"]
    assert "skipped 2 of 5 frames" in caplog.text and "test/r_4.png" in caplog.text
    for image in (*(tmp_path / "train").iterdir(), *(tmp_path / "test").iterdir()):
        image.unlink()
    with pytest.raises(FileNotFoundError, match=rf"{tmp_path}: none of the 5 frames of transforms_train.json, "
                                                r"transforms_test.json has an image file"):
        read_blender(tmp_path)


def test_colmap_images_without_files_are_skipped(tmp_path, caplog):
    poses, _, _ = write_colmap_model(tmp_path, text=True)
    (tmp_path / "images" / "im_2.jpg").unlink()
    capture = read_colmap(tmp_path)
    assert capture.image_paths == ["images/im_0.jpg", "images/im_1.jpg", "images/im_3.jpg"]
    np.testing.assert_allclose(capture.camera_to_world, poses[[0, 1, 3]], atol=1e-9)
    assert capture.extra["n_frames_listed"] == 4 and capture.extra["missing_images"] == ["images/im_2.jpg"]
    assert "sparse/0: skipped 1 of 4 frames" in caplog.text and "images/im_2.jpg" in caplog.text
    for image in (tmp_path / "images").iterdir():
        image.unlink()
    with pytest.raises(FileNotFoundError, match=r"sparse/0: none of the 4 posed images has a file in .*images"):
        read_colmap(tmp_path)


@pytest.mark.bad_input
def test_ground_truth_count_mismatch(tmp_path):
    write_nerfstudio(tmp_path, ring(3))
    labels = tmp_path / "ground_truth" / "labels"
    labels.mkdir(parents=True)
    for name in ("frame_00000", "frame_00001"):
        cv2.imwrite(str(labels / f"{name}.png"), np.zeros((24, 32), np.uint8))
    with pytest.raises(ValueError, match=rf"{labels}: mismatched counts: 2 labels files for 3 frames.*frame_00002"):
        load_capture({"format": "orchard"}, tmp_path)


@pytest.mark.bad_input
def test_corrupt_image_names_file(tmp_path):
    write_nerfstudio(tmp_path, ring(3))
    bad = tmp_path / "images" / "frame_00001.png"
    bad.write_bytes(b"this is not a png at all" * 10)
    with pytest.raises(ValueError, match=rf"{bad}: corrupt"):
        load_capture({"format": "nerfstudio", "path": str(tmp_path)})


@pytest.mark.bad_input
def test_unknown_format_names_capture(tmp_path):
    with pytest.raises(ValueError, match=rf"{tmp_path}: unknown capture format 'polycam'"):
        import_poses({"format": "polycam"}, tmp_path, {}, tmp_path / "poses.zarr")
    with pytest.raises(FileNotFoundError, match=rf"{tmp_path}: no transforms.json"):
        load_capture({"format": "nerfstudio", "path": str(tmp_path)})
    assert not (tmp_path / "poses.zarr").exists()


@pytest.mark.bad_input
def test_cli_reports_bad_input_in_one_line(tmp_path, capsys):
    from srfpipe.cli import main

    write_nerfstudio(tmp_path / "cap", ring(3))
    for i in (1, 2):
        (tmp_path / "cap" / "images" / f"frame_{i:05d}.png").unlink()
    code = main(["poses", "--source", json.dumps({"format": "nerfstudio"}), "--capture", str(tmp_path / "cap"),
                 "--out", str(tmp_path / "poses.zarr")])
    assert code == 1
    err = capsys.readouterr().err
    assert "srfpipe poses: error:" in err and "frame_00002.png" in err
    assert not (tmp_path / "poses.zarr").exists()



@pytest.mark.bad_input
def test_colmap_refinement_of_two_images_is_refused_before_colmap_runs(tmp_path, monkeypatch):
    # the refined cameras are aligned back onto at least 3 given ones: two images went through SIFT,
    # matching and triangulation and then always failed, with a message about matches
    import pycolmap

    def not_reached(*args, **kwargs):
        raise AssertionError("COLMAP ran")

    monkeypatch.setattr(pycolmap, "extract_features", not_reached)
    write_nerfstudio(tmp_path / "cap", ring(2))
    with pytest.raises(ValueError, match=r"transforms.json: poses.refine colmap needs at least 3 images.*got 2"):
        import_poses({"format": "nerfstudio"}, tmp_path / "cap", {"refine": "colmap"}, tmp_path / "poses.zarr")
    assert not (tmp_path / "poses.zarr").exists()

# ----------------------------------------------------------------------------- package structure

# Each module of srfpipe/poses may import only modules before it: the importers and the bounds build
# on `capture`, the refinement on `align`, and only the stage ties everything together.
POSES_MODULE_ORDER = ["geometry", "capture", "bounds", "align", "nerfstudio", "blender", "colmap", "llff", "ground_truth",
                      "colmap_refine", "video", "sfm", "stage"]


def poses_imports(path: Path) -> set[str]:
    """The srfpipe.poses names a module imports, anywhere in it (function-level imports too)."""
    import ast

    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("srfpipe.poses"):
            found.add(node.module)
        elif isinstance(node, ast.ImportFrom) and node.module == "srfpipe":
            found.update(f"srfpipe.{alias.name}" for alias in node.names if alias.name == "poses")
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.startswith("srfpipe.poses"))
    return found


def test_poses_modules_import_one_way():
    import srfpipe.poses

    folder = Path(srfpipe.poses.__file__).parent
    assert sorted(p.stem for p in folder.glob("*.py") if p.stem != "__init__") == sorted(POSES_MODULE_ORDER)
    for position, name in enumerate(POSES_MODULE_ORDER):
        for imported in poses_imports(folder / f"{name}.py"):
            assert imported != "srfpipe.poses", f"{name}.py imports the package itself (a cycle through __init__)"
            target = imported.removeprefix("srfpipe.poses.")
            assert POSES_MODULE_ORDER.index(target) < position, f"{name}.py imports {target}.py, which comes later"


# ----------------------------------------------------------------------------- perturbation and errors


def test_perturbation_has_requested_size():
    poses = ring(10)
    perturbed = perturb_poses(poses, 2.0, 0.1, seed=3)
    errors = pose_errors(perturbed, poses, scene_size=1.0, align=False)
    assert errors["rot_err_deg"] == pytest.approx(2.0, abs=1e-9)
    assert errors["trans_err"] == pytest.approx(0.1, abs=1e-9)
    np.testing.assert_allclose(perturb_poses(poses, 2.0, 0.1, seed=3), perturbed)  # deterministic


def test_pose_errors_ignore_a_change_of_gauge():
    poses = ring(8)
    gauge = np.eye(4)
    gauge[:3, :3] = 2.5 * cv2.Rodrigues(np.array([0.3, -0.2, 0.5]))[0]
    gauge[:3, 3] = [1.0, -4.0, 2.0]
    errors = pose_errors(cameras.transform_poses(gauge, poses), poses, scene_size=1.0)
    assert errors["rot_err_deg"] < 1e-6 and errors["trans_err"] < 1e-9


# ----------------------------------------------------------------------------- the orchard capture


@pytest.fixture(scope="module")
def tiny_orchard(tmp_path_factory):
    from srfpipe.scenes.orchard import generate_orchard

    return generate_orchard(tmp_path_factory.mktemp("orchard") / "capture", progress=False,
                            views=12, width=64, height=48)


def test_orchard_capture_import(tiny_orchard, tmp_path):
    out = import_poses({"format": "orchard"}, tiny_orchard, {}, tmp_path / "poses.zarr")
    group = open_artifact(out, stage="poses")
    info = meta(group)
    scene = json.loads((tiny_orchard / "ground_truth" / "scene.json").read_text())
    np.testing.assert_allclose(group["camera_to_world"][:], scene["camera_to_world"], atol=1e-9)
    k = scene["intrinsics"]
    np.testing.assert_allclose(group["intrinsics"][0], [k["fx"], k["fy"], k["cx"], k["cy"]])
    assert info["bounds_source"] == "ground_truth"
    np.testing.assert_allclose(info["bounds_world"], scene["bounds_world"])
    assert info["ground_truth"] == str((tiny_orchard / "ground_truth").resolve())
    assert info["names"] == scene["names"]
    # every apple lies inside the normalized scene box
    apples = np.array([a["centre"] for a in json.loads((tiny_orchard / "ground_truth" / "apples.json").read_text())])
    scene_points = cameras.transform_points(np.array(info["scene_from_world"]), apples)
    assert np.all(np.abs(scene_points) <= 1.0)
    # without scene.json, the frusta heuristic still finds a box around the tree
    capture = load_capture({"format": "nerfstudio", "path": str(tiny_orchard)})
    frusta = bounds_from_frusta(capture.camera_to_world, capture.intrinsics, capture.image_size)
    assert np.all(frusta[0] < apples.min(0)) and np.all(frusta[1] > apples.max(0))
    assert np.max(frusta[1] - frusta[0]) < 2 * scene["parameters"]["ring_radius"]


# ----------------------------------------------------------------------------- COLMAP refinement


def render_box_corner(pose, intrinsics, width, height, textures, extent=2.0, distortion=None) -> np.ndarray:
    """Ray-cast the inside of a box corner (planes x=0, y=0, z=0 over [0, extent]^2), noise-textured,
    so that SIFT finds plenty of exact features: a tiny capture on which refinement must work.
    `distortion`: seen through that OpenCV lens."""
    origins, directions = cameras.pixel_rays(pose, intrinsics, width, height, distortion)
    image = np.zeros((height, width, 3), np.float32)
    nearest = np.full((height, width), np.inf)
    for axis, texture in enumerate(textures):
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -origins[..., axis] / directions[..., axis]
        hit = origins + t[..., None] * directions
        a, b = [i for i in range(3) if i != axis]
        u, v = hit[..., a] / extent, hit[..., b] / extent
        inside = (t > 0) & (t < nearest) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
        size = texture.shape[0] - 1
        sample = cv2.remap(texture, (u * size).astype(np.float32), (v * size).astype(np.float32), cv2.INTER_LINEAR)
        image[inside], nearest[inside] = sample[inside], t[inside]
    return image.astype(np.uint8)


def write_box_corner_capture(root: Path, views=12, width=320, height=240, lens=None, claimed_lens=None) -> np.ndarray:
    """The box corner's capture; its images taken through `lens` (OpenCV k1, k2, p1, p2), its
    transforms.json claiming `claimed_lens` (default: the lens itself)."""
    rng = np.random.default_rng(0)
    textures = [cv2.resize(rng.uniform(0, 255, (128, 128, 3)).astype(np.float32), (512, 512),
                           interpolation=cv2.INTER_CUBIC).clip(0, 255) for _ in range(3)]
    angles = np.linspace(0.15, 1.4, views)
    poses = np.stack([look_at([0.6 + 2.6 * np.cos(a), 0.6 + 2.6 * np.sin(a), 1.6 + 0.3 * np.sin(3 * a)],
                              [0.5, 0.5, 0.5]) for a in angles])
    k = (220.0, 220.0, width / 2, height / 2)
    claimed = claimed_lens if claimed_lens is not None else lens
    write_nerfstudio(root, poses, width=width, height=height, intrinsics=k,
                     distortion=tuple(claimed) if claimed is not None else (0.0, 0.0, 0.0, 0.0))
    for i, pose in enumerate(poses):
        cv2.imwrite(str(root / "images" / f"frame_{i:05d}.png"), render_box_corner(pose, np.array(k), width, height,
                                                                                  textures, distortion=lens))
    return poses


def test_pairs_from_poses_keeps_the_views_that_can_match():
    ring = [look_at([3 * np.cos(a), 3 * np.sin(a), 0.5], [0, 0, 0]) for a in np.radians(np.arange(0, 360, 10))]
    up = look_at([3.0, 0.1, 0.5], [3.1, 0.1, 10.0])  # beside camera 0, looking at the sky
    pairs = pairs_from_poses(np.stack([*ring, up]), neighbours=20, max_angle_deg=30.0, min_pairs=3)
    in_ring = [(i, j) for i, j in pairs if j < 36]
    steps = [min(j - i, 36 - (j - i)) for i, j in in_ring]
    # every camera meets the three on each side (10, 20, 30 degrees apart) and no one farther round
    assert sorted(set(steps)) == [1, 2, 3] and len(in_ring) == 36 * 3
    # the camera that shares no view direction still gets the three closest in angle
    assert len([p for p in pairs if p[1] == 36]) == 3
    assert len(pairs) < 37 * 36 // 2 / 5  # a fifth of the exhaustive pairs
    # fewer neighbours: each camera keeps its nearest
    assert {(i, j) for i, j in pairs_from_poses(np.stack(ring), neighbours=2) if j - i == 1 or (i, j) == (0, 35)} \
        == {(i, i + 1) for i in range(35)} | {(0, 35)}


@pytest.mark.parametrize("matcher", ["auto", "poses"])
def test_colmap_refinement_repairs_perturbed_poses(tmp_path, matcher):
    truth = write_box_corner_capture(tmp_path / "cap")
    options = {"refine": "colmap", "matcher": matcher, "perturb_rot_deg": 1.0, "perturb_trans_frac": 0.02,
               "bounds": [[0, 0, 0], [2, 2, 2]]}
    out = import_poses({"format": "nerfstudio"}, tmp_path / "cap", options, tmp_path / "poses.zarr", threads=2)
    group = open_artifact(out, stage="poses")
    info = meta(group)
    stats = info["refinement"]
    assert stats["matcher"] == ("exhaustive" if matcher == "auto" else "poses") and stats["num_images_refined"] == 12
    perturbed = perturb_poses(truth, 1.0, 0.02 * 2.0, seed=0)  # what the stage refined
    # 12 views over 72 degrees: pairs from the (given) poses skip those more than 30 degrees apart
    assert stats["pairs_matched"] == (66 if matcher == "auto" else len(pairs_from_poses(perturbed))) >= 44
    assert stats["reprojection_error_after_px"] < 0.5 < stats["reprojection_error_before_px"]
    assert stats["num_points3D"] > 200 and group["points_world"].shape == (stats["num_points3D"], 3)
    before = pose_errors(perturbed, truth, scene_size=2.0)
    after = pose_errors(group["camera_to_world"][:], truth, scene_size=2.0)
    assert after["rot_err_deg"] < 0.25 * before["rot_err_deg"]
    assert after["trans_err"] < 0.25 * before["trans_err"]
    # the world frame is kept: without re-alignment the refined cameras sit where the given ones were
    raw = pose_errors(group["camera_to_world"][:], truth, scene_size=2.0, align=False)
    assert raw["trans_err"] < 0.02
    # the refined points lie on the corner's three planes (each has one coordinate near 0), up to
    # the gauge of the perturbed input that the refined poses were aligned back to
    points = cameras.transform_points(align_poses(group["camera_to_world"][:], truth), group["points_world"][:])
    assert np.median(np.abs(points).min(axis=1)) < 0.005
    assert not list(tmp_path.glob(".colmap-refine-*"))  # the scratch database is gone
    # refine_distortion's default (stated) frees only a stated lens: this pinhole stays a pinhole
    assert info["config"]["poses"]["refine_distortion"] == "stated" and "distortion" not in stats
    assert not group["distortion"][:].any()


def test_colmap_refinement_measures_a_lens_the_capture_misstates(tmp_path):
    """A phone-like lens with strong tangential terms that the capture's calibration leaves out
    (as a poor COLMAP model would): by default (poses.refine_distortion: stated, the capture states
    a lens) the matches measure the lens, and poses.zarr's calibration gives the frame's pixels
    about the rays the lens really gives them; with refine_distortion false the capture's
    calibration is kept as given."""
    k, lens, claimed = (220.0, 220.0, 160.0, 120.0), (-0.05, 0.02, 0.011, 0.0096), (-0.05, 0.02, 0.0, 0.0)
    write_box_corner_capture(tmp_path / "cap", lens=lens, claimed_lens=claimed)
    options = {"refine": "colmap", "bounds": [[0, 0, 0], [2, 2, 2]]}
    kept = open_artifact(import_poses({"format": "nerfstudio"}, tmp_path / "cap", {**options, "refine_distortion": False},
                                      tmp_path / "kept.zarr", threads=2), stage="poses")
    assert "distortion" not in meta(kept)["refinement"]
    np.testing.assert_allclose(kept["distortion"][:], np.tile(claimed, (12, 1)))
    out = import_poses({"format": "nerfstudio"}, tmp_path / "cap", options, tmp_path / "poses.zarr", threads=2)
    group = open_artifact(out, stage="poses")
    stats = meta(group)["refinement"]
    assert meta(group)["config"]["poses"]["refine_distortion"] == "stated"
    assert len(stats["distortion"]) == 1 and stats["distortion"][0]["given"] == list(claimed)
    distortion = group["distortion"][:]
    assert (distortion == distortion[0]).all()  # one lens, shared by the images taken with it
    np.testing.assert_allclose(group["intrinsics"][:], np.tile(k, (12, 1)))  # focal and centre as given

    def ray_error_px(calibration):
        """Per pixel of the frame: the angle, in pixels at the focal length, between the ray the true
        lens gives it and the ray that `calibration` gives it."""
        truth = cameras.pixel_rays(np.eye(4), k, 320, 240, lens)[1]
        found = cameras.pixel_rays(np.eye(4), k, 320, 240, calibration)[1]
        return k[0] * np.arccos(np.clip((truth * found).sum(-1), -1.0, 1.0))

    before, after = ray_error_px(claimed), ray_error_px(distortion[0])
    assert before.mean() > 1.0 and before.max() > 4.0  # the misstated lens: corners several px off
    # what is left is mostly what the refined poses absorb (a turn of a camera shifts its pixels alike)
    assert after.mean() < 0.5 and after.max() < 0.4 * before.max()
    # the reprojection error cannot tell the two apart: points and poses bend round a smooth lens
    # error (0.17 px here with the misstated lens), so the lens is judged by its rays, as above
    assert stats["reprojection_error_after_px"] < 0.5


# ----------------------------------------------------------------------------- LLFF poses_bounds.npy


def forward_facing(n: int = 4) -> np.ndarray:
    """OpenCV camera_to_world of `n` cameras on a small plane at z = 0, all looking at (0, 0, 10)."""
    return np.stack([look_at([0.4 * (i % 2) - 0.2, 0.3 * i - 0.5, 0.0], [0.0, 0.0, 10.0], up=(0.0, -1.0, 0.0))
                     for i in range(n)])


def llff_rows(poses_cv: np.ndarray, width: int, height: int, focal: float, near_far=(2.0, 30.0)) -> np.ndarray:
    """poses_bounds.npy rows for OpenCV poses: LLFF's camera axes are down, right, backwards, i.e.
    the OpenCV columns (y, x, -z); then the original images' height, width, focal, and near, far."""
    rows = []
    for pose in poses_cv:
        rotation = np.stack([pose[:3, 1], pose[:3, 0], -pose[:3, 2]], axis=1)
        matrix = np.concatenate([rotation, pose[:3, 3:4], [[height], [width], [focal]]], axis=1)
        rows.append(np.concatenate([matrix.ravel(), near_far]))
    return np.asarray(rows)


def write_llff(root: Path, poses_cv: np.ndarray, original=(64, 48), focal=60.0,
               folders=(("images_4", 4),)) -> Path:
    """An LLFF capture: poses_bounds.npy for `original` (width, height) images and, per
    (folder, factor), noise PNGs downscaled by factor. Files sort like the rows (LLFF's pairing)."""
    root.mkdir(parents=True, exist_ok=True)
    names = [f"IMG_{i:04d}.png" for i in range(len(poses_cv))]
    for folder, factor in folders:
        write_noise_images(root / folder, names, original[0] // factor, original[1] // factor)
    np.save(root / "poses_bounds.npy", llff_rows(poses_cv, *original, focal))
    return root


def test_llff_import_converts_axes_and_scales_intrinsics(tmp_path):
    truth = forward_facing()
    write_llff(tmp_path, truth)
    capture = read_llff(tmp_path)
    assert capture.source_format == "llff" and capture.source_file == tmp_path / "poses_bounds.npy"
    assert capture.image_paths == [f"images_4/IMG_{i:04d}.png" for i in range(4)]
    np.testing.assert_allclose(capture.camera_to_world, truth, atol=1e-9)
    # 16x12 images of 64x48 originals: focal 60 / 4, principal point at the centre, no distortion
    np.testing.assert_allclose(capture.intrinsics, np.tile([15.0, 15.0, 8.0, 6.0], (4, 1)))
    assert capture.image_size.tolist() == [[16, 12]] * 4
    assert not capture.distortion.any() and capture.points_world is None
    assert capture.extra["near_far"] == [[2.0, 30.0]] * 4
    assert capture.extra["llff_original_size"] == [64.0, 48.0]


def test_llff_projection_matches_llff_camera_axes(tmp_path):
    """A point given in LLFF's camera frame (down, right, back; the camera looks along -back)
    projects where a pinhole with LLFF's axes puts it: u = cx + f right / depth, v = cy + f down / depth."""
    truth = forward_facing()
    write_llff(tmp_path, truth, folders=(("images", 1),))
    capture = read_llff(tmp_path)
    rows = np.load(tmp_path / "poses_bounds.npy")
    for i, row in enumerate(rows):
        matrix = row[:15].reshape(3, 5)
        down, right, back = 0.3, -0.2, -2.5
        point = matrix[:, :3] @ [down, right, back] + matrix[:, 3]
        uv, depth = cameras.project_points(point[None], capture.camera_to_world[i], capture.intrinsics[i])
        np.testing.assert_allclose(depth, [2.5])
        np.testing.assert_allclose(uv[0], [32.0 + 60.0 * right / 2.5, 24.0 + 60.0 * down / 2.5])


def test_llff_images_folder_default_and_override(tmp_path):
    write_llff(tmp_path, forward_facing(3), folders=(("images", 1), ("images_4", 4), ("images_8", 8)))
    assert read_llff(tmp_path).image_paths[0] == "images_4/IMG_0000.png"  # images_4 first
    full = load_capture({"format": "llff", "path": str(tmp_path), "images_dir": "images"})
    np.testing.assert_allclose(full.intrinsics[0], [60.0, 60.0, 32.0, 24.0])
    eighth = read_llff(tmp_path, images_dir="images_8")
    np.testing.assert_allclose(eighth.intrinsics[0], [7.5, 7.5, 4.0, 3.0])
    assert eighth.image_size[0].tolist() == [8, 6]


def test_llff_import_poses_writes_artifact(tmp_path):
    write_llff(tmp_path / "cap", forward_facing())
    out = import_poses({"format": "llff"}, tmp_path / "cap", {}, tmp_path / "poses.zarr")
    group = open_artifact(out, stage="poses")
    info = meta(group)
    assert info["source_format"] == "llff" and info["bounds_source"] == "frusta"
    assert info["source_file"].endswith("poses_bounds.npy") and info["near_far"] == [[2.0, 30.0]] * 4
    assert group["camera_to_world"].shape == (4, 4, 4) and "points_world" not in group


@pytest.mark.bad_input
def test_llff_wrong_shape_names_file(tmp_path):
    write_llff(tmp_path, forward_facing(3))
    npy = tmp_path / "poses_bounds.npy"
    np.save(npy, np.load(npy)[:, :15])  # the 3x5 matrices without near, far
    with pytest.raises(ValueError, match=rf"{npy}: expected shape \(N, 17\).*got \(3, 15\)"):
        read_llff(tmp_path)
    np.save(npy, np.zeros((3, 3, 5)))
    with pytest.raises(ValueError, match=rf"{npy}: expected shape \(N, 17\).*got \(3, 3, 5\)"):
        read_llff(tmp_path)
    npy.write_bytes(b"not an array")
    with pytest.raises(ValueError, match=rf"{npy}: not a NumPy .npy array"):
        read_llff(tmp_path)
    npy.unlink()
    with pytest.raises(FileNotFoundError, match=rf"{npy}: file does not exist"):
        load_capture({"format": "llff", "path": str(tmp_path)})


@pytest.mark.bad_input
def test_llff_count_mismatch_names_file(tmp_path):
    write_llff(tmp_path, forward_facing(3))
    (tmp_path / "images_4" / "IMG_0001.png").unlink()
    with pytest.raises(ValueError, match=rf"{tmp_path / 'poses_bounds.npy'}: mismatched counts: 3 rows for 2 images"):
        read_llff(tmp_path)


@pytest.mark.bad_input
@pytest.mark.parametrize("column", [3, 14, 16])  # a rotation entry, the focal length, the far bound
def test_llff_non_finite_values_name_file_and_row(tmp_path, column):
    write_llff(tmp_path, forward_facing(3))
    npy = tmp_path / "poses_bounds.npy"
    rows = np.load(npy)
    rows[1, column] = np.nan if column != 14 else np.inf
    np.save(npy, rows)
    with pytest.raises(ValueError, match=rf"{npy}: row 1 \(of 3\) holds NaN or infinite values"):
        read_llff(tmp_path)


@pytest.mark.bad_input
def test_llff_missing_image_folder_names_capture(tmp_path):
    write_llff(tmp_path, forward_facing(3), folders=(("images_8", 8),))
    with pytest.raises(FileNotFoundError, match=rf"{tmp_path}: no images folder \(images_4 or images\); "
                                                r"set source.images_dir to one of images_8"):
        read_llff(tmp_path)
    with pytest.raises(FileNotFoundError, match=rf"{tmp_path / 'images_2'}: images folder \(source.images_dir\)"):
        read_llff(tmp_path, images_dir="images_2")


@pytest.mark.bad_input
@pytest.mark.parametrize("images_dir", ["../outside", "/etc"])
def test_llff_images_dir_outside_capture_is_refused(tmp_path, images_dir):
    write_llff(tmp_path / "cap", forward_facing(3))
    write_llff(tmp_path / "outside", forward_facing(3), folders=(("", 4),))
    with pytest.raises(ValueError, match="points outside the dataset folder"):
        read_llff(tmp_path / "cap", images_dir=images_dir)


@pytest.mark.bad_input
def test_llff_symlinked_image_outside_capture_is_refused(tmp_path):
    write_llff(tmp_path / "cap", forward_facing(3))
    write_noise_images(tmp_path / "elsewhere", ["x.png"], 16, 12)
    target = tmp_path / "cap" / "images_4" / "IMG_0002.png"
    target.unlink()
    target.symlink_to(tmp_path / "elsewhere" / "x.png")
    with pytest.raises(ValueError, match=r"row 2: file_path 'images_4/IMG_0002.png' is a symlink"):
        read_llff(tmp_path / "cap")
    assert len(read_llff(tmp_path / "cap", allowed_roots=[tmp_path / "elsewhere"])) == 3


@pytest.mark.bad_input
def test_llff_image_of_another_aspect_ratio_names_row(tmp_path):
    write_llff(tmp_path, forward_facing(3))
    write_noise_images(tmp_path / "images_4", ["IMG_0001.png"], 12, 16)  # rotated
    with pytest.raises(ValueError, match=r"row 1 \(images_4/IMG_0001.png\): image is 12x16, not the aspect "
                                         r"ratio of the poses' 64x48"):
        read_llff(tmp_path)


@pytest.mark.bad_input
def test_llff_bad_rotation_names_row(tmp_path):
    write_llff(tmp_path, forward_facing(3))
    npy = tmp_path / "poses_bounds.npy"
    rows = np.load(npy)
    rows[2, 0:3] *= 2.0  # first row of the 3x5 matrix: the rotation is no longer orthonormal
    np.save(npy, rows)
    with pytest.raises(ValueError, match=r"poses_bounds.npy: row 2 \(images_4/IMG_0002.png\): pose rotation is not"):
        read_llff(tmp_path)


def shared_capture(name: str) -> Path:
    """A capture of ../shared/data beside the repository (read-only test data, never copied)."""
    for folder in (Path(__file__).resolve().parents[2] / "shared" / "data" / name, Path("/work/shared/data") / name):
        if folder.is_dir():
            return folder
    pytest.skip(f"{name}: ../shared/data/{name} is not there (test data beside the repository)")


def test_llff_real_fern_capture():
    fern = shared_capture("fern")
    capture = load_capture({"format": "llff", "path": str(fern)})
    assert len(capture) == 20 and capture.image_paths[0] == "images_4/image000.png"
    assert capture.image_size.tolist() == [[1008, 756]] * 20
    np.testing.assert_allclose(capture.intrinsics[:, :2], 3260.5 / 4, rtol=1e-3)  # 815.1
    np.testing.assert_allclose(capture.intrinsics[:, 2:], np.tile([504.0, 378.0], (20, 1)))
    # forward-facing: every camera looks within 15 degrees of the mean viewing direction, and the
    # scene (LLFF's near bound, 17 to 19 units) lies in front of every camera
    forward = capture.camera_to_world[:, :3, 2]
    mean = forward.mean(0) / np.linalg.norm(forward.mean(0))
    assert np.all(forward @ mean > np.cos(np.radians(15)))
    near_far = np.asarray(capture.extra["near_far"])
    assert near_far.shape == (20, 2) and np.all((near_far[:, 0] > 10) & (near_far[:, 1] > near_far[:, 0]))
    centre = capture.camera_to_world[:, :3, 3].mean(0) + near_far[:, 0].min() * mean
    for pose, k in zip(capture.camera_to_world, capture.intrinsics):
        uv, depth = cameras.project_points(centre[None], pose, k)
        assert depth[0] > 0 and 0 < uv[0, 0] < 1008 and 0 < uv[0, 1] < 756

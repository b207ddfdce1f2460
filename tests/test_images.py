"""Downscaling to images.zarr: sizes, intrinsics, undistortion, ground truth, atomicity, bad images."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from srfpipe import cameras
from srfpipe.artifacts import meta, open_artifact
from srfpipe.images import downscale_images, read_rgb
from srfpipe.poses import import_poses
from test_poses import edit_transforms, ring, write_nerfstudio


def poses_zarr(tmp_path, capture, fmt="nerfstudio"):
    return import_poses({"format": fmt}, capture, {}, tmp_path / "poses.zarr")


def test_downscale_size_intrinsics_and_pixels(tmp_path):
    capture = write_nerfstudio(tmp_path / "cap", ring(4), width=64, height=48, intrinsics=(60.0, 62.0, 32.0, 24.0))
    out = downscale_images(poses_zarr(tmp_path, capture), {"downscale": 4}, tmp_path / "images.zarr", progress=False)
    group = open_artifact(out, stage="downscale")
    info = meta(group)
    assert group["images"].shape == (4, 12, 16, 3) and group["images"].dtype == np.uint8
    assert group["images"].chunks == (1, 12, 16, 3)  # one image per chunk
    np.testing.assert_allclose(group["intrinsics"][:], [[15.0, 15.5, 8.0, 6.0]] * 4)
    np.testing.assert_allclose(group["camera_to_world"][:], ring(4), atol=1e-12)
    assert (info["width"], info["height"], info["downscale"]) == (16, 12, 4.0)
    assert info["names"] == [f"frame_{i:05d}" for i in range(4)]
    assert info["ground_truth"] is None and "ground_truth" not in group
    bgr = cv2.imread(str(capture / "images" / "frame_00002.png"))
    expected = cv2.resize(bgr[..., ::-1], (16, 12), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(group["images"][2], expected)  # RGB order, INTER_AREA
    poses_info = meta(open_artifact(tmp_path / "poses.zarr"))
    assert info["scene_from_world"] == poses_info["scene_from_world"]


def test_non_integer_factor_scales_intrinsics_by_actual_ratio(tmp_path):
    capture = write_nerfstudio(tmp_path / "cap", ring(2), width=64, height=48, intrinsics=(60.0, 60.0, 32.0, 24.0))
    out = downscale_images(poses_zarr(tmp_path, capture), {"downscale": 3}, tmp_path / "images.zarr", progress=False)
    group = open_artifact(out)
    assert group["images"].shape == (2, 16, 21, 3)  # round(64 / 3) = 21, 48 / 3 = 16
    np.testing.assert_allclose(group["intrinsics"][0], [60 * 21 / 64, 60 / 3, 32 * 21 / 64, 24 / 3])


def test_undistortion_moves_points_to_pinhole_projection(tmp_path):
    """Dots drawn where a distorting camera sees 3D points end up where the pinhole camera would."""
    width, height = 160, 120
    k = (100.0, 100.0, 80.5, 60.5)
    distortion = (-0.25, 0.08, 0.002, -0.003)
    capture = write_nerfstudio(tmp_path / "cap", ring(2), width=width, height=height, intrinsics=k,
                               distortion=distortion)
    pose = ring(2)[0]
    grid = np.stack(np.meshgrid(np.linspace(-0.55, 0.55, 5), np.linspace(-0.4, 0.4, 4)), -1).reshape(-1, 2)
    points_cam = np.concatenate([grid, np.ones((len(grid), 1))], 1) * 2.0
    points_world = cameras.transform_points(pose, points_cam)
    # OpenCV's pixel frame has integer pixel centres: its K is ours shifted by 0.5
    k_cv = cameras.intrinsic_matrix(k[0], k[1], k[2] - 0.5, k[3] - 0.5)
    distorted, _ = cv2.projectPoints(points_cam, np.zeros(3), np.zeros(3), k_cv, np.array(distortion))
    distorted = distorted.reshape(-1, 2)
    v, u = np.mgrid[0:height, 0:width]
    image = np.zeros((height, width), np.float64)
    for x, y in distorted:
        image += 255 * np.exp(-((u - x) ** 2 + (v - y) ** 2) / (2 * 1.2**2))
    cv2.imwrite(str(capture / "images" / "frame_00000.png"), np.clip(image, 0, 255).astype(np.uint8))

    out = downscale_images(poses_zarr(tmp_path, capture), {"downscale": 1}, tmp_path / "images.zarr", progress=False)
    undistorted = open_artifact(out)["images"][0, ..., 0].astype(np.float64)
    expected, _ = cameras.project_points(points_world, pose, np.array(k))  # pinhole, centres at +0.5
    shift = np.linalg.norm(distorted + 0.5 - expected, axis=1)
    assert shift.max() > 5.0  # the distortion is large enough to matter
    for x, y in expected:
        cx, cy = int(x), int(y)
        window = undistorted[cy - 4:cy + 5, cx - 4:cx + 5]
        wv, wu = np.mgrid[cy - 4:cy + 5, cx - 4:cx + 5]
        centroid = np.array([(window * wu).sum(), (window * wv).sum()]) / window.sum() + 0.5
        np.testing.assert_allclose(centroid, [x, y], atol=0.35)


def test_rgba_and_grayscale_images(tmp_path):
    rgba = np.zeros((4, 4, 4), np.uint8)
    rgba[..., 2] = 200  # red in BGR order
    rgba[:2, ..., 3] = 255  # top half opaque, bottom half transparent
    cv2.imwrite(str(tmp_path / "a.png"), rgba)
    rgb = read_rgb(tmp_path / "a.png")
    assert rgb[0, 0].tolist() == [200, 0, 0]  # RGB
    assert rgb[3, 0].tolist() == [255, 255, 255]  # composited over white
    cv2.imwrite(str(tmp_path / "g.png"), np.full((3, 5), 7, np.uint8))
    assert read_rgb(tmp_path / "g.png").shape == (3, 5, 3)


def test_failure_mid_way_leaves_no_artifact(tmp_path):
    capture = write_nerfstudio(tmp_path / "cap", ring(5), width=64, height=48)
    poses = poses_zarr(tmp_path, capture)
    bad = capture / "images" / "frame_00003.png"
    bad.write_bytes(bad.read_bytes()[:60])  # a truncated PNG: the header is still fine
    with pytest.raises(ValueError, match=rf"{bad}: corrupt"):
        downscale_images(poses, {"downscale": 2}, tmp_path / "images.zarr", progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "poses.zarr"]  # no images.zarr, no partial


def test_failure_keeps_previous_complete_artifact_untouched(tmp_path):
    capture = write_nerfstudio(tmp_path / "cap", ring(3), width=64, height=48)
    poses = poses_zarr(tmp_path, capture)
    out = downscale_images(poses, {"downscale": 2}, tmp_path / "images.zarr", progress=False)
    (capture / "images" / "frame_00001.png").unlink()
    with pytest.raises(FileNotFoundError, match="frame_00001.png"):
        downscale_images(poses, {"downscale": 4}, out, progress=False)
    assert meta(open_artifact(out))["downscale"] == 2.0


def test_mixed_image_sizes_name_the_file(tmp_path):
    capture = write_nerfstudio(tmp_path / "cap", ring(3), width=64, height=48)
    write_nerfstudio(tmp_path / "other", ring(1), width=80, height=48)
    (capture / "images" / "frame_00002.png").write_bytes((tmp_path / "other" / "images" / "frame_00000.png").read_bytes())
    edit_transforms(capture, lambda d: d["frames"][2].update(w=80, h=48))
    with pytest.raises(ValueError, match=r"frame_00002.png: downscaled size 20x12 differs"):
        downscale_images(poses_zarr(tmp_path, capture), {"downscale": 4}, tmp_path / "images.zarr", progress=False)


def test_image_not_matching_its_camera_names_file(tmp_path):
    capture = write_nerfstudio(tmp_path / "cap", ring(2), width=64, height=48)
    cv2.imwrite(str(capture / "images" / "frame_00001.png"), np.zeros((40, 64, 3), np.uint8))
    with pytest.raises(ValueError, match=r"frame_00001.png: image is 64x40 but its camera says 64x48"):
        downscale_images(poses_zarr(tmp_path, capture), {"downscale": 2}, tmp_path / "images.zarr", progress=False)


def test_orchard_ground_truth_is_downscaled(tmp_path):
    from srfpipe.cli import main
    from srfpipe.scenes.orchard import generate_orchard

    capture = generate_orchard(tmp_path / "capture", progress=False, views=12, width=64, height=48)
    poses = poses_zarr(tmp_path, capture, fmt="orchard")
    code = main(["downscale", "--poses", str(poses), "--options", json.dumps({"downscale": 4}),
                 "--out", str(tmp_path / "images.zarr"), "--no-progress"])
    assert code == 0
    group = open_artifact(tmp_path / "images.zarr", stage="downscale")
    labels = group["ground_truth/labels"][:]
    depth = group["ground_truth/depth"][:]
    assert labels.shape == depth.shape == (12, 12, 16)
    assert group["ground_truth/labels"].chunks == (1, 12, 16)
    assert set(np.unique(labels)) <= {0, 1, 2, 3} and (labels > 0).any()
    full = cv2.imread(str(capture / "ground_truth" / "labels" / "frame_00005.png"), cv2.IMREAD_UNCHANGED)
    # labels by area majority: the class covering most of each 4x4 block
    counts = np.stack([(full == c).reshape(12, 4, 16, 4).sum(axis=(1, 3)) for c in range(4)])
    majority = counts.max(axis=0)
    assert np.all(counts[labels[5], np.arange(12)[:, None], np.arange(16)] == majority)
    full_depth = np.load(capture / "ground_truth" / "depth" / "frame_00005.npy")
    np.testing.assert_array_equal(depth[5], full_depth[2::4, 2::4])
    assert meta(group)["ground_truth"] == str((capture / "ground_truth").resolve())


def test_ground_truth_labels_downscale_by_area_majority():
    from srfpipe.images import downscale_labels

    labels = np.zeros((4, 8), np.uint8)
    labels[:, :4] = 3          # left block: all leaf...
    labels[:2, :3] = 1         # ...but 6 of its 16 pixels are apple: leaf still covers most
    labels[:, 4:] = 2          # right block: 9 of 16 pixels branch, 7 background
    labels[:2, 4:] = 0
    labels[1, 7] = 2
    assert downscale_labels(labels, 2, 1).tolist() == [[3, 2]]
    labels[:3, :3] = 1         # 9 of 16 apple now
    assert downscale_labels(labels, 2, 1).tolist() == [[1, 2]]

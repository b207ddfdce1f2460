"""Downscaling to images.zarr: sizes, intrinsics, undistortion, ground truth, atomicity, bad images."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from srfpipe import cameras
from srfpipe.artifacts import meta, open_artifact
from srfpipe.config import validate_scene
from srfpipe.images import Undistorter, default_downscale, downscale_images, exif_orientation, read_rgb
from srfpipe.poses import import_poses, load_capture
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


@pytest.mark.parametrize("frames, expected", [(4, 1), (16, 2), (64, 4), (300, 4)])
def test_null_downscale_keeps_the_detail_of_a_few_views(tmp_path, frames, expected):
    """images.downscale null: the finest of 1, 2, 4 whose pixels, all frames together, stay within
    images.max_pixels; never coarser than 4. Few views keep their resolution, many are shrunk."""
    capture = write_nerfstudio(tmp_path / "cap", ring(frames), width=64, height=48,
                               intrinsics=(60.0, 60.0, 32.0, 24.0))
    budget = 16 * 64 * 48 // 4  # 16 frames at factor 2
    out = downscale_images(poses_zarr(tmp_path, capture), {"downscale": None, "max_pixels": budget},
                           tmp_path / "images.zarr", progress=False)
    info = meta(open_artifact(out, stage="downscale"))
    assert info["downscale"] == expected and (info["width"], info["height"]) == (64 // expected, 48 // expected)
    assert info["config"]["images"]["downscale"] == expected and info["config"]["downscale_from"] == "max_pixels"


def test_the_captures_this_project_measures_keep_their_factors():
    """The default budget, on the captures of benchmarks/captures.py: the orchard (80 frames of
    640 x 480) and the fox (50 of 1080 x 1920) stay at 4, the plant (18 of 512 x 512) keeps twice
    the resolution."""
    budget = validate_scene({})["images"]["max_pixels"]
    assert default_downscale([(640, 480)] * 80, budget) == 4
    assert default_downscale([(1080, 1920)] * 50, budget) == 4
    assert default_downscale([(512, 512)] * 18, budget) == 2


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
    # pinhole (centres at +0.5) with the intrinsics images.zarr records: the lens's K, scaled and
    # shifted so that every undistorted pixel has a source
    pinhole = open_artifact(out)["intrinsics"][0]
    assert np.abs(np.asarray(pinhole) - k).max() < 0.2 * k[0]  # k1 -0.25: the widest view with no pixel lost
    expected, _ = cameras.project_points(points_world, pose, pinhole)
    shift = np.linalg.norm(distorted + 0.5 - expected, axis=1)
    assert shift.max() > 5.0  # the distortion is large enough to matter
    for x, y in expected:
        cx, cy = int(x), int(y)
        window = undistorted[cy - 4:cy + 5, cx - 4:cx + 5]
        wv, wu = np.mgrid[cy - 4:cy + 5, cx - 4:cx + 5]
        centroid = np.array([(window * wu).sum(), (window * wv).sum()]) / window.sum() + 0.5
        np.testing.assert_allclose(centroid, [x, y], atol=0.35)


def test_undistortion_leaves_no_pixel_without_a_source(tmp_path):
    """A strong tangential lens (a phone's COLMAP calibration): the undistorted frame is all image,
    no black wedge along its edges that training would take for content."""
    width, height = 121, 161
    k = (105.0, 105.0, 60.5, 80.5)
    distortion = (-0.0024, -0.021, 0.011, 0.0096)
    capture = write_nerfstudio(tmp_path / "cap", ring(2), width=width, height=height, intrinsics=k,
                               distortion=distortion)
    for name in ("frame_00000", "frame_00001"):
        cv2.imwrite(str(capture / "images" / f"{name}.png"), np.full((height, width, 3), 200, np.uint8))
    out = downscale_images(poses_zarr(tmp_path, capture), {"downscale": 1}, tmp_path / "images.zarr", progress=False)
    images = np.asarray(open_artifact(out)["images"][:])
    assert images.min() == 200, np.argwhere(images < 200)[:5]
    # every undistorted pixel samples the frame itself (within half a pixel of its edge), not a border
    map_x, map_y = Undistorter().maps(k, distortion, (width, height))
    assert map_x.min() >= -0.5 and map_x.max() <= width - 0.5 and map_y.min() >= -0.5 and map_y.max() <= height - 0.5
    # and nothing is thrown away needlessly: the frame's edge is reached on some side
    assert min(map_x.min() + 0.5, width - 0.5 - map_x.max(), map_y.min() + 0.5, height - 0.5 - map_y.max()) < 1.0


@pytest.mark.bad_input
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


@pytest.mark.bad_input
def test_sixteen_bit_images_scale_to_eight_bit(tmp_path):
    grey = np.array([[0, 257 * 100, 65535]], np.uint16)
    cv2.imwrite(str(tmp_path / "g16.png"), grey)
    assert read_rgb(tmp_path / "g16.png")[0, :, 0].tolist() == [0, 100, 255]
    rgba = np.zeros((1, 2, 4), np.uint16)
    rgba[..., 0] = 257 * 50  # blue in BGRA order
    rgba[0, 0, 3] = 65535  # left opaque, right transparent
    cv2.imwrite(str(tmp_path / "c16.png"), rgba)
    assert read_rgb(tmp_path / "c16.png").tolist() == [[[0, 0, 50], [255, 255, 255]]]


# ----------------------------------------------------------------------------- EXIF orientation


def exif_segment(orientation: int, byte_order: str = "<") -> bytes:
    """A JPEG APP1 segment holding EXIF with one tag, Orientation (a SHORT), in either byte order."""
    header = (b"II*\x00" if byte_order == "<" else b"MM\x00*") + struct.pack(byte_order + "I", 8)
    ifd = struct.pack(byte_order + "H", 1) + struct.pack(byte_order + "HHIHH", 0x0112, 3, 1, orientation, 0)
    payload = b"Exif\x00\x00" + header + ifd + struct.pack(byte_order + "I", 0)
    return b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload


def write_oriented_jpeg(path: Path, bgr: np.ndarray, orientation: int, byte_order: str = "<") -> None:
    """`bgr` stored as a JPEG whose EXIF says how to turn it upright (the segment right after SOI)."""
    ok, encoded = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert ok
    data = encoded.tobytes()
    path.write_bytes(data[:2] + exif_segment(orientation, byte_order) + data[2:])


@pytest.mark.bad_input
@pytest.mark.parametrize("orientation", range(1, 9))
def test_exif_orientation_is_applied_as_opencv_does(tmp_path, orientation):
    stored = np.random.default_rng(orientation).integers(0, 256, (20, 40, 3), dtype=np.uint8)
    path = tmp_path / "o.jpg"
    write_oriented_jpeg(path, stored, orientation)
    upright = cv2.imread(str(path), cv2.IMREAD_COLOR)  # OpenCV applies the orientation for this flag
    np.testing.assert_array_equal(read_rgb(path), upright[..., ::-1])
    assert upright.shape[:2] == ((40, 20) if orientation >= 5 else (20, 40))


@pytest.mark.bad_input
@pytest.mark.parametrize("byte_order", ["<", ">"], ids=["intel", "motorola"])
def test_exif_orientation_6_turns_the_image_90_degrees_clockwise(tmp_path, byte_order):
    stored = np.zeros((24, 40, 3), np.uint8)
    stored[:8, :8] = (0, 0, 255)  # a red block in the stored top-left corner (BGR)
    write_oriented_jpeg(tmp_path / "o.jpg", stored, 6, byte_order)
    rgb = read_rgb(tmp_path / "o.jpg")
    assert rgb.shape == (40, 24, 3)  # portrait now
    assert rgb[:8, -8:, 0].mean() > 200 and rgb[:8, :8, 0].mean() < 50  # top-left went to top-right
    assert exif_orientation(exif_segment(6, byte_order)[4:]) == 6


@pytest.mark.bad_input
def test_exif_orientation_without_a_readable_tag_is_upright():
    assert exif_orientation(b"") == 1
    assert exif_orientation(b"II*\x00" + struct.pack("<I", 500)) == 1  # IFD offset past the end
    assert exif_orientation(exif_segment(9)[4:]) == 1  # not an orientation


def test_rotated_phone_capture_imports_and_downscales_upright(tmp_path):
    """Camera sizes read at import and the pixels downscale decodes agree for EXIF-rotated JPEGs."""
    capture = write_nerfstudio(tmp_path / "cap", ring(2), width=32, height=24)
    stored = np.random.default_rng(0).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    for i in range(2):
        write_oriented_jpeg(capture / "images" / f"frame_{i:05d}.jpg", stored, 6)

    def portrait_frames(data):
        for key in ("w", "h", "cx", "cy"):  # size from the files, principal point at their centre
            del data[key]
        for frame in data["frames"]:
            frame["file_path"] = frame["file_path"].replace(".png", ".jpg")

    edit_transforms(capture, portrait_frames)
    assert load_capture({"format": "nerfstudio", "path": str(capture)}).image_size.tolist() == [[24, 32]] * 2
    out = downscale_images(poses_zarr(tmp_path, capture), {"downscale": 2}, tmp_path / "images.zarr", progress=False)
    images = open_artifact(out)["images"]
    assert images.shape == (2, 16, 12, 3)
    upright = cv2.imread(str(capture / "images" / "frame_00001.jpg"), cv2.IMREAD_COLOR)[..., ::-1]
    np.testing.assert_array_equal(images[1], cv2.resize(upright, (12, 16), interpolation=cv2.INTER_AREA))


def downscale_peak_bytes(tmp_path, n_frames: int) -> int:
    """Peak numpy memory (tracemalloc sees every numpy and OpenCV-returned array) while 1920 x 1080
    phone-sized JPEGs downscale 4x."""
    import tracemalloc

    capture = write_nerfstudio(tmp_path / f"cap{n_frames}", ring(n_frames), width=1920, height=1080,
                               intrinsics=(1500.0, 1500.0, 960.0, 540.0), distortion=(0.01, 0.0, 0.0, 0.0))
    frame = np.random.default_rng(0).integers(0, 256, (1080, 1920, 3), dtype=np.uint8)
    for i in range(n_frames):
        cv2.imwrite(str(capture / "images" / f"frame_{i:05d}.jpg"), frame)
    edit_transforms(capture, lambda d: [f.update(file_path=f["file_path"].replace(".png", ".jpg")) for f in d["frames"]])
    poses = poses_zarr(tmp_path / f"p{n_frames}", capture)
    tracemalloc.start()
    try:
        downscale_images(poses, {"downscale": 4}, tmp_path / f"images{n_frames}.zarr", progress=False)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_full_size_phone_images_downscale_in_bounded_memory(tmp_path):
    """Twelve 1920 x 1080 frames need no more memory than two: one full frame at a time (6 MB each;
    holding them all would add 60 MB)."""
    (tmp_path / "p2").mkdir(), (tmp_path / "p12").mkdir()
    few, many = downscale_peak_bytes(tmp_path, 2), downscale_peak_bytes(tmp_path, 12)
    frame_bytes = 1920 * 1080 * 3
    assert many < few + frame_bytes, (few / 1e6, many / 1e6)
    assert many < 8 * frame_bytes  # a handful of full-size buffers (decode, undistort maps, remap)


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


@pytest.mark.bad_input
def test_mixed_image_sizes_name_the_file(tmp_path):
    capture = write_nerfstudio(tmp_path / "cap", ring(3), width=64, height=48)
    write_nerfstudio(tmp_path / "other", ring(1), width=80, height=48)
    (capture / "images" / "frame_00002.png").write_bytes((tmp_path / "other" / "images" / "frame_00000.png").read_bytes())
    edit_transforms(capture, lambda d: d["frames"][2].update(w=80, h=48))
    with pytest.raises(ValueError, match=r"frame_00002.png: downscaled size 20x12 differs"):
        downscale_images(poses_zarr(tmp_path, capture), {"downscale": 4}, tmp_path / "images.zarr", progress=False)


@pytest.mark.bad_input
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

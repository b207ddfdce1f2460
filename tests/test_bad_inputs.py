"""The bad-input corpus: every case is refused with an error naming the file and the problem, and
nothing is written (or, for inputs that are merely unusual, handled correctly).

Cases that other test files already hold (NaN/scaled/reflected poses, `../` and absolute paths,
16-bit, grey, RGBA and EXIF-rotated images, mixed sizes, wrong ONNX inputs, unknown prompts,
wrongly sized masks, ...) carry the `bad_input` marker there; `benchmarks/reliability.py` counts
the whole corpus with `pytest -m bad_input`.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from srfpipe.artifacts import ArtifactError, create_artifact, open_artifact
from srfpipe.config import ConfigError, validate_scene
from srfpipe.images import downscale_images
from srfpipe.poses import import_poses, read_blender, read_colmap, read_nerfstudio
from tests.test_poses import edit_transforms, ring, write_blender, write_colmap_model, write_nerfstudio

pytestmark = pytest.mark.bad_input

NERFSTUDIO = {"format": "nerfstudio"}


def assert_refused(call, out: Path | None, names, problem: str, exc=(ValueError, OSError, RuntimeError)):
    """`call()` raises `exc` whose message names `names` (a path or its file name) and matches
    `problem`; `out` and any hidden partial sibling of it do not exist afterwards."""
    with pytest.raises(exc) as err:
        call()
    message = str(err.value)
    assert str(names) in message, f"the error does not name {names}: {message}"
    assert re.search(problem, message), f"the error does not say {problem!r}: {message}"
    if out is not None:
        assert not out.exists(), f"{out} was written"
        assert not list(out.parent.glob(f".{out.name}.*")), f"a partial {out.name} was left"
    return message


def capture(root: Path, n: int = 3, ext: str = "png") -> Path:
    """A nerfstudio capture of n noise images (PNG, or JPEG)."""
    write_nerfstudio(root, ring(n))
    if ext != "png":
        for i in range(n):
            png = root / "images" / f"frame_{i:05d}.png"
            cv2.imwrite(str(png.with_suffix(f".{ext}")), cv2.imread(str(png)))
            png.unlink()
        edit_transforms(root, lambda d: [f.update(file_path=f["file_path"].replace(".png", f".{ext}"))
                                         for f in d["frames"]])
    return root


# --------------------------------------------------------------------------------------- images


@pytest.mark.parametrize("damage, problem", [
    ("truncate_png", "corrupt or unreadable image"),
    ("truncate_jpg", "truncated JPEG"),
    ("zero_bytes", "corrupt or unreadable image"),
    ("garbage", "corrupt or unreadable image"),
])
def test_image_damaged_after_import_fails_downscale_naming_it(tmp_path, damage, problem):
    ext = "jpg" if damage == "truncate_jpg" else "png"
    root = capture(tmp_path / "cap", ext=ext)
    poses = import_poses(NERFSTUDIO, root, {}, tmp_path / "poses.zarr", progress=False)
    bad = root / "images" / f"frame_00001.{ext}"
    data = bad.read_bytes()
    bad.write_bytes({"zero_bytes": b"", "garbage": os.urandom(len(data))}.get(damage, data[: len(data) // 2]))
    out = tmp_path / "images.zarr"
    assert_refused(lambda: downscale_images(poses, {"downscale": 1}, out, progress=False), out, bad, problem)


def test_zero_byte_image_is_refused_at_import(tmp_path):
    root = capture(tmp_path / "cap")
    bad = root / "images" / "frame_00002.png"
    bad.write_bytes(b"")
    out = tmp_path / "poses.zarr"
    assert_refused(lambda: import_poses(NERFSTUDIO, root, {}, out, progress=False), out, bad, "corrupt")


def test_complete_jpeg_with_trailing_bytes_is_accepted(tmp_path):
    """The truncation check must not refuse a whole JPEG that carries a trailer after its end."""
    root = capture(tmp_path / "cap", ext="jpg")
    image = root / "images" / "frame_00000.jpg"
    image.write_bytes(image.read_bytes() + b"vendor trailer")
    poses = import_poses(NERFSTUDIO, root, {}, tmp_path / "poses.zarr", progress=False)
    images = open_artifact(downscale_images(poses, {"downscale": 1}, tmp_path / "images.zarr", progress=False))
    assert images["images"].shape == (3, 24, 32, 3)


# ---------------------------------------------------------------------------- poses (nerfstudio)


@pytest.mark.parametrize("matrix, problem", [
    ([[1, 0, 0, np.inf], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "NaN or infinite"),
    ([[1, 0.3, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "not orthonormal"),
    ([[1, 0, 0, 1e200], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "values above"),
    ("identity", "not a numeric matrix"),
    ([[1, 0, 0], [0, 1, 0], [0, 0, 1]], "must be 4x4"),
], ids=["inf", "sheared", "huge_translation", "string", "3x3"])
def test_bad_transform_matrix(tmp_path, matrix, problem):
    path = edit_transforms(capture(tmp_path), lambda d: d["frames"][1].update(transform_matrix=matrix))
    assert_refused(lambda: read_nerfstudio(tmp_path), None, f"{path}: frames[1]", problem)


@pytest.mark.parametrize("edit, where, problem", [
    (lambda d: d["frames"][0].pop("file_path"), "frames[0]", "needs 'file_path'"),
    (lambda d: d["frames"][2].pop("transform_matrix"), "frames[2]", "needs 'file_path' and 'transform_matrix'"),
    (lambda d: d["frames"][2].update(file_path=d["frames"][0]["file_path"]), "frames[2]", "listed twice"),
    (lambda d: d["frames"][1].update(file_path=17), "frames[1]", "must be a non-empty string"),
    (lambda d: d["frames"][1].update(file_path=""), "frames[1]", "must be a non-empty string"),
    (lambda d: d.update(fl_x="thirty"), "frames[0]", "fl_x must be a number, got str"),
    (lambda d: d.update(fl_x=1e300), "frames[0]", r"fl_x=1e\+300 is out of range"),
    (lambda d: d.update(w=10**9), "frames[0]", "w=1000000000 is out of range"),
    (lambda d: d.update(cx=True), "frames[0]", "cx must be a number, got bool"),
    (lambda d: d.update(frames=[]), "transforms.json", "'frames' must be a non-empty list"),
    (lambda d: d.update(frames={"0": {}}), "transforms.json", "'frames' must be a non-empty list"),
    (lambda d: d["frames"].__setitem__(1, "images/frame_00001.png"), "frames[1]", "needs 'file_path'"),
    (lambda d: d["frames"][1].update(file_path="images/a\x00b.png"), "frames[1]", "holds a NUL character"),
    (lambda d: d.update(applied_transform=[["a"] * 4] * 3), "applied_transform", "must be a finite 3x4 or 4x4"),
    (lambda d: d.update(applied_transform=[[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0]]), "applied_transform",
     "must be a finite 3x4 or 4x4"),
], ids=["no_file_path", "no_transform", "duplicate_file_path", "file_path_int", "file_path_empty",
        "focal_string", "focal_huge", "width_huge", "cx_bool", "empty_frames", "frames_dict", "frame_string",
        "file_path_nul", "applied_transform_strings", "applied_transform_ragged"])
def test_bad_transforms_json(tmp_path, edit, where, problem):
    path = edit_transforms(capture(tmp_path), edit)
    out = tmp_path / "poses.zarr"
    message = assert_refused(lambda: import_poses(NERFSTUDIO, tmp_path, {}, out, progress=False), out, path, problem)
    assert where in message


@pytest.mark.parametrize("text, problem", [
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ('{"frames": [' + "{" * 50_000, "not valid JSON"),
    ("\x89PNG not json", "not valid JSON"),
    ("[1, 2, 3]", "expected a JSON object"),
], ids=["json_bomb_lists", "json_bomb_truncated", "binary", "top_level_list"])
def test_transforms_json_that_is_not_a_capture(tmp_path, text, problem):
    capture(tmp_path)
    (tmp_path / "transforms.json").write_text(text)
    out = tmp_path / "poses.zarr"
    assert_refused(lambda: import_poses(NERFSTUDIO, tmp_path, {}, out, progress=False), out,
                   tmp_path / "transforms.json", problem)


@pytest.fixture
def outside_image(tmp_path) -> Path:
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    image = outside / "secret.png"
    cv2.imwrite(str(image), np.zeros((24, 32, 3), np.uint8))
    return image


def test_symlink_pointing_outside_is_refused(tmp_path, outside_image):
    root = capture(tmp_path / "cap")
    link = root / "images" / "frame_00001.png"
    link.unlink()
    link.symlink_to(outside_image)
    out = tmp_path / "poses.zarr"
    assert_refused(lambda: import_poses(NERFSTUDIO, root, {}, out, progress=False), out,
                   "frames[1]", f"is a symlink to {outside_image}, outside the dataset folder")


def test_symlinked_folder_inside_an_allowed_root_is_accepted(tmp_path, outside_image):
    root = capture(tmp_path / "cap")
    (root / "shared").symlink_to(outside_image.parent)
    edit_transforms(root, lambda d: d["frames"][1].update(file_path="shared/secret.png"))
    with pytest.raises(ValueError, match="source.allowed_roots"):
        read_nerfstudio(root)
    source = {**NERFSTUDIO, "allowed_roots": [str(outside_image.parent)]}
    out = import_poses(source, root, {}, tmp_path / "poses.zarr", progress=False)
    assert open_artifact(out).attrs["srfpipe"]["image_paths"][1] == "shared/secret.png"


def test_blender_camera_angle_of_the_wrong_type(tmp_path):
    write_blender(tmp_path, ring(3), 0.69, n_train=2)
    path = tmp_path / "transforms_train.json"
    data = json.loads(path.read_text())
    path.write_text(json.dumps({**data, "camera_angle_x": "wide"}))
    assert_refused(lambda: read_blender(tmp_path), None, path, "camera_angle_x must be a number, got str")


def test_blender_duplicate_frame(tmp_path):
    write_blender(tmp_path, ring(3), 0.69, n_train=2)
    path = tmp_path / "transforms_train.json"
    data = json.loads(path.read_text())
    data["frames"].append(data["frames"][0])
    path.write_text(json.dumps(data))
    assert_refused(lambda: read_blender(tmp_path), None, path, "listed twice")


@pytest.mark.parametrize("damage, problem", [
    ("truncate_ascii", r"truncated PLY \(60 data lines, its header declares 100 records\)"),
    ("truncate_binary", r"truncated PLY|empty or unreadable"),
    ("nan", r"point 7 \(of 100\) is NaN"),
])
def test_damaged_ply_file_path_is_refused_naming_it(tmp_path, damage, problem):
    """nerfstudio's `ply_file_path` (the sparse points the bounds come from): Open3D reads a truncated
    PLY with a printed warning only, the missing points garbage, and keeps NaN points."""
    import open3d as o3d

    capture(tmp_path)
    points = np.random.default_rng(0).uniform(-0.5, 0.5, size=(100, 3))
    if damage == "nan":
        points[7, 1] = np.nan
    ply = tmp_path / "sparse_pc.ply"
    o3d.io.write_point_cloud(str(ply), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)),
                             write_ascii=damage == "truncate_ascii")
    if damage == "truncate_ascii":  # Open3D reads it as 100 points, the last 40 garbage
        header, _, body = ply.read_text().partition("end_header\n")
        ply.write_text(header + "end_header\n" + "".join(body.splitlines(keepends=True)[:60]))
    elif damage == "truncate_binary":
        ply.write_bytes(ply.read_bytes()[:-1000])
    edit_transforms(tmp_path, lambda d: d.update(ply_file_path="sparse_pc.ply"))
    out = tmp_path / "poses.zarr"
    assert_refused(lambda: import_poses(NERFSTUDIO, tmp_path, {}, out, progress=False), out, ply, problem)


# ------------------------------------------------------------------------------------------ COLMAP


@pytest.mark.parametrize("name, keep", [("cameras.bin", 0.9), ("images.bin", 0.5), ("points3D.bin", 0.9),
                                         ("images.bin", 0.0)])
def test_truncated_colmap_binary_names_file_and_record(tmp_path, name, keep):
    write_colmap_model(tmp_path, text=False)
    path = tmp_path / "sparse" / "0" / name
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    out = tmp_path / "poses.zarr"
    source = {"format": "colmap", "path": str(tmp_path)}
    assert_refused(lambda: import_poses(source, None, {}, out, progress=False), out, path, r"truncated \(\d+ bytes\) in")


def test_colmap_binary_with_trailing_bytes(tmp_path):
    write_colmap_model(tmp_path, text=False)
    path = tmp_path / "sparse" / "0" / "cameras.bin"
    path.write_bytes(path.read_bytes() + b"\0" * 7)
    assert_refused(lambda: read_colmap(tmp_path), None, path, "7 bytes after its 2 cameras")


def _deregister(model: Path, keep: int) -> None:
    import pycolmap

    reconstruction = pycolmap.Reconstruction(str(model))
    for frame_id in sorted(reconstruction.reg_frame_ids())[keep:]:
        reconstruction.deregister_frame(frame_id)
    reconstruction.write_binary(str(model))


def test_colmap_images_it_did_not_register_are_left_out(tmp_path):
    """COLMAP writes only the images it registered: image files beside them are not imported."""
    write_colmap_model(tmp_path, text=False)
    _deregister(tmp_path / "sparse" / "0", keep=3)
    capture_ = read_colmap(tmp_path)
    assert capture_.image_paths == ["images/im_0.jpg", "images/im_1.jpg", "images/im_2.jpg"]
    assert (tmp_path / "images" / "im_3.jpg").exists()


def test_colmap_model_without_registered_images(tmp_path):
    write_colmap_model(tmp_path, text=False)
    model = tmp_path / "sparse" / "0"
    _deregister(model, keep=0)
    out = tmp_path / "poses.zarr"
    source = {"format": "colmap", "path": str(tmp_path)}
    assert_refused(lambda: import_poses(source, None, {}, out, progress=False), out, model, "no posed images")


def test_colmap_image_listed_twice_is_refused(tmp_path):
    """Two registered images of one name would give one image file two poses (nerfstudio and
    Blender refuse the same), and two frames of one name downstream."""
    write_colmap_model(tmp_path, text=True)
    images_txt = tmp_path / "sparse" / "0" / "images.txt"
    images_txt.write_text(images_txt.read_text().replace(" im_1.jpg", " im_0.jpg"))
    out = tmp_path / "poses.zarr"
    source = {"format": "colmap", "path": str(tmp_path)}
    assert_refused(lambda: import_poses(source, None, {}, out, progress=False), out, "im_0.jpg", "listed twice")


def test_colmap_zero_quaternion_is_refused(tmp_path):
    """A rotation quaternion (0, 0, 0, 0) reads as the identity rotation through Eigen: refused, not
    imported as a camera facing along +z."""
    write_colmap_model(tmp_path, text=True)
    frames_txt = tmp_path / "sparse" / "0" / "frames.txt"
    lines = frames_txt.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    fields = lines[first].split()
    fields[2:6] = ["0", "0", "0", "0"]
    lines[first] = " ".join(fields)
    frames_txt.write_text("\n".join(lines) + "\n")
    out = tmp_path / "poses.zarr"
    source = {"format": "colmap", "path": str(tmp_path)}
    assert_refused(lambda: import_poses(source, None, {}, out, progress=False), out, "im_0.jpg",
                   "quaternion")


# ------------------------------------------------------------------------------------------ masks


def test_import_mask_of_the_wrong_dtype_or_channels(tmp_path):
    from tests.test_segment import options, red_blue_images, write_images

    from srfpipe.segment.run import prompt_options, segment_images

    images = write_images(tmp_path / "images.zarr", red_blue_images(n=1, width=40, height=30))
    folder = tmp_path / "masks"
    folder.mkdir()
    opts = prompt_options(options(backend="import", **{"import": {"path": str(folder)}}), "apple")
    out = tmp_path / "apple.zarr"
    mask = folder / "frame_00000_apple.tiff"
    opts["import"]["pattern"] = "{name}_{prompt}.tiff"
    cv2.imwrite(str(mask), np.full((30, 40), 0.5, np.float32))
    assert_refused(lambda: segment_images(images, "apple", opts, out, progress=False), out, mask,
                   "expected an 8- or 16-bit mask, got float32")
    colour = np.zeros((30, 40, 3), np.uint8)
    colour[..., 2] = 255  # a red overlay, not a grey mask saved as RGB
    cv2.imwrite(str(mask), colour)
    assert_refused(lambda: segment_images(images, "apple", opts, out, progress=False), out, mask,
                   "expected a single-channel")


@pytest.mark.parametrize("escape", ["symlink", "pattern_dotdot", "pattern_absolute"])
def test_import_mask_outside_the_mask_folder_is_refused(tmp_path, escape):
    """Mask files stay inside segmentation.import.path, as image paths stay inside the capture:
    a symlinked mask, or a pattern with `..` or an absolute path, reads nothing outside it."""
    from tests.test_segment import options, red_blue_images, write_images

    from srfpipe.segment.run import prompt_options, segment_images

    images = write_images(tmp_path / "images.zarr", red_blue_images(n=1, width=40, height=30))
    folder, outside = tmp_path / "masks", tmp_path / "outside"
    folder.mkdir()
    outside.mkdir()
    cv2.imwrite(str(outside / "frame_00000_apple.png"), np.full((30, 40), 255, np.uint8))  # a valid mask
    opts = prompt_options(options(backend="import", **{"import": {"path": str(folder)}}), "apple")
    if escape == "symlink":
        (folder / "frame_00000_apple.png").symlink_to(outside / "frame_00000_apple.png")
    else:
        prefix = "../outside/" if escape == "pattern_dotdot" else f"{outside}/"
        opts["import"]["pattern"] = prefix + "{name}_{prompt}.png"
    out = tmp_path / "apple.zarr"
    assert_refused(lambda: segment_images(images, "apple", opts, out, progress=False), out, "frame_00000_apple.png",
                   "outside the mask folder")


def test_an_imported_mask_path_that_is_a_folder_is_refused(tmp_path):
    """A folder where a frame's mask belongs was read as a missing mask: the frame trained unlabelled
    with only a warning."""
    from tests.test_segment import options, red_blue_images, write_images

    from srfpipe.segment.run import prompt_options, segment_images

    images = write_images(tmp_path / "images.zarr", red_blue_images(n=2, width=40, height=30))
    folder = tmp_path / "masks"
    folder.mkdir()
    cv2.imwrite(str(folder / "frame_00000_apple.png"), np.full((30, 40), 255, np.uint8))
    (folder / "frame_00001_apple.png").mkdir()
    out = tmp_path / "apple.zarr"
    opts = prompt_options(options(backend="import", **{"import": {"path": str(folder)}}), "apple")
    assert_refused(lambda: segment_images(images, "apple", opts, out, progress=False), out, "frame_00001_apple.png",
                   "mask path is not a file")


def test_import_masks_of_frames_whose_names_hold_a_dot(tmp_path):
    """Frames named like `shot.0001` (image `shot.0001.jpg`): {stem} is the whole name, not `shot`
    (which gave every frame the one mask `shot_apple.png`, or none)."""
    from tests.test_segment import options

    from srfpipe.segment.import_backend import import_masks

    names = ["shot.0001", "shot.0002"]  # images.zarr's names: the image files' stems
    folder = tmp_path / "masks"
    folder.mkdir()
    left, right = np.zeros((30, 40), np.uint8), np.zeros((30, 40), np.uint8)
    left[:, :20], right[:, 20:] = 255, 255
    cv2.imwrite(str(folder / "shot.0001_apple.png"), left)
    cv2.imwrite(str(folder / "shot.0002_apple.png"), right)
    cv2.imwrite(str(folder / "shot_apple.png"), np.zeros((30, 40), np.uint8))  # not any frame's mask
    opts = options(backend="import", **{"import": {"path": str(folder)}})
    maps = list(import_masks(names, (40, 30), "apple", opts))
    np.testing.assert_array_equal(maps[0], left / 255.0)
    np.testing.assert_array_equal(maps[1], right / 255.0)


def test_composite_refuses_masks_of_the_wrong_dtype(tmp_path):
    from tests.test_segment import blank_images

    from srfpipe.segment.composite import composite_masks

    images = blank_images(tmp_path / "images.zarr")
    masks = tmp_path / "apple.zarr"
    with create_artifact(masks, stage="segment") as group:
        group.create_array("probability", data=np.full((2, 4, 5), 0.7, np.float32))
        group.attrs["srfpipe"] = {**group.attrs["srfpipe"], "prompt": "apple", "threshold": 0.5,
                                  "names": ["frame_00000", "frame_00001"]}
    out = tmp_path / "labels.zarr"
    assert_refused(lambda: composite_masks(images, [masks], {}, out, progress=False), out, masks,
                   "must be uint8.*found float32")


# ------------------------------------------------------------------------------------------- ONNX


def test_file_that_is_not_onnx(tmp_path):
    from tests.test_segment import options, red_blue_images, write_images

    from srfpipe.segment.run import prompt_options, segment_images

    images = write_images(tmp_path / "images.zarr", red_blue_images(n=1))
    model = tmp_path / "model.onnx"
    model.write_bytes(b"PK\x03\x04 this is a zip, not a protobuf" * 20)
    out = tmp_path / "apple.zarr"
    opts = prompt_options(options(model=str(model)), "apple")
    assert_refused(lambda: segment_images(images, "apple", opts, out, progress=False), out, model,
                   "onnxruntime cannot load the model")


def test_onnx_model_with_the_wrong_output(tmp_path):
    import torch

    from tests.test_segment import export, options, red_blue_images, write_images

    from srfpipe.segment.run import prompt_options, segment_images

    class Pooled(torch.nn.Module):
        def forward(self, image):
            return image.mean(dim=(2, 3))  # (batch, 3): no spatial axes

    model = export(Pooled(), (torch.zeros(1, 3, 8, 8),), tmp_path / "pooled.onnx", ["image"], ["scores"],
                   metadata={"classes": ["apple", "branch", "leaf"]})
    images = write_images(tmp_path / "images.zarr", red_blue_images(n=1))
    out = tmp_path / "apple.zarr"
    opts = prompt_options(options(model=str(model)), "apple")
    assert_refused(lambda: segment_images(images, "apple", opts, out, progress=False), out, model,
                   r"must output \(batch, classes, h, w\)")


# ------------------------------------------------------------------------------------------ config


@pytest.mark.parametrize("scene, key, hint", [
    ({"imagez": {"downscale": 2}}, "(top level)", "'imagez' -> 'images'"),
    ({"train": {"iteration": 5}}, "train", "'iteration' -> 'iterations'"),
    ({"occupancy": {"voxel_sise": 0.1}}, "occupancy", "'voxel_sise' -> 'voxel_size'"),
])
def test_unknown_key_gets_a_suggestion(scene, key, hint):
    assert_refused(lambda: validate_scene(scene, "s.yaml"), None, f"s.yaml: {key}", f"did you mean {re.escape(hint)}",
                   ConfigError)


@pytest.mark.parametrize("scene, key", [
    ({"images": {"downscale": 0}}, "images.downscale"),
    ({"segmentation": {"threshold": 1.5}}, "segmentation.threshold"),
    ({"evaluate": {"holdout_every": 1}}, "evaluate.holdout_every"),
    ({"train": {"iterations": -3}}, "train.iterations"),
    ({"occupancy": {"alpha_threshold": 1.0}}, "occupancy.alpha_threshold"),
])
def test_out_of_range_value_names_the_key(scene, key):
    assert_refused(lambda: validate_scene(scene, "s.yaml"), None, f"s.yaml: {key}", "minimum|maximum", ConfigError)


@pytest.mark.parametrize("scene, problem", [
    ({"poses": {"bounds": [[0, 0, 0], [1, -1, 1]]}}, r"poses.bounds: the minimum \[0, 0, 0\] must be below"),
    ({"segmentation": {"prompts": ["apple"], "thresholds": {"pear": 0.3}}},
     r"segmentation.thresholds: \['pear'\] are not among segmentation.prompts"),
    ({"segmentation": {"backend": "import"}}, "segmentation.import.path is not set"),
    ({"occupancy": {"avoid": ["branch", "apple"], "reach": ["apple"]}}, r"\['apple'\] are both to avoid and to reach"),
    ({"train": {"near": 5.0, "far": 2.0}}, "train.near 5.0 must be below train.far 2.0"),
    ({"poses": {"refine_distortion": True}}, r"poses.refine_distortion is true but poses.refine is 'none'"),
], ids=["bounds", "thresholds", "import_path", "avoid_reach", "near_far", "refine_distortion"])
def test_contradictory_settings(scene, problem):
    assert_refused(lambda: validate_scene(scene, "s.yaml"), None, "s.yaml", problem, ConfigError)


# ---------------------------------------------------------------------------------- Zarr artifacts


@pytest.mark.parametrize("version", [2, 0, None, "1"])
def test_artifact_of_an_incompatible_schema_version(tmp_path, version):
    path = tmp_path / "images.zarr"
    with create_artifact(path, "downscale") as group:
        pass
    import zarr

    group = zarr.open_group(str(path), mode="r+")
    attrs = dict(group.attrs["srfpipe"])
    attrs["schema_version"] = version
    group.attrs["srfpipe"] = attrs
    assert_refused(lambda: open_artifact(path, stage="downscale"), None, path,
                   rf"found {re.escape(repr(version))} .*expected 1", ArtifactError)


def test_stage_refuses_an_input_of_another_schema_version(tmp_path):
    import zarr

    root = capture(tmp_path / "cap")
    poses = import_poses(NERFSTUDIO, root, {}, tmp_path / "poses.zarr", progress=False)
    group = zarr.open_group(str(poses), mode="r+")
    group.attrs["srfpipe"] = {**dict(group.attrs["srfpipe"]), "schema_version": 7}
    out = tmp_path / "images.zarr"
    assert_refused(lambda: downscale_images(poses, {"downscale": 1}, out, progress=False), out, poses,
                   "found 7 .*expected 1")


# ----------------------------------------------------------------------------- hypothesis: capture

_json_scalar = st.one_of(st.none(), st.booleans(), st.integers(-(10**20), 10**20),
                         st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12))
_json_value = st.recursive(_json_scalar, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                                 st.dictionaries(st.text(max_size=8), inner, max_size=4)),
                           max_leaves=12)
_matrix = st.one_of(
    st.lists(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=4, max_size=4),
             min_size=3, max_size=4),
    _json_value,
)
_frame = st.fixed_dictionaries(
    {},
    optional={
        "file_path": st.one_of(st.sampled_from(["images/frame_00000.png", "images/frame_00001.png", "../x.png",
                                                "/etc/passwd", "images/none.png", "", "images/"]), _json_scalar),
        "transform_matrix": _matrix,
        "fl_x": _json_scalar, "w": _json_scalar, "camera_model": _json_scalar,
    },
)
_document = st.one_of(
    _json_value,
    st.fixed_dictionaries({"frames": st.lists(_frame, max_size=4)},
                          optional={"fl_x": st.one_of(st.floats(0.1, 1e4), _json_scalar),
                                    "fl_y": _json_scalar, "w": _json_scalar, "h": _json_scalar,
                                    "cx": _json_scalar, "k1": _json_scalar, "camera_model": _json_scalar,
                                    "applied_transform": _matrix, "ply_file_path": _json_scalar}),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(document=_document)
def test_random_transforms_json_is_read_or_refused_naming_the_file(tmp_path, document):
    """Any JSON document: a valid capture, or ValueError/FileNotFoundError naming transforms.json."""
    root = tmp_path / "cap"
    if not (root / "images").exists():
        write_nerfstudio(root, ring(2))
    path = root / "transforms.json"
    path.write_text(json.dumps(document))  # NaN and inf as the bare literals capture tools write
    try:
        result = read_nerfstudio(root)
    except (ValueError, FileNotFoundError) as exc:
        assert str(path) in str(exc), str(exc)
        return
    assert np.all(np.isfinite(result.camera_to_world)) and np.all(np.isfinite(result.intrinsics))
    assert all(not p.startswith("..") and not p.startswith("/") for p in result.image_paths)


# ------------------------------------------------------------------------------ queries


_coordinate = st.one_of(st.floats(-1.0, 1.0), st.floats(allow_nan=False, allow_infinity=True),
                        st.sampled_from([1e308, -1e308, 3.4e38, 1e20, -1e-300]))
_points = st.lists(st.tuples(_coordinate, _coordinate, _coordinate), min_size=1, max_size=20)


@pytest.fixture(scope="module")
def small_cache(tmp_path_factory):
    from srfpipe.occupancy import OccupancyCache, distill
    from tests.test_occupancy import sphere_field

    path = tmp_path_factory.mktemp("cache") / "occupancy.zarr"
    distill(sphere_field(), path, {"voxel_size": 0.05, "supersample": 2, "avoid": [], "reach": ["apple"],
                                   "brick": 16}, progress=False)
    return OccupancyCache.load(path)


@settings(max_examples=200, deadline=None)
@given(points=_points)
def test_random_cache_queries_answer_or_refuse_clearly(small_cache, points):
    """Finite or infinite points: free space outside the box, a finite gradient of unit length
    there, never NaN. (NaN itself is refused, see test_occupancy.)"""
    cache = small_cache
    p = np.asarray(points, dtype=np.float64)
    outside = ~np.all((p >= cache.bounds_world[0]) & (p <= cache.bounds_world[1]), axis=1)
    occupied = cache.occupancy(p)
    density = cache.density(p)
    semantic = cache.semantic(p)
    distance, gradient = cache.distance(p, "apple")
    assert not occupied[outside].any() and np.all(density[outside] == 0) and np.all(semantic[outside] == 0)
    assert not np.isnan(distance).any() and np.all(np.isfinite(gradient))
    assert np.all(distance[outside] > 0)
    # outside the box: the unit normal from the box plus the tangential part of the gradient at it
    norms = np.linalg.norm(gradient[outside], axis=1)
    assert np.all((norms >= 1 - 1e-6) & (norms <= 2))
    t, hit = cache.raycast(p[np.isfinite(p).all(1)], np.ones((int(np.isfinite(p).all(1).sum()), 3)))
    assert not np.isnan(t).any()


def test_nan_or_inf_query_of_the_field_is_refused_and_huge_points_answer(tiny_field):
    for bad in (np.nan, np.inf, -np.inf):
        points = np.zeros((4, 3))
        points[2, 1] = bad
        for query in (tiny_field.density, tiny_field.semantic):
            with pytest.raises(ValueError, match="NaN or infinite"):
                query(points)


@settings(max_examples=60, deadline=None)
@given(points=st.lists(st.tuples(*[st.one_of(st.floats(-2, 2), st.floats(allow_nan=False, allow_infinity=False))] * 3),
                       min_size=1, max_size=16))
def test_random_field_queries_are_finite(tiny_field, points):
    p = np.asarray(points, dtype=np.float64)
    density = tiny_field.density(p)
    semantic = tiny_field.semantic(p)
    assert np.all(np.isfinite(density)) and np.all(density >= 0)
    assert np.all((semantic >= 0) & (semantic <= 1))
    outside = ~np.all((p >= tiny_field.bounds_world[0]) & (p <= tiny_field.bounds_world[1]), axis=1)
    assert np.all(density[outside] == 0)


def _view():
    """A camera 2 units from the tiny field, looking at it (OpenCV camera_to_world)."""
    pose = np.eye(4)
    pose[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
    pose[:3, 3] = [0.0, -2.0, 0.5]
    return pose, [20.0, 20.0, 8.0, 6.0]


def _bad_view(case):
    pose, k = _view()
    size = (16, 12)
    if case == "scaled":
        pose[:3, :3] *= 3
    elif case == "sheared":
        pose[0, 1] += 0.5
    elif case == "zero_rotation":
        pose[:3, :3] = 0
    elif case == "mirrored":
        pose[:3, 0] *= -1
    elif case == "last_row":
        pose[3] = [1, 2, 3, 4]
    elif case == "zero_focal":
        k = [0.0, 20.0, 8.0, 6.0]
    elif case == "tiny_focal":
        k = [1e-320, 1e-320, 8.0, 6.0]
    elif case == "empty_image":
        size = (0, 0)
    elif case == "fractional_size":
        size = (16.5, 12)
    return pose, k, size


BAD_VIEWS = {"scaled": "rotation is not orthonormal", "sheared": "rotation is not orthonormal",
             "zero_rotation": "rotation is not orthonormal", "mirrored": "reflection",
             "last_row": "last row", "zero_focal": "fx, fy > 0", "tiny_focal": "non-finite ray directions",
             "empty_image": "image size must be positive integers", "fractional_size": "image size must be positive integers"}


@pytest.mark.parametrize("case", list(BAD_VIEWS))
def test_render_refuses_a_view_that_is_no_camera(tiny_field, case):
    """A non-rigid pose was rendered as a distorted image (or raised an index error from the grid),
    a fractional size was truncated: the view is refused naming what is wrong."""
    pose, k, (width, height) = _bad_view(case)
    with pytest.raises(ValueError, match=re.escape(BAD_VIEWS[case])):
        tiny_field.render(pose, k, width, height)


def test_render_of_a_huge_image_is_refused_before_allocating(tiny_field, monkeypatch):
    """100000 x 100000 pixels tried to allocate 80 GB of rays (then an allocator error, or swap)."""
    from srfpipe.memory import MemoryEstimateError

    monkeypatch.setenv("SRFPIPE_MAX_MEMORY_GB", "1")
    pose, k = _view()
    with pytest.raises(MemoryEstimateError, match="the image size: rendering 100000 x 100000 pixels"):
        tiny_field.render(pose, k, 100000, 100000)
    assert tiny_field.render(pose, k, 4, 3)["rgb"].shape == (3, 4, 3)


@pytest.fixture(scope="module")
def tiny_field(tmp_path_factory):
    from srfpipe.srf.query import SemanticRadianceField
    from srfpipe.srf.synthetic import write_scene
    from srfpipe.srf.trainer import train
    from tests.test_train import tiny_options

    folder = tmp_path_factory.mktemp("field")
    images, labels = write_scene(folder, views=6, width=24, height=16)
    train(images, labels, folder / "srf.zarr", tiny_options(iterations=4, checkpoint_every=0), holdout_every=3)
    return SemanticRadianceField.load(folder / "srf.zarr", device="cpu")


# ------------------------------------------------------------------ issue 32: hostile but quiet inputs
# Each of these once passed without a word: a soft mask read as certain, 16-bit 0/255 masks read as
# nearly empty, a role naming a class that is no prompt, a run that diverged to NaN and wrote its
# field, an output path that replaced its own input.


def _import_masks_setup(tmp_path, masks: dict[int, np.ndarray], n: int = 2):
    """images.zarr of n 40x30 frames and an import folder holding `masks` {frame: array} for 'apple'."""
    from srfpipe.segment.run import prompt_options
    from tests.test_segment import options, red_blue_images, write_images

    images = write_images(tmp_path / "images.zarr", red_blue_images(n=n, width=40, height=30))
    folder = tmp_path / "masks"
    folder.mkdir()
    for i, mask in masks.items():
        assert cv2.imwrite(str(folder / f"frame_{i:05d}_apple.png"), mask)
    opts = prompt_options(options(backend="import", **{"import": {"path": str(folder)}}), "apple")
    return images, folder, opts


def _segment(images, opts, out):
    from srfpipe.segment.run import segment_images
    from tests.test_segment import read_masks

    return read_masks(segment_images(images, "apple", opts, out, progress=False))


@pytest.mark.hostile
def test_import_soft_mask_whose_maximum_is_1_is_not_read_as_certain(tmp_path, caplog):
    """The value range is decided per prompt: a soft 8-bit mask that reaches 1 (of 255) in one frame
    is probability 1/255 there, as the prompt's other masks say 8-bit soft, not a 0/1 binary mask."""
    faint = np.zeros((30, 40), np.uint8)
    faint[5:10, 5:10] = 1
    soft = np.zeros((30, 40), np.uint8)
    soft[10:20, 10:30] = 200
    images, _, opts = _import_masks_setup(tmp_path, {0: faint, 1: soft})
    with caplog.at_level("INFO", logger="srfpipe.segment.import_backend"):
        masks = _segment(images, opts, tmp_path / "apple.zarr")
    assert masks[0].max() == pytest.approx(1 / 255)
    assert masks[1].max() == pytest.approx(200 / 255)
    assert "prompt 'apple': 2 masks, 8-bit, values 0..200, read as probability value/255" in caplog.text
    assert "frame_00000_apple.png holds only 0 and 1" in caplog.text


@pytest.mark.hostile
def test_import_masks_that_are_all_0_or_1_are_binary(tmp_path, caplog):
    a = np.zeros((30, 40), np.uint8)
    a[5:10, 5:10] = 1
    images, _, opts = _import_masks_setup(tmp_path, {0: a, 1: np.zeros_like(a)})
    with caplog.at_level("INFO", logger="srfpipe.segment.import_backend"):
        masks = _segment(images, opts, tmp_path / "apple.zarr")
    assert masks[0][5:10, 5:10].min() == 1.0 and masks[1].max() == 0.0
    assert "2 masks, 8-bit, values 0..1, read as binary 0/1" in caplog.text


@pytest.mark.hostile
@pytest.mark.parametrize("high, expected, read_as", [
    (255, 1.0, r"16-bit, values 0..255, read as probability value/255 \(8-bit masks stored in 16 bits, binary 0/255\)"),
    (65535, 1.0, r"16-bit, values 0..65535, read as probability value/65535"),
    (32768, 32768 / 65535, r"16-bit, values 0..32768, read as probability value/65535"),
], ids=["8bit_in_16bit", "full_16bit", "soft_16bit"])
def test_import_16_bit_masks_read_on_the_scale_their_values_show(tmp_path, caplog, high, expected, read_as):
    """16-bit masks holding 0/255 (an 8-bit mask saved in 16 bits) are binary, not 255/65535 = 0.004."""
    mask = np.zeros((30, 40), np.uint16)
    mask[5:15, 10:30] = high
    images, _, opts = _import_masks_setup(tmp_path, {0: mask, 1: mask})
    with caplog.at_level("INFO", logger="srfpipe.segment.import_backend"):
        masks = _segment(images, opts, tmp_path / "apple.zarr")
    assert masks[:, 5:15, 10:30].min() == pytest.approx(expected, abs=1 / 255)
    assert re.search(read_as, caplog.text), caplog.text
    from srfpipe.artifacts import meta

    assert meta(open_artifact(tmp_path / "apple.zarr"))["mask_values"]["bits"] == 16


@pytest.mark.hostile
def test_import_8_and_16_bit_masks_mixed_in_one_prompt_are_refused(tmp_path):
    eight = np.zeros((30, 40), np.uint8)
    sixteen = np.zeros((30, 40), np.uint16)
    eight[:5] = 255
    sixteen[:5] = 65535
    images, folder, opts = _import_masks_setup(tmp_path, {0: eight, 1: sixteen})
    out = tmp_path / "apple.zarr"
    message = assert_refused(lambda: _segment(images, opts, out), out, folder / "frame_00000_apple.png",
                             "mixed bit depth")
    assert str(folder / "frame_00001_apple.png") in message and "16-bit" in message and "\n" not in message


@pytest.mark.hostile
def test_class_above_its_threshold_nowhere_says_the_value_range_found(tmp_path, caplog):
    """Soft masks that never reach the threshold: the segment warning and the composite error say
    the bit depth, the values found and how they were read, not only that no frame holds the class."""
    from srfpipe.segment.composite import composite_masks

    soft = np.zeros((30, 40), np.uint8)
    soft[5:15, 10:30] = 50  # 0.196, below the threshold 0.5 and below the floor of soft masks (0.25)
    images, _, opts = _import_masks_setup(tmp_path, {0: soft, 1: soft})
    with caplog.at_level("WARNING"):
        _segment(images, opts, tmp_path / "apple.zarr")
    assert re.search(r"prompt 'apple': no pixel of its masks reaches the threshold 0.50 \(highest probability "
                     r"0.196; 2 masks, 8-bit, values 0..50, read as probability value/255\)", caplog.text)
    out = tmp_path / "labels.zarr"
    message = assert_refused(lambda: composite_masks(images, [tmp_path / "apple.zarr"], {}, out, progress=False),
                             out, "apple", r"no frame contains any of the classes \['apple'\] \(apple: highest "
                             r"probability 0.196 \(threshold 0.5\), imported 2 masks, 8-bit, values 0..50")
    assert "\n" not in message
    # a soft export that peaks at 0.39 (values 0..100, a percentage) is read on its own scale: its
    # 100 counts as certain, and the log says so
    from srfpipe.artifacts import open_artifact

    soft[5:15, 10:30] = 100
    folder = tmp_path / "percent"
    folder.mkdir()
    images, _, opts = _import_masks_setup(folder, {0: soft, 1: soft})
    with caplog.at_level("INFO"):
        _segment(images, opts, folder / "apple.zarr")
        labels = composite_masks(images, [folder / "apple.zarr"], {}, folder / "labels.zarr", progress=False)
    assert "soft masks read on their own scale (labels.rescale_soft_masks): apple (highest 0.392)" in caplog.text
    assert (np.asarray(open_artifact(labels)["label"][0]) == 1).sum() == 10 * 20


@pytest.mark.hostile
def test_import_label_images_are_read_as_before(tmp_path):
    """The value-range pass is for probability masks: a label image's values select classes."""
    from tests.test_segment import options, red_blue_images, write_images
    from srfpipe.segment.run import prompt_options

    images = write_images(tmp_path / "images.zarr", red_blue_images(n=2, width=40, height=30))
    folder = tmp_path / "labels"
    folder.mkdir()
    label = np.zeros((30, 40), np.uint16)
    label[:10] = 1
    label[10:20] = 300  # a 16-bit label value
    for i in range(2):
        cv2.imwrite(str(folder / f"frame_{i:05d}.png"), label)
    opts = prompt_options(options(backend="import", **{"import": {"path": str(folder), "format": "labels",
                                                                  "values": {"apple": 300}}}), "apple")
    masks = _segment(images, opts, tmp_path / "apple.zarr")
    assert np.array_equal(masks == 1.0, np.broadcast_to(label == 300, masks.shape))
    from srfpipe.artifacts import meta

    assert "mask_values" not in meta(open_artifact(tmp_path / "apple.zarr"))


@pytest.mark.hostile
@pytest.mark.parametrize("scene, problem", [
    ({"segmentation": {"prompts": ["apple", "branch", "leaf"]}, "occupancy": {"reach": ["aple"]}},
     r"occupancy.reach: 'aple' is not a prompt \(segmentation.prompts: apple, branch, leaf\); did you mean 'apple'\?"),
    ({"segmentation": {"prompts": ["stem", "leaf", "berry"]}, "occupancy": {"avoid": ["stems"], "reach": ["berry"]}},
     r"occupancy.avoid: 'stems' is not a prompt \(segmentation.prompts: stem, leaf, berry\); did you mean 'stem'\?"),
    ({"segmentation": {"prompts": ["bottle"]}, "occupancy": {"reach": ["apple"], "avoid": []}},
     r"occupancy.reach: 'apple' is not a prompt \(segmentation.prompts: bottle\)$"),
    ({"segmentation": {"prompts": []}, "occupancy": {"reach": ["apple"], "avoid": []}},
     r"occupancy.reach: 'apple' is not a prompt \(segmentation.prompts is empty"),
], ids=["reach_typo", "avoid_typo", "unrelated", "no_prompts"])
def test_occupancy_roles_must_name_prompts(scene, problem):
    message = assert_refused(lambda: validate_scene(scene, "s.yaml"), None, "s.yaml: occupancy.", problem, ConfigError)
    assert message.count("\n") == 0


@pytest.mark.hostile
def test_occupancy_roles_of_a_scene_file_are_checked_against_the_default_prompts(tmp_path):
    from srfpipe.config import load_scene

    path = tmp_path / "s.yaml"
    path.write_text("occupancy:\n  reach: [aple]\n")
    assert_refused(lambda: load_scene(path), None, f"{path}: occupancy.reach", "did you mean 'apple'", ConfigError)


@pytest.mark.hostile
def test_default_roles_and_a_section_alone_are_not_checked_against_prompts():
    from srfpipe.config import load_scene
    from tests.conftest import REPO

    # the schema's default roles (apple, branch) need not be among a scene's prompts
    validate_scene({"segmentation": {"prompts": ["bottle"]}}, "s.yaml")
    validate_scene({"segmentation": {"prompts": []}}, "s.yaml")
    # a stage validating its section alone does not know the scene's prompts
    validate_scene({"occupancy": {"reach": ["berry"], "avoid": ["stem"]}}, "occupancy options")
    for path in sorted((REPO / "config" / "scenes").glob("*.yaml")):
        load_scene(path)


def _tiny_train_scene(tmp_path):
    from srfpipe.srf.synthetic import write_scene

    return write_scene(tmp_path / "scene", views=6, width=24, height=16)


@pytest.mark.hostile
def test_training_that_diverges_stops_and_writes_nothing(tmp_path):
    """train.lr 1e6 trained to the end and wrote srf.zarr without a word (its semantic loss reached
    1e5..1e14 and never became NaN here); now the first logging step that sees a non-finite or
    exploded loss (or a non-finite parameter) stops it, naming the step, the term and the rate."""
    from srfpipe.srf.hooks import TrainingDiverged
    from srfpipe.srf.trainer import train
    from tests.test_train import tiny_options

    images, labels = _tiny_train_scene(tmp_path)
    out = tmp_path / "srf.zarr"
    message = assert_refused(
        lambda: train(images, labels, out, tiny_options(lr=1e6, iterations=40, checkpoint_every=0),
                      holdout_every=3),
        out, out, r"training diverged, at step \d+ the [a-z_]+ loss (became NaN or infinite|is \S+, over 1000 times "
                  r"the loss at step 1 \(\S+\)) \(train.lr 1e\+06\); lower train.lr \(the default is 0.01\); "
                  r"nothing written$", TrainingDiverged)
    assert "\n" not in message


@pytest.mark.hostile
def test_a_non_finite_loss_term_is_named_with_its_first_step(tmp_path, monkeypatch):
    from srfpipe.srf import losses
    from srfpipe.srf.hooks import TrainingDiverged
    from srfpipe.srf.trainer import train
    from tests.test_train import tiny_options

    real = losses.semantic_loss
    calls = []

    def semantic_goes_nan(*args, **kwargs):
        value = real(*args, **kwargs)
        calls.append(1)
        return value * float("nan") if len(calls) == 7 else value  # step 7: the semantic term alone is NaN

    monkeypatch.setattr(losses, "semantic_loss", semantic_goes_nan)
    images, labels = _tiny_train_scene(tmp_path)
    out = tmp_path / "srf.zarr"
    assert_refused(lambda: train(images, labels, out, tiny_options(iterations=30, log_every=5, checkpoint_every=0),
                                 holdout_every=3),
                   out, out, r"at step 7 the semantic loss became NaN or infinite \(train.lr 0.01\)", TrainingDiverged)
    assert len(calls) == 10  # stopped at the logging step after it (10), not at the end (30)


@pytest.mark.hostile
@pytest.mark.parametrize("argv, how", [
    (["downscale", "--poses", "{poses}", "--out", "{poses}"], r"--out \S+poses.zarr is the input --poses"),
    (["downscale", "--poses", "{poses}", "--out", "{root}/./x/../poses.zarr"], r"--out \S+ is the input --poses"),
    (["segment", "--images", "{poses}", "--prompt", "apple", "--out", "{poses}/masks/apple.zarr"],
     r"--out \S+apple.zarr lies inside the input --images \S+poses.zarr"),
    (["train", "--images", "{poses}", "--labels", "{root}/labels.zarr", "--out", "{root}/srf.zarr",
      "--metrics-log", "{root}/labels.zarr"], r"--metrics-log \S+labels.zarr is the input --labels"),
    (["distill", "--srf", "{poses}", "--out", "{root}"], r"--out \S+ holds the input --srf \S+poses.zarr"),
    (["poses", "--source", '{{"format": "nerfstudio", "path": "{root}/cap"}}', "--out", "{root}/cap"],
     r"--out \S+cap is the input --source path \S+cap"),
    (["poses", "--scene", "{root}/scene.yaml", "--out", "{root}/cap/poses.zarr"],
     r"--out \S+poses.zarr lies inside the input --scene \S+scene.yaml source.path \S+cap"),
], ids=["downscale_same", "downscale_dotted", "segment_inside", "train_metrics_log", "distill_holds", "poses_source",
        "poses_scene_file"])
def test_stage_cli_refuses_an_output_over_its_input(tmp_path, capsys, argv, how):
    """`srfpipe downscale --out X --poses X` replaced the poses with images; every stage now refuses
    an output that is, lies inside or holds one of its inputs, before anything runs."""
    from srfpipe.cli import main

    root = capture(tmp_path / "cap")
    poses = import_poses(NERFSTUDIO, root, {}, tmp_path / "poses.zarr", progress=False)
    # the capture path given only inside a scene file is an input too
    (tmp_path / "scene.yaml").write_text(f"source: {{format: nerfstudio, path: '{root}'}}\n")
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    code = main([a.format(poses=poses, root=tmp_path) for a in argv])
    err = capsys.readouterr().err
    assert code == 1
    assert re.search(how, err), err
    assert len(err.strip().splitlines()) == 1 and "writing it would destroy the input" in err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before
    open_artifact(poses, stage="poses")


# ------------------------------------------------------------------ audit: arrays a stage read unchecked


def _replace_array(artifact: Path, key: str, data: np.ndarray) -> None:
    """Replace one array of an artifact and reseal it: a consistent artifact, wrongly shaped."""
    import zarr

    from srfpipe.artifacts import reseal_artifact

    group = zarr.open_group(str(artifact), mode="r+")
    del group[key]
    group.create_array(key, data=data)
    reseal_artifact(artifact)


@pytest.mark.parametrize("case", ["label frames", "label dtype", "ground truth frames"])
def test_labels_and_ground_truth_of_the_wrong_shape_are_refused_naming_the_file(tmp_path, case):
    """labels.zarr `label` and images.zarr `ground_truth/labels` were read without a check: fewer
    frames than the images ended evaluate in an IndexError, a float label ended train in one."""
    from srfpipe.srf.data import load_posed_images
    from srfpipe.srf.synthetic import write_labels, write_scene

    images, labels = write_scene(tmp_path, views=4, width=12, height=8)
    if case == "label frames":
        target, key, data = labels, "label", np.zeros((3, 8, 12), np.uint8)
    elif case == "label dtype":
        target, key, data = labels, "label", np.zeros((4, 8, 12), np.float32)
    else:
        target, key, data = images, "ground_truth/labels", np.zeros((3, 8, 12), np.uint8)
    _replace_array(target, key, data)
    if target == images:  # labels.zarr records the images' fingerprint: make it this one's again
        labels = write_labels(tmp_path / "labels2.zarr", np.zeros((4, 8, 12), np.uint8), ["a"],
                              [f"frame_{i:05d}" for i in range(4)], inputs=[images])
    with pytest.raises(ValueError, match=rf"{re.escape(str(target))}: {key} must be \(4, 8, 12\) uint8.*got"):
        load_posed_images(images, labels)


@pytest.mark.parametrize("key, value, problem", [
    ("model_config", None, "model_config is missing"),
    ("classes", None, "classes is missing"),
    ("classes", ["apple"], r"classes names 1 classes \['apple'\], the model has \d+ semantic heads"),
    ("scene_from_world", None, "scene_from_world is missing"),
    ("bounds_world", [[0, 0, 0]], "bounds_world is missing or not a finite 2x3"),
    ("scene_scale", "x", "scene_scale must be a positive number"),
    ("model_config", {"hidden": 8}, "model_config does not describe a model"),
])
def test_a_field_with_missing_or_wrong_attributes_is_refused_naming_it(tmp_path, tiny_field, key, value, problem):
    """srf.zarr's attributes were read with `attrs[key]`: one missing ended distill, evaluate and
    package in a KeyError traceback, a class list of the wrong length in a numpy broadcast error."""
    import shutil

    import zarr

    from srfpipe.artifacts import NAMESPACE, reseal_artifact
    from srfpipe.srf.io import read_srf

    path = tmp_path / "srf.zarr"
    shutil.copytree(tiny_field.path, path)
    group = zarr.open_group(str(path), mode="r+")
    attrs = dict(group.attrs[NAMESPACE])
    if value is None:
        del attrs[key]
    else:
        attrs[key] = value
    group.attrs[NAMESPACE] = attrs
    reseal_artifact(path)
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: attribute {problem}.*re-run its stage 'train'"):
        read_srf(path)


def test_a_field_whose_weights_hold_nan_is_refused_naming_the_array(tmp_path, tiny_field):
    """A NaN in a trained parameter made evaluate write `psnr: null` and exit 0, and distill a cache
    of nothing; the camera centres, a buffer that holds NaN on purpose, still load."""
    import shutil

    import zarr

    from srfpipe.artifacts import reseal_artifact
    from srfpipe.srf.io import read_srf

    path = tmp_path / "srf.zarr"
    shutil.copytree(tiny_field.path, path)
    read_srf(path)  # as trained
    weights = zarr.open_group(str(path), mode="r+")["weights"]
    key = next(k for k in sorted(weights.array_keys()) if k.endswith("color_mlp.0.weight"))
    damaged = weights[key][...]
    damaged[0, 0] = np.nan
    weights[key][...] = damaged
    reseal_artifact(path)
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: weights/{re.escape(key)} holds 1 NaN or infinite"):
        read_srf(path)


@pytest.mark.parametrize("case", ["occupancy frames", "no distance", "no grid", "no classes"])
def test_an_occupancy_cache_with_missing_or_wrong_parts_is_refused_naming_it(tmp_path, case):
    """occupancy.zarr's attributes and arrays were read with `attrs[key]` / `group[key]`: one missing
    ended package and OccupancyCache.load in a KeyError traceback, and an occupancy grid of the wrong
    shape was packaged without a word."""
    import zarr

    from srfpipe.artifacts import NAMESPACE, reseal_artifact
    from srfpipe.occupancy import AnalyticField, OccupancyCache, distill
    from srfpipe.sim.package import read_scene

    tree = AnalyticField(["apple", "branch"], np.array([[-0.5, -0.5, 0.0], [0.5, 0.5, 1.0]]), sigma=1000.0)
    tree.add_sphere((0.0, 0.0, 0.5), 0.2, "apple")
    path = distill(tree, tmp_path / "occupancy.zarr", {"voxel_size": 0.1, "avoid": ["branch"], "reach": ["apple"]},
                   progress=False)
    group = zarr.open_group(str(path), mode="r+")
    if case == "occupancy frames":
        _replace_array(path, "occupancy", np.zeros((2, 2, 2), np.uint8))
        problem = r"array 'occupancy' has shape \(2, 2, 2\), the grid and classes need"
    elif case == "no distance":
        del group["distance"]
        reseal_artifact(path)
        problem = "missing array 'distance'"
    else:
        attrs = dict(group.attrs[NAMESPACE])
        del attrs[case.removeprefix("no ")]
        group.attrs[NAMESPACE] = attrs
        reseal_artifact(path)
        problem = f"attribute {case.removeprefix('no ')} is missing"
    for read in (lambda: OccupancyCache.load(path), lambda: read_scene(path, None, {})):
        with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: {problem}.*re-run its stage 'distill'"):
            read()

"""The imported capture (`Capture`) and the checked helpers every importer shares.

A `Capture` is in the project's convention (OpenCV camera, `camera_to_world`, see
`srfpipe.cameras`); the importers convert at the border. Every check raises with the file (and
frame) it found the problem in.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from srfpipe import cameras
from srfpipe.images import check_decodable, image_header_size, read_image
from srfpipe.poses.geometry import check_camera_model, check_camera_spread

log = logging.getLogger(__name__)

# Coordinates, focal lengths and the like beyond this are not a real capture (a unit mix-up, a
# corrupt file): refused at import rather than overflowing later.
MAX_VALUE = 1e12
MAX_IMAGE_SIDE = 1 << 20


@dataclass
class Capture:
    """Posed images as imported, in the project convention (OpenCV camera, camera_to_world)."""

    root: Path  # the capture folder; every image lies inside it
    image_paths: list[str]  # relative to root, POSIX separators
    camera_to_world: np.ndarray  # (N, 4, 4)
    intrinsics: np.ndarray  # (N, 4) fx, fy, cx, cy at full resolution
    image_size: np.ndarray  # (N, 2) width, height
    distortion: np.ndarray  # (N, 4) OpenCV k1, k2, p1, p2
    source_format: str
    source_file: Path  # the file (or model folder) the poses came from, for error messages
    points_world: np.ndarray | None = None  # (M, 3) sparse points
    ground_truth: Path | None = None
    ground_truth_bounds: np.ndarray | None = None  # (2, 3) from ground_truth/scene.json
    extra: dict = field(default_factory=dict)  # format-specific provenance

    @property
    def names(self) -> list[str]:
        """One name per frame: the image file's stem, or its relative path without suffix when stems repeat."""
        stems = [Path(p).stem for p in self.image_paths]
        if len(set(stems)) == len(stems):
            return stems
        return [str(Path(p).with_suffix("")) for p in self.image_paths]

    def __len__(self) -> int:
        return len(self.image_paths)


def load_json(path: Path) -> dict:
    """A JSON file whose top level is an object; errors name the file.

    Nesting deeper than Python's recursion limit (a "JSON bomb") is refused as invalid JSON.
    """
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file does not exist")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    except RecursionError:
        raise ValueError(f"{path}: not valid JSON (nested too deeply)") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object at the top level")
    return data


def _inside(folder: str, path: str) -> bool:
    return os.path.commonpath([folder, path]) == folder


def resolve_inside(root: Path, file_path: str, referenced_from: Path | str, allowed_roots=()) -> str:
    """`file_path` (relative to `root`, or absolute) as a POSIX path relative to `root`.

    Two checks: lexically (`..`, absolute paths) the path must name a location inside the dataset
    folder, and with symlinks resolved it must still lie inside it, or inside one of
    `allowed_roots` (the scene's `source.allowed_roots`: folders outside the capture that a
    symlinked image folder may point into). Anything else is refused, naming the file.
    """
    if not isinstance(file_path, str) or not file_path:
        raise ValueError(f"{referenced_from}: file_path must be a non-empty string, got {file_path!r}")
    if "\0" in file_path:
        raise ValueError(f"{referenced_from}: file_path {file_path!r} holds a NUL character")
    root_abs = os.path.normpath(os.path.abspath(root))
    full = os.path.normpath(os.path.join(root_abs, os.path.expanduser(file_path)))
    if not _inside(root_abs, full) or full == root_abs:
        raise ValueError(
            f"{referenced_from}: file_path {file_path!r} points outside the dataset folder {root_abs}"
        )
    real = os.path.realpath(full)
    allowed = [os.path.realpath(root_abs)] + [os.path.realpath(os.path.abspath(r)) for r in allowed_roots]
    if not any(_inside(folder, real) for folder in allowed):
        raise ValueError(
            f"{referenced_from}: file_path {file_path!r} is a symlink to {real}, outside the dataset folder "
            f"{root_abs} (list its folder in source.allowed_roots to allow it)"
        )
    return Path(os.path.relpath(full, root_abs)).as_posix()


def check_unique(paths: list[str], relative: str, where: str) -> None:
    """Refuse a frame whose image is already listed (two poses for one image)."""
    if relative in paths:
        raise ValueError(f"{where}: file_path {relative!r} is listed twice (first as frame of image "
                         f"{paths.index(relative)})")


def number(value, key: str, where: str, low: float = -MAX_VALUE, high: float = MAX_VALUE) -> float:
    """A JSON value that must be a finite number in [low, high], as float; errors name the key."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where}: {key} must be a number, got {type(value).__name__} {value!r}")
    if not np.isfinite(value) or not low <= value <= high:
        raise ValueError(f"{where}: {key}={value!r} is out of range [{low:g}, {high:g}]")
    return float(value)


def check_image_file(path: Path, referenced_from: Path | str) -> None:
    """The image exists and OpenCV recognises its format (header only; decoding happens at downscale)."""
    import cv2

    if not path.is_file():
        raise FileNotFoundError(f"{referenced_from}: image {path} does not exist")
    if not cv2.haveImageReader(str(path)):
        raise ValueError(f"{path}: corrupt or unsupported image (OpenCV cannot read its header)")


def read_image_size(path: Path, referenced_from: Path | str) -> tuple[int, int]:
    """(width, height) of an image file upright (EXIF orientation applied), for Blender captures
    and nerfstudio frames without w/h: from its header, never decoding its pixels (a format whose
    header Pillow cannot read is decoded by `srfpipe.images.read_image`, the downscale stage's
    decoder, so the camera's size is the size of the pixels it is applied to)."""
    check_image_file(path, referenced_from)
    size = image_header_size(path)
    if size is not None:
        check_decodable(path, size)
        return size
    height, width = read_image(path).shape[:2]
    return int(width), int(height)


def record_missing_images(where: Path | str, n_listed: int, missing: list[str]) -> dict:
    """Warn (naming `where`) about listed frames whose image file does not exist, and return the
    `Capture.extra` keys that record them in poses.zarr: `n_frames_listed`, `missing_images`.

    Real captures list frames whose images were later deleted (blurred, duplicates); they are
    skipped rather than refused, and the stage decides whether enough are left (`poses.min_images`).
    """
    if missing:
        log.warning("%s: skipped %d of %d frames whose image does not exist: %s", where, len(missing),
                    n_listed, ", ".join(missing))
    return {"n_frames_listed": n_listed, "missing_images": list(missing)}


def pose_matrix(value, where: str) -> np.ndarray:
    """A 4x4 (or 3x4) pose from JSON, as a float64 4x4 with a checked rotation."""
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: transform_matrix is not a numeric matrix ({exc})") from exc
    if matrix.shape == (3, 4):
        matrix = np.vstack([matrix, [0.0, 0.0, 0.0, 1.0]])
    if matrix.shape != (4, 4):
        raise ValueError(f"{where}: transform_matrix must be 4x4 (or 3x4), got shape {matrix.shape}")
    check_pose(matrix, where)
    return matrix


def check_pose(camera_to_world: np.ndarray, where: str) -> None:
    """Raise ValueError (naming `where`) unless the pose has a finite translation and a proper rotation."""
    if not np.all(np.isfinite(camera_to_world)):
        raise ValueError(f"{where}: pose contains NaN or infinite values")
    if np.max(np.abs(camera_to_world)) > MAX_VALUE:
        raise ValueError(f"{where}: pose has values above {MAX_VALUE:g} (a unit mix-up or a corrupt file)")
    problem = cameras.check_rotation(camera_to_world[:3, :3])
    if problem:
        raise ValueError(f"{where}: pose rotation {problem}")


def orthonormalize(camera_to_world: np.ndarray) -> np.ndarray:
    """Project the rotation blocks onto the nearest rotations (removes float noise of text formats)."""
    poses = np.array(camera_to_world, dtype=np.float64, copy=True)
    u, _, vt = np.linalg.svd(poses[:, :3, :3])
    poses[:, :3, :3] = u @ vt
    poses[:, 3, :] = [0.0, 0.0, 0.0, 1.0]
    return poses


def validate_capture(capture: Capture) -> None:
    """Per-frame arrays agree in length and hold sane values; errors name the source file."""
    n = len(capture.image_paths)
    arrays = {"camera_to_world": capture.camera_to_world, "intrinsics": capture.intrinsics,
              "image_size": capture.image_size, "distortion": capture.distortion}
    for name, array in arrays.items():
        if len(array) != n:
            raise ValueError(f"{capture.source_file}: mismatched counts: {len(array)} {name} for {n} images")
    for i, path in enumerate(capture.image_paths):
        where = f"{capture.source_file}: {path}"
        check_pose(capture.camera_to_world[i], where)
        fx, fy, cx, cy = capture.intrinsics[i]
        if not (np.all(np.isfinite(capture.intrinsics[i])) and fx > 0 and fy > 0
                and np.max(np.abs(capture.intrinsics[i])) <= MAX_VALUE):
            raise ValueError(f"{where}: invalid intrinsics {capture.intrinsics[i].tolist()}")
        if np.any(capture.image_size[i] <= 0) or np.any(capture.image_size[i] > MAX_IMAGE_SIDE):
            raise ValueError(f"{where}: invalid image size {capture.image_size[i].tolist()}")
        if not np.all(np.isfinite(capture.distortion[i])):
            raise ValueError(f"{where}: distortion contains NaN or infinite values")
        check_camera_model(capture.intrinsics[i], capture.distortion[i], capture.image_size[i], where)
    check_camera_spread(capture.camera_to_world, capture.source_file)

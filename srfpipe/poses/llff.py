"""LLFF `poses_bounds.npy` importer (the NeRF forward-facing scenes: fern, flower, room, ...).

`poses_bounds.npy` holds one row of 17 numbers per image, in the sorted order of the image files:
a 3x5 matrix (row-major) whose first four columns are the camera-to-world pose with the camera
axes in LLFF's order (down, right, backwards) and whose last column holds the height, width and
focal length of the images the poses were made from (the originals), then the near and far depth
bounds of that view. The images read are often a downscaled copy (`images_4/`): the focal length
scales by actual width / original width. Pinhole cameras, principal point at the image centre,
no distortion.

The images folder is `source.images_dir`, by default `images_4` when the capture has one (LLFF's
4x downscaled copy, the size the NeRF papers evaluate forward-facing scenes at), else `images`.
The per-view near and far bounds are kept in `Capture.extra["near_far"]` ((N, 2), world units);
the scene bounds come from the stage's estimators as for every capture without sparse points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from srfpipe.poses.capture import (
    Capture,
    MAX_IMAGE_SIDE,
    MAX_VALUE,
    check_pose,
    number,
    orthonormalize,
    read_image_size,
    resolve_inside,
)

LLFF_FILE = "poses_bounds.npy"
LLFF_IMAGE_DIRS = ("images_4", "images")  # tried in this order when source.images_dir is not set
LLFF_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")  # as LLFF's loader lists them, any case
# LLFF camera axes (down, right, backwards) -> OpenCV's (right, down, forward): columns 1, 0, -2
LLFF_TO_OPENCV = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def llff_to_opencv(rotation: np.ndarray) -> np.ndarray:
    """Camera-to-world rotations (…, 3, 3) with LLFF's camera axes as columns -> OpenCV's."""
    return np.asarray(rotation, dtype=np.float64) @ LLFF_TO_OPENCV


def _load_rows(npy: Path) -> np.ndarray:
    """poses_bounds.npy as a finite (N, 17) float64 array; errors name the file (and the row)."""
    if not npy.is_file():
        raise FileNotFoundError(f"{npy}: file does not exist (is it an LLFF capture?)")
    try:
        rows = np.load(npy, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise ValueError(f"{npy}: not a NumPy .npy array ({exc})") from exc
    if not isinstance(rows, np.ndarray):  # an .npz archive under the .npy name
        raise ValueError(f"{npy}: not a NumPy .npy array (a {type(rows).__name__})")
    if rows.dtype.kind not in "fiu":
        raise ValueError(f"{npy}: expected numbers, got an array of {rows.dtype}")
    if rows.ndim != 2 or rows.shape[0] == 0 or rows.shape[1] != 17:
        raise ValueError(f"{npy}: expected shape (N, 17) (a 3x5 pose-and-size matrix and near, far per "
                         f"image), got {rows.shape}")
    rows = rows.astype(np.float64)
    bad = np.flatnonzero(~np.all(np.isfinite(rows), axis=1))
    if len(bad):
        raise ValueError(f"{npy}: row {bad[0]} (of {len(rows)}) holds NaN or infinite values")
    return rows


def _images_folder(root: Path, images_dir: str | None, allowed_roots) -> str:
    """The images folder relative to root: `images_dir`, or the first of LLFF_IMAGE_DIRS present."""
    if images_dir is not None:
        folder = resolve_inside(root, images_dir, f"{root}: source.images_dir", allowed_roots)
        if not (root / folder).is_dir():
            raise FileNotFoundError(f"{root / folder}: images folder (source.images_dir) does not exist")
        return folder
    for candidate in LLFF_IMAGE_DIRS:
        if (root / candidate).is_dir():
            return resolve_inside(root, candidate, f"{root}: {candidate}", allowed_roots)
    others = sorted(p.name for p in root.glob("images*") if p.is_dir())
    raise FileNotFoundError(
        f"{root}: no images folder ({' or '.join(LLFF_IMAGE_DIRS)})"
        + (f"; set source.images_dir to one of {', '.join(others)}" if others else ""))


def read_llff(path: str | Path, images_dir: str | None = None, allowed_roots=()) -> Capture:
    """Read an LLFF capture: `path` is the folder holding poses_bounds.npy and the images folder.

    Rows pair with the images folder's files in sorted name order, so their counts must agree.
    Image paths must stay inside the capture folder (symlinks may lead into `allowed_roots`)."""
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: LLFF capture folder does not exist")
    npy = root / LLFF_FILE
    rows = _load_rows(npy)
    folder = _images_folder(root, images_dir, allowed_roots)
    names = sorted(p.name for p in (root / folder).iterdir()
                   if p.suffix.lower() in LLFF_IMAGE_SUFFIXES and not p.name.startswith("."))
    if len(names) != len(rows):
        raise ValueError(f"{npy}: mismatched counts: {len(rows)} rows for {len(names)} images in "
                         f"{root / folder} (one row per image, in sorted file order)")

    image_paths, poses, intrinsics, sizes = [], [], [], []
    for index, (row, name) in enumerate(zip(rows, names)):
        relative = resolve_inside(root, f"{folder}/{name}", f"{npy}: row {index}", allowed_roots)
        where = f"{npy}: row {index} ({relative})"
        matrix = row[:15].reshape(3, 5)
        original_height = number(matrix[0, 4], "height", where, 1, MAX_IMAGE_SIDE)
        original_width = number(matrix[1, 4], "width", where, 1, MAX_IMAGE_SIDE)
        focal = number(matrix[2, 4], "focal", where, 1e-9, MAX_VALUE)
        camera_to_world = np.eye(4)
        camera_to_world[:3, :3] = llff_to_opencv(matrix[:, :3])
        camera_to_world[:3, 3] = matrix[:, 3]
        check_pose(camera_to_world, where)
        width, height = read_image_size(root / relative, where)
        scale = width / original_width
        if abs(height - scale * original_height) > 1.0 + 1e-3 * height:
            raise ValueError(
                f"{where}: image is {width}x{height}, not the aspect ratio of the poses' "
                f"{original_width:g}x{original_height:g} (another image folder, or a rotated image?)")
        image_paths.append(relative)
        poses.append(camera_to_world)
        intrinsics.append([focal * scale, focal * scale, width / 2.0, height / 2.0])
        sizes.append((width, height))

    n = len(image_paths)
    extra = {
        "n_frames_listed": n, "missing_images": [],
        "near_far": rows[:, 15:17].tolist(),  # LLFF's per-view depth bounds, world units
        "llff_original_size": [float(rows[0, 9]), float(rows[0, 4])],  # width, height of row 0's originals
    }
    return Capture(
        root=root, image_paths=image_paths, camera_to_world=orthonormalize(np.stack(poses)),
        intrinsics=np.asarray(intrinsics), image_size=np.asarray(sizes, dtype=np.int32),
        distortion=np.zeros((n, 4)), source_format="llff", source_file=npy, extra=extra,
    )

"""COLMAP sparse model importer (binary or text), read through `pycolmap.Reconstruction`.

PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV cameras; `cam_from_world` is inverted
to `camera_to_world`; COLMAP's camera frame and pixel convention are already the project's.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from srfpipe.poses.capture import (
    Capture,
    check_image_file,
    check_pose,
    orthonormalize,
    record_missing_images,
    resolve_inside,
)

log = logging.getLogger(__name__)


def colmap_camera_parameters(camera, where: str) -> tuple[list[float], list[float]]:
    """(fx, fy, cx, cy) and OpenCV (k1, k2, p1, p2) of a pycolmap camera."""
    model = camera.model.name
    p = [float(v) for v in camera.params]
    if model == "SIMPLE_PINHOLE":
        return [p[0], p[0], p[1], p[2]], [0.0, 0.0, 0.0, 0.0]
    if model == "PINHOLE":
        return p[:4], [0.0, 0.0, 0.0, 0.0]
    if model == "SIMPLE_RADIAL":
        return [p[0], p[0], p[1], p[2]], [p[3], 0.0, 0.0, 0.0]
    if model == "RADIAL":
        return [p[0], p[0], p[1], p[2]], [p[3], p[4], 0.0, 0.0]
    if model == "OPENCV":
        return p[:4], p[4:8]
    raise ValueError(
        f"{where}: camera model {model} is not supported "
        "(PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV)"
    )


def _find_colmap_model(root: Path, model_dir: str | None) -> Path:
    candidates = [model_dir] if model_dir else ["sparse/0", "sparse", "."]
    for candidate in candidates:
        folder = root / candidate
        if any((folder / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return folder
    tried = ", ".join(str(root / c) for c in candidates)
    raise FileNotFoundError(f"{root}: no COLMAP model (cameras.bin or cameras.txt) in {tried}")


def read_colmap(path: str | Path, images_dir: str | None = None, model_dir: str | None = None) -> Capture:
    """Read a COLMAP sparse model (binary or text) and its images folder through pycolmap."""
    import pycolmap

    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: COLMAP capture folder does not exist")
    model = _find_colmap_model(root, model_dir)
    reconstruction = pycolmap.Reconstruction()
    try:
        reconstruction.read(str(model))
    except Exception as exc:  # pycolmap raises RuntimeError/ValueError subclasses for bad files
        raise ValueError(f"{model}: cannot read the COLMAP model ({exc})") from exc
    images_folder = resolve_inside(root, images_dir or "images", f"{root}: source.images_dir")

    image_paths, poses, intrinsics, sizes, distortion, missing = [], [], [], [], [], []
    unposed = 0
    for image in sorted(reconstruction.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            unposed += 1  # an unregistered image: COLMAP could not place it
            continue
        where = f"{model}: image {image.name!r}"
        relative = resolve_inside(root, f"{images_folder}/{image.name}", where)
        if not (root / relative).is_file():
            missing.append(relative)
            continue
        check_image_file(root / relative, where)
        camera = reconstruction.cameras[image.camera_id]
        k, dist = colmap_camera_parameters(camera, f"{model}: camera {image.camera_id}")
        camera_to_world = np.linalg.inv(np.vstack([image.cam_from_world().matrix(), [0.0, 0.0, 0.0, 1.0]]))
        check_pose(camera_to_world, where)
        image_paths.append(relative)
        poses.append(camera_to_world)
        intrinsics.append(k)
        sizes.append((int(camera.width), int(camera.height)))
        distortion.append(dist)
    n_posed = len(missing) + len(image_paths)
    if not n_posed:
        raise ValueError(f"{model}: the model has no posed images")
    extra = record_missing_images(model, n_posed, missing)
    if not image_paths:
        raise FileNotFoundError(f"{model}: none of the {n_posed} posed images has a file in {root / images_folder}")
    if unposed:
        log.warning("%s: skipped %d images without a pose (not registered by COLMAP)", model, unposed)
    points = np.array([p.xyz for p in reconstruction.points3D.values()], dtype=np.float64).reshape(-1, 3)
    return Capture(
        root=root, image_paths=image_paths, camera_to_world=orthonormalize(np.stack(poses)),
        intrinsics=np.asarray(intrinsics), image_size=np.asarray(sizes, dtype=np.int32),
        distortion=np.asarray(distortion), source_format="colmap", source_file=model,
        points_world=points if len(points) else None, extra={**extra, "unposed_images_skipped": unposed},
    )

"""COLMAP sparse model importer (binary or text), read through `pycolmap.Reconstruction`.

PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV cameras; `cam_from_world` is inverted
to `camera_to_world`; COLMAP's camera frame and pixel convention are already the project's.
"""

from __future__ import annotations

import logging
import struct
from pathlib import Path

import numpy as np

from srfpipe.poses.capture import (
    Capture,
    check_image_file,
    check_pose,
    check_unique,
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


def _camera_param_counts() -> dict[int, int]:
    import pycolmap

    counts = {}
    for model_id in range(64):
        try:
            model = pycolmap.CameraModelId(model_id)
            counts[model_id] = len(pycolmap.Camera.create_from_model_id(1, model, 1.0, 1, 1).params)
        except (ValueError, TypeError, RuntimeError):
            break
    return counts


class _Records:
    """A cursor over one COLMAP binary file that names the file and the record when it runs out."""

    def __init__(self, path: Path):
        self.path, self.data, self.pos = path, path.read_bytes(), 0

    def take(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise ValueError(f"{self.path}: truncated ({len(self.data)} bytes) in {what}")
        values = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return values

    def skip(self, size: int, what: str) -> None:
        if self.pos + size > len(self.data):
            raise ValueError(f"{self.path}: truncated ({len(self.data)} bytes) in {what}")
        self.pos += size

    def count(self) -> int:
        (n,) = self.take("Q", "the record count")
        return n

    def finish(self, n: int, kind: str) -> None:
        if self.pos != len(self.data):
            raise ValueError(f"{self.path}: {len(self.data) - self.pos} bytes after its {n} {kind} "
                             "(not a COLMAP model file, or a corrupt one)")


def check_colmap_binaries(model: Path) -> None:
    """Walk cameras.bin, images.bin and points3D.bin record by record (COLMAP's binary layout) and
    raise ValueError naming the file when one is truncated or holds trailing bytes."""
    if (model / "cameras.bin").is_file():
        params = _camera_param_counts()
        f = _Records(model / "cameras.bin")
        n = f.count()
        for i in range(n):
            _, model_id, _, _ = f.take("iiQQ", f"camera {i + 1} of {n}")
            if model_id not in params:
                raise ValueError(f"{f.path}: camera {i + 1} of {n} has unknown model id {model_id}")
            f.skip(8 * params[model_id], f"camera {i + 1} of {n}")
        f.finish(n, "cameras")
    if (model / "images.bin").is_file():
        f = _Records(model / "images.bin")
        n = f.count()
        for i in range(n):
            f.skip(4 + 8 * 7 + 4, f"image {i + 1} of {n}")
            end = f.data.find(b"\0", f.pos)
            if end < 0:
                raise ValueError(f"{f.path}: truncated ({len(f.data)} bytes) in the name of image {i + 1} of {n}")
            f.pos = end + 1
            (points,) = f.take("Q", f"image {i + 1} of {n}")
            f.skip(24 * points, f"the {points} 2-D points of image {i + 1} of {n}")
        f.finish(n, "images")
    if (model / "points3D.bin").is_file():
        f = _Records(model / "points3D.bin")
        n = f.count()
        for i in range(n):
            f.skip(8 + 24 + 3 + 8, f"point {i + 1} of {n}")
            (track,) = f.take("Q", f"point {i + 1} of {n}")
            f.skip(8 * track, f"the track of point {i + 1} of {n}")
        f.finish(n, "points")


def _find_colmap_model(root: Path, model_dir: str | None) -> Path:
    candidates = [model_dir] if model_dir else ["sparse/0", "sparse", "."]
    for candidate in candidates:
        folder = root / candidate
        if any((folder / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return folder
    tried = ", ".join(str(root / c) for c in candidates)
    raise FileNotFoundError(f"{root}: no COLMAP model (cameras.bin or cameras.txt) in {tried}")


def read_colmap(path: str | Path, images_dir: str | None = None, model_dir: str | None = None,
                allowed_roots=()) -> Capture:
    """Read a COLMAP sparse model (binary or text) and its images folder through pycolmap.

    Binary files are checked record by record first (`check_colmap_binaries`): pycolmap reads a
    truncated file as garbage, or allocates without bound. Image paths must stay inside the
    capture folder (symlinks may lead into `allowed_roots`)."""
    import pycolmap

    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: COLMAP capture folder does not exist")
    model = _find_colmap_model(root, model_dir)
    check_colmap_binaries(model)
    reconstruction = pycolmap.Reconstruction()
    try:
        reconstruction.read(str(model))
    except Exception as exc:  # pycolmap raises RuntimeError/ValueError subclasses for bad files
        raise ValueError(f"{model}: cannot read the COLMAP model ({exc})") from exc
    images_folder = resolve_inside(root, images_dir or "images", f"{root}: source.images_dir", allowed_roots)

    image_paths, poses, intrinsics, sizes, distortion, missing = [], [], [], [], [], []
    unposed = 0
    for image in sorted(reconstruction.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            unposed += 1  # an unregistered image: COLMAP could not place it
            continue
        where = f"{model}: image {image.name!r}"
        relative = resolve_inside(root, f"{images_folder}/{image.name}", where, allowed_roots)
        check_unique(image_paths + missing, relative, where)
        if not (root / relative).is_file():
            missing.append(relative)
            continue
        check_image_file(root / relative, where)
        camera = reconstruction.cameras[image.camera_id]
        k, dist = colmap_camera_parameters(camera, f"{model}: camera {image.camera_id}")
        cam_from_world = image.cam_from_world()
        # Eigen turns a quaternion (0, 0, 0, w) of any w, (0, 0, 0, 0) included, into the identity:
        # a corrupt or hand-edited rotation would pass the rotation check below as a valid pose
        norm = float(np.linalg.norm(cam_from_world.rotation.quat))
        if not abs(norm - 1.0) <= 1e-3:
            raise ValueError(f"{where}: rotation quaternion has norm {norm:g}, not 1 (a corrupt model file)")
        camera_to_world = np.linalg.inv(np.vstack([cam_from_world.matrix(), [0.0, 0.0, 0.0, 1.0]]))
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

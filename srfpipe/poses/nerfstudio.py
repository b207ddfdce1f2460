"""nerfstudio `transforms.json` importer (also the built-in orchard and plant captures).

OpenGL cameras (flipped to OpenCV), global or per-frame intrinsics (`fl_x/fl_y/cx/cy/w/h` or
`camera_angle_x`), OPENCV distortion `k1, k2, p1, p2`. `applied_transform` (the 3x4 that
nerfstudio's COLMAP converter applied to the original world frame) is undone, so poses and
`ply_file_path` points are back in the original (COLMAP) frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from srfpipe import cameras
from srfpipe.poses.capture import (
    Capture,
    MAX_IMAGE_SIDE,
    MAX_VALUE,
    check_image_file,
    check_unique,
    load_json,
    number,
    orthonormalize,
    pose_matrix,
    read_image_size,
    record_missing_images,
    resolve_inside,
)

NERFSTUDIO_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2",
                             "camera_model", "camera_angle_x", "camera_angle_y")


def _frame_intrinsics(meta: dict, frame: dict, image: Path, where: str):
    """fx, fy, cx, cy, (w, h), (k1, k2, p1, p2) of one nerfstudio frame (frame keys override global)."""
    values = {k: frame.get(k, meta.get(k)) for k in NERFSTUDIO_INTRINSIC_KEYS}
    for key, value in values.items():
        if key != "camera_model" and value is not None:
            high = MAX_IMAGE_SIDE if key in ("w", "h") else None
            values[key] = number(value, key, where, *((1, high) if high else ()))
    model = values["camera_model"] or "OPENCV"
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise ValueError(f"{where}: camera_model {model!r} is not supported (OPENCV, PINHOLE, SIMPLE_PINHOLE)")
    for key in ("k3", "k4"):
        if values[key]:
            raise ValueError(f"{where}: distortion {key}={values[key]} is not supported (OPENCV k1, k2, p1, p2 only)")
    if values["w"] is None or values["h"] is None:
        width, height = read_image_size(image, where)
    else:
        width, height = int(values["w"]), int(values["h"])
    fx, fy = values["fl_x"], values["fl_y"]
    if fx is None and values["camera_angle_x"] is not None:
        fx = 0.5 * width / np.tan(0.5 * float(values["camera_angle_x"]))
    if fy is None and values["camera_angle_y"] is not None:
        fy = 0.5 * height / np.tan(0.5 * float(values["camera_angle_y"]))
    if fx is None and fy is None:
        raise ValueError(f"{where}: no focal length (fl_x/fl_y or camera_angle_x)")
    fx = fy if fx is None else fx
    fy = fx if fy is None else fy
    cx = width / 2.0 if values["cx"] is None else values["cx"]
    cy = height / 2.0 if values["cy"] is None else values["cy"]
    distortion = [float(values[k] or 0.0) for k in ("k1", "k2", "p1", "p2")]
    return [float(fx), float(fy), float(cx), float(cy)], (width, height), distortion


def _similarity_4x4(matrix, where: str) -> np.ndarray:
    """A 3x4/4x4 similarity (rotation times uniform scale, translation) as 4x4, checked."""
    try:
        transform = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: must be a finite 3x4 or 4x4 matrix ({exc})") from None
    if transform.shape == (3, 4):
        transform = np.vstack([transform, [0.0, 0.0, 0.0, 1.0]])
    if transform.shape != (4, 4) or not np.all(np.isfinite(transform)):
        raise ValueError(f"{where}: must be a finite 3x4 or 4x4 matrix")
    scale = np.cbrt(np.linalg.det(transform[:3, :3]))
    problem = cameras.check_rotation(transform[:3, :3] / scale) if scale > 0 else "has det <= 0"
    if problem:
        raise ValueError(f"{where}: is not a similarity transform (its rotation part {problem})")
    return transform


def read_nerfstudio(path: str | Path, source_format: str = "nerfstudio", allowed_roots=()) -> Capture:
    """Read a nerfstudio capture: `path` is the folder holding transforms.json, or the file itself.

    Image paths must stay inside the capture folder (symlinks may lead into `allowed_roots`)."""
    path = Path(path)
    json_path = path / "transforms.json" if path.is_dir() else path
    if path.is_dir() and not json_path.exists():
        raise FileNotFoundError(f"{path}: no transforms.json in this folder (is it a nerfstudio capture?)")
    meta = load_json(json_path)
    root = json_path.parent
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{json_path}: 'frames' must be a non-empty list")

    image_paths, poses, intrinsics, sizes, distortion, missing = [], [], [], [], [], []
    for index, frame in enumerate(frames):
        where = f"{json_path}: frames[{index}]"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise ValueError(f"{where}: needs 'file_path' and 'transform_matrix'")
        relative = resolve_inside(root, frame["file_path"], where, allowed_roots)
        check_unique(image_paths + missing, relative, where)
        if not (root / relative).exists():
            missing.append(relative)
            continue
        check_image_file(root / relative, where)
        where = f"{where} ({relative})"
        poses.append(pose_matrix(frame["transform_matrix"], where))
        k, size, dist = _frame_intrinsics(meta, frame, root / relative, where)
        image_paths.append(relative)
        intrinsics.append(k)
        sizes.append(size)
        distortion.append(dist)

    extra = record_missing_images(json_path, len(frames), missing)
    if not image_paths:
        raise FileNotFoundError(f"{json_path}: none of the {len(frames)} frames has an image file")
    camera_to_world = cameras.opengl_to_opencv(np.stack(poses))
    points = None
    if meta.get("ply_file_path"):
        ply = root / resolve_inside(root, meta["ply_file_path"], f"{json_path}: ply_file_path", allowed_roots)
        points = _read_ply_points(ply)
    if "applied_transform" in meta:
        # transform_matrix = applied_transform @ original camera_to_world: undo it.
        applied = _similarity_4x4(meta["applied_transform"], f"{json_path}: applied_transform")
        original_from_file = np.linalg.inv(applied)
        camera_to_world = cameras.transform_poses(original_from_file, camera_to_world)
        if points is not None:
            points = cameras.transform_points(original_from_file, points)
        extra["applied_transform_undone"] = applied[:3].tolist()
    return Capture(
        root=root, image_paths=image_paths, camera_to_world=orthonormalize(camera_to_world),
        intrinsics=np.asarray(intrinsics), image_size=np.asarray(sizes, dtype=np.int32),
        distortion=np.asarray(distortion), source_format=source_format, source_file=json_path,
        points_world=points, extra=extra,
    )


PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
             "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _check_ply_complete(path: Path) -> None:
    """Raise ValueError when a PLY file holds fewer records than its header declares: Open3D reads a
    truncated file with only a printed warning, the missing points zeros or garbage."""
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no ply ... end_header header)")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    body = data[data.index(b"\n", end) + 1:] if b"\n" in data[end:] else b""
    fmt, elements = None, []  # [count, record size in bytes or None for list properties]
    for line in header:
        words = line.split()
        if words[:1] == ["format"] and len(words) > 1:
            fmt = words[1]
        elif words[:1] == ["element"] and len(words) == 3 and words[2].isdigit():
            elements.append([int(words[2]), 0])
        elif words[:1] == ["property"] and elements and elements[-1][1] is not None:
            size = PLY_SIZES.get(words[1]) if len(words) == 3 else None  # a list property: size varies
            elements[-1][1] = None if size is None else elements[-1][1] + size
    if fmt == "ascii":
        records = sum(count for count, _ in elements)
        lines = len([line for line in body.splitlines() if line.strip()])  # one record a line
        if lines < records:
            raise ValueError(f"{path}: truncated PLY ({lines} data lines, its header declares {records} records)")
    elif fmt in ("binary_little_endian", "binary_big_endian") and all(size is not None for _, size in elements):
        expected = sum(count * size for count, size in elements)
        if len(body) < expected:
            raise ValueError(f"{path}: truncated PLY ({len(body)} bytes of data, its header declares {expected})")


def _read_ply_points(path: Path) -> np.ndarray:
    import open3d as o3d

    if not path.is_file():
        raise FileNotFoundError(f"{path}: point cloud (ply_file_path) does not exist")
    _check_ply_complete(path)
    cloud = o3d.io.read_point_cloud(str(path))
    points = np.asarray(cloud.points, dtype=np.float64)
    if len(points) == 0:
        raise ValueError(f"{path}: point cloud is empty or unreadable")
    bad = np.flatnonzero(~np.all(np.isfinite(points) & (np.abs(points) <= MAX_VALUE), axis=1))
    if len(bad):
        raise ValueError(f"{path}: point {bad[0]} (of {len(points)}) is NaN, infinite or above {MAX_VALUE:g}")
    return points

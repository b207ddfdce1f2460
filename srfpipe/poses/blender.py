"""Blender NeRF synthetic importer: `transforms_{train,val,test}.json`.

OpenGL cameras, `camera_angle_x`, the image size read from the image files, and a `file_path`
without extension gets `.png` (as the Blender NeRF scenes list their frames).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from srfpipe import cameras
from srfpipe.poses.capture import (
    Capture,
    check_unique,
    load_json,
    number,
    orthonormalize,
    pose_matrix,
    read_image_size,
    record_missing_images,
    resolve_inside,
)

BLENDER_SPLITS = ("train", "val", "test")


def read_blender(path: str | Path, allowed_roots=()) -> Capture:
    """Read a Blender NeRF synthetic capture: `path` holds transforms_{train,val,test}.json.

    Image paths must stay inside the capture folder (symlinks may lead into `allowed_roots`)."""
    root = Path(path)
    split_files = [root / f"transforms_{split}.json" for split in BLENDER_SPLITS]
    split_files = [f for f in split_files if f.exists()]
    if not split_files:
        raise FileNotFoundError(f"{root}: no transforms_train/val/test.json (is it a Blender NeRF capture?)")
    image_paths, poses, intrinsics, sizes, splits, missing = [], [], [], [], [], []
    n_listed = 0
    for json_path in split_files:
        meta = load_json(json_path)
        frames = meta.get("frames")
        if not isinstance(frames, list) or not frames:
            raise ValueError(f"{json_path}: 'frames' must be a non-empty list")
        if "camera_angle_x" not in meta:
            raise ValueError(f"{json_path}: missing camera_angle_x")
        angle = number(meta["camera_angle_x"], "camera_angle_x", str(json_path), 1e-6, np.pi - 1e-6)
        n_listed += len(frames)
        for index, frame in enumerate(frames):
            where = f"{json_path}: frames[{index}]"
            if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
                raise ValueError(f"{where}: needs 'file_path' and 'transform_matrix'")
            file_path = frame["file_path"]
            if isinstance(file_path, str) and file_path and not Path(file_path).suffix:
                file_path += ".png"  # Blender NeRF lists frames without the extension
            relative = resolve_inside(root, file_path, where, allowed_roots)
            check_unique(image_paths + missing, relative, where)
            if not (root / relative).exists():
                missing.append(relative)
                continue
            width, height = read_image_size(root / relative, where)
            poses.append(pose_matrix(frame["transform_matrix"], f"{where} ({relative})"))
            focal = 0.5 * width / np.tan(0.5 * angle)
            image_paths.append(relative)
            intrinsics.append([focal, focal, width / 2.0, height / 2.0])
            sizes.append((width, height))
            splits.append(json_path.stem.removeprefix("transforms_"))
    split_names = ", ".join(f.name for f in split_files)
    extra = {"splits": splits, **record_missing_images(f"{root} ({split_names})", n_listed, missing)}
    if not image_paths:
        raise FileNotFoundError(f"{root}: none of the {n_listed} frames of {split_names} has an image file")
    n = len(image_paths)
    return Capture(
        root=root, image_paths=image_paths,
        camera_to_world=orthonormalize(cameras.opengl_to_opencv(np.stack(poses))),
        intrinsics=np.asarray(intrinsics), image_size=np.asarray(sizes, dtype=np.int32),
        distortion=np.zeros((n, 4)), source_format="blender", source_file=split_files[0],
        extra=extra,
    )

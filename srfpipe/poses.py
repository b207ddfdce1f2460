"""Import camera poses (nerfstudio | blender | colmap | orchard), optionally refine them with COLMAP.

Writes `poses.zarr` (see docs/artifacts.md): world-frame `camera_to_world` in the project's OpenCV
camera convention (`srfpipe.cameras`), full-resolution intrinsics and OpenCV distortion, optional
sparse points, and the scene normalization `scene_from_world` that maps the scene bounds into
[-1, 1]^3.

Importers (every convention change happens here, at the border):

* nerfstudio `transforms.json`: OpenGL cameras (flipped to OpenCV), global or per-frame
  intrinsics (`fl_x/fl_y/cx/cy/w/h` or `camera_angle_x`), OPENCV distortion `k1, k2, p1, p2`.
  `applied_transform` (the 3x4 that nerfstudio's COLMAP converter applied to the original world
  frame) is undone, so poses and `ply_file_path` points are back in the original (COLMAP) frame.
* Blender NeRF `transforms_{train,val,test}.json`: OpenGL cameras, `camera_angle_x`, image size
  read from the image files, `file_path` without extension gets `.png`.
* COLMAP sparse model (binary or text) through `pycolmap.Reconstruction`: PINHOLE,
  SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV cameras; `cam_from_world` is inverted to
  `camera_to_world`; COLMAP's camera frame and pixel convention are already the project's.
* orchard: the built-in generator's nerfstudio capture, plus its `ground_truth/` folder.

Scene bounds, first that applies: `poses.bounds` from the config; the capture's own
`ground_truth/scene.json` `bounds_world` (orchard); sparse points (1-99 % percentiles + 5 %
margin); the camera frusta (`bounds_from_frusta`).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from srfpipe import cameras
from srfpipe.config import ConfigError, add_options_arguments, stage_options, validate_scene

log = logging.getLogger(__name__)

FORMATS = ("orchard", "plant", "nerfstudio", "blender", "colmap")
BLENDER_SPLITS = ("train", "val", "test")
POINT_PERCENTILES = (1.0, 99.0)
POINT_MARGIN = 0.05  # fraction of the percentile box added on every side
MIN_POINTS_FOR_BOUNDS = 20


# ----------------------------------------------------------------------------- the imported capture


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


# ----------------------------------------------------------------------------- small checked helpers


def _load_json(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: file does not exist")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a JSON object at the top level")
    return data


def resolve_inside(root: Path, file_path: str, referenced_from: Path | str) -> str:
    """`file_path` (relative to `root`, or absolute) as a POSIX path relative to `root`.

    The check is lexical (`..` and absolute paths), so a dataset may hold symlinked image folders,
    but a path that names a location outside the dataset folder is refused.
    """
    root_abs = os.path.normpath(os.path.abspath(root))
    full = os.path.normpath(os.path.join(root_abs, os.path.expanduser(str(file_path))))
    if os.path.commonpath([root_abs, full]) != root_abs or full == root_abs:
        raise ValueError(
            f"{referenced_from}: file_path {file_path!r} points outside the dataset folder {root_abs}"
        )
    return Path(os.path.relpath(full, root_abs)).as_posix()


def check_image_file(path: Path, referenced_from: Path | str) -> None:
    """The image exists and OpenCV recognises its format (header only; decoding happens at downscale)."""
    import cv2

    if not path.is_file():
        raise FileNotFoundError(f"{referenced_from}: image {path} does not exist")
    if not cv2.haveImageReader(str(path)):
        raise ValueError(f"{path}: corrupt or unsupported image (OpenCV cannot read its header)")


def read_image_size(path: Path, referenced_from: Path | str) -> tuple[int, int]:
    """(width, height) of an image file, decoding it with OpenCV (Blender, or nerfstudio without w/h)."""
    import cv2

    check_image_file(path, referenced_from)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{path}: corrupt image (OpenCV could not decode it)")
    return int(image.shape[1]), int(image.shape[0])


def _pose_matrix(value, where: str) -> np.ndarray:
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


# ----------------------------------------------------------------------------- nerfstudio


NERFSTUDIO_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2",
                             "camera_model", "camera_angle_x", "camera_angle_y")


def _frame_intrinsics(meta: dict, frame: dict, image: Path, where: str):
    """fx, fy, cx, cy, (w, h), (k1, k2, p1, p2) of one nerfstudio frame (frame keys override global)."""
    values = {k: frame.get(k, meta.get(k)) for k in NERFSTUDIO_INTRINSIC_KEYS}
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
    transform = np.asarray(matrix, dtype=np.float64)
    if transform.shape == (3, 4):
        transform = np.vstack([transform, [0.0, 0.0, 0.0, 1.0]])
    if transform.shape != (4, 4) or not np.all(np.isfinite(transform)):
        raise ValueError(f"{where}: must be a finite 3x4 or 4x4 matrix")
    scale = np.cbrt(np.linalg.det(transform[:3, :3]))
    problem = cameras.check_rotation(transform[:3, :3] / scale) if scale > 0 else "has det <= 0"
    if problem:
        raise ValueError(f"{where}: is not a similarity transform (its rotation part {problem})")
    return transform


def read_nerfstudio(path: str | Path, source_format: str = "nerfstudio") -> Capture:
    """Read a nerfstudio capture: `path` is the folder holding transforms.json, or the file itself."""
    path = Path(path)
    json_path = path / "transforms.json" if path.is_dir() else path
    if path.is_dir() and not json_path.exists():
        raise FileNotFoundError(f"{path}: no transforms.json in this folder (is it a nerfstudio capture?)")
    meta = _load_json(json_path)
    root = json_path.parent
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{json_path}: 'frames' must be a non-empty list")

    image_paths, poses, intrinsics, sizes, distortion, missing = [], [], [], [], [], []
    for index, frame in enumerate(frames):
        where = f"{json_path}: frames[{index}]"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise ValueError(f"{where}: needs 'file_path' and 'transform_matrix'")
        relative = resolve_inside(root, frame["file_path"], where)
        if not (root / relative).exists():
            missing.append(relative)  # real captures list frames that were later deleted
            continue
        check_image_file(root / relative, where)
        where = f"{where} ({relative})"
        poses.append(_pose_matrix(frame["transform_matrix"], where))
        k, size, dist = _frame_intrinsics(meta, frame, root / relative, where)
        image_paths.append(relative)
        intrinsics.append(k)
        sizes.append(size)
        distortion.append(dist)

    extra = {"n_frames_listed": len(frames), "missing_images": missing}
    if missing:
        log.warning("%s: skipped %d of %d frames whose image does not exist: %s", json_path, len(missing),
                    len(frames), ", ".join(missing))
    if not image_paths:
        raise FileNotFoundError(f"{json_path}: none of the {len(frames)} frames has an image file")
    camera_to_world = cameras.opengl_to_opencv(np.stack(poses))
    points = None
    if meta.get("ply_file_path"):
        ply = root / resolve_inside(root, meta["ply_file_path"], f"{json_path}: ply_file_path")
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


def _read_ply_points(path: Path) -> np.ndarray:
    import open3d as o3d

    if not path.is_file():
        raise FileNotFoundError(f"{path}: point cloud (ply_file_path) does not exist")
    cloud = o3d.io.read_point_cloud(str(path))
    points = np.asarray(cloud.points, dtype=np.float64)
    if len(points) == 0:
        raise ValueError(f"{path}: point cloud is empty or unreadable")
    return points


# ----------------------------------------------------------------------------- blender


def read_blender(path: str | Path) -> Capture:
    """Read a Blender NeRF synthetic capture: `path` holds transforms_{train,val,test}.json."""
    root = Path(path)
    split_files = [root / f"transforms_{split}.json" for split in BLENDER_SPLITS]
    split_files = [f for f in split_files if f.exists()]
    if not split_files:
        raise FileNotFoundError(f"{root}: no transforms_train/val/test.json (is it a Blender NeRF capture?)")
    image_paths, poses, intrinsics, sizes, splits = [], [], [], [], []
    for json_path in split_files:
        meta = _load_json(json_path)
        frames = meta.get("frames")
        if not isinstance(frames, list) or not frames:
            raise ValueError(f"{json_path}: 'frames' must be a non-empty list")
        if "camera_angle_x" not in meta:
            raise ValueError(f"{json_path}: missing camera_angle_x")
        angle = float(meta["camera_angle_x"])
        for index, frame in enumerate(frames):
            where = f"{json_path}: frames[{index}]"
            if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
                raise ValueError(f"{where}: needs 'file_path' and 'transform_matrix'")
            file_path = str(frame["file_path"])
            if not Path(file_path).suffix:
                file_path += ".png"  # Blender NeRF lists frames without the extension
            relative = resolve_inside(root, file_path, where)
            width, height = read_image_size(root / relative, where)
            poses.append(_pose_matrix(frame["transform_matrix"], f"{where} ({relative})"))
            focal = 0.5 * width / np.tan(0.5 * angle)
            image_paths.append(relative)
            intrinsics.append([focal, focal, width / 2.0, height / 2.0])
            sizes.append((width, height))
            splits.append(json_path.stem.removeprefix("transforms_"))
    n = len(image_paths)
    return Capture(
        root=root, image_paths=image_paths,
        camera_to_world=orthonormalize(cameras.opengl_to_opencv(np.stack(poses))),
        intrinsics=np.asarray(intrinsics), image_size=np.asarray(sizes, dtype=np.int32),
        distortion=np.zeros((n, 4)), source_format="blender", source_file=split_files[0],
        extra={"splits": splits},
    )


# ----------------------------------------------------------------------------- colmap


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
    if missing:
        raise FileNotFoundError(
            f"{model}: mismatched counts: the model has {len(missing) + len(image_paths)} posed images but "
            f"{len(missing)} have no file in {root / images_folder} (first: {', '.join(missing[:3])})"
        )
    if not image_paths:
        raise ValueError(f"{model}: the model has no posed images")
    if unposed:
        log.warning("%s: skipped %d images without a pose (not registered by COLMAP)", model, unposed)
    points = np.array([p.xyz for p in reconstruction.points3D.values()], dtype=np.float64).reshape(-1, 3)
    return Capture(
        root=root, image_paths=image_paths, camera_to_world=orthonormalize(np.stack(poses)),
        intrinsics=np.asarray(intrinsics), image_size=np.asarray(sizes, dtype=np.int32),
        distortion=np.asarray(distortion), source_format="colmap", source_file=model,
        points_world=points if len(points) else None, extra={"unposed_images_skipped": unposed},
    )


# ----------------------------------------------------------------------------- orchard ground truth


def attach_ground_truth(capture: Capture) -> Capture:
    """Attach `ground_truth/` (orchard) when present: check one label and depth file per frame, read bounds."""
    folder = capture.root / "ground_truth"
    if not folder.is_dir():
        return capture
    names = [Path(p).stem for p in capture.image_paths]
    for kind, suffix in (("labels", ".png"), ("depth", ".npy")):
        sub = folder / kind
        if not sub.is_dir():
            continue
        have = {p.stem for p in sub.glob(f"*{suffix}")}
        missing = [n for n in names if n not in have]
        if missing:
            raise ValueError(
                f"{sub}: mismatched counts: {len(have)} {kind} files for {len(names)} frames "
                f"(no {suffix} file for {', '.join(missing[:3])})"
            )
    bounds = None
    scene_json = folder / "scene.json"
    if scene_json.exists():
        scene = _load_json(scene_json)
        if "bounds_world" in scene:
            bounds = _check_bounds(scene["bounds_world"], f"{scene_json}: bounds_world")
    return replace(capture, ground_truth=folder.resolve(), ground_truth_bounds=bounds)


# ----------------------------------------------------------------------------- dispatch and validation


def load_capture(source: dict, capture_dir: str | Path | None = None) -> Capture:
    """Import the capture described by a scene's `source` section; `capture_dir` overrides `source.path`."""
    fmt = source.get("format")
    path = capture_dir if capture_dir is not None else source.get("path")
    if fmt not in FORMATS:
        raise ValueError(f"{path}: unknown capture format {fmt!r} (expected one of {', '.join(FORMATS)})")
    if path is None:
        raise ValueError(f"source: format {fmt} needs a capture path")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: capture does not exist")
    if fmt in ("nerfstudio", "orchard", "plant"):
        capture = read_nerfstudio(path, source_format=fmt)
    elif fmt == "blender":
        capture = read_blender(path)
    else:
        capture = read_colmap(path, source.get("images_dir"), source.get("model_dir"))
    capture = attach_ground_truth(capture)
    validate_capture(capture)
    return capture


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
        if not (np.all(np.isfinite(capture.intrinsics[i])) and fx > 0 and fy > 0):
            raise ValueError(f"{where}: invalid intrinsics {capture.intrinsics[i].tolist()}")
        if np.any(capture.image_size[i] <= 0):
            raise ValueError(f"{where}: invalid image size {capture.image_size[i].tolist()}")
        if not np.all(np.isfinite(capture.distortion[i])):
            raise ValueError(f"{where}: distortion contains NaN or infinite values")


# ----------------------------------------------------------------------------- scene bounds


def _check_bounds(value, where: str) -> np.ndarray:
    bounds = np.asarray(value, dtype=np.float64)
    if bounds.shape != (2, 3) or not np.all(np.isfinite(bounds)) or np.any(bounds[1] <= bounds[0]):
        raise ValueError(f"{where}: bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max, got {value}")
    return bounds


def bounds_from_points(points: np.ndarray) -> np.ndarray:
    """(2, 3) box of the 1-99 % percentiles of sparse points, widened by 5 % per side (outliers ignored)."""
    low, high = np.percentile(points, POINT_PERCENTILES, axis=0)
    margin = POINT_MARGIN * (high - low)
    margin = np.maximum(margin, 1e-3 * max(float(np.max(high - low)), 1e-9))  # flat point sets
    return np.stack([low - margin, high + margin])


def focus_point(camera_to_world: np.ndarray) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis: what the cameras look at.

    When the axes are (nearly) parallel, as in a forward-facing capture, there is no such point;
    then it is the mean camera centre moved forward along the mean viewing direction by the spread
    of the camera centres (at least 1 world unit).
    """
    centres = camera_to_world[:, :3, 3]
    axes = camera_to_world[:, :3, 2]
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]  # I - d d^T per camera
    a = projectors.sum(0)
    b = np.einsum("nij,nj->i", projectors, centres)
    eigenvalues = np.linalg.eigvalsh(a)
    if eigenvalues[0] > 1e-2 * eigenvalues[-1]:
        point = np.linalg.solve(a, b)
        # the axes must meet in front of the cameras, not behind them
        if np.median(np.einsum("ni,ni->n", point[None] - centres, axes)) > 0:
            return point
    spread = max(float(np.linalg.norm(centres - centres.mean(0), axis=1).max()), 1.0)
    direction = axes.mean(0) / max(np.linalg.norm(axes.mean(0)), 1e-9)
    return centres.mean(0) + spread * direction


def bounds_from_frusta(
    camera_to_world: np.ndarray, intrinsics: np.ndarray, image_size: np.ndarray,
    visible_fraction: float = 0.9, resolution: int = 40,
) -> np.ndarray:
    """(2, 3) box of the region (nearly) every camera sees, for captures without sparse points.

    Heuristic: take the cameras' focus point (`focus_point`) and a cube around it whose half-size
    is the median camera distance to it; sample the cube on a grid and keep the points that
    project inside the image, in front of the camera, for at least `visible_fraction` of the
    cameras (the intersection of the frusta, tolerant to a few stray views). For cameras on a ring
    around an object this is the object's neighbourhood; the box is the kept points' extent plus
    one grid cell. When fewer than 8 points are seen by enough cameras, the box is the focus
    point +- half the median camera distance.
    """
    focus = focus_point(camera_to_world)
    radius = float(np.median(np.linalg.norm(camera_to_world[:, :3, 3] - focus, axis=1)))
    radius = max(radius, 1e-6)
    ticks = np.linspace(-radius, radius, resolution)
    grid = np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), -1).reshape(-1, 3) + focus
    seen = np.zeros(len(grid), dtype=np.int32)
    for pose, k, (width, height) in zip(camera_to_world, intrinsics, image_size):
        uv, depth = cameras.project_points(grid, pose, k)
        seen += (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= width) & (uv[:, 1] >= 0) & (uv[:, 1] <= height)
    kept = grid[seen >= visible_fraction * len(camera_to_world)]
    if len(kept) < 8:
        return np.stack([focus - radius / 2, focus + radius / 2])
    cell = ticks[1] - ticks[0]
    return np.stack([kept.min(0) - cell, kept.max(0) + cell])


def resolve_bounds(capture: Capture, camera_to_world: np.ndarray, points: np.ndarray | None,
                   override) -> tuple[np.ndarray, str]:
    """Scene bounds and where they came from: config | ground_truth | points | frusta."""
    if override is not None:
        return _check_bounds(override, "poses.bounds"), "config"
    if capture.ground_truth_bounds is not None:
        return capture.ground_truth_bounds, "ground_truth"
    if points is not None and len(points) >= MIN_POINTS_FOR_BOUNDS:
        return bounds_from_points(points), "points"
    return bounds_from_frusta(camera_to_world, capture.intrinsics, capture.image_size), "frusta"


# ----------------------------------------------------------------------------- perturbation and pose errors


def perturb_poses(camera_to_world: np.ndarray, rot_deg: float, translation: float, seed: int) -> np.ndarray:
    """Testing aid: turn every camera by `rot_deg` about a random axis through its centre and move
    its centre by `translation` (world units) in a random direction."""
    import cv2

    rng = np.random.default_rng(seed)
    poses = np.array(camera_to_world, dtype=np.float64, copy=True)
    for pose in poses:
        axis = rng.normal(size=3)
        rotation, _ = cv2.Rodrigues(np.radians(rot_deg) * axis / np.linalg.norm(axis))
        pose[:3, :3] = pose[:3, :3] @ rotation
        direction = rng.normal(size=3)
        pose[:3, 3] += translation * direction / np.linalg.norm(direction)
    return poses


def similarity_align(source_points: np.ndarray, target_points: np.ndarray) -> np.ndarray:
    """4x4 similarity (Umeyama, via pycolmap) mapping `source_points` onto `target_points`."""
    import pycolmap

    sim = pycolmap.estimate_sim3d(np.asarray(source_points, np.float64), np.asarray(target_points, np.float64))
    if sim is None:
        raise RuntimeError("similarity alignment failed (degenerate camera centres)")
    return np.vstack([sim.matrix(), [0.0, 0.0, 0.0, 1.0]])


def _frame_points(camera_to_world: np.ndarray, length: float) -> np.ndarray:
    """Each camera's centre and the tips of its three axes at `length`: (4N, 3)."""
    centres = camera_to_world[:, :3, 3]
    tips = centres[:, None, :] + length * np.swapaxes(camera_to_world[:, :3, :3], 1, 2)
    return np.concatenate([centres, tips.reshape(-1, 3)])


def align_poses(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """4x4 similarity mapping the `source` cameras onto the `target` cameras.

    Fitted to the camera centres *and* their orientations (the tips of the camera axes, placed at
    the spread of the target centres, before the source is scaled to the target's size): centres
    alone pin the rotation down poorly when the cameras stand almost in one plane, as on one ring.
    """
    source = np.asarray(source, np.float64)
    target = np.asarray(target, np.float64)
    scale = similarity_align(source[:, :3, 3], target[:, :3, 3]) if len(source) >= 3 else np.eye(4)
    source_scale = np.cbrt(np.linalg.det(scale[:3, :3]))
    length = max(float(np.sqrt(((target[:, :3, 3] - target[:, :3, 3].mean(0)) ** 2).sum(1).mean())), 1e-9)
    return similarity_align(_frame_points(source, length / source_scale), _frame_points(target, length))


def pose_errors(estimate: np.ndarray, reference: np.ndarray, scene_size: float, align: bool = True) -> dict:
    """Mean rotation error (degrees) and camera-centre error relative to `scene_size`.

    With `align`, the estimate is first mapped onto the reference by the similarity that best
    aligns the cameras (`align_poses`), so a change of gauge (scale, rotation, shift) is not an error.
    """
    estimate = np.asarray(estimate, np.float64)
    reference = np.asarray(reference, np.float64)
    if align:
        estimate = cameras.transform_poses(align_poses(estimate, reference), estimate)
    relative = np.einsum("nji,njk->nik", estimate[:, :3, :3], reference[:, :3, :3])
    cos = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    rot = np.degrees(np.arccos(cos))
    trans = np.linalg.norm(estimate[:, :3, 3] - reference[:, :3, 3], axis=1) / scene_size
    return {"rot_err_deg": float(rot.mean()), "trans_err": float(trans.mean()),
            "rot_err_deg_max": float(rot.max()), "trans_err_max": float(trans.max())}


# ----------------------------------------------------------------------------- the stage


def import_poses(source: dict, capture_dir: str | Path | None, options: dict, out: str | Path,
                 threads: int = -1, progress: bool = True) -> Path:
    """Import, optionally perturb and refine, normalize, and write `poses.zarr` atomically.

    `source` and `options` are the scene's `source` and `poses` sections (defaults are filled in
    by validation here); `capture_dir` overrides `source.path`.
    """
    from srfpipe.artifacts import create_artifact

    source = dict(source)
    where = capture_dir if capture_dir is not None else source.get("path", "source")
    if source.get("format", "orchard") not in FORMATS:
        raise ValueError(f"{where}: unknown capture format {source.get('format')!r} "
                         f"(expected one of {', '.join(FORMATS)})")
    if capture_dir is not None:
        source.setdefault("path", str(capture_dir))
    source = validate_scene({"source": source}, "source")["source"]
    options = validate_scene({"poses": dict(options)}, "poses options")["poses"]
    capture = load_capture(source, capture_dir)
    if len(capture) < options["min_images"]:
        missing = capture.extra.get("missing_images") or []
        raise ValueError(
            f"{capture.source_file}: only {len(capture)} of {capture.extra.get('n_frames_listed', len(capture))} "
            f"frames have an image ({len(missing)} missing), fewer than poses.min_images={options['min_images']}"
            + (f"; missing: {', '.join(missing)}" if missing else ""))
    log.info("imported %d images (%s) from %s", len(capture), capture.source_format, capture.source_file)

    poses = capture.camera_to_world
    points = capture.points_world
    bounds, bounds_source = resolve_bounds(capture, poses, points, options["bounds"])
    scene_size = float(np.max(bounds[1] - bounds[0]))
    perturbed = options["perturb_rot_deg"] > 0 or options["perturb_trans_frac"] > 0
    if perturbed:
        poses = perturb_poses(poses, options["perturb_rot_deg"], options["perturb_trans_frac"] * scene_size,
                              options["perturb_seed"])
        log.info("perturbed poses by %.3g deg and %.3g world units", options["perturb_rot_deg"],
                 options["perturb_trans_frac"] * scene_size)

    refinement = None
    if options["refine"] == "colmap":
        from srfpipe.colmap_refine import refine_poses

        result = refine_poses(capture, poses, matcher=options["matcher"],
                              workdir_parent=Path(out).parent, threads=threads)
        poses, points, refinement = result.camera_to_world, result.points_world, result.stats
        if bounds_source in ("points", "frusta"):
            bounds, bounds_source = resolve_bounds(capture, poses, points, None)

    scene_from_world = cameras.scene_from_world_transform(bounds[0], bounds[1])
    config = {"source": source, "poses": options}
    inputs = [str(Path(capture.root).resolve())]
    with create_artifact(out, "poses", config=config, inputs=inputs) as group:
        n = len(capture)
        group.create_array("camera_to_world", data=poses.astype(np.float64), dimension_names=("image", "row", "col"))
        group.create_array("intrinsics", data=capture.intrinsics.astype(np.float64), dimension_names=("image", "k"))
        group.create_array("image_size", data=capture.image_size.astype(np.int32), dimension_names=("image", "wh"))
        group.create_array("distortion", data=capture.distortion.astype(np.float64), dimension_names=("image", "k"))
        if points is not None and len(points):
            group.create_array("points_world", data=points.astype(np.float32), dimension_names=("point", "xyz"))
        from srfpipe.artifacts import update_attrs

        update_attrs(
            group,
            capture_root=str(Path(capture.root).resolve()),
            image_paths=capture.image_paths,
            names=capture.names,
            n_images=n,
            scene_from_world=scene_from_world,
            world_from_scene=np.linalg.inv(scene_from_world),
            bounds_world=bounds,
            bounds_source=bounds_source,
            source_format=capture.source_format,
            source_file=str(capture.source_file),
            ground_truth=str(capture.ground_truth) if capture.ground_truth else None,
            perturbed=perturbed,
            refinement=refinement,
            **capture.extra,
        )
    log.info("wrote %s: %d cameras, bounds %s (%s)", out, len(capture), bounds.round(3).tolist(), bounds_source)
    return Path(out)


def add_arguments(parser) -> None:
    add_options_arguments(parser, "poses")
    parser.add_argument(
        "--source", metavar="JSON", default=None,
        help="JSON object: the scene's 'source' section (format nerfstudio|blender|colmap|orchard, path, "
        "images_dir, model_dir); overrides the --scene file's",
    )
    parser.add_argument("--capture", metavar="DIR", default=None,
                        help="capture folder (overrides source.path; the orchard's generated capture)")
    parser.add_argument("--out", required=True, metavar="ZARR", help="poses.zarr to write (atomically)")
    parser.add_argument("--threads", type=int, default=-1, help="COLMAP threads (-1: all cores)")


def run(args) -> int:
    from srfpipe.config import load_scene

    options = stage_options(args, "poses")
    source = dict(load_scene(args.scene)["source"]) if args.scene else {}
    if args.source:
        try:
            override = json.loads(args.source)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"--source: not valid JSON ({exc})") from exc
        if not isinstance(override, dict):
            raise ConfigError("--source: must be a JSON object")
        source.update(override)
    import_poses(source, args.capture, options, args.out, threads=args.threads)
    return 0

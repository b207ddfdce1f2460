"""Cameras: the one convention used inside srfpipe, rays from pixels, and scene normalization.

Convention (everywhere inside the project; importers and exporters convert at the border):

* Camera frame is OpenCV's: +x right, +y down, +z forward (looking direction).
* A pose is `camera_to_world`, a 4x4 matrix T with x_world = T @ x_camera.
* World units are metres for the built-in orchard, and whatever the capture used otherwise.
* Pixels: (u, v) with u along the width, v along the height; the centre of pixel (0, 0) is (0.5, 0.5).
  Intrinsics are `fx, fy, cx, cy` in that pixel frame (cx = width / 2 for a centred principal point).
* The *scene* frame is the world scaled and shifted so that the scene bounds fit in [-1, 1]^3:
  x_scene = s * (x_world - c). `scene_from_world` (4x4) is stored in poses.zarr and copied into
  every later artifact that holds geometry, so every output maps back to world units.

nerfstudio / Blender / OpenGL cameras look down -z with +y up: `opengl_to_opencv` flips y and z.
"""

from __future__ import annotations

import re

import numpy as np

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_to_opencv(camera_to_world: np.ndarray) -> np.ndarray:
    """Convert camera-to-world poses (…, 4, 4) from the OpenGL camera frame to OpenCV's."""
    return np.asarray(camera_to_world, dtype=np.float64) @ OPENGL_TO_OPENCV


def opencv_to_opengl(camera_to_world: np.ndarray) -> np.ndarray:
    """Inverse of `opengl_to_opencv` (the flip is its own inverse)."""
    return np.asarray(camera_to_world, dtype=np.float64) @ OPENGL_TO_OPENCV


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """camera_to_world (4x4, OpenCV camera: +x right, +y down, +z forward) at `eye` looking at `target`;
    a ValueError when the viewing direction is parallel to `up`."""
    eye = np.asarray(eye, np.float64)
    forward = np.asarray(target, np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, np.float64))
    if np.linalg.norm(right) < 1e-9:
        raise ValueError(f"look_at: viewing direction {forward} is parallel to up {up}")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def intrinsic_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def scale_intrinsics(intrinsics: np.ndarray, sx: float, sy: float | None = None) -> np.ndarray:
    """Intrinsics (…, 4) = (fx, fy, cx, cy) for an image resized by (sx, sy).

    With pixel centres at +0.5 the principal point scales exactly: cx' = sx * cx.
    """
    sy = sx if sy is None else sy
    out = np.array(intrinsics, dtype=np.float64, copy=True)
    out[..., 0] *= sx
    out[..., 2] *= sx
    out[..., 1] *= sy
    out[..., 3] *= sy
    return out


def pixel_rays(
    camera_to_world: np.ndarray, intrinsics: np.ndarray, width: int, height: int, distortion=None,
) -> tuple[np.ndarray, np.ndarray]:
    """World-space rays through every pixel centre of one pinhole camera, or of an OpenCV lens.

    `distortion` (k1, k2, p1, p2) makes the pixels those of a lens with that distortion (OpenCV's
    model, as COLMAP's OPENCV camera): each pixel's ray is its undistorted normalized coordinate.
    Returns origins and unit directions, each (height, width, 3), row-major like the image.
    """
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    if distortion is not None and np.any(np.asarray(distortion) != 0):
        x, y = undistort_normalized(u, v, intrinsics, distortion)
        directions_cam = np.stack([x, y, np.ones_like(u)], axis=-1)
    else:
        directions_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1)
    rotation = np.asarray(camera_to_world, dtype=np.float64)[:3, :3]
    directions = directions_cam @ rotation.T
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    origins = np.broadcast_to(np.asarray(camera_to_world)[:3, 3], directions.shape).copy()
    return origins, directions


def undistort_normalized(u: np.ndarray, v: np.ndarray, intrinsics, distortion,
                         iterations: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole normalized coordinates (x, y) of pixel positions (u, v) seen through an OpenCV lens.

    Inverts x_d = x (1 + k1 r^2 + k2 r^4) + 2 p1 x y + p2 (r^2 + 2 x^2),
            y_d = y (1 + k1 r^2 + k2 r^4) + p1 (r^2 + 2 y^2) + 2 p2 x y
    by OpenCV's fixed-point iteration, run to convergence: the 5 iterations of cv2.undistortPoints
    leave pixel-sized errors at the corners of a strong lens (and its iterative variant has no
    Python binding).
    """
    fx, fy, cx, cy = (float(c) for c in intrinsics)
    k1, k2, p1, p2 = (float(c) for c in distortion)
    xd, yd = (np.asarray(u, np.float64) - cx) / fx, (np.asarray(v, np.float64) - cy) / fy
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        x_new = (xd - 2 * p1 * x * y - p2 * (r2 + 2 * x * x)) / radial
        y_new = (yd - p1 * (r2 + 2 * y * y) - 2 * p2 * x * y) / radial
        step = max(float(np.abs(x_new - x).max(initial=0)), float(np.abs(y_new - y).max(initial=0)))
        x, y = x_new, y_new
        if step < 1e-13:
            break
    return x, y


def project_points(points_world: np.ndarray, camera_to_world: np.ndarray, intrinsics: np.ndarray):
    """Project world points (M, 3) into one camera: pixel coords (M, 2) and depth along +z (M,)."""
    world_to_camera = np.linalg.inv(np.asarray(camera_to_world, dtype=np.float64))
    p = np.asarray(points_world, dtype=np.float64) @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    fx, fy, cx, cy = np.asarray(intrinsics, dtype=np.float64)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([fx * p[:, 0] / z + cx, fy * p[:, 1] / z + cy], axis=-1)
    return uv, z


def in_view(points_world: np.ndarray, camera_to_world: np.ndarray, intrinsics: np.ndarray, width: float,
            height: float) -> np.ndarray:
    """(M,) bool: the world points that lie in front of the camera and project inside its image."""
    uv, depth = project_points(points_world, camera_to_world, intrinsics)
    with np.errstate(invalid="ignore"):
        return (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= width) & (uv[:, 1] >= 0) & (uv[:, 1] <= height)


def scene_from_world_transform(bounds_min: np.ndarray, bounds_max: np.ndarray) -> np.ndarray:
    """The similarity (4x4) that maps the axis-aligned world box into [-1, 1]^3.

    One uniform scale (the box's largest half-extent becomes 1) keeps angles and aspect ratios.
    """
    bounds_min = np.asarray(bounds_min, dtype=np.float64)
    bounds_max = np.asarray(bounds_max, dtype=np.float64)
    if not (np.all(np.isfinite(bounds_min)) and np.all(np.isfinite(bounds_max))):
        raise ValueError(f"scene bounds must be finite, got {bounds_min} .. {bounds_max}")
    if np.any(bounds_max <= bounds_min):
        raise ValueError(f"scene bounds are empty: min {bounds_min} is not below max {bounds_max}")
    centre = 0.5 * (bounds_min + bounds_max)
    scale = 1.0 / (0.5 * np.max(bounds_max - bounds_min))
    transform = np.eye(4)
    transform[:3, :3] *= scale
    transform[:3, 3] = -scale * centre
    return transform


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 affine transform to points (…, 3)."""
    transform = np.asarray(transform, dtype=np.float64)
    return np.asarray(points) @ transform[:3, :3].T + transform[:3, 3]


def transform_poses(transform: np.ndarray, camera_to_world: np.ndarray) -> np.ndarray:
    """Map camera-to-world poses (…, 4, 4) through a similarity transform, keeping rotations orthonormal.

    The translation goes through the full transform; the rotation only through its rotation part,
    so a uniformly scaled frame stays a proper camera pose.
    """
    transform = np.asarray(transform, dtype=np.float64)
    scale = np.cbrt(np.linalg.det(transform[:3, :3]))
    rotation = transform[:3, :3] / scale
    poses = np.array(camera_to_world, dtype=np.float64, copy=True)
    poses[..., :3, :3] = rotation @ poses[..., :3, :3]
    poses[..., :3, 3] = transform_points(transform, poses[..., :3, 3])
    return poses


def check_rotation(matrix: np.ndarray, tolerance: float = 1e-3) -> str | None:
    """Why a 3x3 matrix is not a proper rotation, or None when it is."""
    matrix = np.asarray(matrix, dtype=np.float64)
    if not np.all(np.isfinite(matrix)):
        return "contains NaN or infinite values"
    orthogonality = np.abs(matrix @ matrix.T - np.eye(3)).max()
    if orthogonality > tolerance:
        return f"is not orthonormal (|R R^T - I| = {orthogonality:.3g})"
    if np.linalg.det(matrix) < 0:
        return "is a reflection (det < 0)"
    return None


def check_view(camera_to_world, intrinsics, width, height) -> tuple[np.ndarray, np.ndarray, int, int]:
    """A view to render, checked: camera_to_world a rigid 4x4 transform (a proper rotation, last row
    0 0 0 1), intrinsics finite (fx, fy, cx, cy) with fx, fy > 0, the image size positive integers.
    Returns them as float64 arrays and ints; ValueError naming what is wrong."""
    pose = np.asarray(camera_to_world, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise ValueError(f"camera_to_world must be a finite 4x4 matrix, got shape {pose.shape}")
    problem = check_rotation(pose[:3, :3])
    if problem is not None:
        raise ValueError(f"camera_to_world must be a rigid transform: its rotation {problem}")
    if np.abs(pose[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        raise ValueError(f"camera_to_world must be a rigid transform: its last row is {pose[3].tolist()}, not [0, 0, 0, 1]")
    k = np.asarray(intrinsics, dtype=np.float64).reshape(-1)
    if k.shape != (4,) or not np.all(np.isfinite(k)) or k[0] <= 0 or k[1] <= 0:
        raise ValueError(f"intrinsics must be finite (fx, fy, cx, cy) with fx, fy > 0, got {k.tolist()}")
    try:
        size = int(width), int(height)
        whole = size[0] == width and size[1] == height
    except (TypeError, ValueError):
        size, whole = (0, 0), False
    if not whole or min(size) <= 0:
        raise ValueError(f"image size must be positive integers, got {width!r} x {height!r}")
    return pose, k, size[0], size[1]


def axes_meeting_point(camera_to_world: np.ndarray) -> np.ndarray | None:
    """The point closest (least squares) to every camera's optical axis, in front of the cameras;
    None when the axes are (nearly) parallel or meet behind the cameras."""
    centres = camera_to_world[:, :3, 3]
    axes = camera_to_world[:, :3, 2]
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]  # I - d d^T per camera
    a = projectors.sum(0)
    b = np.einsum("nij,nj->i", projectors, centres)
    eigenvalues = np.linalg.eigvalsh(a)
    if eigenvalues[0] > 1e-2 * eigenvalues[-1]:
        point = np.linalg.solve(a, b)
        if np.median(np.einsum("ni,ni->n", point[None] - centres, axes)) > 0:
            return point
    return None


def focus_point(camera_to_world: np.ndarray) -> np.ndarray:
    """What the cameras look at: where their optical axes meet (`axes_meeting_point`).

    When the axes are (nearly) parallel, as in a forward-facing capture, there is no such point;
    then it is the mean camera centre moved forward along the mean viewing direction by the spread
    of the camera centres (at least 1 world unit).
    """
    point = axes_meeting_point(camera_to_world)
    if point is not None:
        return point
    centres = camera_to_world[:, :3, 3]
    axes = camera_to_world[:, :3, 2]
    spread = max(float(np.linalg.norm(centres - centres.mean(0), axis=1).max()), 1.0)
    direction = axes.mean(0) / max(np.linalg.norm(axes.mean(0)), 1e-9)
    return centres.mean(0) + spread * direction


SURROUND_MIN_ANGLE_DEG = 90.0


def cameras_surround(camera_to_world: np.ndarray, point: np.ndarray) -> bool:
    """Whether cameras see `point` from directions at least `SURROUND_MIN_ANGLE_DEG` apart: they
    stand round it (an orbit, a walk round an object, a ring looking down at a table), not all on
    one side of it (a forward-facing capture: the fern's 20 views span 18 deg)."""
    directions = camera_to_world[:, :3, 3] - point
    directions /= np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-12)
    return bool(np.min(directions @ directions.T) <= np.cos(np.radians(SURROUND_MIN_ANGLE_DEG)))


def natural_order(names: list[str]) -> list[int]:
    """Indices that sort `names` as a person would: frame_2 before frame_10."""
    def key(name: str):
        return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name) if part]
    return sorted(range(len(names)), key=lambda index: key(names[index]))


SEQUENCE_MIN_FRACTION = 0.5


def sequence_fraction(names: list[str], camera_to_world: np.ndarray) -> float:
    """The fraction of images whose nearest camera (centre to centre) is the image just before or
    just after it in name order (`natural_order`).

    Frames of a video or of a walk with a camera are named in the order they were taken and each
    stands next to the frames beside it: the fox 0.94, the beer video's frames 0.82. In a set of
    photos taken from here and there it is near chance (2 / count): the bottle's 0.04, the fern's
    0.30. Fewer than three images make no sequence (0).
    """
    count = len(names)
    if count < 3:
        return 0.0
    order = natural_order(names)
    centres = np.asarray(camera_to_world, dtype=np.float64)[order, :3, 3]
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(distance, np.inf)
    nearest = distance.argmin(axis=1)
    return float(np.mean(np.abs(nearest - np.arange(count)) == 1))


def images_form_a_sequence(names: list[str], camera_to_world: np.ndarray) -> bool:
    """Whether the images are a sequence (`sequence_fraction` >= SEQUENCE_MIN_FRACTION)."""
    return sequence_fraction(names, camera_to_world) >= SEQUENCE_MIN_FRACTION

"""Scene bounds: a (2, 3) world box [[xmin, ymin, zmin], [xmax, ymax, zmax]] the scene lives in.

First that applies (`resolve_bounds`): `poses.bounds` from the config; the capture's own
`ground_truth/scene.json` `bounds_world` (orchard); sparse points (1-99 % percentiles + 5 %
margin); the camera frusta (`bounds_from_frusta`). The labels stage may later replace estimated
bounds with the masks' visual hull (`srfpipe/segment/hull.py`).

Each estimator is one small function of plain arrays returning a (2, 3) box, so that another
source of bounds is one more function and one more branch in `resolve_bounds`.
"""

from __future__ import annotations

import numpy as np

from srfpipe import cameras
from srfpipe.poses.capture import Capture

POINT_PERCENTILES = (1.0, 99.0)
POINT_MARGIN = 0.05  # fraction of the percentile box added on every side
MIN_POINTS_FOR_BOUNDS = 20


def check_bounds(value, where: str) -> np.ndarray:
    """`value` as a finite (2, 3) float64 box with min < max on every axis; error naming `where`."""
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


def bounds_from_frusta(
    camera_to_world: np.ndarray, intrinsics: np.ndarray, image_size: np.ndarray,
    visible_fraction: float = 0.9, resolution: int = 40,
) -> np.ndarray:
    """(2, 3) box of the region (nearly) every camera sees, for captures without sparse points.

    Heuristic: take the cameras' focus point (`cameras.focus_point`) and a cube around it whose half-size
    is the median camera distance to it; sample the cube on a grid and keep the points that
    project inside the image, in front of the camera, for at least `visible_fraction` of the
    cameras (the intersection of the frusta, tolerant to a few stray views). For cameras on a ring
    around an object this is the object's neighbourhood; the box is the kept points' extent plus
    one grid cell. When fewer than 8 points are seen by enough cameras, the box is the focus
    point +- half the median camera distance.
    """
    focus = cameras.focus_point(camera_to_world)
    radius = float(np.median(np.linalg.norm(camera_to_world[:, :3, 3] - focus, axis=1)))
    radius = max(radius, 1e-6)
    ticks = np.linspace(-radius, radius, resolution)
    grid = np.stack(np.meshgrid(ticks, ticks, ticks, indexing="ij"), -1).reshape(-1, 3) + focus
    seen = np.zeros(len(grid), dtype=np.int32)
    for pose, k, (width, height) in zip(camera_to_world, intrinsics, image_size):
        seen += cameras.in_view(grid, pose, k, width, height)
    kept = grid[seen >= visible_fraction * len(camera_to_world)]
    if len(kept) < 8:
        return np.stack([focus - radius / 2, focus + radius / 2])
    cell = ticks[1] - ticks[0]
    return np.stack([kept.min(0) - cell, kept.max(0) + cell])


def near_cameras(box: np.ndarray, camera_to_world: np.ndarray) -> np.ndarray:
    """`box` clipped to the cube round the cameras' focus point (`cameras.focus_point`) whose half-size is
    the cameras' median distance to it, when the cameras surround that point.

    Inward-facing captures: the subject lies nearer the point the cameras look at than the
    cameras stand; the sparse points beyond (the ground or the room seen past the subject) are
    background, held by the contracted shell. Unchanged when the cameras do not surround their
    focus point, or when the clipped box would not hold it.
    """
    focus = cameras.focus_point(camera_to_world)
    if not cameras.cameras_surround(camera_to_world, focus):
        return box
    radius = float(np.median(np.linalg.norm(camera_to_world[:, :3, 3] - focus, axis=1)))
    clipped = np.stack([np.maximum(box[0], focus - radius), np.minimum(box[1], focus + radius)])
    if np.any(clipped[1] <= clipped[0]) or np.any(focus < clipped[0]) or np.any(focus > clipped[1]):
        return box
    return clipped


def resolve_bounds(capture: Capture, camera_to_world: np.ndarray, points: np.ndarray | None,
                   override, points_box: str = "all") -> tuple[np.ndarray, str]:
    """Scene bounds and where they came from: config | ground_truth | points | frusta.
    `points_box`: all = the sparse points' box; near_cameras = that box `near_cameras`."""
    if override is not None:
        return check_bounds(override, "poses.bounds"), "config"
    if capture.ground_truth_bounds is not None:
        return capture.ground_truth_bounds, "ground_truth"
    if points is not None and len(points) >= MIN_POINTS_FOR_BOUNDS:
        box = bounds_from_points(points)
        return (near_cameras(box, camera_to_world) if points_box == "near_cameras" else box), "points"
    return bounds_from_frusta(camera_to_world, capture.intrinsics, capture.image_size), "frusta"

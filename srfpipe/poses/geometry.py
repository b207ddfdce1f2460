"""Geometry a radiance field cannot be trained from, refused at pose import with the frame and the
reason: a lens that maps most of its pixels outside the image, a focal length or principal point
no real camera has, cameras that all sit at one point (no parallax, so no depth), scene bounds that
are degenerate, and cameras that see none of the scene's bounds.

Each check is a function of plain arrays (`validate_capture` and the poses stage call them); the
thresholds are far from any real capture's values, so a capture that trips one is broken, not unusual.
"""

from __future__ import annotations

import logging

import numpy as np

from srfpipe import cameras

log = logging.getLogger(__name__)

MIN_VALID_LENS_FRACTION = 0.5  # of a frame's pixels that its lens model must map inside the frame
MIN_FOCAL_PER_SIDE = 0.05  # fx, fy >= this x the image's larger side: a field of view under 170 degrees
MAX_FOCAL_PER_SIDE = 1e4  # ... and <= this: over 0.006 degrees
PRINCIPAL_POINT_MARGIN = 0.5  # cx, cy within [-m, 1 + m] x the image side
MIN_CAMERA_SPREAD = 1e-6  # camera centres closer than this x their distance from the origin (or 1): one point
MIN_SEEING_FRACTION = 0.5  # of the cameras that must see some of the scene bounds


def lens_valid_fraction(intrinsics, distortion, size, samples: int = 33) -> float:
    """The share of a frame's pinhole pixel grid that the OpenCV lens (k1, k2, p1, p2) maps inside
    the frame where its radial profile still grows with the radius: the pixels undistortion can fill."""
    fx, fy, cx, cy = (float(c) for c in intrinsics)
    k1, k2, p1, p2 = (float(c) for c in distortion)
    width, height = (float(s) for s in size)
    u, v = np.meshgrid(np.linspace(0.5, width - 0.5, samples), np.linspace(0.5, height - 0.5, samples))
    x, y = (u - cx) / fx, (v - cy) / fy
    r2 = x * x + y * y
    with np.errstate(over="ignore", invalid="ignore"):
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        ud, vd = fx * xd + cx, fy * yd + cy
        growing = 1.0 + 3 * k1 * r2 + 5 * k2 * r2 * r2 > 0  # d(r radial)/dr > 0: no fold
        inside = (ud >= 0) & (ud <= width) & (vd >= 0) & (vd <= height)
    return float(np.mean(inside & growing & np.isfinite(ud) & np.isfinite(vd)))


def check_camera_model(intrinsics, distortion, size, where: str) -> None:
    """Raise ValueError (naming `where`) for a focal length, principal point or lens no camera has."""
    fx, fy, cx, cy = (float(c) for c in intrinsics)
    width, height = (float(s) for s in size)
    side = max(width, height)
    for name, focal in (("fx", fx), ("fy", fy)):
        if not MIN_FOCAL_PER_SIDE * side <= focal <= MAX_FOCAL_PER_SIDE * side:
            raise ValueError(f"{where}: focal length {name} = {focal:.6g} px for a {width:g} x {height:g} image "
                             f"(a field of view over 170 degrees or under 0.006: expected {MIN_FOCAL_PER_SIDE:g} "
                             f"to {MAX_FOCAL_PER_SIDE:g} x the image side; intrinsics in another image's pixels?)")
    m = PRINCIPAL_POINT_MARGIN
    if not (-m * width <= cx <= (1 + m) * width and -m * height <= cy <= (1 + m) * height):
        raise ValueError(f"{where}: principal point ({cx:.6g}, {cy:.6g}) lies far outside the {width:g} x "
                         f"{height:g} image (intrinsics in another image's pixels?)")
    if np.any(np.asarray(distortion, dtype=np.float64) != 0):
        valid = lens_valid_fraction(intrinsics, distortion, size)
        if valid < MIN_VALID_LENS_FRACTION:
            raise ValueError(f"{where}: distortion {np.asarray(distortion).tolist()} maps {100 * (1 - valid):.0f} % "
                             f"of the image's pixels outside it (or folds the lens over itself): undistorted, the "
                             f"frame would be mostly empty; check the coefficients' order and units (k1, k2, p1, p2)")


def check_camera_spread(camera_to_world: np.ndarray, source) -> None:
    """Raise ValueError when every camera sits at one point: without parallax no depth can be found."""
    centres = np.asarray(camera_to_world, dtype=np.float64)[:, :3, 3]
    if len(centres) < 2:
        return
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
    scale = max(float(np.linalg.norm(centres.mean(0))), 1.0)
    if spread < MIN_CAMERA_SPREAD * scale:
        raise ValueError(f"{source}: all {len(centres)} cameras sit at one point ({centres[0].tolist()}, spread "
                         f"{spread:.3g}): without parallax a radiance field cannot recover depth (a panorama, or "
                         f"poses that were not written)")


def check_scene_bounds(bounds, source, bounds_source: str) -> None:
    """Raise ValueError for bounds that are non-finite or thinner than a millionth of their position."""
    bounds = np.asarray(bounds, dtype=np.float64)
    if bounds.shape != (2, 3) or not np.all(np.isfinite(bounds)):
        raise ValueError(f"{source}: scene bounds ({bounds_source}) are not a finite box: {bounds.tolist()}")
    extent = bounds[1] - bounds[0]
    scale = max(float(np.abs(bounds).max()), 1e-12)
    if np.any(extent <= 1e-6 * scale):
        raise ValueError(f"{source}: scene bounds ({bounds_source}) {bounds.tolist()} are degenerate (extent "
                         f"{extent.tolist()}); set poses.bounds, or check the poses")


def cameras_seeing(camera_to_world: np.ndarray, intrinsics: np.ndarray, image_size: np.ndarray,
                   bounds, samples: int = 8) -> np.ndarray:
    """Per camera: whether any of a grid of points in the bounds projects into its image, in front of it."""
    bounds = np.asarray(bounds, dtype=np.float64)
    ticks = [np.linspace(bounds[0, a], bounds[1, a], samples) for a in range(3)]
    grid = np.stack(np.meshgrid(*ticks, indexing="ij"), -1).reshape(-1, 3)
    seeing = np.zeros(len(camera_to_world), dtype=bool)
    for i, (pose, k, (width, height)) in enumerate(zip(camera_to_world, intrinsics, image_size)):
        seeing[i] = bool(cameras.in_view(grid, pose, k, width, height).any())
    return seeing


def check_cameras_see_bounds(camera_to_world, intrinsics, image_size, bounds, names, source,
                             bounds_source: str) -> list[str]:
    """Raise ValueError when most cameras see none of the bounds (poses that face away from the
    scene, a bounds box in other units); return the names of the few that do not (a warning)."""
    seeing = cameras_seeing(camera_to_world, intrinsics, image_size, bounds)
    blind = [str(n) for n, s in zip(names, seeing) if not s]
    if seeing.mean() < MIN_SEEING_FRACTION:
        raise ValueError(f"{source}: {len(blind)} of {len(seeing)} cameras see none of the scene bounds "
                         f"({bounds_source}: {np.asarray(bounds).round(6).tolist()}), e.g. {', '.join(blind[:5])}: "
                         f"the poses face away from the scene, or the bounds are in other units")
    if blind:
        log.warning("%s: %d cameras see none of the scene bounds (%s): %s", source, len(blind), bounds_source,
                    ", ".join(blind[:10]))
    return blind

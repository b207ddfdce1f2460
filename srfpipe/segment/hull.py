"""Scene bounds from the masks: the visual hull of the labelled classes (Laurentini 1994).

The labels stage knows, per frame, which pixels show a class of the scene. A point of space that
(nearly) every camera framing it sees on a labelled pixel belongs to the hull; the box around the
hull is what the field has to model in detail. Everything else (a room, a table that runs out of
view) is left to the contracted shell. Cameras far from a small object make the frusta a poor
guide (their intersection is many times the object), which is where the hull matters most.
"""

from __future__ import annotations

import logging
from typing import Callable, Iterable, Sequence

import numpy as np

from srfpipe import cameras

log = logging.getLogger(__name__)

HULL_RESOLUTION = 96  # grid points along the longest axis of the searched box
# A point stays when this fraction of the views framing it see a label there: a thin part (a
# stalk, a twig) drops out of some views' masks (a soft mask thresholded, a segmenter's miss), and
# a box that cuts it off cuts off what it carries.
HULL_AGREEMENT = 0.65  # tolerates a part missing from a third of the views framing it
# A pixel marks the hull where any class's probability reaches this, not the label threshold: a stalk
# under a pixel wide keeps only part of a pixel's probability once the masks are area-downscaled.
HULL_MIN_PROBABILITY = 0.1
HULL_MARGIN = 0.05  # fraction of the hull's extent added on every side of its box
SEARCH_GROWTH = 0.25  # the searched box: the poses' bounds grown by this fraction per side
CARVES = 2  # the poses' box, then the first hull's box: each at HULL_RESOLUTION
MASK_DILATION_PX = 2  # tolerance for mask edges and sub-pixel pose error
# A point framed by fewer views than this fraction of the cameras is not carved, it is dropped:
# with two or three views a whole cone of space behind the object agrees with every mask (on the
# built-in plant, 18 narrow views: a box 71x the object's with 2 views, 1.5x with half of them).
MIN_VIEW_FRACTION = 0.5


def visual_hull(camera_to_world: np.ndarray, intrinsics: np.ndarray, masks: Iterable[np.ndarray],
                search_box: np.ndarray, resolution: int = HULL_RESOLUTION,
                agreement: float = HULL_AGREEMENT, min_views: int | None = None,
                tolerance_px: float = MASK_DILATION_PX) -> tuple[np.ndarray, float]:
    """Grid points of `search_box` carved by foreground masks, and the grid spacing.

    camera_to_world (N, 4, 4) and intrinsics (N, 4) at the masks' resolution; `masks` yields N
    boolean (H, W) images (read one at a time). A view carves only the points inside its image
    and in front of it, so an object cut by the frame edge survives; `agreement` < 1 tolerates
    views whose mask missed part of the object; points framed by fewer than `min_views` cameras
    (default: MIN_VIEW_FRACTION of them) are dropped. Returns kept points (M, 3) and the spacing.

    A view marks a point when a masked pixel lies within the point's cell as that view sees it:
    the cell's half-diagonal projected at the point's depth, plus `tolerance_px` for mask edges
    and pose error. So a structure thinner than a cell (a stem a few pixels wide) keeps its cells
    in every view that masks it, where testing the pixel under the cell centre would miss it.
    """
    import cv2

    camera_to_world = np.asarray(camera_to_world)
    if min_views is None:
        min_views = max(2, int(np.ceil(MIN_VIEW_FRACTION * len(camera_to_world))))
    search_box = np.asarray(search_box, dtype=np.float64)
    spacing = float((search_box[1] - search_box[0]).max()) / (resolution - 1)
    half_diagonal = 0.5 * np.sqrt(3.0) * spacing
    ticks = [np.arange(lo + spacing / 2, hi, spacing) for lo, hi in zip(*search_box)]
    grid = np.stack(np.meshgrid(*ticks, indexing="ij"), -1).reshape(-1, 3)
    seen = np.zeros(len(grid), dtype=np.int32)
    labelled = np.zeros(len(grid), dtype=np.int32)
    for pose, k, mask in zip(camera_to_world, intrinsics, masks):
        height, width = mask.shape
        uv, depth = cameras.project_points(grid, pose, k)
        with np.errstate(invalid="ignore"):
            inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)
        index = np.flatnonzero(inside)
        seen[index] += 1
        if not mask.any():
            continue
        # pixels to the nearest masked pixel (0 on the mask)
        distance = cv2.distanceTransform((~mask.astype(bool)).astype(np.uint8), cv2.DIST_L2, 5)
        reach = tolerance_px + max(float(k[0]), float(k[1])) * half_diagonal / depth[index]
        near = distance[uv[index, 1].astype(np.int64), uv[index, 0].astype(np.int64)] <= reach
        labelled[index[near]] += 1
    kept = (seen >= min_views) & (labelled >= agreement * seen)
    return grid[kept], spacing


def hull_box(points: np.ndarray, spacing: float, margin: float = HULL_MARGIN) -> np.ndarray:
    """(2, 3) box around hull points (cell centres): their cells' extent plus `margin` per side."""
    low, high = points.min(0), points.max(0)
    pad = 0.5 * spacing + margin * (high - low)
    return np.stack([low - pad, high + pad])


def grown(box: np.ndarray, fraction: float) -> np.ndarray:
    box = np.asarray(box, dtype=np.float64)
    pad = fraction * (box[1] - box[0])
    return np.stack([box[0] - pad, box[1] + pad])


def bounds_from_masks(camera_to_world: np.ndarray, intrinsics: np.ndarray,
                      masks: Callable[[], Iterable[np.ndarray]] | Sequence[np.ndarray],
                      poses_bounds: np.ndarray) -> tuple[np.ndarray, dict] | None:
    """The hull's box and a record of how it was found, or None when the masks carve nothing.

    The search covers the poses' bounds grown by SEARCH_GROWTH per side, so a hull can be found
    anywhere the earlier bounds roughly pointed to; a second carve at the same resolution over
    that first box (grown by one of its cells) refines it, so the cell-sized tolerance of the
    carve stays small against the object. `masks` is a sequence or a function that yields them
    afresh (one image in memory at a time), since each carve reads them once. The record says
    how tight the result is: the hull's share of its box and the box's volume relative to the
    poses' bounds.
    """
    read = masks if callable(masks) else (lambda: masks)
    search = grown(poses_bounds, SEARCH_GROWTH)
    box = spacing = points = None
    for _ in range(CARVES):
        points, spacing = visual_hull(camera_to_world, intrinsics, read(), search)
        if len(points) < 8:
            if box is None:
                log.warning("the masks carve no visual hull (%d grid points kept); keeping the poses' bounds",
                            len(points))
                return None
            break  # the finer carve lost the object (views disagree below a coarse cell): keep the coarse box
        box = hull_box(points, spacing)
        search = np.stack([box[0] - spacing, box[1] + spacing])
    box_volume = float(np.prod(box[1] - box[0]))
    record = {
        "hull_points": int(len(points)),
        "hull_fill": float(len(points) * spacing**3 / box_volume),
        "volume_vs_poses_bounds": box_volume / float(np.prod(np.asarray(poses_bounds)[1] - np.asarray(poses_bounds)[0])),
        "grid_spacing": spacing,
        "agreement": HULL_AGREEMENT,
        "mask_dilation_px": MASK_DILATION_PX,
    }
    return box, record

"""`OccupancyCache`: the distilled field in memory, answering the simulator's queries fast.

Every query takes world points (..., 3) (float32 or float64, metres for the orchard) and is
batched: one parallel pass over the points (numba). Semantics of space:

* Points outside the grid box are **free space**: occupancy 0, density 0, probability 0, no class;
  `distance` continues beyond the box as d(q) + |p - q| with q the nearest point of the box.
* A NaN coordinate raises ValueError (a simulator that produced NaN has a bug to surface).
* Huge and infinite coordinates are far free space: `distance` is d(q) + |p - q| (inf for an
  infinite one) and its gradient the unit direction from the box, computed without overflow.
* Nearest-voxel queries (`occupancy`, `class_occupancy`) read the voxel containing the point;
  `density`, `semantic` and `distance` interpolate trilinearly between voxel centres.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from srfpipe.occupancy import kernels
from srfpipe.occupancy.distill import STAGE, pyramid_shapes
from srfpipe.occupancy.grid import VoxelGrid, morton_decode


def _points(points) -> tuple[np.ndarray, tuple]:
    """(..., 3) -> contiguous (M, 3) float32/float64 and the batch shape."""
    array = np.asarray(points)
    if array.shape[-1:] != (3,):
        raise ValueError(f"points must have shape (..., 3), got {array.shape}")
    if array.dtype not in (np.float32, np.float64):
        array = array.astype(np.float64)
    return np.ascontiguousarray(array.reshape(-1, 3)), array.shape[:-1]


def _check_nan(bad: int, total: int, what: str = "points") -> None:
    if bad:
        raise ValueError(f"{bad} of {total} {what} have NaN coordinates")


def check_cache(path, group, attrs: dict) -> VoxelGrid:
    """The grid of an opened occupancy.zarr, after checking what its readers (`OccupancyCache.load`,
    the simulator package) take from it: the attributes `grid`, `classes`, `distance` and the voxel
    arrays of the grid's shape, one channel per class or distance class. ValueError naming the file."""
    def refuse(problem: str) -> ValueError:
        return ValueError(f"{path}: {problem}; the artifact is damaged: delete it and re-run its stage '{STAGE}'")

    try:
        grid = VoxelGrid.from_attrs(attrs["grid"])
        if len(grid.origin) != 3 or len(grid.shape) != 3 or not grid.voxel_size > 0 or min(grid.shape) < 1:
            raise ValueError("origin, voxel_size or shape out of range")
    except (KeyError, TypeError, ValueError) as exc:
        raise refuse(f"attribute grid is missing or invalid ({type(exc).__name__}: {exc})") from None
    classes = attrs.get("classes")
    if not isinstance(classes, list) or not all(isinstance(c, str) for c in classes):
        raise refuse("attribute classes is missing or not a list of names")
    distance = attrs.get("distance")
    if (not isinstance(distance, dict) or not isinstance(distance.get("classes"), list)
            or not isinstance(distance.get("roles"), list) or len(distance["classes"]) != len(distance["roles"])
            or not set(distance["classes"]) <= set(classes)):
        raise refuse(f"attribute distance must name classes of {classes} and one role each, got {distance!r}")
    shape = tuple(grid.shape)
    for key, channels in (("occupancy", None), ("density", None), ("probability", len(classes)),
                          ("class_occupancy", len(classes)), ("distance", len(distance["classes"]))):
        if key not in group:
            raise refuse(f"missing array '{key}'")
        want = shape if channels is None else (channels, *shape)
        if tuple(group[key].shape) != want:
            raise refuse(f"array '{key}' has shape {tuple(group[key].shape)}, the grid and classes need {want}")
    return grid


class OccupancyCache:
    """The arrays of one `occupancy.zarr`, loaded into memory. Build with `OccupancyCache.load`."""

    def __init__(self, grid: VoxelGrid, classes: list[str], occupancy: np.ndarray, density: np.ndarray,
                 probability: np.ndarray, class_occupancy: np.ndarray, distance: dict[str, np.ndarray],
                 octree_levels: list[np.ndarray], leaf_class: np.ndarray, attrs: dict | None = None):
        self.grid = grid
        self.classes = list(classes)
        self.attrs = attrs or {}
        self.path: Path | None = None  # the occupancy.zarr it was loaded from
        self._occupancy = np.ascontiguousarray(occupancy, dtype=np.uint8)
        self._density = np.ascontiguousarray(density, dtype=np.float32)
        # channels last: the 8 corners of a trilinear lookup read C contiguous bytes each
        self._probability = np.ascontiguousarray(np.moveaxis(probability, 0, -1), dtype=np.uint8)
        self._class_occupancy = np.ascontiguousarray(np.moveaxis(class_occupancy, 0, -1), dtype=np.uint8)
        self._distance = {name: np.ascontiguousarray(d, dtype=np.float32) for name, d in distance.items()}
        self._origin = np.asarray(grid.origin, dtype=np.float64)
        self._inv_v = 1.0 / grid.voxel_size
        self._leaf_class = np.ascontiguousarray(leaf_class, dtype=np.int8)
        self._levels_dense = self._dense_levels(octree_levels)
        self._levels_flat = np.concatenate([lv.reshape(-1) for lv in self._levels_dense])
        self._level_shapes = np.array([lv.shape for lv in self._levels_dense], dtype=np.int64)
        self._level_offsets = np.concatenate([[0], np.cumsum([lv.size for lv in self._levels_dense])[:-1]]).astype(np.int64)

    # ---------------------------------------------------------------------------------------------
    # loading

    @classmethod
    def load(cls, path: str | Path) -> "OccupancyCache":
        """Read an occupancy.zarr written by `srfpipe distill` (checked) into memory."""
        from srfpipe.artifacts import meta, open_artifact

        group = open_artifact(path, stage=STAGE)
        attrs = meta(group)
        grid = check_cache(path, group, attrs)
        classes = list(attrs["classes"])
        distance = group["distance"][...]
        distance_fields = {name: distance[i] for i, name in enumerate(attrs["distance"]["classes"])}
        octree = group["octree"]
        depth = int(octree.attrs["octree"]["depth"])
        codes = [octree[f"level_{level:02d}"][...] for level in range(depth + 1)]
        leaves = codes[-1]
        leaf_class = np.full(grid.shape, -1, dtype=np.int8)
        if len(leaves):
            xyz = morton_decode(leaves)
            leaf_class[xyz[:, 2], xyz[:, 1], xyz[:, 0]] = octree["leaf_class"][...]
        cache = cls(grid, classes, group["occupancy"][...], group["density"][...], group["probability"][...],
                    group["class_occupancy"][...], distance_fields, codes, leaf_class, attrs)
        cache.path = Path(path)
        return cache

    def _dense_levels(self, octree_levels: list[np.ndarray]) -> list[np.ndarray]:
        """Octree levels (root first, Morton codes) -> dense uint8 grids, finest (the voxels) first."""
        shapes = pyramid_shapes(self.grid.shape)
        if len(octree_levels) != len(shapes):
            raise ValueError(f"octree has {len(octree_levels)} levels, the grid {self.grid.shape} needs {len(shapes)}")
        dense = []
        for k, shape in enumerate(shapes):
            level = np.zeros(shape, dtype=np.uint8)
            codes = octree_levels[len(shapes) - 1 - k]
            if len(codes):
                xyz = morton_decode(codes)
                level[xyz[:, 2], xyz[:, 1], xyz[:, 0]] = 1
            dense.append(level)
        if not np.array_equal(dense[0], self._occupancy):
            raise ValueError("octree leaves do not match the occupancy grid")
        return dense

    # ---------------------------------------------------------------------------------------------
    # properties

    @property
    def voxel_size(self) -> float:
        return self.grid.voxel_size

    @property
    def bounds_world(self) -> np.ndarray:
        return self.grid.bounds_world

    @property
    def n_levels(self) -> int:
        return len(self._levels_dense)

    def distance_classes(self) -> list[str]:
        return list(self._distance)

    def distance_field(self, class_name: str) -> np.ndarray:
        """The (z, y, x) float32 signed distance grid of `class_name` (world units, negative inside,
        clipped at the truncation distance): what `distance` samples, for callers with their own
        sampler (srfpipe.sim.runtime.DistanceFields). Not a copy: do not write to it."""
        if class_name not in self._distance:
            raise ValueError(f"no distance field for {class_name!r}; the cache has {list(self._distance)} "
                             "(occupancy.avoid / occupancy.reach)")
        return self._distance[class_name]

    def class_index(self, name: str) -> int:
        if name not in self.classes:
            raise ValueError(f"unknown class {name!r}; the cache has {self.classes}")
        return self.classes.index(name)

    # ---------------------------------------------------------------------------------------------
    # queries

    def occupancy(self, points, level: int = 0) -> np.ndarray:
        """Occupied (bool) at each point: the voxel containing it (level 0), or the octree cell of
        2^level voxels containing it (coarse-to-fine: a free coarse cell is free all through)."""
        pts, batch = _points(points)
        if not 0 <= level < self.n_levels:
            raise ValueError(f"level must be in [0, {self.n_levels}), got {level}")
        out = np.empty(len(pts), dtype=np.uint8)
        bad = kernels.nearest_u8(pts, self._levels_dense[level], self._origin, self._inv_v / (1 << level), out)
        _check_nan(bad, len(pts))
        return out.view(bool).reshape(batch)

    def class_occupancy(self, points, class_name: str | None = None) -> np.ndarray:
        """Per-class occupancy (bool) of the voxel containing each point: (..., C), or (...) for one class."""
        pts, batch = _points(points)
        out = np.empty((len(pts), len(self.classes)), dtype=np.uint8)
        _check_nan(kernels.nearest_channels_u8(pts, self._class_occupancy, self._origin, self._inv_v, out), len(pts))
        out = out.view(bool).reshape(batch + (len(self.classes),))
        return out if class_name is None else out[..., self.class_index(class_name)]

    def density(self, points) -> np.ndarray:
        """sigma (per world unit), trilinear between voxel centres: (...) float32."""
        pts, batch = _points(points)
        out = np.empty(len(pts), dtype=np.float32)
        _check_nan(kernels.trilinear_f32(pts, self._density, self._origin, self._inv_v, out), len(pts))
        return out.reshape(batch)

    def semantic(self, points) -> np.ndarray:
        """Per-class probabilities sigma(s(x)), trilinear between voxel centres: (..., C) float32."""
        pts, batch = _points(points)
        out = np.empty((len(pts), len(self.classes)), dtype=np.float32)
        _check_nan(kernels.trilinear_channels_u8(pts, self._probability, self._origin, self._inv_v,
                                                 np.float32(1 / 255), out), len(pts))
        return out.reshape(batch + (len(self.classes),))

    def distance(self, points, class_name: str) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance to the surface of `class_name` (world units, negative inside) and its
        gradient (..., 3), which points away from the surface: the contact signal (c_t, grad d).

        Distances are exact to about half a voxel near surfaces and clipped at the truncation
        distance stored in the attributes (the gradient is 0 where the field is clipped).
        """
        if class_name not in self._distance:
            raise ValueError(f"no distance field for {class_name!r}; the cache has {list(self._distance)} "
                             "(occupancy.avoid / occupancy.reach)")
        pts, batch = _points(points)
        d = np.empty(len(pts), dtype=np.float64)
        grad = np.empty((len(pts), 3), dtype=np.float64)
        bad = kernels.distance_gradient(pts, self._distance[class_name], self._origin, self.grid.voxel_size, d, grad)
        _check_nan(bad, len(pts))
        far = ~np.isfinite(grad).all(axis=1) | ~np.isfinite(d)
        if far.any():
            self._far_distance(class_name, pts[far], d, grad, far)
        return d.reshape(batch), grad.reshape(batch + (3,))

    def _far_distance(self, class_name: str, pts: np.ndarray, d: np.ndarray, grad: np.ndarray, rows: np.ndarray) -> None:
        """Distance and gradient of points so far out (huge or infinite coordinates) that the
        kernel's |p - q| overflowed: d(q) + |p - q| and its gradient,
        with q the nearest point of the box, computed scaled (infinite axes dominate)."""
        lo, hi = self.bounds_world
        pts = pts.astype(np.float64)
        inside = np.clip(pts, lo, hi)
        with np.errstate(invalid="ignore", over="ignore"):
            diff = pts - inside
            infinite = np.isinf(diff)
            diff = np.where(infinite.any(axis=1, keepdims=True), np.where(infinite, np.sign(diff), 0.0), diff)
            scale = np.max(np.abs(diff), axis=1, keepdims=True)
            unit = diff / scale
            norm = np.linalg.norm(unit, axis=1, keepdims=True)
        edge_d = np.empty(len(pts), dtype=np.float64)
        edge_g = np.empty((len(pts), 3), dtype=np.float64)
        kernels.distance_gradient(np.ascontiguousarray(inside), self._distance[class_name], self._origin,
                                  self.grid.voxel_size, edge_d, edge_g)
        with np.errstate(over="ignore"):
            d[rows] = edge_d + np.where(infinite.any(axis=1), np.inf, (scale * norm)[:, 0])
        # as the kernel: the normal from the box plus the gradient at q along the unclamped axes
        grad[rows] = unit / norm + np.where((pts < lo) | (pts > hi), 0.0, edge_g)

    def raycast(self, origins, directions, max_t=np.inf) -> tuple[np.ndarray, np.ndarray]:
        """First occupied voxel along each ray, through the octree.

        origins, directions (..., 3) (directions need not be unit); max_t scalar or (...) in world
        units. Returns t (...) the distance along the ray to the entry of the hit voxel (inf for
        a miss) and the hit class index (...) int (-1 for a miss or a voxel with no class).
        """
        o, batch = _points(origins)
        d, batch_d = _points(directions)
        if batch_d != batch:
            raise ValueError(f"origins {batch} and directions {batch_d} must have the same shape")
        o = o.astype(np.float64)
        norm = np.linalg.norm(d.astype(np.float64), axis=1, keepdims=True)
        if np.any(norm == 0):
            raise ValueError("ray directions must be non-zero")
        d = d / norm
        limit = np.ascontiguousarray(np.broadcast_to(np.asarray(max_t, dtype=np.float64), batch).reshape(-1))
        t = np.empty(len(o), dtype=np.float64)
        hit_class = np.empty(len(o), dtype=np.int8)
        bad = kernels.raycast(o, d, limit, self._levels_flat, self._level_offsets, self._level_shapes,
                              self._leaf_class, self._origin, self.grid.voxel_size, t, hit_class)
        _check_nan(bad, len(o), "rays")
        return t.reshape(batch), hit_class.astype(np.int64).reshape(batch)

    def occupied_cells(self, level: int = 0, class_name: str | None = None) -> tuple[np.ndarray, float]:
        """World centres (K, 3) of the occupied cells of a level and their edge length; with
        `class_name` (level 0 only) the voxels occupied by that class (e.g. apple targets)."""
        if class_name is not None:
            if level != 0:
                raise ValueError("per-class cells are available at level 0 only")
            occupied = self._class_occupancy[..., self.class_index(class_name)]
        else:
            occupied = self._levels_dense[level]
        kji = np.argwhere(occupied)
        size = self.grid.voxel_size * (1 << level)
        return self._origin + (kji[:, ::-1] + 0.5) * size, size

"""The voxel grid: an axis-aligned box of cubic voxels in world units, and its transforms.

Axis conventions (the same in every array of `occupancy.zarr`):

* Arrays are indexed ``[z, y, x]`` (OME-Zarr order: x is the fastest axis); per-class arrays put
  the class first, ``[c, z, y, x]``.
* *Grid coordinates* are continuous and ordered ``(x, y, z)`` like world points:
  ``g = (x_world - origin) / voxel_size``. Voxel ``(i, j, k)`` (x, y, z indices, stored at
  ``array[k, j, i]``) covers ``i <= g_x < i + 1`` and its centre is at ``g = i + 0.5``.
* ``grid_from_world`` is the 4x4 matrix of that map; ``world_from_grid`` its inverse.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class VoxelGrid:
    """A box of ``shape`` = (nz, ny, nx) cubic voxels of edge ``voxel_size``, min corner ``origin``."""

    origin: tuple[float, float, float]  # world xyz of the grid's min corner
    voxel_size: float
    shape: tuple[int, int, int]  # (nz, ny, nx), array order

    @classmethod
    def from_bounds(cls, bounds_world, voxel_size: float) -> "VoxelGrid":
        """The smallest grid of `voxel_size` voxels covering `bounds_world` ([[min xyz], [max xyz]]).

        The grid is centred on the bounds, so the extent left over is split evenly on both sides.
        """
        bounds = check_bounds(bounds_world)
        if not voxel_size > 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        counts_xyz = voxel_counts(bounds[1] - bounds[0], voxel_size)
        centre = bounds.mean(axis=0)
        origin = centre - counts_xyz * voxel_size / 2
        return cls(tuple(float(v) for v in origin), float(voxel_size), tuple(int(n) for n in counts_xyz[::-1]))

    @property
    def dims_xyz(self) -> np.ndarray:
        """Voxel counts in (x, y, z) order."""
        return np.array(self.shape[::-1], dtype=np.int64)

    @property
    def bounds_world(self) -> np.ndarray:
        """[[min xyz], [max xyz]] of the grid box (it covers the scene bounds, maybe a bit more)."""
        lo = np.asarray(self.origin)
        return np.stack([lo, lo + self.dims_xyz * self.voxel_size])

    @property
    def grid_from_world(self) -> np.ndarray:
        """4x4: world xyz -> continuous grid coordinates (x, y, z); voxel centres at index + 0.5."""
        m = np.eye(4)
        m[:3, :3] /= self.voxel_size
        m[:3, 3] = -np.asarray(self.origin) / self.voxel_size
        return m

    @property
    def world_from_grid(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] *= self.voxel_size
        m[:3, 3] = self.origin
        return m

    def world_to_grid(self, points_world) -> np.ndarray:
        return (np.asarray(points_world, dtype=np.float64) - np.asarray(self.origin)) / self.voxel_size

    def grid_to_world(self, points_grid) -> np.ndarray:
        return np.asarray(points_grid, dtype=np.float64) * self.voxel_size + np.asarray(self.origin)

    def voxel_centres(self, zyx_slices: tuple[slice, slice, slice]) -> np.ndarray:
        """World xyz of the centres of the voxels in a box of the array, shape (nz, ny, nx, 3)."""
        axes = []
        for axis_slice, n in zip(zyx_slices, self.shape):
            start, stop, _ = axis_slice.indices(n)
            axes.append(np.arange(start, stop) + 0.5)
        gz, gy, gx = np.meshgrid(*axes, indexing="ij")
        return self.grid_to_world(np.stack([gx, gy, gz], axis=-1))

    def bricks(self, brick: int):
        """Slices (z, y, x) of every brick of edge `brick` voxels (the last ones may be smaller)."""
        nz, ny, nx = self.shape
        for z0 in range(0, nz, brick):
            for y0 in range(0, ny, brick):
                for x0 in range(0, nx, brick):
                    yield (slice(z0, min(z0 + brick, nz)), slice(y0, min(y0 + brick, ny)),
                           slice(x0, min(x0 + brick, nx)))

    def n_bricks(self, brick: int) -> int:
        return math.prod(-(-n // brick) for n in self.shape)

    def to_attrs(self) -> dict:
        return {
            "origin": list(self.origin),
            "voxel_size": self.voxel_size,
            "shape": list(self.shape),
            "axes": ["z", "y", "x"],
            "grid_from_world": self.grid_from_world.tolist(),
            "world_from_grid": self.world_from_grid.tolist(),
            "grid_box_world": self.bounds_world.tolist(),
        }

    @classmethod
    def from_attrs(cls, attrs: dict) -> "VoxelGrid":
        return cls(tuple(float(v) for v in attrs["origin"]), float(attrs["voxel_size"]),
                   tuple(int(n) for n in attrs["shape"]))


def check_bounds(bounds_world) -> np.ndarray:
    """bounds_world as a (2, 3) float array, checked finite and non-empty along every axis."""
    bounds = np.asarray(bounds_world, dtype=np.float64)
    if bounds.shape != (2, 3) or not np.all(np.isfinite(bounds)):
        raise ValueError(f"bounds_world must be finite [[min xyz], [max xyz]], got {bounds.tolist()}")
    if np.any(bounds[1] - bounds[0] <= 0):
        raise ValueError(f"bounds_world {bounds.tolist()} is empty along some axis")
    return bounds


def voxel_counts(extent_xyz, voxel_size: float) -> np.ndarray:
    """Voxels (x, y, z) of edge `voxel_size` needed to cover `extent_xyz`, at least 1 per axis."""
    # 1e-9 keeps an extent that is an exact multiple of the voxel size from gaining a voxel
    return np.maximum(1, np.ceil(np.asarray(extent_xyz, dtype=np.float64) / voxel_size - 1e-9)).astype(np.int64)


def voxel_size_within(bounds_world, voxel_size: float, max_voxels: int) -> float:
    """The smallest voxel size >= `voxel_size` whose grid over `bounds_world` has <= `max_voxels` voxels.

    The voxel count only falls as the size grows, so a bisection (in log size) finds the counts of
    the finest grid that fits; the size returned is the smallest that gives those counts.
    """
    extent = np.diff(check_bounds(bounds_world), axis=0)[0]
    if max_voxels < 1:
        raise ValueError(f"max_voxels must be >= 1, got {max_voxels}")

    def fits(size: float) -> bool:
        return int(np.prod(voxel_counts(extent, size))) <= max_voxels

    if fits(voxel_size):
        return float(voxel_size)
    too_fine, coarse = float(voxel_size), float(extent.max())  # one voxel along the largest axis fits
    while coarse / too_fine - 1 > 1e-12:
        middle = math.sqrt(too_fine * coarse)
        too_fine, coarse = (too_fine, middle) if fits(middle) else (middle, coarse)
    counts = voxel_counts(extent, coarse)
    return float(max(voxel_size, (extent / counts).max()))


# Morton (Z-order) codes: 21 bits per axis interleaved into a uint64, x in bit 0, y in bit 1, z in bit 2.
_MORTON_MASKS = [(32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                 (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)]
MORTON_BITS = 21


def _spread_bits(v: np.ndarray) -> np.ndarray:
    v = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in _MORTON_MASKS:
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def _compact_bits(v: np.ndarray) -> np.ndarray:
    v = v.astype(np.uint64) & np.uint64(0x1249249249249249)
    v = (v ^ (v >> np.uint64(2))) & np.uint64(0x10C30C30C30C30C3)
    v = (v ^ (v >> np.uint64(4))) & np.uint64(0x100F00F00F00F00F)
    v = (v ^ (v >> np.uint64(8))) & np.uint64(0x1F0000FF0000FF)
    v = (v ^ (v >> np.uint64(16))) & np.uint64(0x1F00000000FFFF)
    v = (v ^ (v >> np.uint64(32))) & np.uint64(0x1FFFFF)
    return v


def morton_encode(ijk_xyz: np.ndarray) -> np.ndarray:
    """(M, 3) integer voxel indices in (x, y, z) order -> (M,) uint64 Morton codes."""
    ijk = np.asarray(ijk_xyz)
    if ijk.size and (ijk.min() < 0 or ijk.max() >= 1 << MORTON_BITS):
        raise ValueError(f"Morton codes hold indices in [0, 2^{MORTON_BITS}), got {ijk.min()}..{ijk.max()}")
    return _spread_bits(ijk[:, 0]) | (_spread_bits(ijk[:, 1]) << np.uint64(1)) | (_spread_bits(ijk[:, 2]) << np.uint64(2))


def morton_decode(codes: np.ndarray) -> np.ndarray:
    """(M,) uint64 Morton codes -> (M, 3) int64 indices in (x, y, z) order."""
    codes = np.asarray(codes, dtype=np.uint64)
    return np.stack([_compact_bits(codes >> np.uint64(a)) for a in range(3)], axis=-1).astype(np.int64)

"""Distill a trained semantic radiance field into the occupancy cache (occupancy.zarr), and query it.

`srfpipe distill --srf results/S/srf.zarr --out results/S/occupancy.zarr` samples the field's
density and per-class probabilities on a voxel grid covering the scene bounds and writes, in bricks
that store nothing for empty space (C may be 0: a field without classes gives density and occupancy only):

| array | shape, dtype | meaning |
|---|---|---|
| `density` | (z, y, x) float32 | max of sigma over supersample^3 points per voxel, per world unit |
| `occupancy` | (z, y, x) uint8 | voxel opacity 1 - exp(-sigma * voxel_size) >= alpha_threshold |
| `probability` | (c, z, y, x) uint8 | round(255 p), p = density-weighted mean of sigma(s(x)) in the voxel |
| `class_occupancy` | (c, z, y, x) uint8 | occupied and p > the class threshold |
| `distance` | (d, z, y, x) float32 | signed distance (world units, < 0 inside, clipped) to each avoid/reach class |
| `pyramid/s0..sN` | (1 + c, z, y, x) uint8 | OME-Zarr `multiscales`, max-pooled 2x; channel 0 = any class |
| `octree/level_00..` | (n_l,) uint64 | sorted Morton codes of the occupied cells per level; `leaf_class` int8 |

Sizes follow the scene, whatever its units: by default the voxel is the largest bounds extent /
`voxels_across` and the distance truncation `truncation_voxels` voxels; `voxel_size` and
`distance_truncation` (world units) override them, and a grid above `max_voxels` gets coarser voxels
(a warning). The `srfpipe` attributes hold the grid (origin, voxel size, `grid_from_world`), the
`resolution` asked for and used, the world `unit` (config, else the field's, else unknown), classes,
thresholds, distance classes and provenance. `OccupancyCache.load(path)` answers queries from it:
points outside the grid are free space; NaN points raise ValueError.
"""

from __future__ import annotations

from srfpipe.occupancy.analytic import AnalyticField
from srfpipe.occupancy.distill import (
    SemanticField,
    cell_subsamples,
    distill,
    max_density_in_cells,
    voxel_alpha,
)
from srfpipe.occupancy.grid import VoxelGrid, morton_decode, morton_encode

__all__ = [
    "AnalyticField", "OccupancyCache", "SemanticField", "VoxelGrid", "cell_subsamples", "distill",
    "max_density_in_cells", "morton_decode", "morton_encode", "voxel_alpha", "add_arguments", "run",
]


def __getattr__(name):
    # the cache compiles numba kernels: import it only when asked for
    if name == "OccupancyCache":
        from srfpipe.occupancy.cache import OccupancyCache

        return OccupancyCache
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def add_arguments(parser) -> None:
    from srfpipe.config import add_options_arguments

    parser.add_argument("--srf", required=True, metavar="ZARR", help="trained field (srf.zarr from `srfpipe train`)")
    parser.add_argument("--out", required=True, metavar="ZARR", help="occupancy cache to write (occupancy.zarr)")
    add_options_arguments(parser, "occupancy")
    parser.add_argument("--no-progress", action="store_true", help="no progress bars")


def run(args) -> int:
    from pathlib import Path

    from srfpipe.config import stage_options

    options = stage_options(args, "occupancy")
    srf_path = Path(args.srf)
    if not srf_path.exists():
        raise FileNotFoundError(f"{srf_path}: trained field does not exist (run `srfpipe train` first)")
    try:
        from srfpipe.srf.query import SemanticRadianceField
    except ModuleNotFoundError as exc:
        raise RuntimeError(f"srfpipe.srf.query is not available in this checkout ({exc})") from exc
    field = SemanticRadianceField.load(srf_path, device=options["device"])
    extra = {}
    for key in ("scene_from_world", "world_from_scene"):
        value = getattr(field, key, None)
        if value is not None:
            extra[key] = value
    distill(field, args.out, options, inputs=[srf_path], progress=not args.no_progress, **extra)
    return 0

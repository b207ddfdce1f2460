"""Voxel distillation: a semantic field (a trained SRF, an analytic scene) -> `occupancy.zarr`.

Four passes, each brick by brick so memory stays bounded by a few bricks plus the octree's codes:

1. density, occupancy, per-class probability and per-class occupancy (the field is queried at
   supersample^3 points per voxel; `max_density_in_cells` is the same operation as the occupancy-grid
   update used while training);
2. truncated signed distance fields of the classes to avoid or reach (brick + halo, SciPy EDT);
3. the OME-Zarr `multiscales` pyramid of max-pooled occupancy;
4. the sparse octree: sorted Morton codes of the occupied cells of every level.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Callable, Protocol, Sequence, runtime_checkable

import numpy as np
from tqdm.auto import tqdm

from srfpipe.occupancy.grid import (MORTON_BITS, VoxelGrid, check_bounds, morton_encode, voxel_counts,
                                    voxel_size_within)

log = logging.getLogger(__name__)

STAGE = "distill"
FORMAT_VERSION = 1


@runtime_checkable
class SemanticField(Protocol):
    """What distillation needs from a field (a trained SRF or `AnalyticField`).

    A field may also say in which unit its world frame is (`unit`, or `attrs["unit"]` as read
    from srf.zarr); without one the cache's unit is unknown unless `occupancy.unit` is set.
    """

    classes: Sequence[str]
    bounds_world: np.ndarray  # (2, 3) [[min xyz], [max xyz]]

    def density(self, points_world: np.ndarray) -> np.ndarray:
        """(M, 3) world points -> (M,) sigma per world unit, 0 outside the bounds."""

    def semantic(self, points_world: np.ndarray) -> np.ndarray:
        """(M, 3) world points -> (M, C) per-class probabilities in [0, 1]."""


# --------------------------------------------------------------------------------------------------
# Sampling inside cells (shared with the training-time occupancy grid)


def cell_subsamples(cell_centres: np.ndarray, cell_size, supersample: int, rng=None) -> np.ndarray:
    """Points inside each cell: a supersample^3 stratified grid, jittered within strata if `rng`.

    cell_centres (M, 3), cell_size scalar or (3,) -> (M, supersample^3, 3). Without `rng` the points
    are the strata centres (deterministic: the same cache from the same field).
    """
    n = int(supersample)
    if n < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    strata = (np.arange(n) + 0.5) / n - 0.5
    offsets = np.stack(np.meshgrid(strata, strata, strata, indexing="ij"), axis=-1).reshape(-1, 3)
    centres = np.asarray(cell_centres, dtype=np.float64).reshape(-1, 1, 3)
    offsets = np.broadcast_to(offsets, (centres.shape[0],) + offsets.shape)
    if rng is not None:
        offsets = offsets + rng.uniform(-0.5 / n, 0.5 / n, size=offsets.shape)
    return centres + offsets * np.asarray(cell_size, dtype=np.float64)


def max_density_in_cells(
    density_fn: Callable[[np.ndarray], np.ndarray],
    cell_centres: np.ndarray,
    cell_size,
    supersample: int = 2,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """max over supersample^3 points in each cell of sigma(x): (M, 3) centres -> (M,) float32.

    The occupancy-grid update of training (nerfacc: EMA of this at jittered points, then a
    threshold) and voxel distillation are the same operation; pass `rng` for jittered points.
    Taking the max, not the mean, keeps structures thinner than a cell (twigs) from vanishing.
    """
    points = cell_subsamples(cell_centres, cell_size, supersample, rng)
    sigma = np.asarray(density_fn(points.reshape(-1, 3)), dtype=np.float32).reshape(points.shape[:2])
    return sigma.max(axis=1)


def voxel_alpha(sigma, voxel_size: float):
    """Opacity of one voxel crossed by a ray: alpha = 1 - exp(-sigma * voxel_size)."""
    return -np.expm1(-np.asarray(sigma, dtype=np.float64) * voxel_size)


def alpha_to_sigma(alpha: float, voxel_size: float) -> float:
    """The density whose voxel opacity is `alpha` (the inverse of `voxel_alpha`)."""
    return float(-math.log1p(-alpha) / voxel_size) if alpha < 1 else math.inf


def class_thresholds(classes: Sequence[str], options: dict) -> np.ndarray:
    """Per-class probability thresholds: `class_threshold`, overridden per name by `class_thresholds`."""
    per_class = options.get("class_thresholds") or {}
    unknown = sorted(set(per_class) - set(classes))
    if unknown:
        log.warning("class_thresholds for classes the field does not have: %s", unknown)
    return np.array([per_class.get(name, options["class_threshold"]) for name in classes], dtype=np.float64)


# --------------------------------------------------------------------------------------------------
# Pass 1: one brick of density / occupancy / semantics


def distill_brick(field: SemanticField, grid: VoxelGrid, zyx: tuple[slice, slice, slice], options: dict,
                  thresholds: np.ndarray) -> dict:
    """Distill one brick: density (max over subsamples), occupancy, probability, class occupancy.

    The voxel probability is the density-weighted mean of sigma(s(x)) over the voxel's subsamples
    (where the matter is), computed only where the voxel alpha reaches `semantic_alpha_min`
    (probability 0, no class, in free space).
    """
    v = grid.voxel_size
    centres = grid.voxel_centres(zyx)
    box = centres.shape[:3]
    points = cell_subsamples(centres.reshape(-1, 3), v, options["supersample"])
    sigma = _query_density(field, points.reshape(-1, 3), options["batch_points"]).reshape(points.shape[:2])
    sigma_max = sigma.max(axis=1)
    alpha = voxel_alpha(sigma_max, v)
    occupied = alpha >= options["alpha_threshold"]
    density = np.where(alpha >= options["density_floor_alpha"], sigma_max, 0.0).astype(np.float32)

    n_classes = len(field.classes)
    probability = np.zeros((len(sigma_max), n_classes), dtype=np.float32)
    dense = np.flatnonzero(alpha >= options["semantic_alpha_min"])
    if dense.size and n_classes:
        weights = sigma[dense]  # (K, S)
        has_mass = weights > 0
        p = _query_semantic(field, points[dense][has_mass], options["batch_points"], n_classes)
        weighted = np.zeros(weights.shape + (n_classes,), dtype=np.float64)
        weighted[has_mass] = p * weights[has_mass][:, None]
        probability[dense] = weighted.sum(axis=1) / weights.sum(axis=1)[:, None]
    class_occupied = occupied[:, None] & (probability > thresholds[None, :])
    return {
        "density": density.reshape(box),
        "occupancy": occupied.reshape(box),
        "probability": probability.T.reshape((n_classes,) + box),
        "class_occupancy": class_occupied.T.reshape((n_classes,) + box),
    }


def _query_density(field, points: np.ndarray, batch: int) -> np.ndarray:
    out = np.empty(len(points), dtype=np.float32)
    for start in range(0, len(points), batch):
        out[start:start + batch] = np.asarray(field.density(points[start:start + batch]), dtype=np.float32).reshape(-1)
    if not np.all(np.isfinite(out)) or np.any(out < 0):
        raise ValueError("the field returned a negative or non-finite density")
    return out


def _query_semantic(field, points: np.ndarray, batch: int, n_classes: int) -> np.ndarray:
    out = np.empty((len(points), n_classes), dtype=np.float32)
    for start in range(0, len(points), batch):
        out[start:start + batch] = np.asarray(field.semantic(points[start:start + batch]), dtype=np.float32)
    return np.clip(out, 0.0, 1.0)


def leaf_class(probability_u8: np.ndarray, class_occupied: np.ndarray) -> np.ndarray:
    """Class index per voxel: the most probable class among those occupying it, -1 for none.

    probability_u8, class_occupied: (C, ...) -> (...) int8.
    """
    if probability_u8.shape[0] == 0:
        return np.full(probability_u8.shape[1:], -1, dtype=np.int8)
    masked = np.where(class_occupied, probability_u8.astype(np.int16), -1)
    best = masked.argmax(axis=0).astype(np.int8)
    return np.where(class_occupied.any(axis=0), best, np.int8(-1)).astype(np.int8)


# --------------------------------------------------------------------------------------------------
# Pass 2: truncated signed distance, brick + halo


def signed_distance_brick(occupancy_array, channel: int, grid: VoxelGrid, zyx, truncation: float) -> np.ndarray | None:
    """Signed distance (world units, negative inside) from voxel centres to one class's surface.

    The surface lies half a voxel beyond the occupied voxel centres. Values are clipped to
    +-truncation; the EDT runs on the brick plus a halo of truncation, outside the grid is free.
    Returns None when nothing is occupied within reach (the whole brick is +truncation).
    """
    from scipy.ndimage import distance_transform_edt

    v = grid.voxel_size
    halo = int(math.ceil(truncation / v)) + 1
    lo = [s.start - halo for s in zyx]
    hi = [s.stop + halo for s in zyx]
    src_lo = [max(0, a) for a in lo]
    src_hi = [min(n, b) for b, n in zip(hi, grid.shape)]
    region = np.zeros([b - a for a, b in zip(lo, hi)], dtype=bool)
    region[tuple(slice(a - l, b - l) for a, b, l in zip(src_lo, src_hi, lo))] = np.asarray(
        occupancy_array[(channel,) + tuple(slice(a, b) for a, b in zip(src_lo, src_hi))], dtype=bool)
    if not region.any():
        return None
    crop = tuple(slice(halo, halo + (s.stop - s.start)) for s in zyx)
    if region.all():
        return np.full(region[crop].shape, -truncation, dtype=np.float32)
    outside = distance_transform_edt(~region, sampling=v)[crop] - v / 2
    inside = distance_transform_edt(region, sampling=v)[crop] - v / 2
    d = np.where(region[crop], -inside, outside)
    return np.clip(d, -truncation, truncation).astype(np.float32)


# Bytes per voxel of a distance transform over a whole grid: scipy's EDT keeps a feature transform
# (3 int32) and the float64 distances, and the signed field adds the mask, the crop and the result
EDT_BYTES_PER_VOXEL = 40


def signed_distance_field(occupied: np.ndarray, grid: VoxelGrid, truncation: float) -> np.ndarray:
    """Signed distance over the whole grid to the surface of one (z, y, x) occupancy, as the cache's
    `distance` array holds it per class: float32 world units, negative inside, clipped to
    +-truncation, +truncation everywhere when nothing is occupied (outside the grid is free)."""
    from srfpipe.memory import check_allocation

    halo = int(math.ceil(truncation / grid.voxel_size)) + 1
    voxels = math.prod(n + 2 * halo for n in grid.shape)
    check_allocation(voxels * EDT_BYTES_PER_VOXEL, "occupancy.voxels_across",
                     f"the signed distance over the whole {' x '.join(map(str, grid.shape))} voxel grid (with a "
                     f"halo of {halo})")
    whole = tuple(slice(0, n) for n in grid.shape)
    d = signed_distance_brick(np.asarray(occupied, dtype=bool)[None], 0, grid, whole, truncation)
    return np.full(grid.shape, truncation, np.float32) if d is None else d


def distance_classes(classes: Sequence[str], options: dict) -> list[tuple[str, str]]:
    """(class, role) for every class to avoid or reach that the field has, in config order."""
    if not classes:
        # a field without classes (a capture without masks) has nothing to name: one note, not one per class
        if options["avoid"] or options["reach"]:
            log.info("the field has no classes: no distance fields (occupancy.avoid %s, reach %s unused)",
                     options["avoid"], options["reach"])
        return []
    chosen = []
    for role in ("avoid", "reach"):
        for name in options[role]:
            if name not in classes:
                log.warning("occupancy.%s lists %r, which the field does not have (classes %s): no distance field",
                            role, name, list(classes))
            elif name not in [c for c, _ in chosen]:
                chosen.append((name, role))
    return chosen


# --------------------------------------------------------------------------------------------------
# Pass 3 and 4: pyramid and octree


def pyramid_shapes(shape: tuple[int, int, int]) -> list[tuple[int, int, int]]:
    """Shapes of levels s0..sN, halving (rounding up) until a single voxel: N = ceil(log2(max n))."""
    depth = max(0, math.ceil(math.log2(max(shape))))
    return [tuple(-(-n // (1 << k)) for n in shape) for k in range(depth + 1)]


def downsample_max(src, dst, brick: int) -> None:
    """dst = 2x2x2 max-pool of src over the last three axes, brick by brick (odd edges pad with 0)."""
    channels = dst.shape[0]
    _, nz, ny, nx = dst.shape
    for z0 in range(0, nz, brick):
        for y0 in range(0, ny, brick):
            for x0 in range(0, nx, brick):
                out_box = (slice(z0, min(z0 + brick, nz)), slice(y0, min(y0 + brick, ny)), slice(x0, min(x0 + brick, nx)))
                block = np.asarray(src[(slice(None),) + tuple(slice(2 * s.start, 2 * s.stop) for s in out_box)])
                if not block.any():
                    continue
                want = [2 * (s.stop - s.start) for s in out_box]
                padded = np.zeros((channels, *want), dtype=block.dtype)
                padded[:, :block.shape[1], :block.shape[2], :block.shape[3]] = block
                c, z, y, x = padded.shape
                pooled = padded.reshape(c, z // 2, 2, y // 2, 2, x // 2, 2).max(axis=(2, 4, 6))
                dst[(slice(None),) + out_box] = pooled


def multiscales_metadata(grid: VoxelGrid, n_levels: int, channels: list[str], unit: str | None) -> dict:
    """OME-Zarr (NGFF 0.5) `multiscales` for the pyramid; translation = centre of voxel 0 of the level."""
    axes = [{"name": "c", "type": "channel"}] + [
        {"name": a, "type": "space", **({"unit": unit} if unit else {})} for a in ("z", "y", "x")]
    origin_zyx = np.asarray(grid.origin)[::-1]
    datasets = []
    for k in range(n_levels):
        size = grid.voxel_size * (1 << k)
        datasets.append({
            "path": f"s{k}",
            "coordinateTransformations": [
                {"type": "scale", "scale": [1.0, size, size, size]},
                {"type": "translation", "translation": [0.0] + (origin_zyx + size / 2).tolist()},
            ],
        })
    return {
        "version": "0.5",
        "multiscales": [{
            "name": "occupancy",
            "axes": axes,
            "datasets": datasets,
            "type": "max",
            "metadata": {
                "description": "occupancy max-pooled 2x2x2 per level; channel 0 any class, then one per class",
                "method": "srfpipe.occupancy.distill.downsample_max",
                "channels": channels,
            },
        }],
    }


def octree_levels(leaf_codes: np.ndarray, depth: int) -> list[np.ndarray]:
    """Sorted Morton codes of the occupied cells of levels 0 (root) .. depth (voxels).

    A cell of level l is occupied if any voxel below it is; its code is its voxels' code >> 3(depth-l).
    """
    levels = [np.unique(leaf_codes)]
    for _ in range(depth):
        levels.append(np.unique(levels[-1] >> np.uint64(3)))
    return levels[::-1]


# --------------------------------------------------------------------------------------------------
# The whole stage


def resolve_options(options: dict | None) -> dict:
    """Defaults of the schema's `occupancy` section, overridden by `options`, validated."""
    from srfpipe.config import validate_scene

    return validate_scene({"occupancy": dict(options or {})}, "occupancy options")["occupancy"]


# Sizes follow the scene (its bounds), never one scene's units: world-unit values are overrides.


def choose_voxel_size(bounds_world, options: dict) -> dict:
    """The voxel size asked for and the one used, and why they differ.

    Asked: `voxel_size` (world units) when set, else the largest bounds extent / `voxels_across`.
    Used: the asked size, or the finest coarser one whose grid holds at most `max_voxels` voxels
    (with a warning), so that a scene in unexpected units still distills.
    """
    bounds = check_bounds(bounds_world)
    extent = bounds[1] - bounds[0]
    if options["voxel_size"] is not None:
        asked, source = float(options["voxel_size"]), "voxel_size"
    else:
        asked, source = float(extent.max()) / options["voxels_across"], "voxels_across"
    used = voxel_size_within(bounds, asked, options["max_voxels"])
    record = {"voxel_size_asked": asked, "voxel_size": used, "asked_from": source,
              "voxels_across": options["voxels_across"] if source == "voxels_across" else None,
              "largest_extent": float(extent.max()), "max_voxels": options["max_voxels"],
              "coarsened": used > asked, "reason": None}
    if used > asked:
        counts = voxel_counts(extent, asked)
        record["reason"] = (f"voxel size {asked:.6g} (from {source}) over bounds {bounds.tolist()} gives "
                            f"{' x '.join(map(str, counts.tolist()))} = {int(np.prod(counts))} voxels "
                            f"> max_voxels {options['max_voxels']}; used {used:.6g}, the finest that fits")
        log.warning("occupancy: %s", record["reason"])
    return record


def choose_truncation(voxel_size: float, options: dict) -> dict:
    """The signed-distance truncation: `distance_truncation` (world units) when set, else
    `truncation_voxels` voxels (the distances are only exact to about half a voxel anyway)."""
    if options["distance_truncation"] is not None:
        truncation, source = float(options["distance_truncation"]), "distance_truncation"
    else:
        truncation, source = float(options["truncation_voxels"]) * voxel_size, "truncation_voxels"
    return {"truncation": truncation, "truncation_from": source, "truncation_voxels": truncation / voxel_size}


def world_unit(field, options: dict) -> tuple[str | None, str]:
    """The unit of the world frame and where it comes from: config, field (its data), or unknown."""
    if options["unit"] is not None:
        return str(options["unit"]), "config"
    unit = getattr(field, "unit", None) or (getattr(field, "attrs", None) or {}).get("unit")
    return (str(unit), "field") if unit else (None, "unknown")


def _create(group, name, shape, chunks, dtype, dims, fill_value):
    # write_empty_chunks=False: a brick equal to the fill value is not stored (empty space is free)
    return group.create_array(name, shape=shape, chunks=chunks, dtype=dtype, dimension_names=dims,
                              fill_value=fill_value, config={"write_empty_chunks": False})


def cache_region(field: SemanticField) -> np.ndarray:
    """The box the cache covers: the field's semantic region (where its classes are) inside its bounds.

    A field that models a whole room keeps the cache on the objects its classes name; a field
    without a semantic region (an `AnalyticField`, an older srf.zarr) is cached over its bounds.
    """
    bounds = check_bounds(field.bounds_world)
    region = getattr(field, "semantic_bounds_world", None)
    if region is None:
        return bounds
    region = check_bounds(region)
    low, high = np.maximum(region[0], bounds[0]), np.minimum(region[1], bounds[1])
    return np.stack([low, high]) if np.all(high > low) else bounds


def distill(field: SemanticField, out_path: str | Path, options: dict | None = None,
            inputs: list | None = None, progress: bool = True, **extra_attrs) -> Path:
    """Distill `field` into an occupancy cache at `out_path` (an atomic srfpipe artifact)."""
    from srfpipe.artifacts import create_artifact, update_attrs

    options = resolve_options(options)
    classes = [str(c) for c in field.classes]
    region = cache_region(field)
    resolution = choose_voxel_size(region, options)
    grid = VoxelGrid.from_bounds(region, resolution["voxel_size"])
    if max(grid.shape) > 1 << MORTON_BITS:  # found now, not after the bricks before the first voxel beyond
        raise ValueError(f"occupancy.{resolution['asked_from']}: a grid of {' x '.join(map(str, grid.shape))} voxels "
                         f"(z, y, x) has more than the {1 << MORTON_BITS} voxels along an axis that the octree's "
                         f"Morton codes hold; ask for coarser voxels")
    truncation = choose_truncation(grid.voxel_size, options)
    unit, unit_source = world_unit(field, options)
    v, brick, trunc = grid.voxel_size, options["brick"], truncation["truncation"]
    thresholds = class_thresholds(classes, options)
    dist_classes = distance_classes(classes, options)
    shapes = pyramid_shapes(grid.shape)
    n_c = len(classes)
    log.info("grid %s voxels of %.4g %s (origin %s), %d bricks of %d^3, classes %s", list(grid.shape), v,
             unit or "world units (unit unknown)", np.round(grid.origin, 4).tolist(), grid.n_bricks(brick), brick,
             classes)
    if not classes:
        log.info("the field has no semantic classes: distilling density and occupancy only")

    with create_artifact(out_path, STAGE, config=options, inputs=inputs) as group:
        b3, cb3 = (brick,) * 3, (1,) + (brick,) * 3
        arrays = {
            "density": _create(group, "density", grid.shape, b3, "float32", ("z", "y", "x"), 0.0),
            "occupancy": _create(group, "occupancy", grid.shape, b3, "uint8", ("z", "y", "x"), 0),
            "probability": _create(group, "probability", (n_c,) + grid.shape, cb3, "uint8", ("c", "z", "y", "x"), 0),
            "class_occupancy": _create(group, "class_occupancy", (n_c,) + grid.shape, cb3, "uint8",
                                       ("c", "z", "y", "x"), 0),
        }
        pyramid = group.create_group("pyramid")
        levels = [_create(pyramid, f"s{k}", (1 + n_c,) + s, cb3, "uint8", ("c", "z", "y", "x"), 0)
                  for k, s in enumerate(shapes)]

        leaf_codes, leaf_classes, counts = _write_bricks(field, grid, options, thresholds, arrays, levels, progress)
        distance = _write_distances(group, arrays["class_occupancy"], grid, classes, dist_classes, brick, trunc,
                                    progress)
        for k in tqdm(range(1, len(levels)), desc="pyramid", disable=not progress, unit="level"):
            downsample_max(levels[k - 1], levels[k], brick)
        pyramid.attrs["ome"] = multiscales_metadata(grid, len(levels), ["any"] + classes, unit)
        depth = len(shapes) - 1
        _write_octree(group, leaf_codes, leaf_classes, depth)

        storage = storage_bytes(group, [*arrays.values(), distance, *levels])
        update_attrs(
            group,
            **storage,
            grid={**grid.to_attrs(), "unit": unit},
            resolution=resolution,
            unit=unit,
            unit_source=unit_source,
            classes=classes,
            density_only=not classes,
            semantics=("none: the field has no classes, so probability and class_occupancy have 0 channels, "
                       "there are no distance fields and every octree leaf_class is -1") if not classes else
                      "per-class probability and occupancy, distance fields for the avoid/reach classes",
            class_table=[{"value": i, "name": name} for i, name in enumerate(classes)],
            thresholds={"alpha_threshold": options["alpha_threshold"],
                        "sigma_threshold": alpha_to_sigma(options["alpha_threshold"], v),
                        "class_thresholds": dict(zip(classes, thresholds.tolist())),
                        "density_floor_alpha": options["density_floor_alpha"],
                        "semantic_alpha_min": options["semantic_alpha_min"]},
            distance={"classes": [c for c, _ in dist_classes], "roles": [r for _, r in dist_classes],
                      **truncation, "signed": "negative inside, world units"},
            probability_encoding="uint8 round(255 p)",
            counts={"occupied_voxels": int(counts[0]),
                    "class_voxels": dict(zip(classes, counts[1:].tolist()))},
            pyramid_levels=len(levels),
            octree_depth=depth,
            format_version=FORMAT_VERSION,
            field_bounds_world=np.asarray(field.bounds_world, dtype=np.float64).tolist(),
            cache_region_world=region.tolist(),
            **extra_attrs,
        )
    log.info("occupied voxels %d (%s); %.3g MB on disk, %.3g MB as dense arrays (%.2g %%)", counts[0],
             dict(zip(classes, counts[1:].tolist())), storage["bytes_on_disk"] / 1e6, storage["dense_bytes"] / 1e6,
             100 * storage["bytes_on_disk"] / max(storage["dense_bytes"], 1))
    return Path(out_path)


def _write_bricks(field, grid, options, thresholds, arrays, levels, progress):
    """Pass 1: the field queried brick by brick into the voxel arrays and the pyramid's finest
    level; the occupied voxels' Morton codes and classes (per brick), and the occupied-voxel counts
    (any, then per class)."""
    n_c = arrays["probability"].shape[0]
    leaf_codes, leaf_classes, counts = [], [], np.zeros(1 + n_c, dtype=np.int64)
    for zyx in tqdm(grid.bricks(options["brick"]), total=grid.n_bricks(options["brick"]), desc="distill bricks",
                    disable=not progress, unit="brick"):  # one brick's slices at a time, not a list of them all
        out = distill_brick(field, grid, zyx, options, thresholds)
        prob_u8 = np.rint(out["probability"] * 255).astype(np.uint8)
        occ = out["occupancy"].astype(np.uint8)
        cls_occ = out["class_occupancy"].astype(np.uint8)
        arrays["density"][zyx] = out["density"]
        arrays["occupancy"][zyx] = occ
        arrays["probability"][(slice(None),) + zyx] = prob_u8
        arrays["class_occupancy"][(slice(None),) + zyx] = cls_occ
        levels[0][(slice(None),) + zyx] = np.concatenate([occ[None], cls_occ])
        counts[0] += int(occ.sum())
        counts[1:] += cls_occ.sum(axis=(1, 2, 3), dtype=np.int64)
        kji = np.argwhere(occ)
        if len(kji):
            offset = np.array([s.start for s in zyx])
            leaf_codes.append(morton_encode((kji + offset)[:, ::-1]))
            leaf_classes.append(leaf_class(prob_u8, cls_occ.astype(bool))[tuple(kji.T)])
    return leaf_codes, leaf_classes, counts


def _write_distances(group, class_occupancy, grid, classes, dist_classes, brick, trunc, progress):
    """Pass 2: a truncated signed distance field per avoid/reach class (`dist_classes`)."""
    distance = _create(group, "distance", (len(dist_classes),) + grid.shape, (1,) + (brick,) * 3, "float32",
                       ("c", "z", "y", "x"), float(trunc))
    for d_index, (name, _role) in enumerate(dist_classes):
        channel = classes.index(name)
        for zyx in tqdm(grid.bricks(brick), total=grid.n_bricks(brick), desc=f"distance {name}", disable=not progress,
                        unit="brick"):
            d = signed_distance_brick(class_occupancy, channel, grid, zyx, trunc)
            if d is not None:
                distance[(d_index,) + zyx] = d
    return distance


def _write_octree(group, leaf_codes, leaf_classes, depth: int) -> None:
    """Pass 4: the sparse octree of the occupied voxels, one array of Morton codes a level."""
    # Morton order within each brick differs from global order: sort the leaves once
    codes = np.concatenate(leaf_codes) if leaf_codes else np.zeros(0, np.uint64)
    cls_of_leaf = np.concatenate(leaf_classes) if leaf_classes else np.zeros(0, np.int8)
    order = np.argsort(codes, kind="stable")
    codes, cls_of_leaf = codes[order], cls_of_leaf[order]
    octree = group.create_group("octree")
    for level, level_codes in enumerate(octree_levels(codes, depth)):
        _write_1d(octree, f"level_{level:02d}", level_codes, "uint64")
    _write_1d(octree, "leaf_class", cls_of_leaf, "int8")
    octree.attrs["octree"] = {
        "depth": depth, "root_size_voxels": 1 << depth, "levels": [f"level_{l:02d}" for l in range(depth + 1)],
        "morton": "21 bits per axis interleaved, x in bit 0, y in bit 1, z in bit 2; voxel (x, y, z) indices",
        "cell_of_level": "level l cell c covers voxels whose code >> 3*(depth-l) == c",
        "leaf_class": "class index per leaf (aligned with the last level), -1 when no class passes its threshold",
    }


def storage_bytes(group, dense_arrays) -> dict:
    """What the cache costs on disk against a dense grid: `bytes_on_disk`, the size of every file
    of the artifact (chunks of empty bricks are never written, the rest compressed; measured before
    the final attributes, a few kB, are written), and `dense_bytes`, what `dense_arrays` (the
    voxel arrays and the pyramid, not the octree) would take stored whole and uncompressed."""
    root = Path(group.store.root)
    on_disk = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    dense = sum(math.prod(a.shape) * a.dtype.itemsize for a in dense_arrays)
    return {"bytes_on_disk": int(on_disk), "dense_bytes": int(dense)}


def _write_1d(group, name: str, values: np.ndarray, dtype: str) -> None:
    chunk = max(1, min(len(values), 1 << 20))
    array = group.create_array(name, shape=(len(values),), chunks=(chunk,), dtype=dtype)
    if len(values):
        array[:] = values

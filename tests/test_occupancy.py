"""The occupancy cache: distillation of analytic fields with known answers, queries, and the stage."""

from __future__ import annotations

import importlib.util
import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from srfpipe.artifacts import open_artifact, read_provenance
from srfpipe.occupancy import AnalyticField, OccupancyCache, VoxelGrid, distill, max_density_in_cells, morton_decode
from srfpipe.occupancy.distill import choose_voxel_size, resolve_options
from srfpipe.occupancy.grid import voxel_counts, voxel_size_within

CLASSES = ["apple", "branch", "leaf"]
BOUNDS = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
CENTRE = np.array([0.03, -0.02, 0.01])
RADIUS = 0.3
VOXEL = 0.0125  # the sphere is 24 voxels across: max-over-subsamples dilates by ~0.4 voxel


def sphere_field() -> AnalyticField:
    return AnalyticField(list(CLASSES), BOUNDS).add_sphere(CENTRE, RADIUS, "apple")


@pytest.fixture(scope="module")
def sphere_cache(tmp_path_factory) -> tuple[Path, OccupancyCache]:
    path = tmp_path_factory.mktemp("sphere") / "occupancy.zarr"
    distill(sphere_field(), path, {"voxel_size": VOXEL, "supersample": 2, "avoid": [], "reach": ["apple"],
                                   "brick": 16}, progress=False)
    return path, OccupancyCache.load(path)


def chunk_files(array_dir: Path) -> list[Path]:
    return [p for p in (array_dir / "c").rglob("*") if p.is_file()] if (array_dir / "c").exists() else []


def test_sphere_distills_with_iou_above_095(sphere_cache):
    _, cache = sphere_cache
    points = np.random.default_rng(0).uniform(-0.45, 0.45, size=(400_000, 3))
    truth = np.linalg.norm(points - CENTRE, axis=1) <= RADIUS
    occupied = cache.occupancy(points)
    iou = (truth & occupied).sum() / (truth | occupied).sum()
    assert iou >= 0.95, f"IoU {iou:.4f}"
    # the class follows: everything occupied is apple
    assert np.array_equal(cache.class_occupancy(points, "apple"), occupied)
    assert not cache.class_occupancy(points, "branch").any()
    inside = points[np.linalg.norm(points - CENTRE, axis=1) < RADIUS - 2 * VOXEL]
    np.testing.assert_allclose(cache.semantic(inside), np.tile([1.0, 0, 0], (len(inside), 1)), atol=1e-6)
    np.testing.assert_allclose(cache.density(inside), 1000.0, rtol=1e-6)


def test_world_grid_transform_round_trips(sphere_cache):
    path, cache = sphere_cache
    grid = VoxelGrid.from_bounds([[-1.0, 0.2, 3.0], [0.7, 0.9, 3.05]], 0.1)
    assert grid.shape == (1, 7, 17)  # (z, y, x): the extent / voxel size, rounded up
    assert np.all(grid.bounds_world[0] <= [-1.0, 0.2, 3.0]) and np.all(grid.bounds_world[1] >= [0.7, 0.9, 3.05])
    x = np.random.default_rng(1).normal(size=(100, 3))
    np.testing.assert_allclose(grid.grid_to_world(grid.world_to_grid(x)), x, atol=1e-12)
    np.testing.assert_allclose(grid.world_from_grid @ grid.grid_from_world, np.eye(4), atol=1e-12)
    homogeneous = np.c_[x, np.ones(len(x))]
    np.testing.assert_allclose((homogeneous @ grid.grid_from_world.T)[:, :3], grid.world_to_grid(x), atol=1e-12)
    # voxel (i, j, k) = (x, y, z) is stored at [k, j, i] and its centre sits at grid coordinate + 0.5
    centres = grid.voxel_centres((slice(0, 1), slice(2, 3), slice(5, 6)))
    np.testing.assert_allclose(grid.world_to_grid(centres.reshape(-1, 3)), [[5.5, 2.5, 0.5]])

    # the stored attributes describe the same grid the cache uses, and index the arrays as documented
    stored = VoxelGrid.from_attrs(read_provenance(path)["grid"])
    assert stored == cache.grid
    group = open_artifact(path, stage="distill")
    occupancy = group["occupancy"][...]
    k, j, i = np.argwhere(occupancy)[123]
    centre = stored.grid_to_world([[i + 0.5, j + 0.5, k + 0.5]])
    assert cache.occupancy(centre)[0]
    np.testing.assert_allclose(np.asarray(read_provenance(path)["grid"]["grid_from_world"]), stored.grid_from_world)


def test_empty_scene_gives_an_empty_cache_with_no_chunks(tmp_path):
    path = tmp_path / "occupancy.zarr"
    distill(AnalyticField(list(CLASSES), BOUNDS), path, {"voxel_size": 0.05, "brick": 16}, progress=False)
    meta = read_provenance(path)
    assert meta["complete"] and meta["counts"]["occupied_voxels"] == 0
    for name in ("density", "occupancy", "probability", "class_occupancy", "distance", "pyramid/s0", "pyramid/s1"):
        assert chunk_files(path / name) == [], f"{name} stored chunks for empty space"
    cache = OccupancyCache.load(path)
    points = np.random.default_rng(2).uniform(-0.6, 0.6, size=(1000, 3))
    assert not cache.occupancy(points).any()
    assert not cache.semantic(points).any()
    t, hit = cache.raycast(np.tile([-1.0, 0, 0], (5, 1)), np.tile([1.0, 0, 0], (5, 1)))
    assert np.all(np.isinf(t)) and np.all(hit == -1)
    d, _ = cache.distance(points, "apple")
    assert np.all(d >= meta["distance"]["truncation"] - 1e-6), "nothing to reach: as far as the field records"


def test_only_occupied_bricks_store_chunks(sphere_cache):
    path, cache = sphere_cache
    n_bricks = cache.grid.n_bricks(16)
    stored = len(chunk_files(path / "occupancy"))
    # bricks that the sphere does not touch are not written
    assert 0 < stored < n_bricks


def test_distance_gradient_points_away_from_the_surface(sphere_cache):
    path, cache = sphere_cache
    truncation = read_provenance(path)["distance"]["truncation"]
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(5000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    offsets = rng.uniform(-0.1, 0.1, size=5000)  # signed distance to the sphere's surface
    points = CENTRE + directions * (RADIUS + offsets)[:, None]
    d, grad = cache.distance(points, "apple")
    assert np.abs(d - offsets).max() < 1.5 * VOXEL
    assert np.median(np.abs(d - offsets)) < 0.5 * VOXEL
    cosine = np.sum(grad * directions, axis=1) / np.linalg.norm(grad, axis=1)
    assert np.quantile(cosine, 0.05) > 0.9, "the gradient points away from the surface"
    norms = np.linalg.norm(grad, axis=1)
    assert 0.8 < np.median(norms) < 1.2, "a distance field has a unit gradient"
    # beyond the grid: farther is larger, and the gradient still points away
    far = np.array([[2.0, 0.0, 0.0], [0.0, -3.0, 0.0]])
    d_far, g_far = cache.distance(far, "apple")
    assert np.all(d_far > truncation) and g_far[0, 0] > 0.5 and g_far[1, 1] < -0.5
    with pytest.raises(ValueError, match="no distance field for 'branch'"):
        cache.distance(points, "branch")


def ray_sphere(origins, directions):
    oc = origins - CENTRE
    b = np.sum(oc * directions, axis=1)
    disc = b * b - (np.sum(oc * oc, axis=1) - RADIUS**2)
    return np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)


def test_octree_raycast_hits_the_sphere_at_the_analytic_distance(sphere_cache):
    _, cache = sphere_cache
    rng = np.random.default_rng(4)
    origins = rng.normal(size=(2000, 3))
    origins = origins / np.linalg.norm(origins, axis=1, keepdims=True) * rng.uniform(0.7, 2.0, (2000, 1))
    targets = CENTRE + rng.uniform(-0.5, 0.5, size=(2000, 3))
    directions = targets - origins
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    expected = ray_sphere(origins, directions)
    t, hit = cache.raycast(origins, directions * 3.0)  # t is in world units whatever the direction's length
    normals = (origins + np.where(np.isfinite(expected), expected, 0)[:, None] * directions - CENTRE) / RADIUS
    incidence = np.abs(np.sum(normals * directions, axis=1))  # cosine between the ray and the normal
    hits = np.isfinite(expected) & (incidence > 0.3)  # grazing rays may clip a voxel corner first
    assert hits.sum() > 500 and (~np.isfinite(expected)).sum() > 100
    error = t[hits] - expected[hits]
    # the voxel surface lies within about a voxel diagonal of the sphere, stretched by 1/cos along the ray
    assert np.all(np.abs(error) <= np.sqrt(3) * VOXEL / incidence[hits]), np.abs(error).max()
    assert np.median(np.abs(error)) < VOXEL
    # against the voxels themselves the octree traversal is exact: march each ray in tiny steps
    step = VOXEL / 50
    ts = np.arange(0, 3.0, step)
    sample = np.flatnonzero(hits)[:200]
    marched = cache.occupancy(origins[sample, None] + ts[None, :, None] * directions[sample, None])
    first = ts[marched.argmax(axis=1)]
    assert marched.any(axis=1).all()
    assert np.abs(t[sample] - first).max() <= step + 1e-9
    assert np.all(hit[hits] == CLASSES.index("apple"))
    misses = ~np.isfinite(expected)
    assert np.mean(np.isinf(t[misses])) > 0.95  # a few rays graze the voxelized surface
    # max_t stops rays before the sphere
    t_short, hit_short = cache.raycast(origins[hits], directions[hits], max_t=t[hits] - VOXEL / 10)
    assert np.all(np.isinf(t_short)) and np.all(hit_short == -1)
    t_long, _ = cache.raycast(origins[hits], directions[hits], max_t=t[hits] + VOXEL / 10)
    np.testing.assert_allclose(t_long, t[hits])


@pytest.mark.bad_input
def test_nan_points_raise_a_clear_error(sphere_cache):
    _, cache = sphere_cache
    points = np.zeros((10, 3))
    points[7, 1] = np.nan
    for query in (cache.occupancy, cache.density, cache.semantic, cache.class_occupancy,
                  lambda p: cache.distance(p, "apple")):
        with pytest.raises(ValueError, match="1 of 10 points have NaN"):
            query(points)
    with pytest.raises(ValueError, match="NaN"):
        cache.raycast(points, np.ones((10, 3)))
    with pytest.raises(ValueError, match="shape"):
        cache.occupancy(np.zeros((4, 2)))


def test_thin_cylinder_survives_thanks_to_supersampling(tmp_path):
    voxel = 0.04
    radius = 0.15 * voxel  # a twig a third of a voxel thick
    start, end = np.array([-0.4, -0.33, -0.21]), np.array([0.41, 0.37, 0.27])
    field = AnalyticField(list(CLASSES), BOUNDS).add_capsule(start, end, radius, "branch")
    axis_points = start + np.linspace(0.02, 0.98, 500)[:, None] * (end - start)
    kept = {}
    for supersample in (1, 4):
        path = tmp_path / f"s{supersample}.zarr"
        distill(field, path, {"voxel_size": voxel, "supersample": supersample, "avoid": ["branch"], "reach": []},
                progress=False)
        kept[supersample] = OccupancyCache.load(path).class_occupancy(axis_points, "branch").mean()
    assert kept[4] >= 0.98, f"supersample 4 kept {kept[4]:.2%} of the twig"
    assert kept[1] < 0.5, f"without supersampling the twig should mostly vanish (kept {kept[1]:.2%})"
    # the shared training-time operation sees the same thing: max density over jittered points
    cell = np.floor((axis_points[:50] - BOUNDS[0]) / voxel) * voxel + BOUNDS[0] + voxel / 2
    rng = np.random.default_rng(0)
    hits = np.mean([max_density_in_cells(field.density, cell, voxel, 4, rng) > 0 for _ in range(4)])
    assert hits > 0.9


def test_pyramid_and_octree_match_the_voxels(sphere_cache):
    path, cache = sphere_cache
    group = open_artifact(path, stage="distill")
    ome = dict(group["pyramid"].attrs)["ome"]["multiscales"][0]
    assert [a["name"] for a in ome["axes"]] == ["c", "z", "y", "x"] and ome["type"] == "max"
    paths = [d["path"] for d in ome["datasets"]]
    assert paths == [f"s{k}" for k in range(len(paths))] and len(paths) == cache.n_levels
    s0 = group["pyramid/s0"][...]
    assert np.array_equal(s0[0], group["occupancy"][...])
    for k in range(1, len(paths)):
        scale = ome["datasets"][k]["coordinateTransformations"][0]["scale"]
        assert scale[1:] == pytest.approx([VOXEL * 2**k] * 3)
        level = group[f"pyramid/s{k}"][...]
        pad = [(0, 0)] + [(0, 2 ** k * n - m) for n, m in zip(level.shape[1:], s0.shape[1:])]
        expected = np.pad(s0, pad).reshape(s0.shape[0], level.shape[1], 2**k, level.shape[2], 2**k,
                                           level.shape[3], 2**k).max(axis=(2, 4, 6))
        assert np.array_equal(level, expected)
        codes = group[f"octree/level_{len(paths) - 1 - k:02d}"][...]
        xyz = morton_decode(codes)
        assert np.array_equal(np.sort(np.ravel_multi_index(xyz[:, ::-1].T, level.shape[1:])),
                              np.flatnonzero(level[0]))
    # coarse-to-fine: a coarse cell is occupied wherever a voxel inside it is
    points = np.random.default_rng(5).uniform(-0.5, 0.5, size=(20000, 3))
    fine = cache.occupancy(points)
    for level in range(1, cache.n_levels):
        assert np.all(cache.occupancy(points, level=level)[fine])
    centres, size = cache.occupied_cells(0, "apple")
    assert size == VOXEL and np.all(np.linalg.norm(centres - CENTRE, axis=1) < RADIUS + VOXEL)


@pytest.mark.bad_input
def test_cli_errors_name_the_problem(tmp_path):
    missing = tmp_path / "nope" / "srf.zarr"
    result = subprocess.run([sys.executable, "-m", "srfpipe.cli", "distill", "--srf", str(missing),
                             "--out", str(tmp_path / "o.zarr")], capture_output=True, text=True)
    assert result.returncode == 1 and str(missing) in result.stderr
    result = subprocess.run([sys.executable, "-m", "srfpipe.cli", "distill", "--srf", str(missing), "--out",
                             str(tmp_path / "o.zarr"), "--options", '{"supersample": 9}'], capture_output=True, text=True)
    assert result.returncode == 1 and "supersample" in result.stderr


# ------------------------------------------------------------------- any capture: units, classes


def elongated_scene(scale: float) -> AnalyticField:
    """An apple and a branch in a 1 x 0.25 x 0.25 box, everything (densities too) scaled by `scale`.

    Density is per world unit, so a scene `scale` times larger has `1 / scale` the density for the
    same opacity: the same matter measured in other units.
    """
    bounds = np.array([[-0.5, -0.125, -0.125], [0.5, 0.125, 0.125]]) * scale
    field = AnalyticField(list(CLASSES), bounds, sigma=1000.0 / scale)
    field.add_sphere(np.array([0.13, 0.01, -0.02]) * scale, 0.09 * scale, "apple")
    field.add_capsule(np.array([-0.45, -0.1, 0.05]) * scale, np.array([0.4, 0.08, -0.06]) * scale, 0.013 * scale,
                      "branch")
    return field


def test_default_grid_follows_the_scene_not_its_units(tmp_path):
    results = {}
    for scale in (1.0, 100.0, 0.01):
        path = distill(elongated_scene(scale), tmp_path / f"x{scale}.zarr", {}, progress=False)
        group, attrs = open_artifact(path, stage="distill"), read_provenance(path)
        results[scale] = (group["occupancy"][...], group["class_occupancy"][...], group["distance"][...], attrs)
    occupancy, class_occupancy, distance, attrs = results[1.0]
    defaults = resolve_options({})
    assert occupancy.shape == (34, 34, defaults["voxels_across"])  # the 1-unit axis holds voxels_across
    assert 0.03 < occupancy.mean() < 0.2 and class_occupancy[1].any()
    for scale in (100.0, 0.01):
        occ, cls_occ, dist, scaled = results[scale]
        assert occ.shape == occupancy.shape
        assert occ.mean() == occupancy.mean() and np.array_equal(cls_occ, class_occupancy)
        assert scaled["grid"]["voxel_size"] == pytest.approx(attrs["grid"]["voxel_size"] * scale)
        assert scaled["distance"]["truncation"] == pytest.approx(attrs["distance"]["truncation"] * scale)
        np.testing.assert_allclose(dist / scale, distance, rtol=1e-5, atol=1e-6 * attrs["grid"]["voxel_size"])
    assert attrs["resolution"]["asked_from"] == "voxels_across" and not attrs["resolution"]["coarsened"]
    assert attrs["distance"]["truncation_voxels"] == pytest.approx(defaults["truncation_voxels"])
    assert attrs["unit"] is None and attrs["unit_source"] == "unknown"  # nothing said which unit


def test_world_unit_overrides_stay_available(tmp_path):
    path = distill(elongated_scene(1.0), tmp_path / "o.zarr",
                   {"voxel_size": 0.02, "distance_truncation": 0.1, "unit": "meter"}, progress=False)
    attrs = read_provenance(path)
    assert attrs["grid"]["voxel_size"] == 0.02 and attrs["grid"]["shape"] == [13, 13, 50]
    assert attrs["resolution"]["asked_from"] == "voxel_size" and attrs["resolution"]["voxels_across"] is None
    assert attrs["distance"]["truncation"] == 0.1 and attrs["distance"]["truncation_from"] == "distance_truncation"
    assert attrs["unit"] == "meter" and attrs["unit_source"] == "config"
    axes = dict(open_artifact(path)["pyramid"].attrs)["ome"]["multiscales"][0]["axes"]
    assert [a.get("unit") for a in axes] == [None, "meter", "meter", "meter"]


def test_unit_comes_from_the_field_when_it_knows(tmp_path):
    field = elongated_scene(100.0)
    field.unit = "centimeter"
    path = distill(field, tmp_path / "cm.zarr", {"voxels_across": 20}, progress=False)
    attrs = read_provenance(path)
    assert attrs["unit"] == "centimeter" and attrs["unit_source"] == "field"
    assert attrs["grid"]["unit"] == "centimeter"
    path = distill(field, tmp_path / "m.zarr", {"voxels_across": 20, "unit": "meter"}, progress=False)
    assert read_provenance(path)["unit"] == "meter"  # the config overrides the data


def test_too_large_grid_is_coarsened_with_a_warning(tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="srfpipe.occupancy.distill")
    path = distill(sphere_field(), tmp_path / "big.zarr", {"voxel_size": 0.001, "max_voxels": 40**3}, progress=False)
    attrs = read_provenance(path)
    assert attrs["grid"]["shape"] == [40, 40, 40] and attrs["grid"]["voxel_size"] == pytest.approx(0.025)
    resolution = attrs["resolution"]
    assert resolution["coarsened"] and resolution["voxel_size_asked"] == 0.001
    assert resolution["voxel_size"] == attrs["grid"]["voxel_size"] and "max_voxels 64000" in resolution["reason"]
    warning = " ".join(r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    assert "voxel size 0.001" in warning and "1000 x 1000 x 1000" in warning and "used 0.025" in warning
    assert attrs["distance"]["truncation"] == pytest.approx(15 * 0.025)  # relative to the voxel used
    assert OccupancyCache.load(path).occupancy(CENTRE[None])[0]


@pytest.mark.bad_input
def test_a_grid_longer_than_the_morton_codes_hold_is_refused_before_the_field_is_queried(tmp_path):
    """A long thin scene fits max_voxels but has more voxels along x than the octree's 21-bit Morton
    codes index: refused naming the key before any brick is distilled (not after the 65 536 bricks
    before the first voxel beyond), and nothing is written."""

    class Unqueried(AnalyticField):
        def density(self, points):
            raise AssertionError("the field was queried")

    field = Unqueried(list(CLASSES), np.array([[0.0, 0.0, 0.0], [1.0, 1e-7, 1e-7]]))
    with pytest.raises(ValueError, match=r"occupancy.voxel_size: a grid of 1 x 1 x 10000000 voxels \(z, y, x\) "
                                         r"has more than the 2097152 voxels along an axis"):
        distill(field, tmp_path / "long.zarr", {"voxel_size": 1e-7, "brick": 64}, progress=False)
    assert not (tmp_path / "long.zarr").exists()


def test_bricks_are_distilled_one_at_a_time_not_listed_first(tmp_path, monkeypatch):
    """A grid raised to billions of bricks (occupancy.max_voxels) must not list every brick's slices
    before the first is distilled: memory stays bounded by a few bricks (the module docstring)."""
    handed_out = []
    bricks = VoxelGrid.bricks

    def counted(self, brick):
        for zyx in bricks(self, brick):
            handed_out.append(zyx)
            yield zyx

    class Stop(Exception):
        pass

    class FirstQueryStops(AnalyticField):
        def density(self, points):
            raise Stop(len(handed_out))

    monkeypatch.setattr(VoxelGrid, "bricks", counted)
    with pytest.raises(Stop) as stopped:
        distill(FirstQueryStops(list(CLASSES), BOUNDS), tmp_path / "c.zarr", {"voxels_across": 64, "brick": 16},
                progress=False)
    assert stopped.value.args == (1,)  # of 64 bricks
    assert not (tmp_path / "c.zarr").exists()


def test_the_scene_that_asked_for_billions_of_voxels_fits():
    # the capture: 128 units wide, cameras 100 units away, and a 0.02-unit voxel asked for
    bounds = np.array([[-64.0, -64.0, -60.0], [64.0, 64.0, 99.25]])
    options = resolve_options({"voxel_size": 0.02})
    record = choose_voxel_size(bounds, options)
    counts = voxel_counts(bounds[1] - bounds[0], record["voxel_size"])
    assert record["coarsened"] and np.prod(counts) <= options["max_voxels"]
    assert np.prod(voxel_counts(bounds[1] - bounds[0], record["voxel_size"] * (1 - 1e-6))) > options["max_voxels"]
    default = choose_voxel_size(bounds, resolve_options({}))
    assert not default["coarsened"] and default["voxel_size"] == pytest.approx(159.25 / options["voxels_across"])


@pytest.mark.parametrize("extent, max_voxels", [((1.0, 0.3, 2.7), 1000), ((5.0, 5.0, 1e-3), 400),
                                                ((3.0, 3.0, 3.0), 1), ((0.7, 11.0, 2.0), 123457)])
def test_coarsened_voxel_is_the_finest_that_fits(extent, max_voxels):
    bounds = np.array([[0.0, 0.0, 0.0], extent])
    chosen = voxel_size_within(bounds, 1e-4, max_voxels)
    assert np.prod(voxel_counts(extent, chosen)) <= max_voxels
    assert np.prod(voxel_counts(extent, chosen * (1 - 1e-6))) > max_voxels
    assert voxel_size_within(bounds, chosen * 2, max_voxels) == chosen * 2  # a size that fits is kept


def test_field_without_classes_distills_density_and_occupancy_only(tmp_path, caplog):
    caplog.set_level(logging.WARNING, logger="srfpipe.occupancy.distill")
    field = AnalyticField([], BOUNDS).add_sphere(CENTRE, RADIUS, None)
    path = distill(field, tmp_path / "o.zarr", {"voxels_across": 40}, progress=False)
    assert not caplog.records, "the default avoid/reach classes are not worth a warning per class"
    group, attrs = open_artifact(path, stage="distill"), read_provenance(path)
    assert attrs["classes"] == [] and attrs["density_only"] and "no classes" in attrs["semantics"]
    assert attrs["distance"]["classes"] == []
    grid = tuple(attrs["grid"]["shape"])
    for name in ("probability", "class_occupancy", "distance"):
        assert group[name].shape == (0,) + grid, name
    occupied = int(group["occupancy"][...].sum())
    assert occupied == attrs["counts"]["occupied_voxels"] > 0
    leaf_class = group["octree/leaf_class"][...]
    assert len(leaf_class) == occupied and np.all(leaf_class == -1)
    cache = OccupancyCache.load(path)
    points = np.random.default_rng(6).uniform(-0.45, 0.45, size=(20000, 3))
    truth = np.linalg.norm(points - CENTRE, axis=1) <= RADIUS
    occupancy = cache.occupancy(points)
    assert (truth & occupancy).sum() / (truth | occupancy).sum() > 0.85
    assert cache.semantic(points).shape == (20000, 0) and cache.class_occupancy(points).shape == (20000, 0)
    t, hit = cache.raycast(np.array([[-2.0, CENTRE[1], CENTRE[2]]]), np.array([[1.0, 0.0, 0.0]]))
    assert abs(t[0] - (2.0 + CENTRE[0] - RADIUS)) < 2 * 0.025 and hit[0] == -1


PIPELINE_MODULES = ("srfpipe.scenes.orchard", "srfpipe.segment.composite", "srfpipe.srf.trainer", "srfpipe.srf.query")


@pytest.mark.workflow
@pytest.mark.skipif(any(importlib.util.find_spec(m) is None for m in PIPELINE_MODULES),
                    reason="the stages before distill are not all in this checkout yet")
def test_snakemake_builds_the_tiny_orchard_occupancy_cache(workflow):
    from tests.conftest import TINY_ORCHARD

    scene = {**TINY_ORCHARD, "train": {"iterations": 30, "rays_per_batch": 256},
             "occupancy": {"voxel_size": 0.1, "supersample": 2}}
    workflow.write_scene("tiny", scene)
    workflow.run("results/tiny/occupancy.zarr")
    path = workflow.root / "results/tiny/occupancy.zarr"
    meta = read_provenance(path)
    assert meta["stage"] == "distill" and meta["config"]["voxel_size"] == 0.1
    assert any(entry["path"].endswith("srf.zarr") for entry in meta["inputs"])
    cache = OccupancyCache.load(path)
    srf_classes = read_provenance(workflow.root / "results/tiny/srf.zarr").get("classes")
    if srf_classes is not None:
        assert cache.classes == list(srf_classes)
    points = np.random.default_rng(0).uniform(*cache.bounds_world, size=(1000, 3))
    assert cache.semantic(points).shape == (1000, len(cache.classes))
    assert (workflow.root / "logs/tiny/distill.log").exists()
    assert (workflow.root / "benchmarks/runs/tiny/distill.tsv").exists()

"""Numerical stability at the extremes (issue 12): scene scale 0.01x-100x, images of 16-2000 px,
0-16 classes, fp32/bf16/fp16 autocast, densities up to 1e12 and steps of 1e-9-1e3, and the
degenerate cases (a camera inside geometry, rays that miss the box, a class in one frame only).

Each sweep checks finite outputs and gradients, and an accuracy where one applies. The table of
what was tried and what happened is docs/stability.md. Rendering and loss maths at the extremes
are also in test_rendering.py / test_losses.py, the cache's scales in test_occupancy.py.
"""

from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
import torch

from srfpipe.artifacts import create_artifact, meta, open_artifact
from srfpipe.cameras import look_at, project_points, scene_from_world_transform, transform_poses
from srfpipe.config import section_defaults
from srfpipe.srf import losses, rendering
from srfpipe.srf.data import image_rays, load_posed_images
from srfpipe.srf.model import MAX_STEPS_ACROSS_BOX, SRFModel, build_model_config
from srfpipe.srf.synthetic import write_labels, write_scene
from srfpipe.srf.trainer import train
from test_train import tiny_options as quick_training

CUBE = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def tiny_model(classes: int = 3, bounds=CUBE, **overrides) -> SRFModel:
    """A small field over `bounds` (world = scene frame for the cube); fp32 weights, seed 0."""
    options = dict(section_defaults("train"), default_cells=16, grid_levels=1, features=8, outer_resolution=8,
                   hidden=16, appearance_dim=0, initial_opacity=0.01)
    options.update(overrides)
    config = build_model_config(options, bounds, scene_from_world_transform(*bounds),
                                [f"class{i}" for i in range(classes)], num_images=2)
    torch.manual_seed(0)
    return SRFModel(config)


def rays(n: int = 48, radius: float = 2.5, seed: int = 0):
    """Rays from a sphere of `radius` towards the box centre, slightly spread."""
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=g)
    origins = origins / origins.norm(dim=1, keepdim=True) * radius
    directions = -origins + 0.3 * torch.randn(n, 3, generator=g)
    return origins, directions / directions.norm(dim=1, keepdim=True)


def assert_finite_gradients(model: SRFModel) -> int:
    """Every parameter gradient is finite; returns how many parameters received one."""
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert all(torch.isfinite(g).all() for g in grads)
    return len(grads)


def tiny_options(**overrides) -> dict:
    """test_train's quick training settings, smaller still (15 steps of 128 rays, a 16-cell grid)."""
    smaller = dict(iterations=15, rays_per_batch=128, default_cells=16, grid_levels=1, outer_resolution=8,
                   hidden=16, outer_samples=8, before_samples=4, checkpoint_every=0, occupancy_update_every=4,
                   occupancy_warmup=8)
    return quick_training(**{**smaller, **overrides})


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    folder = tmp_path_factory.mktemp("synthetic")
    images, labels = write_scene(folder, views=6, width=24, height=16)
    return folder, images, labels


# ------------------------------------------------------------------------------- scene scale


def scaled_images(images, scale: float, out):
    """images.zarr of the same capture in units `scale` times smaller: poses, bounds and the scene
    normalization scaled, pixels unchanged."""
    group = open_artifact(images, stage="downscale")
    attrs = meta(group)
    bounds = np.asarray(attrs["bounds_world"]) * scale
    poses = np.asarray(group["camera_to_world"][...])
    poses[:, :3, 3] *= scale
    scene_from_world = scene_from_world_transform(*bounds)
    keep = {k: v for k, v in attrs.items() if k in ("names", "width", "height", "downscale", "ground_truth")}
    with create_artifact(out, "downscale", bounds_world=bounds, scene_from_world=scene_from_world,
                         world_from_scene=np.linalg.inv(scene_from_world), **keep) as g:
        for name in ("images", "intrinsics"):
            g.create_array(name, data=np.asarray(group[name][...]))
        g.create_array("camera_to_world", data=poses)
    return out


@pytest.fixture(scope="module")
def fields_at_scales(synthetic, tmp_path_factory, device):
    """The synthetic scene trained in world units 0.01x, 1x and 100x as large (same seed)."""
    from srfpipe.srf.query import SemanticRadianceField

    _, images, labels = synthetic
    folder = tmp_path_factory.mktemp("scales")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # one reduction order: the three runs differ only by the units
    try:
        fields = {}
        for scale in (0.01, 1.0, 100.0):
            scaled = scaled_images(images, scale, folder / f"images_{scale}.zarr")  # 1x too: the same path
            # the same label images, recorded as composited from these images (train checks the pair)
            composite = open_artifact(labels, stage="composite")
            scaled_labels = write_labels(folder / f"labels_{scale}.zarr", np.asarray(composite["label"][...]),
                                         meta(composite)["classes"], meta(composite)["names"], inputs=[scaled])
            out = folder / f"srf_{scale}.zarr"
            train(scaled, scaled_labels, out, tiny_options(), holdout_every=3)
            fields[scale] = SemanticRadianceField.load(out, device=device)
    finally:
        torch.set_num_threads(threads)
    return fields


def test_fields_trained_at_any_scale_render_the_same_after_normalization(fields_at_scales):
    """0.01x and 100x world units: the same scene frame, so the same images; depth and density
    come back in the capture's units (depth x scale, density / scale)."""
    reference = fields_at_scales[1.0]
    pose = look_at((1.9, 0.7, 0.9), (0.0, 0.0, 0.35))
    intrinsics = [20.0, 20.0, 12.0, 8.0]
    expected = reference.render(pose, intrinsics, 24, 16)
    points = np.random.default_rng(0).uniform([-0.5, -0.5, 0.05], [0.5, 0.5, 0.85], (500, 3))
    density = reference.density(points)
    assert np.isfinite(density).all() and density.max() > 0
    for scale in (0.01, 100.0):
        field = fields_at_scales[scale]
        assert field.scale == pytest.approx(reference.scale / scale)
        scaled_pose = pose.copy()
        scaled_pose[:3, 3] *= scale
        got = field.render(scaled_pose, intrinsics, 24, 16)
        # measured: equal to the last bit but for depth (1.2e-7 relative); slack for other machines
        for key in ("rgb", "semantic", "accumulation"):
            np.testing.assert_allclose(got[key], expected[key], atol=1e-4, err_msg=key)
        np.testing.assert_allclose(got["depth"] / scale, expected["depth"], rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(field.density(points * scale) * scale, density, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(field.semantic(points * scale), reference.semantic(points), atol=1e-4)


@pytest.mark.parametrize("scale", [0.01, 100.0])
def test_pose_import_normalizes_any_scale_to_the_same_scene_frame(tmp_path, scale):
    from srfpipe.poses import import_poses
    from test_poses import ring, write_nerfstudio

    frames = {}
    for s in (1.0, scale):
        poses = ring(4)
        poses[:, :3, 3] *= s
        capture = write_nerfstudio(tmp_path / f"cap{s}", poses)
        group = open_artifact(import_poses({"format": "nerfstudio"}, capture, {}, tmp_path / f"poses{s}.zarr",
                                           progress=False))
        attrs = meta(group)
        frames[s] = (transform_poses(attrs["scene_from_world"], group["camera_to_world"][...]),
                     np.asarray(attrs["bounds_world"]))
    np.testing.assert_allclose(frames[scale][0], frames[1.0][0], atol=1e-9)
    np.testing.assert_allclose(frames[scale][1], frames[1.0][1] * scale, rtol=1e-9, atol=1e-12 * scale)


# ------------------------------------------------------------------------------- image size


@pytest.mark.parametrize("width, height, downscale", [(16, 12, 1), (64, 48, 4), (2000, 1500, 1), (2000, 1500, 125)])
def test_images_from_16_to_2000_px_give_exact_rays_and_finite_renders(tmp_path, width, height, downscale):
    """Undistort + downscale, rays through every pixel, and a render of a few of them. Rays are
    exact: a ray's points project back onto its pixel centre in the downscaled camera."""
    from srfpipe.images import downscale_images, target_size
    from srfpipe.poses import import_poses
    from test_poses import ring, write_nerfstudio

    k = (0.9 * width, 0.9 * width, width / 2, height / 2)
    capture = write_nerfstudio(tmp_path / "cap", ring(2), width=width, height=height, intrinsics=k,
                               distortion=(-0.1, 0.02, 0.001, -0.001))
    poses = import_poses({"format": "nerfstudio"}, capture, {}, tmp_path / "poses.zarr", progress=False)
    images = downscale_images(poses, {"downscale": downscale}, tmp_path / "images.zarr", progress=False)
    data = load_posed_images(images)
    w, h = target_size(width, height, downscale)
    assert (data.width, data.height) == (w, h) and data.images.shape == (2, h, w, 3)
    assert max(w, h) in (16, 2000)
    origins, directions = image_rays(data.poses_scene[0], data.intrinsics[0], w, h)
    assert origins.shape == (w * h, 3) and torch.isfinite(directions).all()
    torch.testing.assert_close(directions.norm(dim=1), torch.ones(w * h), atol=1e-6, rtol=0)
    corners = torch.tensor([0, w - 1, (h // 2) * w + w // 2, (h - 1) * w, h * w - 1])
    pose = data.poses_scene[0].double().numpy()
    points = (origins[corners] + 1.5 * directions[corners]).double().numpy()
    uv, depth = project_points(points, pose, data.intrinsics[0].double().numpy())
    expected = np.stack([corners.numpy() % w + 0.5, corners.numpy() // w + 0.5], axis=1)
    np.testing.assert_allclose(uv, expected, atol=2e-3 * max(1.0, max(w, h) / 100))  # float32 rays
    assert np.all(depth > 0)
    config = build_model_config(dict(section_defaults("train"), default_cells=16, grid_levels=1, features=8,
                                     outer_resolution=8, hidden=16, appearance_dim=0, initial_opacity=0.01),
                                data.bounds_world, data.scene_from_world, [], data.count)
    model = SRFModel(config)
    out = model(origins[corners], directions[corners])
    out["rgb"].sum().backward()
    assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["depth"]).all() and out["samples"] > 0
    assert_finite_gradients(model)


# ------------------------------------------------------------------------------- classes


@pytest.mark.parametrize("classes", [0, 1, 2, 16])
def test_zero_to_sixteen_classes_build_and_train_finitely(classes):
    model = tiny_model(classes)
    assert model.field.semantic_mlp[-1].out_features == classes
    assert model.field.background_logits.shape == (classes,)
    origins, directions = rays()
    out = model(origins, directions)
    assert out["logits"].shape == (48, classes)
    labels = torch.randint(0, 2, (48, classes)).float()
    parts = losses.total_loss(out["rgb"], torch.rand(48, 3), out["logits"], labels)
    parts["loss"].backward()
    assert all(torch.isfinite(v) for v in parts.values())
    assert assert_finite_gradients(model) > 0
    if classes:
        assert model.field.semantic_mlp[-1].weight.grad.abs().sum() > 0


def test_sixteen_classes_distill_and_get_colours(tmp_path):
    from srfpipe.artifacts import read_provenance
    from srfpipe.evaluate import class_colours
    from srfpipe.occupancy import AnalyticField, OccupancyCache, distill

    names = [f"class{i}" for i in range(16)]
    field = AnalyticField(names, np.array([[0.0, 0.0, 0.0], [4.0, 4.0, 1.0]]))
    centres = [(0.5 + i % 4, 0.5 + i // 4, 0.5) for i in range(16)]
    for centre, name in zip(centres, names):
        field.add_sphere(centre, 0.3, name)
    path = distill(field, tmp_path / "o.zarr", {"voxels_across": 32, "avoid": [], "reach": names[-2:]},
                   progress=False)
    counts = read_provenance(path)["counts"]["class_voxels"]
    assert all(counts[name] > 0 for name in names)
    cache = OccupancyCache.load(path)
    np.testing.assert_array_equal(cache.semantic(np.array(centres)).argmax(axis=1), np.arange(16))
    colours = class_colours(names)
    assert colours.shape == (17, 3) and (colours[1:].sum(axis=1) > 0).all()


# ------------------------------------------------------------------------------- precision


@pytest.mark.parametrize("encoding", ["dense", "hash"])
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_model_and_loss_under_cpu_autocast_match_fp32(encoding, dtype):
    """bf16 and fp16 autocast on the CPU (torch >= 2.1 supports both there): the forward, Eq. 1/3
    rendering, the loss and the backward stay finite and close to fp32. The grid lookup and the
    rendering run in fp32 whatever autocast says; the MLPs run in half precision."""
    options = {"hash_log2_table_size": 12, "hash_levels": 4} if encoding == "hash" else {}
    origins, directions = rays()
    target, labels = torch.rand(48, 3), torch.randint(0, 2, (48, 3)).float()
    reference = tiny_model(3, encoding=encoding, **options)
    expected = reference(origins, directions)
    model = tiny_model(3, encoding=encoding, **options)
    with torch.autocast("cpu", dtype=dtype):
        out = model(origins, directions)
        parts = losses.total_loss(out["rgb"], target, out["logits"], labels)
    parts["loss"].backward()
    assert out["rgb"].dtype == torch.float32 and parts["loss"].dtype == torch.float32
    tolerance = 1e-2 if dtype == torch.bfloat16 else 2e-3  # measured: 2e-3 and 2.4e-4
    torch.testing.assert_close(out["rgb"], expected["rgb"], atol=tolerance, rtol=0)
    torch.testing.assert_close(out["depth"], expected["depth"], atol=tolerance * 4, rtol=0)
    assert torch.isfinite(parts["loss"]) and assert_finite_gradients(model) > 0


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_appearance_smoothness_under_cpu_autocast_is_float32(dtype):
    """The appearance penalty's product W_a (a_i - a_n(i)) ran in half precision under autocast
    like the other losses must not: bf16 lost ~0.3 % of it, and in fp16 a difference of a few
    hundred squared overflowed to inf (here 2 * 40 * 3 * 4 = 960 per row, 9.2e5 squared)."""
    embedding = torch.tensor([[40.0] * 4, [-40.0] * 4, [0.3, -0.2, 0.1, 0.05]], requires_grad=True)
    weight = torch.full((8, 4), 3.0, requires_grad=True)
    pairs = torch.tensor([[0, 1], [1, 2], [2, 0]])
    expected = losses.appearance_smoothness_loss(embedding, weight, pairs)
    with torch.autocast("cpu", dtype=dtype):
        loss = losses.appearance_smoothness_loss(embedding, weight, pairs)
    loss.backward()
    assert loss.dtype == torch.float32
    torch.testing.assert_close(loss, expected, rtol=1e-6, atol=0.0)
    assert torch.isfinite(embedding.grad).all() and torch.isfinite(weight.grad).all()


@pytest.mark.parametrize("precision", ["bf16", "fp16"])
def test_training_with_half_precision_autocast_on_the_cpu(synthetic, tmp_path, precision):
    """train.precision bf16 / fp16 on the CPU trains and records what it used. fp16 runs without
    loss scaling there (GradScaler is CUDA-only): the losses are computed in fp32."""
    from srfpipe.srf.io import read_curve, read_srf

    _, images, labels = synthetic
    out = tmp_path / "srf.zarr"
    summary = train(images, labels, out, tiny_options(iterations=6, log_every=3, precision=precision), holdout_every=3)
    assert summary["precision"] == precision and read_srf(out)[1]["precision"] == precision
    curve = read_curve(out)
    assert len(curve["loss"]) == 2 and np.isfinite(curve["loss"]).all() and np.isfinite(curve["psnr"]).all()


# ------------------------------------------------------------------------------- densities and steps


@pytest.mark.parametrize("step", [1e-9, 1e-3, 1.0, 1e3])
@pytest.mark.parametrize("sigma", [1e6, 1e12])
def test_dense_slab_is_opaque_at_its_surface_for_any_step(step, sigma):
    """A slab of density sigma beginning at t = 2 sampled with steps from 1e-9 to 1e3: the opacity
    of its 32 samples is 1 - exp(-32 sigma step) (1 unless the slab is thinner than ~1e-6), the depth
    within one step of the surface once a sample is opaque, gradients finite."""
    k = 64
    t_start = 2.0 + (torch.arange(k, dtype=torch.float64) - k / 2) * step
    t_mid = (t_start + step / 2).float()[None]
    density = torch.where(t_start >= 2.0, sigma, 0.0).float()[None].requires_grad_(True)
    colours = torch.rand(1, k, 3, requires_grad=True)
    weights = rendering.render_weights(density, torch.full((1, k), step))
    depth = rendering.expected_depth(weights, t_mid)
    (rendering.accumulate(weights, colours).sum() + depth.sum()).backward()
    opacity = -np.expm1(-min(sigma * step * k / 2, rendering.MAX_OPTICAL_THICKNESS))
    assert float(rendering.accumulation(weights).detach()) == pytest.approx(opacity, abs=1e-6)
    if sigma * step >= 20:  # the first sample inside is opaque: its colour is the ray's
        assert abs(float(depth) - 2.0) <= step
    assert torch.isfinite(density.grad).all() and torch.isfinite(colours.grad).all()


@pytest.mark.parametrize("overrides, warned", [
    ({"step_ratio": 1e-9}, "step_ratio"), ({"step_ratio": 1e3}, None),
    ({"detail_size": 1e-9, "max_resolution": 24}, "max_resolution 24"),
    ({"default_cells": 1000, "max_resolution": 24}, "max_resolution 24"), ({"detail_size": 1e3}, None)])
def test_extreme_steps_through_the_model_stay_bounded_and_finite(overrides, warned, caplog):
    """Steps of 1e-9 and 1e3 scene units asked for through the config: a step finer than the grid
    (or than MAX_STEPS_ACROSS_BOX across the box) is widened with a warning instead of allocating
    billions of samples per ray; huge steps still put one sample in the box."""
    caplog.set_level(logging.WARNING, logger="srfpipe.srf.model")
    model = tiny_model(3, **overrides)
    warnings = " ".join(r.getMessage() for r in caplog.records)
    assert (warned in warnings) if warned else not warnings
    settings = model.settings
    assert np.linalg.norm(CUBE[1] - CUBE[0]) / settings.step <= MAX_STEPS_ACROSS_BOX + 1e-6
    origins, directions = rays(32)
    out = model(origins, directions)
    per_ray = out["samples"] / 32
    assert 1 <= per_ray <= MAX_STEPS_ACROSS_BOX + settings.outer_samples + settings.before_samples + 3
    (out["rgb"].sum() + out["depth"].sum() + out["distortion"]).backward()
    assert torch.isfinite(out["rgb"]).all() and torch.isfinite(out["depth"]).all()
    assert assert_finite_gradients(model) > 0


INF = float("inf")


@pytest.mark.parametrize("packed", [False, True])
def test_infinite_density_or_step_times_zero_renders_nothing_and_keeps_gradients_finite(packed):
    """sigma * delta where one factor is infinite and the other 0: a padded slot (delta = 0) of
    infinite density, an empty last interval reaching to infinity. Such a slot adds nothing
    (0 * inf was NaN, and packed, the running sum carried the NaN into every later ray); an
    infinite step of positive density is opaque with a finite gradient (0 * inf in the backward),
    and an infinite density opaque over any step."""
    sigma = torch.tensor([[1.0, INF, INF], [1.0, 1.0, 0.0], [1.0, 1.0, 2.0], [0.0, 0.0, 0.0], [1e30, 0.0, 1.0],
                          [INF, 1.0, 1.0]])
    delta = torch.tensor([[0.1, 0.1, 0.0], [0.1, 0.1, INF], [0.1, 0.1, INF], [INF, INF, INF], [0.1, 1e-30, 1e30],
                          [1e-30, 0.1, 0.1]])
    expected = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0],
                             [1.0, 0.0, 0.0]])
    expected[:3, :2] = torch.tensor([-math.expm1(-0.1), math.exp(-0.1) * -math.expm1(-0.1)])
    expected[0, 1] = math.exp(-0.1)  # the infinite density at 0.1 takes all that is left
    expected[2, 2] = math.exp(-0.2)
    sigma.requires_grad_(True)
    colours = torch.rand(6, 3, 3, requires_grad=True)
    if packed:
        segments = rendering.Segments.of(torch.arange(6).repeat_interleave(3), 6)
        weights = rendering.render_weights(sigma.reshape(-1), delta.reshape(-1), segments).view(6, 3)
        acc = rendering.accumulation(weights.reshape(-1), segments)
        rgb = rendering.accumulate(weights.reshape(-1), colours.reshape(-1, 3), segments)
    else:
        weights = rendering.render_weights(sigma, delta)
        acc, rgb = rendering.accumulation(weights), rendering.accumulate(weights, colours)
    torch.testing.assert_close(weights.detach(), expected, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(acc.detach(), expected.sum(-1), rtol=1e-6, atol=1e-7)
    (rgb.sum() + acc.sum()).backward()
    assert torch.isfinite(sigma.grad).all() and torch.isfinite(colours.grad).all()


@pytest.mark.parametrize("far", [1e9, 1e30])
def test_a_far_plane_at_any_distance_gives_finite_intervals_and_renders(far):
    """train.far 1e9 or 1e30 (the schema takes any finite positive number): the contracted shell's
    last interval ended at t = inf (disparity 1 - s rounded to 0 in float32), whose midpoint was NaN
    once contracted, which crashed the grid lookup. An infinite far is refused, naming the key."""
    from srfpipe.config import ConfigError
    from srfpipe.srf.sampling import generate_intervals

    with pytest.raises(ConfigError, match="train.far: inf is not a finite number"):
        tiny_model(3, far=INF)
    model = tiny_model(3, far=far).train()
    origins, directions = rays(8)
    t_start, t_end = generate_intervals(origins, directions, model.field.box_min, model.field.box_max,
                                        model.settings)
    assert torch.isfinite(t_end).all() and (t_end >= t_start).all() and (t_end <= far).all()
    assert (t_end[:, -1] > 1e6).all()  # still far beyond the box (a half-side of 1)
    out = model(origins, directions)
    (out["rgb"].sum() + out["logits"].sum() + out["distortion"]).backward()
    assert all(torch.isfinite(out[key]).all() for key in ("rgb", "logits", "depth", "accumulation", "distortion"))
    assert assert_finite_gradients(model) > 0


def test_densities_up_to_1e12_distill_into_a_finite_cache(tmp_path):
    from srfpipe.occupancy import AnalyticField, OccupancyCache, distill

    centre = np.array([0.1, 0.0, -0.1])
    for sigma in (1e-6, 1e12):
        field = AnalyticField(["apple"], CUBE, sigma=sigma).add_sphere(centre, 0.5, "apple")
        cache = OccupancyCache.load(distill(field, tmp_path / f"o{sigma}.zarr", {"voxels_across": 24},
                                            progress=False))
        density = cache.density(np.array([centre, [0.9, 0.9, 0.9]]))
        assert np.isfinite(density).all() and density[1] == 0
        assert density[0] == pytest.approx(sigma, rel=1e-6) if sigma > 1 else density[0] <= sigma
        assert bool(cache.occupancy(centre[None])[0]) == (sigma > 1)  # 1e-6 per unit is free space


# ------------------------------------------------------------------------------- degenerate cases


def slab_model(contraction: bool = False, z_range=(-0.25, 0.25)) -> SRFModel:
    """A field over the cube [-1, 1]^3 (scene frame = world) whose density is opaque in the slab
    z_range and empty elsewhere: the density grid set directly, 17 grid points per axis."""
    model = tiny_model(3, contraction=contraction)
    grid = model.field.inner_sigma
    rx, ry, rz = grid.resolution
    z = torch.linspace(-1.0, 1.0, rz)
    inside = (z >= z_range[0] - 1e-6) & (z <= z_range[1] + 1e-6)
    with torch.no_grad():
        grid.table.view(rx, ry, rz)[:] = torch.where(inside, 40.0, -40.0)
        if model.field.outer_sigma is not None:  # the contracted shell: empty (not the initial fog)
            model.field.outer_sigma.table.fill_(-40.0)
    return model.eval()


def test_rendered_depth_of_a_known_plane_and_opacity_of_a_dense_slab():
    model = slab_model()
    cell = 2.0 / (model.field.inner_sigma.resolution[2] - 1)
    origins = torch.tensor([[0.1, -0.2, 3.0], [0.3, 0.4, 3.0], [-0.5, 0.2, 3.0]])
    directions = torch.tensor([[0.0, 0.0, -1.0], [0.1, 0.0, -1.0], [0.0, -0.2, -1.0]])
    directions = directions / directions.norm(dim=1, keepdim=True)
    out = model(origins, directions)
    expected = (3.0 - 0.25) / -directions[:, 2]  # the distance along each ray to the plane z = 0.25
    np.testing.assert_allclose(out["accumulation"].detach(), 1.0, atol=1e-5)
    np.testing.assert_allclose(out["depth"].detach(), expected, atol=cell)


def test_camera_inside_geometry_sees_opaque_matter_at_the_near_plane():
    model = slab_model()
    origins = torch.zeros(6, 3)
    directions = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    out = model(origins, directions)
    (out["rgb"].sum() + out["logits"].sum()).backward()
    np.testing.assert_allclose(out["accumulation"].detach(), 1.0, atol=1e-5)
    assert (out["depth"] <= model.settings.near + 2 * model.settings.step).all()
    assert torch.isfinite(out["rgb"]).all() and assert_finite_gradients(model) > 0


@pytest.mark.parametrize("contraction", [False, True])
def test_rays_that_miss_the_box_see_the_background(contraction):
    """Rays leaving the box: without contraction they have no samples at all (rgb = the
    background, opacity 0, depth 0); with it, only the contracted shell's samples (empty here)."""
    model = slab_model(contraction)
    model.occupancy.update(model.field.sigma, torch.Generator().manual_seed(0), all_cells=True)
    origins = torch.tensor([[3.0, 3.0, 3.0], [0.0, 0.0, 5.0], [-4.0, 0.0, 0.0]])
    directions = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    out = model(origins, directions)
    (out["rgb"].sum() + out["logits"].sum()).backward()
    if not contraction:
        assert out["samples"] == 0 and out["kept_samples"].sum() == 0
    np.testing.assert_allclose(out["accumulation"].detach(), 0.0, atol=1e-4)
    background = model.field.background(directions).detach()
    torch.testing.assert_close(out["rgb"].detach(), background, atol=1e-4, rtol=0)
    assert torch.isfinite(out["depth"]).all() and assert_finite_gradients(model) > 0


def test_class_present_in_one_frame_only_trains_and_evaluates(synthetic, tmp_path, device):
    """apple only in frame 0 (held out: never seen in training), branch only in frame 1 (trained
    on): the heads train, the loss stays finite, metrics.json has no NaN (None where undefined)."""
    from srfpipe.evaluate import evaluate
    from srfpipe.srf.io import read_curve

    _, images, labels = synthetic
    group = open_artifact(labels, stage="composite")
    label = np.asarray(group["label"][...])
    for value, frame in ((1, 0), (2, 1)):
        others = np.arange(len(label)) != frame
        label[others] = np.where(label[others] == value, 0, label[others])
    assert (label[0] == 1).any() and (label[1] == 2).any()
    one_frame = write_labels(tmp_path / "labels.zarr", label, ["apple", "branch", "leaf"], meta(group)["names"])
    out = tmp_path / "srf.zarr"
    train(images, one_frame, out, tiny_options(), holdout_every=3)
    curve = read_curve(out)
    assert np.isfinite(curve["semantic"]).all() and np.isfinite(curve["loss"]).all()
    evaluate(images, one_frame, out, tmp_path / "eval", {"holdout_every": 3}, device=device)

    def no_nan(name):
        raise AssertionError(f"metrics.json holds {name}")

    metrics = json.loads((tmp_path / "eval" / "metrics.json").read_text(), parse_constant=no_nan)
    assert set(metrics["iou"]) == {"background", "apple", "branch", "leaf"}
    assert all(v is None or 0 <= v <= 1 for v in metrics["iou"].values())
    assert 0 <= metrics["miou"] <= 1 and np.isfinite(metrics["psnr"])

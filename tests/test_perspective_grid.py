"""The perspective grid (`train.grid_frame: perspective`, srf/warp.py) for captures whose cameras
all look one way: cells that span the same pixels near and far, samples that tile every ray,
coordinates that stay finite anywhere, and a forward-facing capture that trains through it."""

import logging
import math

import numpy as np
import pytest
import torch

from srfpipe.cameras import look_at
from srfpipe.config import section_defaults
from srfpipe.srf.field import contract, grid_points, uncontract
from srfpipe.srf.io import read_curve, read_srf
from srfpipe.srf.model import SRFModel, build_model_config
from srfpipe.srf.sampling import generate_intervals
from srfpipe.srf.synthetic import write_scene
from srfpipe.srf.trainer import train
from srfpipe.srf.warp import looks_one_way

WIDTH, HEIGHT, FOCAL = 80, 60, 70.0
# held-out PSNR of the forward-facing test capture at 120 steps: the box grid reaches 20.78 dB, the
# perspective grid 20.90 (a perspective grid capped at the box's 24 cells, 2 px each: 19.1)
HELDOUT_PSNR = 20.0
BOX = np.array([[-8.0, -6.0, 3.0], [8.0, 6.0, 30.0]])  # from 3 to 30 units in front of the cameras


def forward_rig():
    """12 cameras on a 2 x 1 patch of the plane z = 0, all looking down +z (OpenCV axes)."""
    poses = [look_at(np.array([x, y, 0.0]), np.array([x * 0.5, y * 0.5, 10.0]), up=np.array([0.0, -1.0, 0.0]))
             for x in np.linspace(-1, 1, 4) for y in np.linspace(-0.5, 0.5, 3)]
    poses = torch.tensor(np.stack(poses), dtype=torch.float32)
    intrinsics = torch.tensor([[FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2]] * len(poses))
    return poses, intrinsics


def perspective_model(cells: int = 64, **options) -> SRFModel:
    poses, intrinsics = forward_rig()
    config = build_model_config({"grid_frame": "perspective", "default_cells": cells, **options}, BOX, np.eye(4),
                                ["apple"], len(poses), cameras=(poses, intrinsics, WIDTH, HEIGHT))
    return SRFModel(config)


def cell_pixels(model: SRFModel, depth: float) -> tuple[float, float]:
    """(across, deep) size in pixels of the centre camera's view of one grid cell at `depth` on the axis:
    the world distance between neighbouring grid points, times focal / depth."""
    field = model.field
    u = field.box_coordinates(torch.tensor([[0.0, 0.0, depth]]))
    res = torch.tensor(model.config["inner"]["resolution"], dtype=torch.float32)
    cell_u = 2.0 / (res - 1)
    points = grid_points(torch.cat([u, u + cell_u * torch.eye(3)]), field.grid_min, field.grid_max, field.warp)
    across = float((points[1] - points[0]).norm())
    deep = float((points[3] - points[0]).norm())
    return across * FOCAL / depth, deep * FOCAL / depth


def test_a_cell_spans_the_same_pixels_near_and_far_where_a_box_cell_does_not():
    model = perspective_model()
    near, far = cell_pixels(model, 4.0), cell_pixels(model, 28.0)
    assert near[0] == pytest.approx(far[0], rel=0.02) and near[1] == pytest.approx(far[1], rel=0.02)
    # one pixel across where 64 points allow it, else the 64 points over the views' width
    assert 1.0 <= near[0] <= 2.5, near
    # as deep as wide where the cell cap allows: here 64 points over a depth ratio of 10 (ln 10 = 2.3)
    # against 98 cells of the width's log step, so 1.5 times as deep
    assert near[0] <= near[1] <= 2.0 * near[0], near
    poses, intrinsics = forward_rig()
    box = SRFModel(build_model_config({"default_cells": 64}, BOX, np.eye(4), ["apple"], len(poses)))
    box_near, box_far = cell_pixels(box, 4.0), cell_pixels(box, 28.0)
    assert box_near[0] > 5.0 * box_far[0], (box_near, box_far)  # the box's near cells are 7x as coarse in pixels


def test_coordinates_round_trip_in_front_and_stay_finite_anywhere():
    model = perspective_model()
    field, grid = model.field, model.occupancy
    front = torch.tensor([[0.5, -0.3, 5.0], [-2.0, 1.0, 25.0], [0.0, 0.0, 12.0]])
    assert torch.allclose(grid._x(grid._u(front)), front, rtol=1e-4, atol=1e-4)
    inside = field.box_coordinates(front)
    assert (inside.abs() <= 1.0).all()
    # behind the cameras, on their plane, absurdly far: finite, and in the contracted shell
    hostile = torch.tensor([[0.0, 0.0, -5.0], [0.0, 0.0, 0.0], [1e6, -1e6, 1e7], [3.0, 0.0, 1e-9]])
    u = field.box_coordinates(hostile)
    assert torch.isfinite(u).all() and (u.abs().amax(dim=-1) > 1.0).all()
    assert torch.isfinite(contract(u)).all()
    # the shell's outermost cells map back to finite scene points (occupancy updates sample them)
    edge = torch.tensor([[2.0 - 1e-4, 0.0, 0.0], [0.0, -2.0 + 1e-4, 2.0 - 1e-4], [0.0, 0.0, -2.0 + 1e-4]])
    assert torch.isfinite(grid._x(uncontract(edge))).all()
    assert torch.isfinite(field.sigma(hostile)).all()


def test_samples_tile_every_ray_in_log_steps_without_gaps():
    model = perspective_model()
    poses, intrinsics = forward_rig()
    generator = torch.Generator().manual_seed(0)
    # the cameras' rays, and rays from inside the grid (whose chord's depth ratio is the largest)
    origins = torch.cat([poses[:, :3, 3].repeat(20, 1), torch.rand(60, 3, generator=generator) * 4 + torch.tensor([-2, -2, 4.0])])
    directions = torch.nn.functional.normalize(
        torch.cat([poses[:, :3, 2].repeat(20, 1), torch.zeros(60, 3)]) + 0.3 * torch.randn(300, 3, generator=generator), dim=-1)
    settings = model.settings
    jitter = torch.rand(300, generator=generator)
    t_start, t_end = generate_intervals(origins, directions, model.field.box_min, model.field.box_max, settings, jitter,
                                        model.extent)
    assert torch.isfinite(t_start).all() and (t_end >= t_start).all()
    # the intervals of positive length tile [near, far]: no gap, no overlap (a ray that misses the
    # grid keeps zero-length ones where it would have entered)
    for starts, ends in zip(t_start, t_end):
        kept = ends > starts
        starts, ends = starts[kept], ends[kept]
        assert starts[0] == settings.near and ends[-1] >= settings.far * 0.999
        assert torch.equal(starts[1:], ends[:-1])
    # inside the grid the steps grow with t: the ratio of consecutive interval ends is exp(log_step)
    rays = poses.shape[0]
    inner = t_end[:rays, settings.before_samples + 2:settings.before_samples + 20]
    ratio = inner[:, 1:] / inner[:, :-1]
    assert torch.allclose(ratio, torch.full_like(ratio, math.exp(settings.log_step)), rtol=1e-3)


def test_cameras_round_a_subject_are_told_to_use_the_box():
    ring = np.stack([look_at(np.array([5.0 * np.cos(a), 5.0 * np.sin(a), 1.0]), np.zeros(3))
                     for a in np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)])
    poses = torch.tensor(ring, dtype=torch.float32)
    intrinsics = torch.tensor([[FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2]] * len(poses))
    box = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    with pytest.raises(ValueError, match="they stand round what they look at: use grid_frame: box"):
        build_model_config({"grid_frame": "perspective"}, box, np.eye(4), ["apple"], 8,
                           cameras=(poses, intrinsics, WIDTH, HEIGHT))
    with pytest.raises(ValueError, match="from the training cameras"):
        build_model_config({"grid_frame": "perspective"}, box, np.eye(4), ["apple"], 8)


def test_auto_chooses_the_perspective_grid_only_for_cameras_that_look_one_way():
    forward, intrinsics = forward_rig()
    assert looks_one_way(forward.numpy())
    ring = np.stack([look_at(np.array([5.0 * np.cos(a), 5.0 * np.sin(a), 1.0]), np.zeros(3))
                     for a in np.linspace(0.0, 2.0 * np.pi, 8, endpoint=False)])
    assert not looks_one_way(ring)
    # half a turn round a subject: the cameras stand round it, though they all face one half-space
    half = np.stack([look_at(np.array([5.0 * np.cos(a), 5.0 * np.sin(a), 1.0]), np.zeros(3))
                     for a in np.linspace(0.0, np.pi, 8)])
    assert not looks_one_way(half)
    auto = build_model_config({"grid_frame": "auto", "default_cells": 64}, BOX, np.eye(4), ["apple"], len(forward),
                              cameras=(forward, intrinsics, WIDTH, HEIGHT))
    assert auto["warp"]["type"] == "perspective"
    # without cameras to lay it out from, the box
    assert "warp" not in build_model_config({"grid_frame": "auto"}, BOX, np.eye(4), ["apple"], len(forward))


def test_auto_keeps_the_box_grid_where_the_cameras_barely_see_the_box(caplog):
    """Bounds given beside the views (a config box the forward cameras do not look into): a
    perspective grid cannot be laid out there. Asked for, it is a clear error; by default (auto) the
    box grid is built, in the trainer and in build_model_config alike, and the log says why."""
    from tests.test_train import camera_ring_data
    from srfpipe.srf.trainer import resolve_data_defaults

    poses, intrinsics = forward_rig()
    aside = BOX + np.array([200.0, 0.0, 0.0])  # far to the side of every view
    cameras = (poses, intrinsics, WIDTH, HEIGHT)
    with pytest.raises(ValueError, match="use grid_frame: box"):
        build_model_config({"grid_frame": "perspective"}, aside, np.eye(4), ["apple"], len(poses), cameras=cameras)
    assert "warp" not in build_model_config({"grid_frame": "auto"}, aside, np.eye(4), ["apple"], len(poses),
                                            cameras=cameras)
    data = camera_ring_data(FOCAL, n=len(poses))
    data.poses_scene, data.intrinsics, data.width, data.height = poses, intrinsics, WIDTH, HEIGHT
    data.scene_from_world = np.eye(4)
    data.bounds_world = BOX
    assert resolve_data_defaults({"grid_frame": "auto"}, data).grid_frame == "perspective"
    data.bounds_world = aside
    with caplog.at_level(logging.WARNING, logger="srfpipe.train"):
        assert resolve_data_defaults({"grid_frame": "auto"}, data).grid_frame == "box"
    assert "see next to nothing of the model box" in caplog.text


def test_a_forward_facing_capture_trains_through_the_perspective_grid(tmp_path):
    images, labels = write_scene(tmp_path, views=10, width=32, height=24, arc_deg=40.0)
    out = tmp_path / "srf.zarr"
    options = section_defaults("train")
    options.update(iterations=120, rays_per_batch=512, outer_resolution=12, hidden=32, outer_samples=16,
                   before_samples=8, checkpoint_every=0, log_every=10, eval_every=120, occupancy_update_every=8,
                   occupancy_warmup=16, time_budget=0, grid_frame="auto")
    train(images, labels, out, options, holdout_every=5)
    model, attrs = read_srf(out)
    # auto chose the perspective grid for these cameras, which span 40 degrees of a ring
    assert attrs["config"]["grid_frame"] == "perspective"
    assert model.config["warp"]["type"] == "perspective" and model.settings.log_step > 0
    heldout = read_curve(out, "eval_curve")["psnr"][-1]
    assert heldout > HELDOUT_PSNR, heldout

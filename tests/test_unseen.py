"""Space no training camera sees is empty: nothing is lost that a training ray samples, and what no
camera saw is neither rendered nor queried (the wall the fox grew before a held-out camera)."""

import numpy as np
import pytest
import torch

from srfpipe.artifacts import reseal_artifact
from srfpipe.cameras import look_at
from srfpipe.srf.data import image_rays
from srfpipe.srf.sampling import OccupancyGrid, spheres_in_view

WIDTH, HEIGHT = 40, 30
INTRINSICS = torch.tensor([[36.0, 36.0, 20.0, 15.0]])


def ring_cameras(count: int = 6, radius: float = 2.5) -> torch.Tensor:
    """Cameras on an arc around the origin at box distance 2.5 (in the shell), looking at the origin."""
    angles = np.linspace(0.0, np.pi, count)
    poses = [look_at((radius * np.cos(a), radius * np.sin(a), 0.3), (0.0, 0.0, 0.0)) for a in angles]
    return torch.as_tensor(np.stack(poses), dtype=torch.float32)


def marked_grid(poses, half: float = 1.0):
    grid = OccupancyGrid([-half] * 3, [half] * 3, (16, 16, 16), True, outer_resolution=16)
    fractions = grid.mark_seen(poses, INTRINSICS.expand(len(poses), 4), WIDTH, HEIGHT)
    return grid, fractions


def test_sphere_test_keeps_the_frustum_and_drops_what_lies_behind_or_beside():
    pose = ring_cameras(1)  # at (2.5, 0, 0.3), looking at the origin
    k = INTRINSICS
    centres = torch.tensor([[0.0, 0.0, 0.0],      # straight ahead
                            [5.0, 0.0, 0.3],      # behind the camera
                            [2.5, 2.0, 0.3]])     # far to the side, level with the camera
    meets, within = spheres_in_view(centres, 0.01, pose, k, WIDTH, HEIGHT)
    assert meets.tolist() == [True, False, False] and within.tolist() == [True, False, False]
    # a sphere beside the frustum whose surface reaches into it counts as seen, not as inside
    meets, within = spheres_in_view(centres[2:], 3.0, pose, k, WIDTH, HEIGHT)
    assert meets.tolist() == [True] and within.tolist() == [False]


def test_training_rays_lose_no_sample_and_rendering_keeps_nearly_all():
    poses = ring_cameras()
    grid, fractions = marked_grid(poses)
    assert 0.0 < fractions["shell"] < 1.0
    generator = torch.Generator().manual_seed(0)
    points = []
    for pose in poses:
        origins, directions = image_rays(pose, INTRINSICS[0], WIDTH, HEIGHT)
        t = 0.05 + 30.0 * torch.rand(origins.shape[0], 1, generator=generator) ** 3  # near and far
        points.append(origins + directions * t)
    points = torch.cat(points)
    assert bool(grid.train().occupied(points).all())  # the untrained grid: nothing is dropped
    # a shell cell on a view's boundary goes with its centre: some points at the views' edges near
    # these few, small cameras fall in cells counted as unseen, which only rendering skips
    assert float(grid.seen(points).float().mean()) > 0.9
    assert float(grid.eval().occupied(points).float().mean()) > 0.9


@pytest.mark.parametrize("half", [1.0, 4.0])  # the cameras in the shell, and inside the box
def test_space_no_camera_sees_is_never_occupied(half):
    poses = ring_cameras()
    grid, _ = marked_grid(poses, half)
    # behind the arc of cameras, and high above and below the box they look at (the shell's far
    # cells are large and count as seen once any part of them is: these lie within a few box sizes)
    behind = torch.tensor([[0.0, 3.5, 0.3], [0.5, 3.3, 0.0], [0.0, 6.0, 0.3], [0.0, 0.0, -3.0], [0.0, 0.0, 3.0]])
    assert not bool(grid.seen(behind).any())
    grid.occ1.fill_(1.0)
    grid.binary1.fill_(True)
    # the occupancy update never marks an unseen box cell again, whatever the field's density
    grid.update(lambda x: torch.full((x.shape[0],), 1e3), torch.Generator().manual_seed(0), all_cells=True)
    assert not bool(grid.eval().occupied(behind).any())  # what rendering samples
    assert bool(grid.occupied(torch.zeros(1, 3)).all())
    if half > 2.5:
        assert int(grid.binary0.sum()) == int(grid.seen0.sum()) < grid.seen0.numel()


@pytest.mark.parametrize("drop", [False, True])
def test_srf_zarr_keeps_the_mark_and_reads_one_written_without_it(tmp_path, drop, device):
    import zarr

    from srfpipe.config import section_defaults
    from srfpipe.srf.io import read_srf
    from srfpipe.srf.query import SemanticRadianceField
    from srfpipe.srf.synthetic import write_scene
    from srfpipe.srf.trainer import train

    images, labels = write_scene(tmp_path, views=6, width=24, height=18)
    options = section_defaults("train")
    options.update(iterations=4, rays_per_batch=64, default_cells=12, outer_resolution=8, hidden=16,
                   outer_samples=8, before_samples=4, time_budget=0, occupancy_warmup=2,
                   occupancy_update_every=2)
    out = tmp_path / "srf.zarr"
    train(images, labels, out, options, holdout_every=3)
    model, _ = read_srf(out)
    seen1 = model.occupancy.seen1.clone()
    assert not bool(seen1.all())  # the cameras do not see the whole shell
    if drop:  # as an srf.zarr written before the mark existed
        for key in ("occupancy.seen0", "occupancy.seen1"):
            del zarr.open_group(out / "weights", mode="a")[key]
        reseal_artifact(out)  # a deliberate edit of a finished artifact
        model, _ = read_srf(out)
        assert bool(model.occupancy.seen1.all()) and bool(model.occupancy.seen0.all())
    else:
        assert torch.equal(model.occupancy.seen1, seen1)
    # Occupancy(x) is zero where no camera saw, whatever the field holds there: this scene's
    # cameras see its whole box, so the test marks half of the box unseen
    field = SemanticRadianceField.load(out, device=device)
    lo, hi = field.bounds_world
    points = lo + (hi - lo) * np.random.default_rng(0).uniform(0.0, 1.0, (2000, 3))
    before = field.density(points)
    assert np.count_nonzero(before) > 1000
    field.model.occupancy.seen0[: field.model.occupancy.seen0.numel() // 2] = False
    x = field._to_scene(points)
    unseen = ~field.model.occupancy.seen(x).cpu().numpy()
    after = field.density(points)
    assert 0 < unseen.sum() < len(points)
    assert np.all(after[unseen] == 0.0) and np.array_equal(after[~unseen], before[~unseen])

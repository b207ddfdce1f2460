"""Random draws on any device (issue 31): a per-step CPU generator with a CUDA model crashed the
occupancy update at step 16 ("Expected a 'cuda' device type for generator but found 'cpu'").

Every seeded draw goes through `srfpipe.device.rand` / `randint` / `randperm`, which draw on the
generator's device and move the result. Without a GPU these tests still catch the bug class: the
source scan finds any other `generator=` call, the helpers must match a plain CPU draw value for
value, and the "meta" device stands in for a non-CPU target (a draw left on the CPU would meet meta
tensors and fail). With a GPU, the `device` fixture runs the occupancy update, the batch sampler,
the TV estimate and a short training on CUDA with the CPU step generators.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
import torch

from srfpipe.device import rand, randint, randperm
from srfpipe.srf.sampling import OccupancyGrid
from srfpipe.srf.trainer import step_generator

PACKAGE = Path(__file__).resolve().parent.parent / "srfpipe"
HELPERS = PACKAGE / "device.py"


def generator_calls(path: Path) -> list[str]:
    """'file:line call' for every call in `path` that passes a `generator=` keyword."""
    tree = ast.parse(path.read_text(), filename=str(path))
    calls = [node for node in ast.walk(tree) if isinstance(node, ast.Call)
             and any(keyword.arg == "generator" for keyword in node.keywords)]
    return [f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {ast.unparse(node.func)}(...)"
            for node in sorted(calls, key=lambda node: node.lineno)]


def test_no_draw_outside_the_device_helpers_passes_a_generator():
    """torch.rand(..., generator=g, device=d) fails when g and d differ (a CPU step generator, a
    CUDA model): every seeded draw must go through srfpipe.device's helpers instead."""
    files = sorted(PACKAGE.rglob("*.py"))
    assert HELPERS in files and len(files) > 20
    offending = [call for path in files if path != HELPERS for call in generator_calls(path)]
    assert offending == [], "draw through srfpipe.device.rand/randint/randperm instead:\n" + "\n".join(offending)
    # the scan sees the calls it forbids: the helpers themselves pass generator=
    assert len(generator_calls(HELPERS)) == 3


def test_helpers_return_the_same_values_as_a_plain_cpu_draw_on_the_requested_device(device):
    """Same seed, same numbers, whatever the target device: one generator feeds several draws
    in a row (as a training step does) and each matches the plain CPU draw of that position."""
    helper, plain = torch.Generator().manual_seed(31), torch.Generator().manual_seed(31)
    drawn = [rand((5, 3), helper, device), randint(2, 9, 11, helper, device), randperm(7, helper, device),
             rand(4, helper, device, dtype=torch.float64), randint(0, 1 << 40, (2, 3), helper, device)]
    expected = [torch.rand(5, 3, generator=plain), torch.randint(2, 9, (11,), generator=plain),
                torch.randperm(7, generator=plain), torch.rand(4, generator=plain, dtype=torch.float64),
                torch.randint(0, 1 << 40, (2, 3), generator=plain)]
    for got, want in zip(drawn, expected):
        assert got.device.type == device.type and got.dtype == want.dtype
        assert torch.equal(got.cpu(), want)


def test_without_a_generator_the_helpers_draw_from_the_global_cpu_generator(device):
    torch.manual_seed(5)
    got = rand(6, None, device), randint(0, 100, 6, None, device)
    torch.manual_seed(5)
    want = torch.rand(6), torch.randint(0, 100, (6,))
    assert all(g.device.type == device.type and torch.equal(g.cpu(), w) for g, w in zip(got, want))


def test_helpers_move_their_draw_to_a_non_cpu_device():
    """'meta' stands in for CUDA on a machine without one: the helpers must hand back tensors on
    the requested device, not the generator's."""
    generator = torch.Generator().manual_seed(0)
    values = rand((4, 3), generator, "meta"), randint(0, 10, 8, generator, "meta"), randperm(5, generator, "meta")
    assert [v.device.type for v in values] == ["meta"] * 3
    assert [tuple(v.shape) for v in values] == [(4, 3), (8,), (5,)]
    assert [v.dtype for v in values] == [torch.float32, torch.int64, torch.int64]


@pytest.mark.parametrize("level", [0, 1])
def test_occupancy_jitter_lands_on_the_grids_device(level):
    """An occupancy grid on a non-CPU device ('meta') jitters its cells with the CPU step
    generator: a jitter left on the CPU (or drawn for the wrong device) would fail against the
    grid's meta tensors."""
    grid = OccupancyGrid([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], (6, 5, 4), contraction=True,
                         outer_resolution=8).to("meta")
    cells = torch.arange(50, device="meta")
    points = grid._cell_points(level, cells, step_generator(0, 16))
    assert points.device.type == "meta" and tuple(points.shape) == (50, 3)


def density(points: torch.Tensor) -> torch.Tensor:
    """A smooth blob: every jittered point gives a different value, so a different draw shows."""
    return 50.0 * torch.exp(-4.0 * points.square().sum(dim=-1))


def test_occupancy_update_on_the_device_with_a_cpu_step_generator_matches_the_cpu(device):
    """The crash of issue 31 (the first occupancy update, step 16 by default, jitters its cells
    with the step generator; after warm-up it also draws random cells): the same (seed, step)
    generators update a grid on `device` as they update one on the CPU."""
    grids = {}
    for where in ("cpu", device):
        grid = OccupancyGrid([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0], (12, 10, 8), contraction=True,
                             outer_resolution=8, step=0.1).to(where)
        for step in (8, 16, 24):  # warm-up (every cell), then random cells plus occupied ones
            grid.update(density, step_generator(0, step), all_cells=step < 16)
        grids[str(where)] = grid
    cpu, other = grids["cpu"], grids[str(device)]
    assert other.occ0.device.type == device.type
    for name in ("occ0", "occ1"):
        torch.testing.assert_close(getattr(other, name).cpu(), getattr(cpu, name), rtol=1e-5, atol=1e-6)
    assert 0.0 < cpu.occupied_fraction() < 1.0


def test_batch_sampling_and_tv_estimate_draw_the_same_with_the_model_on_the_device(tmp_path, device):
    from srfpipe.srf.data import load_posed_images, split_views
    from srfpipe.srf.losses import total_variation
    from srfpipe.srf.synthetic import write_scene
    from srfpipe.srf.trainer import sample_batch

    images, labels = write_scene(tmp_path, views=4, width=16, height=12)
    data = load_posed_images(images, labels)
    train_views, _ = split_views(data.count, 4)
    on_cpu = sample_batch(data, train_views, 64, step_generator(3, 16), torch.device("cpu"))
    on_device = sample_batch(data, train_views, 64, step_generator(3, 16), device)
    for want, got in zip(on_cpu, on_device):
        assert got.device.type == device.type and torch.equal(got.cpu(), want)

    table = torch.linspace(0.0, 1.0, 6 * 7 * 8).reshape(-1, 1)
    want = total_variation(table, (6, 7, 8), 100, step_generator(3, 16))
    got = total_variation(table.to(device), (6, 7, 8), 100, step_generator(3, 16))
    assert got.device.type == device.type
    torch.testing.assert_close(got.cpu(), want)


def test_training_past_the_first_random_occupancy_update_runs_on_the_device(tmp_path, device):
    """A short real training on `device` (CUDA when present) through the draws that crashed:
    occupancy updates (warm-up, then random cells) and the TV estimate at random cells."""
    from srfpipe.srf.io import read_curve
    from srfpipe.srf.synthetic import write_scene
    from srfpipe.srf.trainer import train
    from test_train import tiny_options

    images, labels = write_scene(tmp_path, views=6, width=16, height=12)
    options = tiny_options(iterations=20, rays_per_batch=64, default_cells=12, outer_resolution=8,
                           occupancy_update_every=4, occupancy_warmup=8, checkpoint_every=0, log_every=10,
                           tv_density=1e-3, tv_samples=64, device=str(device))
    summary = train(images, labels, tmp_path / "srf.zarr", options, holdout_every=3)
    assert summary["iterations"] == 20 and summary["device"] == str(device)
    curve = read_curve(tmp_path / "srf.zarr")
    assert list(curve["step"]) == [10, 20] and all(torch.isfinite(torch.as_tensor(curve["loss"])))

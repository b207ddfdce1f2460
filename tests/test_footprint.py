"""Model only what a scene requires (issue 12): one class trains one head, the grid and the cache
follow the scene's bounds and voxel size, and empty space costs neither samples nor storage
(`samples_skipped_fraction` in eval/metrics.json, `bytes_on_disk` / `dense_bytes` of occupancy.zarr)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from srfpipe.artifacts import MANIFEST_NAME, meta, open_artifact, read_provenance
from srfpipe.cameras import scene_from_world_transform
from srfpipe.config import section_defaults
from srfpipe.occupancy import AnalyticField, VoxelGrid, distill
from srfpipe.occupancy.distill import choose_voxel_size, resolve_options
from srfpipe.srf.model import build_model_config
from srfpipe.srf.synthetic import write_labels, write_scene
from test_stability import rays, slab_model, tiny_options


def test_a_scene_with_one_class_trains_exactly_one_head(tmp_path):
    from srfpipe.srf.io import read_srf
    from srfpipe.srf.trainer import train

    images, labels = write_scene(tmp_path, views=6, width=24, height=16)
    group = open_artifact(labels, stage="composite")
    label = np.asarray(group["label"][...])
    only_apple = write_labels(tmp_path / "apple.zarr", np.where(label == 1, 1, 0).astype(np.uint8), ["apple"],
                              meta(group)["names"])
    out = tmp_path / "srf.zarr"
    train(images, only_apple, out, tiny_options(iterations=5), holdout_every=3)
    model, attrs = read_srf(out)
    assert attrs["classes"] == ["apple"] and attrs["model_config"]["num_classes"] == 1
    head = model.field.semantic_mlp[-1]
    assert head.out_features == 1 and model.field.background_logits.shape == (1,)
    hidden = attrs["model_config"]["hidden"]
    semantic = sum(p.numel() for p in model.field.semantic_mlp.parameters())
    three = sum(p.numel() for p in read_srf_like(attrs, 3).field.semantic_mlp.parameters())
    assert three - semantic == 2 * (hidden + 1), "each further class costs one output row of the head"


def read_srf_like(attrs: dict, classes: int):
    from srfpipe.srf.model import SRFModel

    return SRFModel(dict(attrs["model_config"], num_classes=classes))


def model_config(bounds, **options):
    bounds = np.asarray(bounds, dtype=np.float64)
    merged = dict(section_defaults("train"), default_cells=32, grid_levels=1, features=8, **options)
    return build_model_config(merged, bounds, scene_from_world_transform(*bounds), ["apple"], num_images=2)


@pytest.mark.parametrize("scale", [0.01, 1.0, 100.0])
def test_grid_resolution_follows_the_bounds_and_the_cell_size(scale):
    box = np.array([[0.0, 0.0, 0.0], [2.0, 1.0, 0.5]]) * scale
    # relative cells (the default): any units give the same grid, elongated boxes keep square cells
    config = model_config(box)
    assert config["inner"]["resolution"] == [33, 17, 9]
    # a cell size in world units: twice the bounds, twice the cells along every axis
    cell = 0.125 * scale
    small, large = model_config(box, detail_size=cell), model_config(box * 2, detail_size=cell)
    assert small["inner"]["resolution"] == [17, 9, 5] and large["inner"]["resolution"] == [33, 17, 9]
    # the same cell and step in world units (the scene frame of the larger box is scaled by 1/2)
    assert large["sampler"]["step"] == pytest.approx(small["sampler"]["step"] / 2)
    assert large["occupancy"]["resolution"] == [16, 8, 4]


def test_cache_grid_follows_the_bounds_and_the_voxel_size():
    box = np.array([[0.0, 0.0, 0.0], [2.0, 1.0, 0.5]])
    options = resolve_options({"voxel_size": 0.05})
    for factor in (1, 2, 4):
        grid = VoxelGrid.from_bounds(box * factor, choose_voxel_size(box * factor, options)["voxel_size"])
        assert grid.shape == (10 * factor, 20 * factor, 40 * factor)  # (z, y, x)
    relative = resolve_options({"voxels_across": 40})
    for factor in (0.01, 1, 100):
        size = choose_voxel_size(box * factor, relative)["voxel_size"]
        assert VoxelGrid.from_bounds(box * factor, size).shape == (10, 20, 40)


def test_empty_space_costs_no_storage(tmp_path):
    """The same apple in a box 1, 2 and 4 times as wide at one voxel size: the dense arrays grow
    with the box's volume, the files on disk with the apple (empty bricks are never written)."""
    stored = {}
    for factor in (1, 2, 4):
        bounds = np.array([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]) * factor
        field = AnalyticField(["apple"], bounds).add_sphere([0.05, 0.0, 0.0], 0.3, "apple")
        path = distill(field, tmp_path / f"x{factor}.zarr",
                       {"voxel_size": 1 / 32, "brick": 16, "avoid": [], "reach": []}, progress=False)
        attrs = read_provenance(path)
        # measured before the last attributes and the integrity manifest (written as the artifact closes)
        on_disk = sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and p.name != MANIFEST_NAME)
        assert abs(attrs["bytes_on_disk"] - on_disk) < 4096
        stored[factor] = (attrs["bytes_on_disk"], attrs["dense_bytes"])
    assert stored[4][1] == pytest.approx(64 * stored[1][1], rel=0.05)  # dense: the volume
    assert stored[1][0] < stored[1][1] / 4
    assert stored[4][0] < 1.5 * stored[1][0]  # on disk: the apple (and the pyramid's few extra levels)


def test_empty_space_costs_no_samples_and_no_accuracy():
    """A box that is empty but for a thin slab: after the occupancy grid's updates most of the
    intervals placed on the rays are skipped, and the render is the same as without skipping."""
    model = slab_model(z_range=(0.0, 0.0))
    origins, directions = rays(256, radius=2.5)
    with torch.no_grad():
        everything = model(origins, directions)  # the occupancy grid starts all occupied
        generator = torch.Generator().manual_seed(0)
        for _ in range(16):  # one jittered point per cell and update: the EMA of the max needs a few
            model.occupancy.update(model.field.sigma, generator, all_cells=True)
        culled = model(origins, directions)
    assert torch.equal(everything["kept_samples"], everything["candidate_samples"])
    assert torch.equal(culled["candidate_samples"], everything["candidate_samples"])
    skipped = 1 - culled["kept_samples"].sum() / culled["candidate_samples"].sum()
    assert skipped > 0.5, float(skipped)
    torch.testing.assert_close(culled["rgb"], everything["rgb"], atol=1e-3, rtol=0)
    torch.testing.assert_close(culled["accumulation"], everything["accumulation"], atol=1e-3, rtol=0)

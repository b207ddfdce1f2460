"""The field: semantic heads cannot move geometry, encodings, contraction, the query API."""

import math

import numpy as np
import pytest
import torch

from srfpipe.cameras import scene_from_world_transform
from srfpipe.config import section_defaults
from srfpipe.srf import losses
from srfpipe.srf.encodings import DenseGrid, HashGrid, _axis_weights, interpolated_gather, weighted_rows
from srfpipe.srf.field import contract, spherical_harmonics, uncontract
from srfpipe.srf.model import SRFModel, build_model_config
from srfpipe.srf.trainer import EMPTY_BACKDROP_SH_DEGREE

BOUNDS = np.array([[-1.0, -1.0, 0.0], [1.0, 1.0, 1.5]])


def small_model(encoding="dense", classes=("a", "b", "c"), **overrides):
    options = section_defaults("train")
    options.update(encoding=encoding, default_cells=16, outer_resolution=8, hidden=16, **overrides)
    config = build_model_config(options, BOUNDS, scene_from_world_transform(*BOUNDS), list(classes), 4)
    torch.manual_seed(0)
    return SRFModel(config)


def rays(n=64, seed=0):
    g = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=g)
    origins = origins / origins.norm(dim=1, keepdim=True) * 2.5
    directions = -origins + 0.3 * torch.randn(n, 3, generator=g)
    return origins, directions / directions.norm(dim=1, keepdim=True)


@pytest.mark.parametrize("encoding", ["dense", "hash"])
def test_semantic_loss_sends_no_gradient_into_density_parameters(encoding):
    model = small_model(encoding)
    origins, directions = rays()
    out = model(origins, directions)
    assert out["samples"] > 0
    labels = torch.randint(0, 2, out["logits"].shape).float()
    losses.semantic_loss(out["logits"], labels).backward()
    for p in model.field.density_parameters():
        assert p.grad is None or torch.count_nonzero(p.grad) == 0
    assert any(p.grad is not None and torch.count_nonzero(p.grad) > 0 for p in model.field.semantic_mlp.parameters())
    # while the photometric loss does reach the geometry
    model.zero_grad()
    out = model(origins, directions)
    losses.photometric_loss(out["rgb"], torch.rand_like(out["rgb"])).backward()
    assert any(p.grad is not None and torch.count_nonzero(p.grad) > 0 for p in model.field.density_parameters())


def test_dense_grid_interpolates_trilinearly_and_hits_the_corners():
    grid = DenseGrid((3, 4, 5), features=2)
    with torch.no_grad():
        table = grid.table.view(3, 4, 5, 2)
        ijk = torch.stack(torch.meshgrid(*[torch.arange(r) for r in (3, 4, 5)], indexing="ij"), -1).float()
        table.copy_(torch.stack([ijk @ torch.tensor([1.0, 2.0, 3.0]), ijk[..., 0] * 0 + 7], -1))
    u = torch.rand(100, 3) * 2 - 1
    pos = (u + 1) / 2 * torch.tensor([2.0, 3.0, 4.0])
    out = grid(u)
    # a linear function of the grid index is reproduced exactly by trilinear interpolation
    assert torch.allclose(out[:, 0], pos @ torch.tensor([1.0, 2.0, 3.0]), atol=1e-4)
    assert torch.allclose(out[:, 1], torch.full((100,), 7.0))
    corner = grid(torch.tensor([[1.0, 1.0, 1.0]]))
    assert torch.allclose(corner[0, 0], torch.tensor(2 * 1 + 3 * 2 + 4 * 3.0))


@pytest.mark.parametrize("features", [1, 16])
def test_dense_grid_gradient_matches_autograd_of_the_same_interpolation(features):
    # the hand-written backward (index_add_ of weighted rows) against autograd through a plain
    # gather, with repeated corners so that contributions to one row must add up
    grid = DenseGrid((4, 3, 5), features=features)
    u = torch.rand(300, 3) * 2 - 1
    u[:50] = u[0]
    weights_out = torch.randn(300, features)
    (grid(u) * weights_out).sum().backward()
    pos = (u + 1.0) * 0.5 * (grid._res - 1.0)
    origin = torch.minimum(pos.floor(), grid._res - 2.0)
    index = (origin.long() * grid._strides).sum(-1, keepdim=True) + grid._corner_offsets
    table = grid.table.detach().clone().requires_grad_(True)
    reference = (table[index] * _axis_weights(pos - origin).unsqueeze(-1)).sum(1)
    (reference * weights_out).sum().backward()
    assert torch.allclose(grid(u), reference, atol=1e-6)
    assert torch.allclose(grid.table.grad, table.grad, atol=1e-5)


@pytest.mark.parametrize("features", [1, 8])
def test_grid_sample_reads_a_dense_grid_as_the_corner_sum_does(features, device):
    # CUDA's forward (grid_sample on a strided view of the channels-last table) against the CPU's
    # corner sum: values, table gradient and position gradient, with points on the box's faces
    torch.manual_seed(0)
    grid = DenseGrid((5, 3, 7), features=features)
    u = torch.rand(400, 3) * 2 - 1
    u[:40] = u[0]  # repeated cells: their contributions add up
    u[40:60] = torch.tensor([1.0, -1.0, 1.0])
    u[60:80, 1] = 1.0
    u.requires_grad_(True)
    weights_out = torch.randn(400, features)
    (grid(u) * weights_out).sum().backward()  # on the CPU: the corner sum
    grid_device = grid.to(device)
    table = grid_device.table.detach().clone().requires_grad_(True)
    u_device = u.detach().to(device).requires_grad_(True)
    pos = (u_device + 1.0) * 0.5 * (grid_device._res - 1.0)
    origin = torch.minimum(pos.floor(), grid_device._res - 2.0)
    index = (origin.long() * grid_device._strides).sum(-1, keepdim=True) + grid_device._corner_offsets
    sampled = interpolated_gather(table, index, _axis_weights(pos - origin), (grid.resolution, u_device.detach()))
    (sampled * weights_out.to(device)).sum().backward()
    assert sampled.shape == (400, features)
    assert torch.allclose(sampled.detach().cpu(), grid.to("cpu")(u).detach(), atol=1e-5)
    assert torch.allclose(table.grad.cpu(), grid.table.grad, atol=1e-4)
    assert torch.allclose(u_device.grad.cpu(), u.grad, atol=1e-3)


@pytest.mark.parametrize("features", [1, 16])
def test_the_fused_corner_sum_equals_the_gather_and_product(features):
    # the CPU's embedding_bag pass and the gather + bmm that CUDA runs: one sum, two kernels
    table = torch.randn(500, features)
    index = torch.randint(0, 500, (2000, 8))
    index[:100] = index[0]  # repeated corners
    weights = torch.rand(2000, 8)
    fused = weighted_rows(table, index, weights, fused=True)
    gathered = weighted_rows(table, index, weights, fused=False)
    reference = (table[index] * weights.unsqueeze(-1)).sum(1)
    assert fused.shape == gathered.shape == (2000, features)
    assert torch.allclose(fused, reference, atol=1e-5) and torch.allclose(gathered, reference, atol=1e-5)


def test_hash_grid_output_shape_and_gradients():
    enc = HashGrid(levels=4, features_per_level=2, log2_table_size=10, base_resolution=4, max_resolution=64)
    u = (torch.rand(50, 3) * 2 - 1)
    out = enc(u)
    assert out.shape == (50, 8)
    out.square().sum().backward()
    assert torch.isfinite(enc.table.grad).all() and enc.table.grad.abs().sum() > 0


def test_contraction_round_trip_and_range():
    u = torch.randn(1000, 3) * 5
    v = contract(u)
    assert (v.abs() < 2).all()
    assert torch.allclose(uncontract(v), u, rtol=1e-3, atol=1e-4)
    inside = torch.rand(10, 3) * 2 - 1
    assert torch.equal(contract(inside), inside)


def test_spherical_harmonics_are_orthonormal_on_the_sphere():
    d = torch.randn(200000, 3, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    y = spherical_harmonics(d, 4).double()
    gram = (y.T @ y) / d.shape[0] * 4 * np.pi
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.05)


def test_multi_resolution_dense_grid_levels_and_outputs():
    from srfpipe.srf.encodings import MultiResolutionDenseGrid, build_encoding

    grid = build_encoding({"type": "dense", "resolution": [17, 33, 9], "features": 4, "levels": 3})
    assert isinstance(grid, MultiResolutionDenseGrid)
    assert [g.resolution for g in grid.grids] == [(5, 9, 3), (9, 17, 5), (17, 33, 9)]  # coarse first
    u = torch.rand(50, 3) * 2 - 1
    assert grid(u).shape == (50, 12) and grid.output_dim == 12
    summed = build_encoding(dict(grid.config(), features=1, combine="sum"))
    for g in summed.grids:
        torch.nn.init.constant_(g.table, 0.5)
    np.testing.assert_allclose(summed(u).detach().numpy(), 1.5, rtol=1e-6)  # each level interpolates 0.5
    assert build_encoding(grid.config()).config() == grid.config()


def test_fine_levels_resolve_detail_the_dense_grid_cannot_in_a_hashed_table():
    """A fine level twice as fine as the grid, in a table of fewer rows than its points, fits
    stripes whose zeros fall on every grid point (the grid alone can only return their mean);
    its config round-trips."""
    from srfpipe.srf.encodings import build_encoding

    torch.manual_seed(0)
    coarse = build_encoding({"type": "dense", "resolution": [9, 2, 2], "features": 2, "levels": 1})
    fine = build_encoding({"type": "dense", "resolution": [9, 2, 2], "features": 2, "levels": 1,
                           "fine_levels": 1, "log2_table_size": 7})
    level = fine.grids[-1]
    assert level.resolution == (17, 3, 3) and level.hashed and level.table.shape == (128, 2)
    assert fine.output_dim == 4 and build_encoding(fine.config()).config() == fine.config()

    def stripes(u):  # period: two grid cells (cells 0.25 wide): zero at the grid's points
        return torch.sin(math.pi * (u[:, :1] + 1.0) / 0.25)

    x = torch.rand(4096, 3) * 2 - 1
    errors = []
    for grid in (coarse, fine):
        head = torch.nn.Linear(grid.output_dim, 1)
        optimizer = torch.optim.Adam([*grid.parameters(), *head.parameters()], lr=0.05)
        for _ in range(300):
            optimizer.zero_grad()
            loss = ((head(grid(x)) - stripes(x)) ** 2).mean()
            loss.backward()
            optimizer.step()
        assert all(torch.isfinite(p.grad).all() for p in grid.parameters())
        test = torch.rand(2048, 3) * 2 - 1
        errors.append(float(((head(grid(test)) - stripes(test)) ** 2).mean()))
    assert errors[0] > 0.4 and errors[1] < 0.1, errors  # the mean square of the stripes is 0.5


def test_multi_resolution_model_renders_and_learns_a_coarse_shape_through_its_coarse_level():
    """A one-ray gradient reaches every level, and a coarse cell covers 4x as much of the box."""
    options = dict(section_defaults("train"), grid_levels=3, features=4, appearance_dim=0)
    config = build_model_config(options, [[-1, -1, -1], [1, 1, 1]], np.eye(4), ["a"], num_images=1)
    model = SRFModel(config)
    assert model.field.inner.output_dim == 12 and model.field.outer.output_dim == 12
    origins = torch.tensor([[0.0, 0.0, -3.0]])
    out = model(origins, torch.tensor([[0.0, 0.0, 1.0]]), torch.zeros(1, dtype=torch.long), torch.zeros(1))
    (out["rgb"].sum() + out["distortion"]).backward()
    for level in model.field.inner_sigma.grids:
        assert level.table.grad is not None and level.table.grad.abs().sum() > 0
    touched = [int((g.table.grad.abs().sum(-1) > 0).sum()) for g in model.field.inner_sigma.grids]
    cells = [math.prod(g.resolution) for g in model.field.inner_sigma.grids]
    assert touched[0] / cells[0] > touched[-1] / cells[-1]


def test_novel_view_borrows_the_appearance_of_the_nearest_training_image():
    options = dict(section_defaults("train"), default_cells=8, outer_resolution=4, hidden=8, appearance_dim=4,
                   novel_view_appearances=1)
    config = build_model_config(options, [[-1, -1, -1], [1, 1, 1]], np.eye(4), [], num_images=3)
    model = SRFModel(config)
    assert model.field.nearest_training_view(torch.zeros(3), torch.tensor([0.0, 0.0, 1.0])) is None
    poses = torch.eye(4).repeat(3, 1, 1)
    poses[:, :3, 3] = torch.tensor([[0.0, 0.0, -3.0], [3.0, 0.0, 0.0], [0.0, 0.0, -3.1]])
    poses[1, :3, :3] = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # +z -> -x
    model.field.record_training_cameras(poses, [1, 2])  # view 0 is held out
    assert model.field.nearest_training_view(torch.tensor([0.0, 0.0, -3.0]), torch.tensor([0.0, 0.0, 1.0])) == 2
    assert model.field.nearest_training_view(torch.tensor([2.9, 0.1, 0.0]), torch.tensor([-1.0, 0.0, 0.0])) == 1
    with torch.no_grad():
        model.field.appearance.weight[1] = 5.0
    origins = torch.tensor([[2.9, 0.1, 0.0]]).repeat(4, 1)
    directions = torch.tensor([[-1.0, 0.0, 0.0]]).repeat(4, 1)
    rendered = model.eval().render_rays_chunked(origins, directions)["rgb"]
    expected = model(origins, directions, torch.ones(4, dtype=torch.long))["rgb"]
    np.testing.assert_allclose(rendered.numpy(), expected.detach().numpy(), rtol=1e-6)
    # training view 1 rendered as a new view at its own pose borrows the other one's appearance
    assert model.field.nearest_training_view(torch.tensor([2.9, 0.1, 0.0]), torch.tensor([-1.0, 0.0, 0.0]),
                                             exclude=1) == 2
    borrowed = model.render_rays_chunked(origins, directions, exclude_view=1)["rgb"]
    expected = model(origins, directions, torch.full((4,), 2, dtype=torch.long))["rgb"]
    np.testing.assert_allclose(borrowed.numpy(), expected.detach().numpy(), rtol=1e-6)
    assert float((borrowed - rendered).abs().max()) > 1e-3


def test_novel_view_is_the_weighted_mean_of_its_nearest_training_images_appearances():
    """The default: a new view's colour is what its two nearest training images' appearances
    make of it, weighted by 1 / distance; a view at a training image's pose keeps that image's own."""
    options = dict(section_defaults("train"), default_cells=8, outer_resolution=4, hidden=8, appearance_dim=4)
    assert options["novel_view_appearances"] == 2
    model = SRFModel(build_model_config(options, [[-1, -1, -1], [1, 1, 1]], np.eye(4), [], num_images=3)).eval()
    poses = torch.eye(4).repeat(3, 1, 1)
    poses[:, :3, 3] = torch.tensor([[0.0, 0.0, -3.0], [0.0, 0.0, -3.4], [0.0, 0.0, -2.0]])
    model.field.record_training_cameras(poses, [0, 1, 2])
    with torch.no_grad():
        model.field.appearance.weight[0] = 5.0
        model.field.appearance.weight[1] = -5.0
    axis = torch.tensor([0.0, 0.0, 1.0])
    picks = model.field.nearest_training_views(torch.tensor([0.0, 0.0, -3.1]), axis, count=2)
    assert [i for i, _ in picks] == [0, 1]
    # 0.1 and 0.3 from the two (in box sizes, whatever the box): weights 3 : 1
    assert [w for _, w in picks] == pytest.approx([0.75, 0.25], rel=1e-5)
    origins = torch.tensor([[0.0, 0.0, -3.1]]).repeat(4, 1)
    directions = axis.repeat(4, 1)
    density = "sigma" if model.field.density_grid else "density"
    read = getattr(model.field, density)
    reads = []
    setattr(model.field, density, lambda x: (reads.append(len(x)), read(x))[1])
    rendered = model.render_rays_chunked(origins, directions)["rgb"]
    # one pass: the rays are sampled and their density read once; the two appearances shade the same samples
    assert len(reads) == 1 and reads[0] > 0
    delattr(model.field, density)
    each = [model(origins, directions, torch.full((4,), i, dtype=torch.long))["rgb"].detach() for i in (0, 1)]
    np.testing.assert_allclose(rendered.numpy(), (0.75 * each[0] + 0.25 * each[1]).numpy(), rtol=1e-5, atol=1e-6)
    assert float((each[0] - each[1]).abs().max()) > 1e-3  # the two appearances do differ
    # a camera at training image 1's own pose: its own appearance alone
    assert model.field.nearest_training_views(torch.tensor([0.0, 0.0, -3.4]), axis, count=2) == [(1, 1.0)]
    own = model.render_rays_chunked(origins * 0 + torch.tensor([0.0, 0.0, -3.4]), directions)["rgb"]
    expected = model(origins * 0 + torch.tensor([0.0, 0.0, -3.4]), directions, torch.ones(4, dtype=torch.long))["rgb"]
    np.testing.assert_allclose(own.numpy(), expected.detach().numpy(), rtol=1e-6)


def test_appearance_smoothness_pulls_each_images_embedding_towards_its_nearest_neighbours():
    options = dict(section_defaults("train"), default_cells=8, outer_resolution=4, hidden=8, appearance_dim=4)
    config = build_model_config(options, [[-1, -1, -1], [1, 1, 1]], np.eye(4), [], num_images=4)
    model = SRFModel(config)
    poses = torch.eye(4).repeat(4, 1, 1)
    poses[:, :3, 3] = torch.tensor([[0.0, 0.0, -3.0], [0.0, 0.0, -3.1], [0.2, 0.0, -3.0], [0.0, 0.0, -3.05]])
    model.field.record_training_cameras(poses, [0, 1, 2])  # view 3 is held out
    pairs = model.field.training_neighbours()
    # each training image with the one a new view at its pose would borrow from; never a held-out one
    assert sorted(map(tuple, pairs.tolist())) == [(0, 1), (1, 0), (2, 0)]
    with torch.no_grad():
        model.field.appearance.weight.normal_(generator=torch.Generator().manual_seed(0))
    weights = model.field.appearance_weights()
    assert weights.shape == (model.field.color_mlp[0].out_features, 4)
    loss = losses.appearance_smoothness_loss(model.field.appearance.weight, weights, pairs)
    a, w = model.field.appearance.weight.detach(), weights.detach()
    expected = sum(float(((a[i] - a[j]) @ w.T).pow(2).sum()) for i, j in pairs.tolist()) / 3
    assert loss.item() == pytest.approx(expected, rel=1e-5)
    # what the colour MLP receives is penalised: shrinking the embeddings as W_a grows undoes nothing
    scaled = losses.appearance_smoothness_loss(a * 0.01, w * 100.0, pairs)
    assert float(scaled) == pytest.approx(expected, rel=1e-4)
    loss.backward()
    step = -model.field.appearance.weight.grad
    assert float(((a[0] + 1e-3 * step[0]) - a[1]).norm()) < float((a[0] - a[1]).norm())
    assert float(step[3].abs().max()) == 0.0  # the held-out image's row is never trained
    empty = losses.appearance_smoothness_loss(a, w, torch.zeros((0, 2), dtype=torch.long))
    assert float(empty) == 0.0


def test_the_affine_appearance_transforms_each_images_colours_and_nothing_else():
    options = dict(section_defaults("train"), default_cells=8, outer_resolution=4, hidden=8, appearance_dim=4,
                   appearance_model="affine")
    config = build_model_config(options, [[-1, -1, -1], [1, 1, 1]], np.eye(4), [], num_images=3)
    model = SRFModel(config).eval()
    # the colour MLP sees no appearance: the transform is the images' only difference
    assert model.field.color_mlp[0].in_features == model.field.geo_features + model.field.sh_degree ** 2
    origins = torch.tensor([[0.0, 0.0, -3.0]]).repeat(4, 1)
    directions = torch.nn.functional.normalize(torch.randn(4, 3, generator=torch.Generator().manual_seed(0))
                                               * 0.2 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    with torch.no_grad():
        plain = model(origins, directions, torch.zeros(4, dtype=torch.long))["rgb"]  # zero-initialised: identity
        model.field.appearance.weight[1, [0, 4, 8]] = 0.5  # image 1 half again as bright
        model.field.appearance.weight[1, 11] = -0.1  # and less blue
        bright = model(origins, directions, torch.ones(4, dtype=torch.long))["rgb"]
        unchanged = model(origins, directions, torch.zeros(4, dtype=torch.long))["rgb"]
    assert torch.allclose(unchanged, plain)
    assert torch.allclose(bright, plain * 1.5 + torch.tensor([0.0, 0.0, -0.1]), atol=1e-6)
    # a blend of the two images' appearances is the blend of their renders
    blended = model(origins, directions, appearances=[(torch.zeros(4, dtype=torch.long), 0.25),
                                                      (torch.ones(4, dtype=torch.long), 0.75)])["rgb"].detach()
    assert torch.allclose(blended, 0.25 * unchanged + 0.75 * bright, atol=1e-6)


def test_a_model_built_without_validation_is_the_workflows_model():
    """build_model_config fills missing train keys from the schema: the same config as from the
    validated defaults (the code's old literal fallbacks said 48 / 16 / 2 where the schema says
    32 / 8 / 1 for outer_samples, before_samples, color_layers)."""
    from srfpipe.config import section_defaults
    from srfpipe.srf.model import build_model_config

    bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    bare = build_model_config({}, bounds, np.eye(4), ["apple"], 4)
    validated = build_model_config(section_defaults("train"), bounds, np.eye(4), ["apple"], 4)
    assert bare == validated
    assert bare["color_layers"] == section_defaults("train")["color_layers"]


def ring_of_views(azimuths_deg, per_view=400, half_angle_deg=5.0, seed=0) -> torch.Tensor:
    """Unit directions inside narrow cones (a long lens) round a horizontal ring of views."""
    g = torch.Generator().manual_seed(seed)
    azimuth = torch.tensor(azimuths_deg, dtype=torch.float32).repeat_interleave(per_view) * math.pi / 180
    azimuth = azimuth + (torch.rand(len(azimuth), generator=g) * 2 - 1) * math.radians(half_angle_deg)
    elevation = (torch.rand(len(azimuth), generator=g) * 2 - 1) * math.radians(half_angle_deg)
    return torch.stack([torch.cos(elevation) * torch.cos(azimuth), torch.cos(elevation) * torch.sin(azimuth),
                        torch.sin(elevation)], -1)


def test_the_background_model_interpolates_a_backdrop_between_the_views_that_saw_it():
    # the built-in plant's case: a dark mottled backdrop (8 cells a radian) seen through narrow
    # views 20 degrees apart; a held-out view looks at directions no training view saw. Fitting the
    # seen directions with every band (sh_degree 4) guessed the plant's held-out backdrop 8.5 times
    # worse (in MSE) than the training views' mean colour; an empty backdrop's bands interpolate
    frequencies = torch.randn(3, 6, generator=torch.Generator().manual_seed(3)) * 8.0

    def backdrop(directions):
        return (0.05 + 0.01 * torch.sin(directions @ frequencies).sum(-1, keepdim=True)).expand(-1, 3)

    held_out = [0, 160, 320]
    seen = ring_of_views([a for a in range(0, 360, 20) if a not in held_out])
    new = ring_of_views(held_out, seed=1)

    def fitted(**overrides):
        model = small_model(**overrides)
        optimizer = torch.optim.Adam(model.field.background_mlp.parameters(), 1e-2)
        for _ in range(400):
            loss = ((model.field.background(seen) - backdrop(seen)) ** 2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        with torch.no_grad():
            return {"seen": float(loss.sqrt()), "new": float(((model.field.background(new) - backdrop(new)) ** 2).mean().sqrt())}

    default, every_band = fitted(background_sh_degree=EMPTY_BACKDROP_SH_DEGREE), fitted(background_sh_degree=4)
    assert every_band["seen"] < default["seen"]  # every band fits the training views more closely ...
    assert default["new"] < 0.8 * every_band["new"], (default, every_band)  # ... and new views worse
    assert default["new"] < 0.012  # about 3 levels of 255


def test_a_field_without_classes_renders_no_logits_and_never_runs_its_semantic_head():
    """A capture without masks (the fox, the fern, the beer) trains colour and geometry only: the
    semantic head's layers would otherwise run at every shaded sample for logits of width 0."""
    model = small_model(classes=())
    calls = []
    model.field.semantic_mlp.register_forward_hook(lambda *args: calls.append(1))
    origins, directions = rays()
    out = model(origins, directions, torch.zeros(len(origins), dtype=torch.long), torch.zeros(len(origins)))
    assert out["shaded"] > 0 and out["logits"].shape == (len(origins), 0) and not calls
    loss = losses.total_loss(out["rgb"], torch.zeros_like(out["rgb"]), out["logits"],
                             torch.zeros_like(out["logits"]))
    assert float(loss["semantic"].detach()) == 0.0
    loss["loss"].backward()
    assert model.field.inner_sigma.table.grad.abs().sum() > 0

"""Volumetric rendering (Eq. 1 / Eq. 3) against closed forms and at numerical extremes."""

import math

import numpy as np

import pytest
import torch

from srfpipe.srf import rendering


def test_homogeneous_medium_transmittance_is_exponential():
    sigma, delta, k = 0.7, 0.05, 200
    s = torch.full((1, k), sigma)
    d = torch.full((1, k), delta)
    tau = rendering.optical_thickness(s, d)
    t = rendering.transmittance(tau)[0]
    distances = torch.arange(k) * delta  # T at the start of each interval
    assert torch.allclose(t, torch.exp(-sigma * distances), rtol=1e-5, atol=1e-7)
    weights = rendering.render_weights(s, d)
    # the weights telescope: sum_k w_k = 1 - T(end)
    assert math.isclose(float(weights.sum()), 1 - math.exp(-sigma * delta * k), rel_tol=1e-5)


def test_single_opaque_sample_has_weight_one_and_hides_the_rest():
    sigma = torch.tensor([[0.0, 1e6, 5.0, 5.0]])
    delta = torch.tensor([[0.1, 0.1, 0.1, 0.1]])
    w = rendering.render_weights(sigma, delta)
    assert torch.allclose(w, torch.tensor([[0.0, 1.0, 0.0, 0.0]]))
    colours = torch.tensor([[[0.0, 0, 0], [0.2, 0.4, 0.6], [1, 1, 1], [1, 1, 1]]])
    assert torch.allclose(rendering.accumulate(w, colours), torch.tensor([[0.2, 0.4, 0.6]]))
    depth = rendering.expected_depth(w, torch.tensor([[0.05, 0.15, 0.25, 0.35]]))
    assert torch.allclose(depth, torch.tensor([0.15]))


def test_background_fills_the_remaining_transmittance():
    w = rendering.render_weights(torch.tensor([[2.0]]), torch.tensor([[0.5]]))
    acc = rendering.accumulation(w)
    out = rendering.composite_background(rendering.accumulate(w, torch.ones(1, 1, 3)), acc, torch.zeros(3))
    assert torch.allclose(out, torch.full((1, 3), 1 - math.exp(-1.0)))


@pytest.mark.parametrize("sigma_value", [0.0, 1e-8, 1e6, 1e12])
@pytest.mark.parametrize("delta_value", [1e-9, 1e3])
def test_extreme_sigma_and_delta_keep_outputs_and_gradients_finite(sigma_value, delta_value):
    sigma = torch.full((3, 8), sigma_value, requires_grad=True)
    delta = torch.full((3, 8), delta_value)
    values = torch.rand(3, 8, 4, requires_grad=True)
    w = rendering.render_weights(sigma, delta)
    out = rendering.accumulate(w, values).sum() + rendering.expected_depth(w, torch.rand(3, 8)).sum()
    out.backward()
    assert torch.isfinite(w).all() and torch.isfinite(out)
    assert torch.isfinite(sigma.grad).all() and torch.isfinite(values.grad).all()
    total = w.sum(-1)
    assert (total <= 1 + 1e-6).all() and (w >= 0).all()
    expected_total = 1 - math.exp(-min(sigma_value * delta_value * 8, 80.0))
    assert torch.allclose(total, torch.full_like(total, expected_total), atol=1e-5)


def test_empty_rays_render_nothing():
    sigma = torch.zeros(4, 0, requires_grad=True)
    w = rendering.render_weights(sigma, torch.zeros(4, 0))
    assert w.shape == (4, 0)
    rgb = rendering.accumulate(w, torch.zeros(4, 0, 3))
    assert torch.equal(rgb, torch.zeros(4, 3))
    assert torch.equal(rendering.expected_depth(w, torch.zeros(4, 0)), torch.zeros(4))
    rgb.sum().backward()  # a graph through zero samples must not fail


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_autocast_on_cpu_renders_in_float32(dtype):
    sigma = torch.rand(16, 32, requires_grad=True) * 10
    delta = torch.full((16, 32), 0.02)
    layer = torch.nn.Linear(4, 3)
    with torch.autocast("cpu", dtype=dtype):
        colours = layer(torch.rand(16, 32, 4))
        w = rendering.render_weights(sigma, delta)
        rgb = rendering.accumulate(w, colours)
    assert w.dtype == torch.float32 and rgb.dtype == torch.float32
    rgb.square().sum().backward()
    assert torch.isfinite(layer.weight.grad).all()


def test_floater_counts_find_weight_off_the_surface():
    from srfpipe.srf.rendering import floater_counts, render_weights

    t = torch.arange(10, dtype=torch.float32)[None].repeat(3, 1) + 0.5
    delta = torch.ones(3, 10)
    sigma = torch.zeros(3, 10)
    sigma[0, 6] = 1e12  # one opaque surface: no floater
    sigma[1, 2], sigma[1, 7] = 0.5, 1e12  # a veil two cells in front of the surface
    sigma[2] = 0.05  # uniform fog along the whole ray
    weights = render_weights(sigma, delta)
    significant, floaters = floater_counts(weights, t, torch.full((3, 10), 1.5))
    assert significant.tolist()[0] == 1 and floaters.tolist()[0] == 0
    assert floaters.tolist()[1] == 1
    assert floaters[2] >= 4 and significant[2] >= 8
    assert torch.isfinite(significant).all() and torch.isfinite(floaters).all()


def test_floater_counts_of_empty_rays_are_zero():
    from srfpipe.srf.rendering import floater_counts

    significant, floaters = floater_counts(torch.zeros(4, 0), torch.zeros(4, 0), torch.zeros(4, 0))
    assert significant.tolist() == [0, 0, 0, 0] and floaters.tolist() == [0, 0, 0, 0]
    significant, floaters = floater_counts(torch.zeros(2, 5), torch.rand(2, 5), torch.ones(2, 5))
    assert significant.sum() == 0 and floaters.sum() == 0


# ----------------------------------------------------------------------------- distortion loss


def brute_force_distortion(w, s0, s1):
    mid, length = 0.5 * (s0 + s1), s1 - s0
    between = (w[:, :, None] * w[:, None, :] * (mid[:, :, None] - mid[:, None, :]).abs()).sum((1, 2))
    return between + (w**2 * length).sum(-1) / 3.0


def test_distortion_matches_the_double_sum_of_mip_nerf_360():
    g = torch.Generator().manual_seed(0)
    edges = torch.rand(16, 33, generator=g).sort(dim=-1).values.double()
    w = torch.rand(16, 32, generator=g).double()
    w = w / w.sum(-1, keepdim=True) * 0.9
    np.testing.assert_allclose(rendering.distortion(w, edges[:, :-1], edges[:, 1:]),
                               brute_force_distortion(w, edges[:, :-1], edges[:, 1:]), rtol=1e-5)


def test_distortion_is_small_for_a_surface_and_large_for_fog():
    edges = torch.linspace(0.0, 1.0, 65)[None]
    s0, s1 = edges[:, :-1], edges[:, 1:]
    surface = torch.zeros(1, 64)
    surface[0, 40] = 1.0
    fog = torch.full((1, 64), 1.0 / 64)
    assert rendering.distortion(surface, s0, s1) < 0.01 < 0.3 < rendering.distortion(fog, s0, s1)
    # two halves of the weight 0.5 apart: 2 * 0.5 * 0.5 * 0.5 between them, and tiny within
    split = torch.zeros(1, 64)
    split[0, 8], split[0, 40] = 0.5, 0.5
    np.testing.assert_allclose(rendering.distortion(split, s0, s1), 0.25 + 0.5 / 64 / 3.0, rtol=1e-5)


def test_distortion_is_finite_for_empty_rays_and_huge_densities():
    s = torch.linspace(0, 1, 9)[None].expand(3, -1)
    sigma = torch.tensor([[0.0] * 8, [1e30] * 8, [1e-30] * 8])
    w = rendering.render_weights(sigma, s[:, 1:] - s[:, :-1])
    loss = rendering.distortion(w, s[:, :-1], s[:, 1:])
    assert torch.isfinite(loss).all() and loss[0] == 0.0
    empty = rendering.distortion(torch.zeros(2, 0), torch.zeros(2, 0), torch.zeros(2, 0))
    assert empty.tolist() == [0.0, 0.0]


def _packed(values, counts):
    """The samples of padded (R, K) values, ray after ray, `counts` (R,) of each ray kept."""
    keep = torch.arange(values.shape[1])[None, :] < counts[:, None]
    return values[keep], rendering.Segments.of(keep.nonzero()[:, 0], values.shape[0])


@pytest.mark.parametrize("sigma_scale", [1.0, 1e6])
def test_packed_samples_render_and_differentiate_like_padded_ones(sigma_scale):
    """Training renders the samples packed ray after ray; the padded layout (what a CUDA graph
    replays) must give the same colours, depth, opacity, distortion and gradients, rays without
    samples included."""
    generator = torch.Generator().manual_seed(0)
    counts = torch.tensor([5, 0, 1, 8, 3, 0])
    k = int(counts.max())
    keep = torch.arange(k)[None, :] < counts[:, None]
    sigma = (torch.rand(6, k, generator=generator) * sigma_scale).requires_grad_()
    delta = torch.rand(6, k, generator=generator) * 0.3 * keep
    t_start = torch.cumsum(delta, dim=1) - delta + 1.0
    colours = torch.rand(6, k, 3, generator=generator, requires_grad=True)

    def render(sigma, delta, t_start, colours, segments):
        w = rendering.render_weights(sigma, delta, segments)
        t_end = t_start + delta
        return (rendering.accumulate(w, colours, segments), rendering.accumulation(w, segments),
                rendering.expected_depth(w, 0.5 * (t_start + t_end), segments=segments),
                rendering.distortion(w, t_start / (t_start + 2), t_end / (t_end + 2), segments))

    padded = render(sigma, delta, t_start, colours, None)
    flat = [_packed(v, counts)[0] for v in (sigma, delta, t_start)]
    flat_colours = colours[keep]
    segments = rendering.Segments.of(keep.nonzero()[:, 0], 6)
    packed = render(*flat, flat_colours, segments)
    for a, b in zip(padded, packed):
        torch.testing.assert_close(b, a, rtol=1e-5, atol=1e-6)
    assert torch.equal(packed[1][counts == 0], torch.zeros(2))  # no samples: nothing gathered
    grads = torch.autograd.grad(sum(x.sum() for x in padded), (sigma, colours))
    flat_grads = torch.autograd.grad(sum(x.sum() for x in packed), (sigma, colours))
    for flat_grad, grad in zip(flat_grads, grads):  # the padding's gradient is 0 in both
        torch.testing.assert_close(flat_grad, grad, rtol=1e-5, atol=1e-6)
    assert torch.equal(segments.pad(flat[0]), (sigma * keep).detach())


def test_packed_transmittance_of_a_ray_after_an_opaque_one_is_exact():
    """Packed, each ray's transmittance is a running sum over the whole batch less its value at
    the ray's start: after a ray of optical thickness 800 000, the next ray's small terms
    (1e-3 each) must not be rounded away (in float32 they would be: its ulp there is 0.06)."""
    counts = torch.tensor([10_000, 100])
    tau = torch.cat([torch.full((10_000,), 80.0), torch.full((100,), 1e-3)])
    segments = rendering.Segments.of(torch.repeat_interleave(torch.arange(2), counts), 2)
    weights = rendering.render_weights(tau, torch.ones_like(tau), segments)
    expected = math.exp(-1e-3) ** torch.arange(100, dtype=torch.float64) * -math.expm1(-1e-3)
    torch.testing.assert_close(weights[10_000:].double(), expected, rtol=1e-6, atol=0.0)
    assert float(weights[0]) == 1.0 and float(weights[1:10_000].max()) < 1e-30
    assert torch.isfinite(rendering.distortion(weights, torch.rand(10_100), torch.rand(10_100), segments)).all()

"""Volumetric rendering along rays: the paper's Eq. 1 (colour) and Eq. 3 (semantic logits).

Samples come in one of two layouts, and every function here takes either:

* padded, (R, K): R rays with up to K intervals each; a padded slot has delta = 0 (and so
  contributes nothing). The static shapes a CUDA graph replays need this;
* packed, (M,): the M samples of R rays stored flat, ray after ray, with `Segments` saying which
  ray each belongs to. Nothing is computed for padding: a training ray through empty space keeps
  a few of its samples, and padding them to the batch's longest ray multiplied the work.

Everything is computed in float32 whatever autocast says, because transmittance is a product of
many terms (the packed layout's running sum along all its rays in float64: `exclusive_cumsum`).

    weights_k = T_k * alpha(sigma_k * delta_k),   T_k = exp(-sum_{a<k} sigma_a delta_a),
    alpha(x) = 1 - exp(-x)

>>> import torch
>>> w = render_weights(torch.tensor([[1e12, 1.0]]), torch.tensor([[1.0, 1.0]]))
>>> [round(x, 6) for x in w[0].tolist()]
[1.0, 0.0]
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

# Optical thickness at which a sample is already fully opaque in float32 (exp(-80) ~ 1e-35):
# clamping here keeps huge sigma*delta products finite without changing any weight.
MAX_OPTICAL_THICKNESS = 80.0
# sigma and delta are clamped to these before their product: an infinite density in a padded
# slot (delta = 0) or an empty interval reaching to infinity (sigma = 0) then adds nothing (0 * inf
# is NaN, and packed, the running sum would carry it into every later ray), and the backward of a
# product clamped at MAX_OPTICAL_THICKNESS (0 times the other factor) stays 0. The step's bound is
# far below float32's largest, as it is the gradient of sigma where sigma is 0; an infinite density
# stays opaque over any step. No real density or step comes near either.
MAX_DENSITY = torch.finfo(torch.float32).max
MAX_STEP = 1e30


@dataclass(frozen=True)
class Segments:
    """The rays of packed samples (M,), stored ray after ray: `ray` (M,) each sample's ray,
    `rays` R; `first` (M,) the index of the first sample of each sample's ray (needed by the
    sums along a ray, `exclusive_cumsum`, and only there)."""

    ray: torch.Tensor
    rays: int
    first: torch.Tensor | None = None

    @classmethod
    def of(cls, ray: torch.Tensor, rays: int) -> "Segments":
        """Segments of samples whose rays `ray` (M,) are sorted."""
        counts = torch.bincount(ray, minlength=rays)
        return cls(ray, rays, (torch.cumsum(counts, 0) - counts)[ray])

    def subset(self, index: torch.Tensor) -> "Segments":
        """The rays of some of the samples (sums only: their `first` would index the others)."""
        return Segments(self.ray[index], self.rays)

    def counts(self) -> torch.Tensor:
        """Samples per ray (R,)."""
        return torch.bincount(self.ray, minlength=self.rays)

    def sum(self, values: torch.Tensor) -> torch.Tensor:
        """Per ray, the sum of its samples' values (M, ...) -> (R, ...); 0 for a ray without any."""
        return values.new_zeros((self.rays,) + tuple(values.shape[1:])).index_add(0, self.ray, values)

    def pad(self, values: torch.Tensor) -> torch.Tensor:
        """The padded layout (R, K) of values (M,), K the longest ray; zeros in the padding."""
        counts = self.counts()
        width = int(counts.max()) if counts.numel() else 0
        slot = self.ray * width + torch.arange(self.ray.numel(), device=self.ray.device) - self.first
        out = values.new_zeros(self.rays * width)
        out[slot] = values
        return out.view(self.rays, width)


def optical_thickness(sigma: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """tau_k = sigma_k * delta_k, in float32, clamped to [0, MAX_OPTICAL_THICKNESS] (0 where
    either factor is 0, even if the other is infinite: see MAX_DENSITY)."""
    tau = sigma.float().clamp(max=MAX_DENSITY) * delta.float().clamp(max=MAX_STEP)
    return tau.clamp(0.0, MAX_OPTICAL_THICKNESS)


def transmittance(tau: torch.Tensor, segments: Segments | None = None) -> torch.Tensor:
    """T_k = exp(-sum_{a<k} tau_a): an *exclusive* cumulative sum, never cumsum(tau) - tau.

    Subtracting would cancel catastrophically once the sum is huge; shifting keeps it exact.
    """
    return torch.exp(-exclusive_cumsum(tau, segments))


def render_weights(sigma: torch.Tensor, delta: torch.Tensor, segments: Segments | None = None) -> torch.Tensor:
    """Eq. 1 weights w_k = T_k alpha(sigma_k delta_k) for samples (…, K) or packed (M,); sum_k w_k <= 1."""
    tau = optical_thickness(sigma, delta)
    alpha = -torch.expm1(-tau)  # 1 - exp(-x), exact for tiny x
    return transmittance(tau, segments) * alpha


def ray_sum(values: torch.Tensor, segments: Segments | None = None) -> torch.Tensor:
    """sum_k v_k along each ray: values (…, K) -> (…,), or packed (M,) -> (R,)."""
    return values.sum(dim=-1) if segments is None else segments.sum(values)


def accumulate(weights: torch.Tensor, values: torch.Tensor, segments: Segments | None = None) -> torch.Tensor:
    """sum_k w_k v_k: weights (…, K), values (…, K, D) -> (…, D), or packed (M,), (M, D) -> (R, D).
    Used for rgb (Eq. 1) and logits (Eq. 3)."""
    weighted = weights.unsqueeze(-1) * values.float()
    return weighted.sum(dim=-2) if segments is None else segments.sum(weighted)


def accumulation(weights: torch.Tensor, segments: Segments | None = None) -> torch.Tensor:
    """Opacity of each ray, sum_k w_k = 1 - T_{K+1} (…,) or (R,)."""
    return ray_sum(weights, segments)


def expected_depth(weights: torch.Tensor, t_mid: torch.Tensor, eps: float = 1e-10,
                   segments: Segments | None = None) -> torch.Tensor:
    """Depth along the ray, sum_k w_k t_k / sum_k w_k (…,) or (R,); 0 for a ray that hits nothing."""
    acc = accumulation(weights, segments)
    return ray_sum(weights * t_mid.float(), segments) / (acc + eps)


def composite_background(value: torch.Tensor, acc: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """value + (1 - acc) * background: what the ray sees beyond the last sample."""
    return value + (1.0 - acc).unsqueeze(-1) * background.float()


def median_depth(weights: torch.Tensor, t_mid: torch.Tensor) -> torch.Tensor:
    """Depth where the accumulated weight first reaches half of the ray's total (…,); robust to
    a faint haze that pulls the expected depth off the surface."""
    cumulative = torch.cumsum(weights.float(), dim=-1)
    half = 0.5 * cumulative[..., -1:]
    index = torch.searchsorted(cumulative.contiguous(), half.contiguous()).clamp(max=t_mid.shape[-1] - 1)
    return t_mid.float().gather(-1, index).squeeze(-1)


def exclusive_cumsum(values: torch.Tensor, segments: Segments | None = None) -> torch.Tensor:
    """sum_{a<k} v_a along each ray (shifted, not cumsum - v, for the reason in `transmittance`).

    Packed, it is one running sum over all the rays, less its value at each ray's first sample.
    The running sum is kept in float64: in float32 a long ray's total (thousands) would round
    away the next ray's small terms; float64's rounding at any batch's total stays below 1e-8."""
    if segments is None:
        zeros = torch.zeros_like(values[..., :1])
        return torch.cat([zeros, torch.cumsum(values, dim=-1)], dim=-1)[..., :values.shape[-1]]
    wide = values.double()
    running = torch.cat([wide.new_zeros(1), torch.cumsum(wide, dim=0)])[:-1]
    return (running - running[segments.first]).to(values.dtype)


def distortion(weights: torch.Tensor, s_start: torch.Tensor, s_end: torch.Tensor,
               segments: Segments | None = None) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss per ray (…,) or (R,), for intervals [s_k, s_k+1) in a
    normalized distance:

        L_dist = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s_i+1 - s_i),   m = midpoints.

    It is small when a ray's weight sits in one short interval (a surface) and large when it is
    spread along the ray (fog, floaters). The double sum is computed in O(K) for sorted intervals:
    sum_{i,j} w_i w_j |m_i - m_j| = 2 sum_i w_i (m_i sum_{j<i} w_j - sum_{j<i} w_j m_j).
    Padded slots (w = 0, zero length) add nothing.
    """
    w = weights.float()
    mid = 0.5 * (s_start.float() + s_end.float())
    length = (s_end.float() - s_start.float()).clamp(min=0.0)
    before = mid * exclusive_cumsum(w, segments) - exclusive_cumsum(w * mid, segments)
    between = 2.0 * ray_sum(w * before, segments)
    within = ray_sum(w.square() * length, segments) / 3.0
    return between + within


def floater_counts(weights: torch.Tensor, t_mid: torch.Tensor, tolerance: torch.Tensor,
                   min_weight: float = 0.03) -> tuple[torch.Tensor, torch.Tensor]:
    """Per ray: samples with weight > `min_weight`, and those of them farther than `tolerance`
    (…, K) from the ray's median depth (floaters, fog in front of or behind the surface)."""
    significant = weights > min_weight
    if weights.shape[-1] == 0:
        zeros = torch.zeros(weights.shape[:-1], device=weights.device)
        return zeros, zeros
    far = (t_mid.float() - median_depth(weights, t_mid).unsqueeze(-1)).abs() > tolerance
    return significant.sum(-1).float(), (significant & far).sum(-1).float()

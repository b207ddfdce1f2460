"""Volumetric rendering along rays: the paper's Eq. 1 (colour) and Eq. 3 (semantic logits).

Samples are stored padded, (R, K): R rays with up to K intervals each; a padded slot has
delta = 0 (and so contributes nothing). Everything here is a small pure function, computed in
float32 whatever autocast says, because transmittance is a product of many terms.

    weights_k = T_k * alpha(sigma_k * delta_k),   T_k = exp(-sum_{a<k} sigma_a delta_a),
    alpha(x) = 1 - exp(-x)

>>> import torch
>>> w = render_weights(torch.tensor([[1e12, 1.0]]), torch.tensor([[1.0, 1.0]]))
>>> [round(x, 6) for x in w[0].tolist()]
[1.0, 0.0]
"""

from __future__ import annotations

import torch

# Optical thickness at which a sample is already fully opaque in float32 (exp(-80) ~ 1e-35):
# clamping here keeps huge sigma*delta products finite without changing any weight.
MAX_OPTICAL_THICKNESS = 80.0


def optical_thickness(sigma: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """tau_k = sigma_k * delta_k (R, K), in float32, clamped to [0, MAX_OPTICAL_THICKNESS]."""
    tau = sigma.float() * delta.float()
    return tau.clamp(0.0, MAX_OPTICAL_THICKNESS)


def transmittance(tau: torch.Tensor) -> torch.Tensor:
    """T_k = exp(-sum_{a<k} tau_a): an *exclusive* cumulative sum, never cumsum(tau) - tau.

    Subtracting would cancel catastrophically once the sum is huge; shifting keeps it exact.
    """
    return torch.exp(-exclusive_cumsum(tau))


def render_weights(sigma: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """Eq. 1 weights w_k = T_k alpha(sigma_k delta_k) for samples (…, K); sum_k w_k <= 1."""
    tau = optical_thickness(sigma, delta)
    alpha = -torch.expm1(-tau)  # 1 - exp(-x), exact for tiny x
    return transmittance(tau) * alpha


def accumulate(weights: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """sum_k w_k v_k: weights (…, K), values (…, K, D) -> (…, D). Used for rgb (Eq. 1) and logits (Eq. 3)."""
    return torch.sum(weights.unsqueeze(-1) * values.float(), dim=-2)


def accumulation(weights: torch.Tensor) -> torch.Tensor:
    """Opacity of each ray, sum_k w_k = 1 - T_{K+1} (…,)."""
    return weights.sum(dim=-1)


def expected_depth(weights: torch.Tensor, t_mid: torch.Tensor, eps: float = 1e-10) -> torch.Tensor:
    """Depth along the ray, sum_k w_k t_k / sum_k w_k (…,); 0 for a ray that hits nothing."""
    acc = accumulation(weights)
    return torch.sum(weights * t_mid.float(), dim=-1) / (acc + eps)


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


def exclusive_cumsum(values: torch.Tensor) -> torch.Tensor:
    """sum_{a<k} v_a along the last axis (shifted, not cumsum - v, for the reason in `transmittance`)."""
    zeros = torch.zeros_like(values[..., :1])
    return torch.cat([zeros, torch.cumsum(values, dim=-1)], dim=-1)[..., :values.shape[-1]]


def distortion(weights: torch.Tensor, s_start: torch.Tensor, s_end: torch.Tensor) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss per ray (…,), for intervals [s_k, s_k+1) in a normalized distance:

        L_dist = sum_{i,j} w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 (s_i+1 - s_i),   m = midpoints.

    It is small when a ray's weight sits in one short interval (a surface) and large when it is
    spread along the ray (fog, floaters). The double sum is computed in O(K) for sorted intervals:
    sum_{i,j} w_i w_j |m_i - m_j| = 2 sum_i w_i (m_i sum_{j<i} w_j - sum_{j<i} w_j m_j).
    Padded slots (w = 0, zero length) add nothing.
    """
    w = weights.float()
    mid = 0.5 * (s_start.float() + s_end.float())
    length = (s_end.float() - s_start.float()).clamp(min=0.0)
    between = 2.0 * torch.sum(w * (mid * exclusive_cumsum(w) - exclusive_cumsum(w * mid)), dim=-1)
    within = torch.sum(w.square() * length, dim=-1) / 3.0
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

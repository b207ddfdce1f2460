"""The semantic radiance field: F_sigma (density + latent h), F_c (colour) and F_s (C semantic logits).

Nerfacto's factorization, with the paper's multi-class semantic heads:

    F_sigma : x -> (sigma, h)        encoding(x) -> MLP; sigma through a truncated exponential
    F_c     : (h, d[, a_i]) -> rgb   spherical harmonics of the view direction, optional per-image
                                     appearance embedding a_i
    F_s     : h.detach() -> s in R^C independent logits; the semantic loss cannot move geometry

Positions are given in the *scene* frame (see `srfpipe.cameras`). The model box (the scene bounds
in the scene frame) is mapped to box coordinates u in [-1, 1]^3. With `contraction`, space outside
the box is folded into [-2, 2]^3 as in mip-NeRF 360 / Nerfacto (L-inf norm):

    contract(u) = u                              if |u|_inf <= 1
                = (2 - 1/|u|_inf) u / |u|_inf    otherwise

so unbounded backgrounds (a ground plane, far trees) live in the field too. The dense encoding
then uses a fine grid inside the box and a coarse one for the contracted shell (the detail is in
the box); the hash encoding covers the whole contracted cube. A learned background colour model
(a function of direction only, for the sky) takes whatever transmittance is left at the far end.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn

from srfpipe.srf.encodings import build_encoding


class _TruncExp(torch.autograd.Function):
    """exp(x) with its argument and gradient clamped at 15 (Instant-NGP / Nerfacto's trunc_exp):
    keeps sigma (< 3.3e6) and its gradient finite in float16 and float32."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=15.0))

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        return grad * torch.exp(x.clamp(-15.0, 15.0))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    return _TruncExp.apply(x.float())


def spherical_harmonics(directions: torch.Tensor, degree: int = 4) -> torch.Tensor:
    """Real spherical harmonics of unit directions (M, 3) up to band `degree - 1`: (M, degree^2)."""
    if not 1 <= degree <= 4:
        raise ValueError(f"spherical harmonics degree must be 1..4, got {degree}")
    x, y, z = directions.float().unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree > 1:
        out += [0.4886025119029199 * y, 0.4886025119029199 * z, 0.4886025119029199 * x]
    if degree > 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            1.0925484305920792 * x * y,
            1.0925484305920792 * y * z,
            0.9461746957575601 * zz - 0.31539156525252005,
            1.0925484305920792 * x * z,
            0.5462742152960396 * (xx - yy),
        ]
    if degree > 3:
        out += [
            0.5900435899266435 * y * (3 * xx - yy),
            2.890611442640554 * x * y * z,
            0.4570457994644658 * y * (5 * zz - 1),
            0.3731763325901154 * z * (5 * zz - 3),
            0.4570457994644658 * x * (5 * zz - 1),
            1.445305721320277 * z * (xx - yy),
            0.5900435899266435 * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def contract(u: torch.Tensor) -> torch.Tensor:
    """mip-NeRF 360 contraction with the L-inf norm: R^3 -> (-2, 2)^3, identity inside [-1, 1]^3."""
    norm = u.abs().amax(dim=-1, keepdim=True).clamp_min(1e-9)
    return torch.where(norm <= 1.0, u, (2.0 - 1.0 / norm) * u / norm)


def uncontract(v: torch.Tensor) -> torch.Tensor:
    """Inverse of `contract` for v in (-2, 2)^3."""
    norm = v.abs().amax(dim=-1, keepdim=True).clamp_min(1e-9)
    outer_norm = 1.0 / (2.0 - norm.clamp(max=2.0 - 1e-6))
    return torch.where(norm <= 1.0, v, v / norm * outer_norm)


def mlp(inputs: int, hidden: int, outputs: int, layers: int = 1) -> nn.Sequential:
    """`layers` hidden ReLU layers of width `hidden`."""
    modules: list[nn.Module] = []
    width = inputs
    for _ in range(layers):
        modules += [nn.Linear(width, hidden), nn.ReLU(inplace=True)]
        width = hidden
    modules.append(nn.Linear(width, outputs))
    return nn.Sequential(*modules)


class SemanticField(nn.Module):
    """F_sigma, F_c and F_s over the scene frame. `config` is JSON-able and rebuilds the module.

    Keys: box_min, box_max (scene frame), contraction, inner (encoding config), outer (encoding
    config or None), hidden, geo_features, sh_degree, num_classes, appearance_dim, num_images,
    density_bias.
    """

    def __init__(self, config: dict, device="cpu"):
        super().__init__()
        self.config = dict(config)
        c = self.config
        self.register_buffer("box_min", torch.tensor(c["box_min"], dtype=torch.float32))
        self.register_buffer("box_max", torch.tensor(c["box_max"], dtype=torch.float32))
        self.contraction = bool(c["contraction"])
        self.inner = build_encoding(c["inner"], device)
        self.outer = build_encoding(c["outer"], device) if c.get("outer") else None
        if self.outer is not None and self.outer.output_dim != self.inner.output_dim:
            raise ValueError("inner and outer encodings must produce the same number of features")
        hidden, geo = int(c["hidden"]), int(c["geo_features"])
        self.geo_features = geo
        self.density_bias = float(c.get("density_bias", -1.0))
        self.density_mlp = mlp(self.inner.output_dim, hidden, 1 + geo)
        self.sh_degree = int(c["sh_degree"])
        appearance_dim = int(c.get("appearance_dim", 0))
        self.appearance = (
            nn.Embedding(int(c["num_images"]), appearance_dim) if appearance_dim > 0 else None
        )
        if self.appearance is not None:
            nn.init.zeros_(self.appearance.weight)
        self.color_mlp = mlp(geo + self.sh_degree**2 + appearance_dim, hidden, 3, layers=2)
        self.num_classes = int(c["num_classes"])
        self.semantic_mlp = mlp(geo, hidden, self.num_classes)
        self.background_mlp = mlp(self.sh_degree**2, 32, 3)
        # background logits: rays that leave the field see "no class" unless learned otherwise
        self.background_logits = nn.Parameter(torch.full((self.num_classes,), -2.0))

    # ---------------------------------------------------------------- geometry

    def box_coordinates(self, x: torch.Tensor) -> torch.Tensor:
        """Scene-frame points (M, 3) -> box coordinates u ([-1, 1]^3 inside the model box)."""
        centre = 0.5 * (self.box_min + self.box_max)
        half = 0.5 * (self.box_max - self.box_min)
        return (x.float() - centre) / half

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Features (M, F) and a mask of points the field covers (outside: sigma = 0)."""
        u = self.box_coordinates(x)
        if not self.contraction:
            inside = (u.abs() <= 1.0).all(dim=-1)
            return self.inner(u), inside
        covered = torch.ones(u.shape[0], dtype=torch.bool, device=u.device)
        if self.outer is None:
            return self.inner(contract(u) * 0.5), covered
        inside = (u.abs() <= 1.0).all(dim=-1)
        idx_in = inside.nonzero().squeeze(1)
        idx_out = (~inside).nonzero().squeeze(1)
        parts = []
        if idx_in.numel():
            parts.append((idx_in, self.inner(u[idx_in])))
        if idx_out.numel():
            parts.append((idx_out, self.outer(contract(u[idx_out]) * 0.5)))
        if len(parts) == 1 and parts[0][0].numel() == u.shape[0]:
            return parts[0][1], covered
        features = torch.zeros(u.shape[0], self.inner.output_dim, device=u.device, dtype=parts[0][1].dtype)
        for index, values in parts:
            features = features.index_copy(0, index, values.to(features.dtype))
        return features, covered

    def density(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """F_sigma: sigma (M,) per scene-frame unit length, and the latent h (M, geo_features)."""
        features, covered = self.encode(x)
        raw = self.density_mlp(features)
        sigma = trunc_exp(raw[:, 0] + self.density_bias) * covered
        return sigma, raw[:, 1:]

    # ---------------------------------------------------------------- heads

    def color(self, h: torch.Tensor, directions: torch.Tensor, image_index: torch.Tensor | None = None):
        """F_c: rgb (M, 3) in [0, 1] from h and unit view directions (M, 3)."""
        inputs = [h, spherical_harmonics(directions, self.sh_degree).to(h.dtype)]
        if self.appearance is not None:
            if image_index is None:  # a novel view: the mean appearance of the training images
                emb = self.appearance.weight.mean(dim=0, keepdim=True).expand(h.shape[0], -1)
            else:
                emb = self.appearance(image_index)
            inputs.append(emb.to(h.dtype))
        return torch.sigmoid(self.color_mlp(torch.cat(inputs, dim=-1)))

    def semantics(self, h: torch.Tensor) -> torch.Tensor:
        """F_s: C independent logits (M, C) from h.detach(): no semantic gradient reaches geometry."""
        return self.semantic_mlp(h.detach())

    def background(self, directions: torch.Tensor) -> torch.Tensor:
        """Colour (R, 3) seen along directions that leave the field (sky)."""
        return torch.sigmoid(self.background_mlp(spherical_harmonics(directions, self.sh_degree)))

    def density_parameters(self) -> list[nn.Parameter]:
        """The parameters of F_sigma (geometry)."""
        params = list(self.inner.parameters()) + list(self.density_mlp.parameters())
        if self.outer is not None:
            params += list(self.outer.parameters())
        return params


def grid_resolution(extent: float, detail: float, cap: int) -> int:
    """Grid points along one axis so that cells are `detail` wide (at least 2, at most `cap`)."""
    return int(min(max(math.ceil(extent / detail) + 1, 2), cap))

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

so unbounded backgrounds (a ground plane, far trees) live in the field too. With `train.grid_frame: perspective`
u covers the grid's range in the cameras' (x/z, y/z, ln z) instead of the box (srf/warp.py). The dense encoding
then uses a fine grid inside the box and a coarse one for the contracted shell (the detail is in
the box); the hash encoding covers the whole contracted cube. A learned background colour model
(a function of direction only, for the sky) takes whatever transmittance is left at the far end.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn

from srfpipe.srf.encodings import build_encoding
from srfpipe.srf.warp import build_warp


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


AFFINE_APPEARANCE_DIM = 12  # a 3 x 3 colour matrix and an offset per image
# a camera this close to a training image's (in `nearest_training_views`' distance) stands at its pose
SAME_POSE = 1e-6


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


def grid_coordinates(x: torch.Tensor, grid_min, grid_max, warp=None) -> torch.Tensor:
    """Scene-frame points (M, 3) -> u, [-1, 1]^3 over the grid (through `warp` when there is one)."""
    w = x.float() if warp is None else warp(x)
    return (w - 0.5 * (grid_min + grid_max)) / (0.5 * (grid_max - grid_min))


def grid_points(u: torch.Tensor, grid_min, grid_max, warp=None) -> torch.Tensor:
    """Inverse of `grid_coordinates`."""
    w = u * (0.5 * (grid_max - grid_min)) + 0.5 * (grid_min + grid_max)
    return w if warp is None else warp.inverse(w)


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
    config or None), density_grid, hidden, geo_features, sh_degree, background_sh_degree (default
    sh_degree), num_classes, appearance_dim, num_images, density_bias, color_layers.

    Two forms of F_sigma:
    * `density_grid: true` (the CPU default with dense grids): sigma reads its own one-channel
      grid, sigma = trunc_exp(g_sigma(x) + bias), and h is the feature grid's value at x. sigma
      alone is then a cheap lookup, so empty-space tests, occupancy updates and the transmittance
      pass touch no MLP, and h is computed only where a sample's weight matters (DVGO-style).
    * otherwise (hash grids, Nerfacto): encoding(x) -> MLP -> (sigma, h).
    """

    def __init__(self, config: dict, device="cpu"):
        super().__init__()
        self.config = dict(config)
        c = self.config
        self.register_buffer("box_min", torch.tensor(c["box_min"], dtype=torch.float32))
        self.register_buffer("box_max", torch.tensor(c["box_max"], dtype=torch.float32))
        # the grid's frame (srf/warp.py): the box itself, or a perspective frustum whose range in
        # warped coordinates is grid_min..grid_max
        self.warp = build_warp(c.get("warp"))
        # (from the config, so not in the weights: a field saved before them loads unchanged)
        self.register_buffer("grid_min", torch.tensor(c.get("grid_min", c["box_min"]), dtype=torch.float32),
                             persistent=False)
        self.register_buffer("grid_max", torch.tensor(c.get("grid_max", c["box_max"]), dtype=torch.float32),
                             persistent=False)
        self.contraction = bool(c["contraction"])
        self.static_shapes = False  # SRFModel.use_static_shapes: every lookup the same size (CUDA graphs)
        self.inner = build_encoding(c["inner"], device)
        self.outer = build_encoding(c["outer"], device) if c.get("outer") else None
        if self.outer is not None and self.outer.output_dim != self.inner.output_dim:
            raise ValueError("inner and outer encodings must produce the same number of features")
        hidden = int(c["hidden"])
        self.density_bias = float(c["density_bias"])
        self.density_grid = bool(c["density_grid"])
        if self.density_grid:
            # one channel; levels of a multi-resolution grid add up to one log-density
            self.inner_sigma = build_encoding(dict(c["inner"], features=1, combine="sum"), device)
            self.outer_sigma = (build_encoding(dict(c["outer"], features=1, combine="sum"), device)
                                if c.get("outer") else None)
            for grid in (self.inner_sigma, self.outer_sigma):
                if grid is not None:
                    for table in grid.parameters():
                        nn.init.zeros_(table)
            geo = self.inner.output_dim
            self.density_mlp = None
        else:
            geo = int(c["geo_features"])
            self.density_mlp = mlp(self.inner.output_dim, hidden, 1 + geo)
        self.geo_features = geo
        self.sh_degree = int(c["sh_degree"])
        appearance_dim = int(c["appearance_dim"])
        # "latent": a_i is an input of F_c (NeRF-W, Nerfacto); "affine": a_i is a colour transform
        # of each image's rendered pixels (rgb + M_i rgb + b_i, 12 numbers), which can correct
        # exposure and white balance but not learn what a single view shows
        self.appearance_model = str(c.get("appearance_model", "latent"))
        if self.appearance_model not in ("latent", "affine"):
            raise ValueError(f"appearance_model must be latent or affine, got {self.appearance_model!r}")
        self.appearance = (
            nn.Embedding(int(c["num_images"]), AFFINE_APPEARANCE_DIM if self.appearance_model == "affine"
                         else appearance_dim) if appearance_dim > 0 else None
        )
        colour_appearance_dim = appearance_dim if self.appearance_model == "latent" else 0
        if self.appearance is not None:
            nn.init.zeros_(self.appearance.weight)
            # where each training image was taken (scene frame): a novel view borrows the
            # appearance of the nearest one; NaN for images the field never trained on
            num_images = int(c["num_images"])
            self.register_buffer("camera_centres", torch.full((num_images, 3), float("nan")))
            self.register_buffer("camera_axes", torch.full((num_images, 3), float("nan")))
            # (K, 2) each training image and the one taken nearest to it (train.appearance_smoothness);
            # not a buffer: a trained field's file does not carry it
            self.appearance_pairs = torch.zeros((0, 2), dtype=torch.long)
        # how many training images' appearances a new view is rendered with (fields saved before
        # this key took the nearest image's alone)
        self.novel_view_appearances = int(c.get("novel_view_appearances", 1))
        self.color_mlp = mlp(geo + self.sh_degree**2 + colour_appearance_dim, hidden, 3,
                             layers=int(c["color_layers"]))
        self.num_classes = int(c["num_classes"])
        # F_s reads h.detach() and, optionally, a frequency encoding of the (contracted) position:
        # with a dense grid h is the colour features only, and green leaves and green grass share
        # colours; the position is not a parameter, so geometry stays out of reach of L_sem.
        self.semantic_octaves = int(c["semantic_octaves"])
        self.semantic_mlp = mlp(geo + 6 * self.semantic_octaves, hidden, self.num_classes)
        # the background model may read fewer bands than the colour: a backdrop seen through a few
        # narrow views must be interpolated between them, not fitted per direction (fields saved
        # before this key read all of the colour's bands)
        self.background_sh_degree = int(c.get("background_sh_degree", self.sh_degree))
        self.background_mlp = mlp(self.background_sh_degree**2, 32, 3)
        # background logits: rays that leave the field see "no class" unless learned otherwise
        self.background_logits = nn.Parameter(torch.full((self.num_classes,), -2.0))

    # ---------------------------------------------------------------- geometry

    def box_coordinates(self, x: torch.Tensor) -> torch.Tensor:
        """Scene-frame points (M, 3) -> box coordinates u ([-1, 1]^3 inside the model's grid)."""
        return grid_coordinates(x, self.grid_min, self.grid_max, self.warp)

    def _encode(self, x: torch.Tensor, inner, outer) -> tuple[torch.Tensor, torch.Tensor]:
        """Features (M, F) from the inner/outer encodings, and a mask of points the field covers."""
        u = self.box_coordinates(x)
        if not self.contraction:
            inside = (u.abs() <= 1.0).all(dim=-1)
            return inner(u), inside
        covered = torch.ones(u.shape[0], dtype=torch.bool, device=u.device)
        if outer is None:
            return inner(contract(u) * 0.5), covered
        inside = (u.abs() <= 1.0).all(dim=-1)
        if self.static_shapes:
            # both grids read at every point and the right one kept: no shape depends on the data
            # (a CUDA graph replays it); the unused reads get zero gradient
            values_in = inner(u)
            values_out = outer(contract(u) * 0.5).to(values_in.dtype)
            return torch.where(inside.unsqueeze(-1), values_in, values_out), covered
        idx_in = inside.nonzero().squeeze(1)
        idx_out = (~inside).nonzero().squeeze(1)
        if idx_out.numel() == 0:
            return inner(u), covered
        if idx_in.numel() == 0:
            return outer(contract(u) * 0.5), covered
        values_in = inner(u[idx_in])
        values_out = outer(contract(u[idx_out]) * 0.5)
        features = torch.zeros(u.shape[0], values_in.shape[1], device=u.device, dtype=values_in.dtype)
        features = features.index_copy(0, idx_in, values_in)
        return features.index_copy(0, idx_out, values_out.to(values_in.dtype)), covered

    def sigma(self, x: torch.Tensor) -> torch.Tensor:
        """sigma (M,) per scene-frame unit length (cheap with `density_grid`)."""
        if not self.density_grid:
            return self.density(x)[0]
        raw, covered = self._encode(x, self.inner_sigma, self.outer_sigma)
        return trunc_exp(raw[:, 0] + self.density_bias) * covered

    def latent(self, x: torch.Tensor) -> torch.Tensor:
        """h (M, geo_features) at scene-frame points."""
        if not self.density_grid:
            return self.density(x)[1]
        return self._encode(x, self.inner, self.outer)[0]

    def density(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """F_sigma: sigma (M,) per scene-frame unit length, and the latent h (M, geo_features)."""
        if self.density_grid:
            return self.sigma(x), self.latent(x)
        features, covered = self._encode(x, self.inner, self.outer)
        raw = self.density_mlp(features)
        sigma = trunc_exp(raw[:, 0] + self.density_bias) * covered
        return sigma, raw[:, 1:]

    # ---------------------------------------------------------------- heads

    def color(self, h: torch.Tensor, directions: torch.Tensor, image_index: torch.Tensor | None = None,
              ray_index: torch.Tensor | None = None):
        """F_c: rgb (M, 3) in [0, 1] from h (M, geo) and unit view directions.

        With `ray_index` (M,), `directions` (R, 3) and `image_index` (R,) are per *ray*: the
        direction and appearance terms of the first layer are computed once per ray and gathered,
        which is the same function as concatenating them per sample, at a fraction of the cost.
        """
        first, rest = self.color_mlp[0], self.color_mlp[1:]
        geo = h.shape[1]
        per_ray = [spherical_harmonics(directions, self.sh_degree)]
        if self.appearance is not None and self.appearance_model == "latent":
            per_ray.append(self.appearance_code(image_index, directions.shape[0]))
        ray_term = torch.cat(per_ray, dim=-1) @ first.weight[:, geo:].T + first.bias
        if ray_index is not None:
            # index_select: its backward is an index_add_, ~15x faster on the CPU than the
            # accumulating index_put_ behind ray_term[ray_index]
            ray_term = ray_term.index_select(0, ray_index)
        return torch.sigmoid(rest(h @ first.weight[:, :geo].T + ray_term))

    def appearance_code(self, image_index: torch.Tensor | None, rays: int) -> torch.Tensor:
        """a_i (R, dim) of each ray's image; with no image known, the mean of the training images'."""
        if image_index is None:
            return self.appearance.weight.mean(dim=0, keepdim=True).expand(rays, -1)
        return self.appearance(image_index)

    def image_colour(self, rgb: torch.Tensor, image_index: torch.Tensor | None) -> torch.Tensor:
        """The rendered colours (R, 3) of rays as their image saw them: rgb + M_i rgb + b_i with the
        affine appearance (zero-initialised: the identity), unchanged otherwise."""
        if self.appearance is None or self.appearance_model != "affine":
            return rgb
        code = self.appearance_code(image_index, rgb.shape[0]).float()
        matrix = code[:, :9].reshape(-1, 3, 3)
        return rgb + torch.einsum("rij,rj->ri", matrix, rgb) + code[:, 9:]

    def record_training_cameras(self, camera_to_scene: torch.Tensor, views) -> None:
        """Remember the centres and viewing axes (OpenCV +z) of the training `views`."""
        if self.appearance is None:
            return
        views = torch.as_tensor(views, dtype=torch.long)
        poses = camera_to_scene[views].to(self.camera_centres)
        self.camera_centres[views] = poses[:, :3, 3]
        self.camera_axes[views] = poses[:, :3, 2]
        self.appearance_pairs = self.training_neighbours()

    def nearest_training_view(self, origin: torch.Tensor, axis: torch.Tensor, exclude: int | None = None) -> int | None:
        """The training image taken nearest to a camera at `origin` looking along `axis`, or None
        (see `nearest_training_views`)."""
        nearest = self.nearest_training_views(origin, axis, exclude)
        return nearest[0][0] if nearest else None

    def nearest_training_views(self, origin: torch.Tensor, axis: torch.Tensor, exclude: int | None = None,
                               count: int = 1) -> list[tuple[int, float]]:
        """The `count` training images taken nearest to a camera at `origin` looking along `axis`
        (distance in box sizes plus 1 - cos of the angle between the axes), each with a weight
        proportional to 1 / that distance (the weights sum to 1); a camera at a training image's
        own pose gets that image alone. `exclude`: an image that may not be chosen (a training view
        rendered as a new view would be). Empty without an appearance embedding."""
        if self.appearance is None:
            return []
        known = torch.isfinite(self.camera_centres).all(dim=-1)
        if exclude is not None:
            known[int(exclude)] = False
        count = min(int(count), int(known.sum()))
        if count < 1:
            return []
        size = float((self.box_max - self.box_min).max())
        axis = axis / axis.norm().clamp(min=1e-12)
        cost = (self.camera_centres - origin).norm(dim=-1) / size + (1.0 - self.camera_axes @ axis)
        cost, index = torch.where(known, cost, torch.full_like(cost, float("inf"))).topk(count, largest=False)
        if float(cost[0]) < SAME_POSE:
            return [(int(index[0]), 1.0)]
        weight = 1.0 / cost
        return list(zip(index.tolist(), (weight / weight.sum()).tolist()))

    def appearance_weights(self) -> torch.Tensor:
        """W_a (hidden, dim): the colour MLP's first-layer weights on the appearance embedding."""
        return self.color_mlp[0].weight[:, self.geo_features + self.sh_degree**2:]

    def training_neighbours(self) -> torch.Tensor:
        """Pairs (K, 2) of each training image and the other training image taken nearest to it
        (the choice a new view at its pose makes: `nearest_training_view`)."""
        if self.appearance is None:
            return torch.zeros((0, 2), dtype=torch.long)
        known = torch.isfinite(self.camera_centres).all(dim=-1).nonzero().flatten().tolist()
        pairs = [(i, self.nearest_training_view(self.camera_centres[i], self.camera_axes[i], exclude=i))
                 for i in known]
        return torch.tensor([p for p in pairs if p[1] is not None], dtype=torch.long,
                            device=self.camera_centres.device).reshape(-1, 2)

    def semantics(self, h: torch.Tensor, x: torch.Tensor | None = None) -> torch.Tensor:
        """F_s: C independent logits (M, C) from h.detach() (and the position x when the field
        was built with `semantic_octaves`): no semantic gradient reaches the geometry."""
        if self.num_classes == 0:
            # a capture without masks: no logits to compute, and the head's hidden layers at every
            # shaded sample cost the fern a third of its training step (602 against 845 ms)
            return h.new_zeros((h.shape[0], 0))
        inputs = [h.detach()]
        if self.semantic_octaves:
            if x is None:
                raise ValueError("this field's semantic head needs the sample positions")
            inputs.append(self.position_encoding(x))
        return self.semantic_mlp(torch.cat(inputs, dim=-1))

    def position_encoding(self, x: torch.Tensor) -> torch.Tensor:
        """sin/cos of the contracted box coordinates at `semantic_octaves` octaves (M, 6 * octaves)."""
        u = self.box_coordinates(x)
        v = contract(u) * 0.5 if self.contraction else u.clamp(-1.0, 1.0)
        scales = (2.0 ** torch.arange(self.semantic_octaves, device=x.device, dtype=torch.float32)) * math.pi
        angles = (v.unsqueeze(-1) * scales).flatten(1)  # (M, 3 * octaves); M may be 0
        return torch.cat([torch.sin(angles), torch.cos(angles)], dim=-1)

    def background(self, directions: torch.Tensor) -> torch.Tensor:
        """Colour (R, 3) seen along directions that leave the field (sky)."""
        return torch.sigmoid(self.background_mlp(spherical_harmonics(directions, self.background_sh_degree)))

    def density_parameters(self) -> list[nn.Parameter]:
        """The parameters of F_sigma (geometry: sigma and the latent h)."""
        modules = [self.inner, self.outer, self.density_mlp]
        if self.density_grid:
            modules += [self.inner_sigma, self.outer_sigma]
        return [p for m in modules if m is not None for p in m.parameters()]


def grid_resolution(extent: float, detail: float, cap: int) -> int:
    """Grid points along one axis so that cells are `detail` wide (at least 2, at most `cap`)."""
    # ceil with a tolerance: an extent of exactly 32 cells computed as 32.000000000000004 is 32 cells
    return int(min(max(math.ceil(extent / detail - 1e-6) + 1, 2), cap))

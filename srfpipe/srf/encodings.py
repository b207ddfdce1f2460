"""Position encodings of the density field: pluggable modules mapping u in [-1, 1]^3 to features.

* `DenseGrid`: one trainable feature table of shape (Rx*Ry*Rz, F), read by trilinear interpolation
  computed by hand (8 corner indices and weights, one `embedding` gather). On the CPU this
  channels-last gather was ~3x faster than `grid_sample` on a (1, F, Rz, Ry, Rx) volume, which
  parallelises only over its batch dimension. The fast default on CPU. On CUDA the forward of a
  grid without a hashed table is `grid_sample` on a strided view of the same table (`sampled_volume`).
* `HashGrid`: Instant-NGP's multi-resolution hash encoding in plain PyTorch, vectorised over levels
  (one gather for all levels and corners); on CUDA `TcnnHashGrid` (tiny-cuda-nn) replaces it when
  that package can be imported.

Every encoding has `.output_dim` and `.config()` (a JSON-able dict that rebuilds it through
`build_encoding`).
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn

# The 8 corners of a cell as (dx, dy, dz) in {0, 1}^3.
_CORNERS = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=torch.long)
# Instant-NGP's spatial-hash primes (the first is 1 so that the x axis stays coherent in memory).
_PRIMES = (1, 2654435761, 805459861)


def spatial_hash(corners: torch.Tensor) -> torch.Tensor:
    """Instant-NGP's spatial hash xor_i(x_i * pi_i) of integer grid points (..., 3); the caller
    takes it modulo its (power-of-two) table size."""
    return (corners[..., 0] * _PRIMES[0]) ^ (corners[..., 1] * _PRIMES[1]) ^ (corners[..., 2] * _PRIMES[2])


class _InterpolatedGather(torch.autograd.Function):
    """out[m] = sum_k weights[m, k] * table[index[m, k]] for a channels-last table (N, F).

    Forward reads whole rows (one cache line per corner for F <= 16). The backward adds rows with
    `index_add_` into a channels-last (N, F) buffer: 35 ms on 2 cores for 112 k samples (0.9 M
    corner rows) into a 96^3 x 16 grid, where `embedding`'s backward pays ~100 ns per row and a
    feature-major (F, N) buffer plus the transpose of the whole grid gradient took 66 ms.

    Both passes run in the table's precision whatever autocast says: the gather is memory-bound
    (nothing to gain from bf16 on the CPU), and under bf16/fp16 autocast the interpolation would
    round log-densities to 8 or 11 bits and the backward would add ~10^6 corner rows in half
    precision (it failed outright: `index_add_` of float32 contributions into a bf16 buffer).
    """

    @staticmethod
    def forward(ctx, table, index, weights, volume=None):
        with torch.autocast(table.device.type, enabled=False):
            out = weighted_rows(table, index, weights) if volume is None else sampled_volume(table, *volume)
        ctx.save_for_backward(index, weights, table if ctx.needs_input_grad[2] else None)
        ctx.rows, ctx.dtype = table.shape[0], table.dtype
        return out

    @staticmethod
    def backward(ctx, grad_out):
        index, weights, table = ctx.saved_tensors
        grad_out = grad_out.to(ctx.dtype)
        features = grad_out.shape[1]
        flat = index.reshape(-1)
        # d out[m] / d weights[m, k] = table[index[m, k]]: only when positions learn (camera refinement)
        grad_weights = None
        if ctx.needs_input_grad[2]:
            rows = table.index_select(0, flat).view(*index.shape, features)
            grad_weights = (rows * grad_out.unsqueeze(1)).sum(-1)
        if features == 1:
            contributions = (weights.to(ctx.dtype) * grad_out).reshape(-1)
            grad = torch.zeros(ctx.rows, dtype=ctx.dtype, device=grad_out.device)
            return grad.index_add_(0, flat, contributions).unsqueeze(1), None, grad_weights, None
        contributions = (grad_out.unsqueeze(1) * weights.to(ctx.dtype).unsqueeze(-1)).reshape(-1, features)
        grad = torch.zeros(ctx.rows, features, dtype=ctx.dtype, device=grad_out.device)
        return grad.index_add_(0, flat, contributions), None, grad_weights, None


def weighted_rows(table: torch.Tensor, index: torch.Tensor, weights: torch.Tensor, fused: bool = True) -> torch.Tensor:
    """sum_k weights[m, k] * table[index[m, k]] (M, F), without autograd's bookkeeping.

    `fused`: one `embedding_bag` pass that never writes the (M, K, F) corner rows. On 2 CPU cores
    it takes a fifth of the time of the row gather and batched product (20 against 100 ms for
    100 k points into a 96^3 x 16 grid): a 320 x 240 render of the orchard 2.9-3.2 s against
    3.4-4.0. On an H100, for the paper preset's hash grid (2 M rows of 8 corners, 2 features),
    2.0 against 3.0 ms (gpu.json `interpolation_ms`). The gather (`fused=False`) stays as the
    reference the tests and that benchmark compare with.
    """
    if fused:
        return torch.nn.functional.embedding_bag(index, table, per_sample_weights=weights.to(table.dtype), mode="sum")
    m, k = index.shape
    values = table.index_select(0, index.reshape(-1)).view(m, k, table.shape[1])
    return torch.bmm(weights.unsqueeze(1).to(values.dtype), values).squeeze(1)


def interpolated_gather(table: torch.Tensor, index: torch.Tensor, weights: torch.Tensor, volume=None) -> torch.Tensor:
    """sum_k weights[m, k] * table[index[m, k]] for a channels-last table (N, F): (M, K) -> (M, F).

    The weights depend only on sample positions, which learn only when the rays do (camera
    refinement): otherwise they are detached, and the backward skips their gradient (a second
    gather of every corner row). `volume` = (resolution, u): the table is a dense grid of that
    resolution, and the forward reads it at u by `grid_sample` (see `sampled_volume`); the
    backward is the same either way.
    """
    return _InterpolatedGather.apply(table, index, weights.float(), volume)


def sampled_volume(table: torch.Tensor, resolution: tuple[int, int, int], u: torch.Tensor) -> torch.Tensor:
    """A dense grid's trilinear interpolation (M, F) at u (M, 3) in [-1, 1] through `grid_sample`,
    equal to the corner sum (align_corners=True, border padding): the forward of `DenseGrid` on CUDA.

    Why: on CUDA the corner sum wrote the (M, 8, F) corner rows and read them back in tiny batched
    products, 4.1 of 9.1 ms of kernels a step of the orchard on an H200 (gpu.json `earlier_leases`);
    grid_sample reads the corners in one kernel (0.23 ms a step on an H100). Only the forward:
    grid_sample's own backward adds each point's corners one thread at a time, and a ray's samples
    share cells, so the atomic adds collide (3.4 ms a step on an H100, against 1.7 on an H200 for `index_add_`
    of the contributions). The table stays channels-last: the volume is a strided view, x the
    slowest axis (D), z the fastest (W), so the sample points go in as (z, y, x).
    """
    rx, ry, rz = resolution
    features = table.shape[1]
    volume = table.view(rx, ry, rz, features).permute(3, 0, 1, 2).unsqueeze(0)  # (1, F, Rx, Ry, Rz), no copy
    grid = u.float().clamp(-1.0, 1.0).flip(-1).view(1, -1, 1, 1, 3)
    out = torch.nn.functional.grid_sample(volume, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.view(features, -1).t()


def _axis_weights(frac: torch.Tensor) -> torch.Tensor:
    """Trilinear weights (…, 8) of the cell corners, corner i = (x, y, z) = (i>>2&1, i>>1&1, i&1)."""
    f = frac.unsqueeze(-1)
    pairs = torch.cat([1.0 - f, f], dim=-1)  # (…, 3, 2)
    wx, wy, wz = pairs.unbind(-2)
    w = wx[..., :, None, None] * wy[..., None, :, None] * wz[..., None, None, :]
    return w.reshape(*frac.shape[:-1], 8)


class DenseGrid(nn.Module):
    """A trainable feature grid over [-1, 1]^3 (grid points at the box corners, like
    `align_corners=True`), with per-axis resolution so an elongated box keeps square cells.

    With `table_rows` smaller than the number of grid points, the points share a table of that
    many rows through Instant-NGP's spatial hash: a fine grid costs the memory (and the optimizer
    the time) of the rows, not of the box, and since most of a box is empty, the few occupied
    cells rarely collide (their gradients dominate every row they share with empty space).
    """

    def __init__(self, resolution: tuple[int, int, int], features: int = 16, init_scale: float = 0.1,
                 table_rows: int | None = None):
        super().__init__()
        if any(int(r) < 2 for r in resolution):
            raise ValueError(f"dense grid resolution must be >= 2 per axis, got {resolution}")
        self.resolution = tuple(int(r) for r in resolution)
        self.features = int(features)
        rx, ry, rz = self.resolution
        points = rx * ry * rz
        self.hashed = table_rows is not None and int(table_rows) < points
        if self.hashed and int(table_rows) & (int(table_rows) - 1):
            raise ValueError(f"a hashed grid's table_rows must be a power of two, got {table_rows}")
        rows = int(table_rows) if self.hashed else points
        self.table = nn.Parameter(torch.empty(rows, self.features).uniform_(-init_scale, init_scale))
        self.register_buffer("_res", torch.tensor(self.resolution, dtype=torch.float32), persistent=False)
        self.register_buffer("_strides", torch.tensor([ry * rz, rz, 1], dtype=torch.long), persistent=False)
        self.register_buffer("_corner_offsets", _CORNERS @ self._strides, persistent=False)
        self.register_buffer("_corners", _CORNERS.clone(), persistent=False)  # on the grid's device: no copy a call

    @property
    def output_dim(self) -> int:
        return self.features

    def config(self) -> dict:
        return {"type": "dense", "resolution": list(self.resolution), "features": self.features}

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        """u (M, 3) in [-1, 1] -> features (M, F)."""
        pos = (u.float().clamp(-1.0, 1.0) + 1.0) * 0.5 * (self._res - 1.0)
        origin = torch.minimum(pos.floor(), self._res - 2.0)
        frac = pos - origin
        if self.hashed:
            corners = origin.long().unsqueeze(1) + self._corners  # (M, 8, 3)
            index = spatial_hash(corners) & (self.table.shape[0] - 1)
        else:
            base = (origin.long() * self._strides).sum(dim=-1)  # (M,)
            index = base.unsqueeze(1) + self._corner_offsets  # (M, 8)
            if u.device.type == "cuda":  # on the CPU embedding_bag's fused corner sum is the faster forward
                return interpolated_gather(self.table, index, _axis_weights(frac), (self.resolution, u))
        return interpolated_gather(self.table, index, _axis_weights(frac))


class MultiResolutionDenseGrid(nn.Module):
    """Dense grids at `levels` resolutions, each twice as coarse as the next (the finest is
    `resolution`): Instant-NGP's multi-resolution idea without the hash. The coarse levels are
    seen by many rays and learn the shape quickly; the fine ones add detail on top, so a fine
    grid no longer has to be fit cell by cell from the few rays that cross each cell.

    `combine` = "concat" (features of all levels, coarse first: M x levels*F) or "sum" (one
    F-vector, the sum over levels: the density grid's log-density is a coarse term plus corrections).

    `fine_levels` more levels, each twice as fine again as `resolution`, hold the detail that a
    dense grid cannot afford (a 384^3 x 8 grid is 0.6 GB before Adam's state): each keeps at
    most 2^`log2_table_size` rows, hashed when its points are more (see `DenseGrid`).
    """

    def __init__(self, resolution, features: int = 8, levels: int = 3, combine: str = "concat",
                 fine_levels: int = 0, log2_table_size: int = 22):
        super().__init__()
        if combine not in ("concat", "sum"):
            raise ValueError(f"combine must be 'concat' or 'sum', got {combine!r}")
        self.resolution = tuple(int(r) for r in resolution)
        self.features, self.levels, self.combine = int(features), int(levels), combine
        self.fine_levels, self.log2_table_size = int(fine_levels), int(log2_table_size)
        grids = [DenseGrid(level_resolution(self.resolution, self.levels - 1 - level), self.features)
                 for level in range(self.levels)]
        grids += [DenseGrid(finer_resolution(self.resolution, level + 1), self.features,
                            table_rows=2**self.log2_table_size) for level in range(self.fine_levels)]
        self.grids = nn.ModuleList(grids)

    @property
    def output_dim(self) -> int:
        return self.features * (len(self.grids) if self.combine == "concat" else 1)

    def config(self) -> dict:
        config = {"type": "dense", "resolution": list(self.resolution), "features": self.features,
                  "levels": self.levels, "combine": self.combine}
        if self.fine_levels:
            config.update(fine_levels=self.fine_levels, log2_table_size=self.log2_table_size)
        return config

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        values = [grid(u) for grid in self.grids]
        return torch.cat(values, dim=-1) if self.combine == "concat" else torch.stack(values).sum(0)


def level_resolution(resolution, halvings: int) -> tuple[int, int, int]:
    """Grid points per axis of a grid with cells 2^halvings times as wide over the same box."""
    return tuple(max(int(math.ceil((int(r) - 1) / 2**halvings)) + 1, 2) for r in resolution)


def finer_resolution(resolution, doublings: int) -> tuple[int, int, int]:
    """Grid points per axis of a grid with cells 2^doublings times as fine over the same box."""
    return tuple((int(r) - 1) * 2**doublings + 1 for r in resolution)


class HashGrid(nn.Module):
    """Multi-resolution hash encoding (Mueller et al. 2022), all levels in one vectorised pass.

    Level l has resolution N_l = floor(base * b^l) with b chosen so the finest level reaches
    `max_resolution`; a level whose (N_l + 1)^3 grid fits in the table is indexed densely,
    the others through the spatial hash xor_i(x_i * pi_i) mod T.
    """

    def __init__(
        self,
        levels: int = 16,
        features_per_level: int = 2,
        log2_table_size: int = 19,
        base_resolution: int = 16,
        max_resolution: int = 1024,
        init_scale: float = 1e-4,
    ):
        super().__init__()
        self.levels = int(levels)
        self.features_per_level = int(features_per_level)
        self.log2_table_size = int(log2_table_size)
        self.base_resolution = int(base_resolution)
        self.max_resolution = int(max(max_resolution, base_resolution))
        table_size = 2 ** self.log2_table_size
        growth = math.exp(
            (math.log(self.max_resolution) - math.log(self.base_resolution)) / max(self.levels - 1, 1)
        )
        resolutions = [int(math.floor(self.base_resolution * growth**l)) for l in range(self.levels)]
        dense = [(r + 1) ** 3 <= table_size for r in resolutions]
        self.table = nn.Parameter(  # levels one after another
            torch.empty(self.levels * table_size, self.features_per_level).uniform_(-init_scale, init_scale)
        )
        self.register_buffer("_res", torch.tensor(resolutions, dtype=torch.float32), persistent=False)
        self.register_buffer("_dense", torch.tensor(dense), persistent=False)
        self.register_buffer("_corners", _CORNERS.clone(), persistent=False)
        self.register_buffer(
            "_offsets", torch.arange(self.levels, dtype=torch.long) * table_size, persistent=False
        )
        self.table_size = table_size

    @property
    def output_dim(self) -> int:
        return self.levels * self.features_per_level

    def config(self) -> dict:
        return {
            "type": "hash", "levels": self.levels, "features_per_level": self.features_per_level,
            "log2_table_size": self.log2_table_size, "base_resolution": self.base_resolution,
            "max_resolution": self.max_resolution,
        }

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        """u (M, 3) in [-1, 1] -> features (M, L*F), levels coarse to fine."""
        m = u.shape[0]
        unit = (u.float().clamp(-1.0, 1.0) + 1.0) * 0.5  # [0, 1]
        pos = unit.unsqueeze(1) * self._res.view(1, -1, 1)  # (M, L, 3), vertices 0..N_l
        upper = (self._res - 1.0).view(1, -1, 1)
        origin = torch.minimum(pos.floor().clamp_min(0), upper)
        frac = (pos - origin).clamp(0.0, 1.0)
        corners = origin.long().unsqueeze(2) + self._corners  # (M, L, 8, 3)
        weights = _axis_weights(frac)  # (M, L, 8)
        side = self._res.long().view(1, -1, 1) + 1  # vertices per axis
        dense_index = corners[..., 0] * side * side + corners[..., 1] * side + corners[..., 2]
        index = torch.where(self._dense.view(1, -1, 1), dense_index, spatial_hash(corners)) & (self.table_size - 1)
        index = index + self._offsets.view(1, -1, 1)  # (M, L, 8)
        # one gather for all levels: rows are (point, level) pairs
        out = interpolated_gather(self.table, index.view(m * self.levels, 8), weights.view(m * self.levels, 8))
        return out.view(m, self.output_dim)


class TcnnHashGrid(nn.Module):
    """tiny-cuda-nn's fused hash grid (CUDA only); same config keys as `HashGrid`."""

    def __init__(self, levels=16, features_per_level=2, log2_table_size=19, base_resolution=16,
                 max_resolution=1024, **_):
        super().__init__()
        import tinycudann as tcnn

        self._config = {
            "type": "hash", "levels": levels, "features_per_level": features_per_level,
            "log2_table_size": log2_table_size, "base_resolution": base_resolution,
            "max_resolution": max_resolution,
        }
        growth = math.exp((math.log(max_resolution) - math.log(base_resolution)) / max(levels - 1, 1))
        self.encoding = tcnn.Encoding(3, {
            "otype": "HashGrid", "n_levels": levels, "n_features_per_level": features_per_level,
            "log2_hashmap_size": log2_table_size, "base_resolution": base_resolution,
            "per_level_scale": growth,
        })

    @property
    def output_dim(self) -> int:
        return self.encoding.n_output_dims

    def config(self) -> dict:
        return dict(self._config)

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        return self.encoding(((u.clamp(-1.0, 1.0) + 1.0) * 0.5).contiguous()).float()


def tcnn_available(device) -> bool:
    if torch.device(device).type != "cuda":
        return False
    try:
        import tinycudann  # noqa: F401
    except ImportError:
        return False
    return True


def build_encoding(config: dict, device="cpu") -> nn.Module:
    """An encoding from its `config()` dict; the hash grid uses tiny-cuda-nn when it can.

    The tiny-cuda-nn and torch hash grids store their tables differently, so a model saved
    from one is loaded into the torch implementation (`prefer_tcnn=False` in the config).
    """
    config = dict(config)
    kind = config.pop("type")
    prefer_tcnn = config.pop("prefer_tcnn", True)
    if kind == "dense":
        # a model config names levels and fine levels only when a grid has them (build_model_config)
        if int(config.get("levels", 1)) > 1 or int(config.get("fine_levels", 0)) > 0:
            return MultiResolutionDenseGrid(config["resolution"], config["features"],
                                            int(config.get("levels", 1)), config.get("combine", "concat"),
                                            int(config.get("fine_levels", 0)), int(config.get("log2_table_size", 22)))
        return DenseGrid(tuple(config["resolution"]), config["features"])
    if kind == "hash":
        if prefer_tcnn and tcnn_available(device):
            return TcnnHashGrid(**config)
        return HashGrid(**config)
    raise ValueError(f"unknown encoding type {kind!r} (expected 'dense' or 'hash')")

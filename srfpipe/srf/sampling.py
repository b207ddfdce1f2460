"""Where to put samples along rays: near/far from the model box, and an occupancy grid that
skips empty space (nerfacc's estimator, written in plain torch so it runs on CPU and CUDA).

Intervals along a ray come from up to three segments (scene-frame distances t):

* inside the model box [t_enter, t_exit]: uniform steps of `step` (a fraction of the detail size),
  or with a perspective grid (srf/warp.py) steps uniform in ln t, as its cells are;
* with contraction, beyond the box [t_exit, far]: `outer_samples` steps uniform in
  s = (t - a) / (t - a + L), i.e. in disparity, so far space costs a fixed number of samples;
* with contraction, between the camera and the box [near, t_enter]: `before_samples` uniform steps.

Segments are covered completely (no gaps), so dropping an interval is exactly sigma = 0 there.
Training jitters every ray by one random fraction of a step (stratified sampling).
Intervals in unoccupied cells are then dropped and the rest stored flat, ray after ray
(`PackedSamples`), as `srfpipe.srf.rendering` consumes them; a training step of fixed shapes (CUDA
graphs) keeps them padded instead (`RaySamples`), the culled ones with sigma = 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn as nn

from srfpipe.device import rand, randint
from srfpipe.srf.field import contract, grid_coordinates, grid_points, uncontract
from srfpipe.srf.rendering import Segments
from srfpipe.srf.warp import PerspectiveWarp


@dataclass
class RaySamples:
    """Padded intervals: t_start, t_end, mask (R, K); intervals with mask False are padding."""

    t_start: torch.Tensor
    t_end: torch.Tensor
    mask: torch.Tensor

    @property
    def delta(self) -> torch.Tensor:
        return torch.where(self.mask, self.t_end - self.t_start, torch.zeros_like(self.t_start))


@dataclass
class PackedSamples:
    """The intervals the occupancy grid kept, stored flat ray after ray (rendering.Segments):
    t_start, t_end (M,), their midpoints `points` (M, 3), and the intervals each ray had before
    the culling, `candidates` (R,)."""

    t_start: torch.Tensor
    t_end: torch.Tensor
    points: torch.Tensor
    segments: Segments
    candidates: torch.Tensor

    @property
    def delta(self) -> torch.Tensor:
        return self.t_end - self.t_start


def ray_aabb(origins, directions, box_min, box_max):
    """Slab test: entry and exit distances (R,) of rays against an axis-aligned box.

    A ray that misses gets t_exit < t_enter. Axis-parallel rays are handled by IEEE infinities.
    """
    with torch.no_grad():
        inv = 1.0 / torch.where(directions == 0, torch.full_like(directions, 1e-12), directions)
        t0 = (box_min - origins) * inv
        t1 = (box_max - origins) * inv
        t_enter = torch.minimum(t0, t1).amax(dim=-1)
        t_exit = torch.maximum(t0, t1).amin(dim=-1)
    return t_enter, t_exit


def _uniform_edges(start, end, count: int, jitter):
    """count + 1 intervals tiling [start, end] per ray (the jitter shifts them by a step fraction,
    so one extra interval closes the end)."""
    k = torch.arange(count + 2, device=start.device, dtype=start.dtype)
    step = (end - start).clamp_min(0) / count
    edges = start[:, None] + (k[None, :] - 1.0 + jitter[:, None]) * step[:, None]
    return torch.minimum(torch.maximum(edges, start[:, None]), torch.maximum(end, start)[:, None])


def _fixed_step_edges(start, end, step: float, count: int, jitter):
    """Intervals of length `step` from `start`, clipped to `end` (count chosen to reach any end)."""
    k = torch.arange(count + 1, device=start.device, dtype=start.dtype)
    edges = start[:, None] + (k[None, :] - 1.0 + jitter[:, None]) * step
    return torch.minimum(torch.maximum(edges, start[:, None]), torch.maximum(end, start)[:, None])


def _log_step_edges(start, end, log_step: float, count: int, jitter):
    """count intervals tiling [start, end] uniformly in ln t, `log_step` apart or wider where
    count such steps would not reach `end` (no gaps)."""
    k = torch.arange(count + 1, device=start.device, dtype=start.dtype)
    first = start.clamp_min(1e-6)  # train.near may be 0
    span = torch.log(torch.maximum(end, first) / first)
    step = torch.clamp_min(span / max(count - 1, 1), log_step)
    edges = first[:, None] * torch.exp((k[None, :] - 1.0 + jitter[:, None]) * step[:, None])
    edges[:, -1] = end  # exp(ln(end / start)) can fall an ulp short of it
    return torch.minimum(torch.maximum(edges, start[:, None]), torch.maximum(end, start)[:, None])


# Disparity 1 - s is kept at float32's epsilon at least: a far plane some 1e7 scales away (or
# infinite) rounds s_far to 1, and t to infinity (NaN for an infinite far); the last edge then
# stops at start + scale / eps ~ 8e6 scales, far enough to stand for infinity in the shell.
_DISPARITY_EPS = torch.finfo(torch.float32).eps
_MAX_SPAN = 1e30  # keeps span / (span + scale) from inf / inf


def _disparity_edges(start, far: float, scale: float, count: int, jitter):
    """count + 1 intervals tiling [start, far], uniform in s = (t - start) / (t - start + scale)
    (for a far plane beyond float32's reach, up to ~8e6 scales: see _DISPARITY_EPS)."""
    k = torch.arange(count + 2, device=start.device, dtype=start.dtype)
    span = (far - start).clamp(0, _MAX_SPAN)
    s_far = span / (span + scale)
    s = ((k[None, :] - 1.0 + jitter[:, None]) / count).clamp(0.0, 1.0) * s_far[:, None]
    return start[:, None] + scale * s / (1.0 - s).clamp_min(_DISPARITY_EPS)


def _intervals(edges):
    return edges[:, :-1], edges[:, 1:]


@dataclass
class SamplerSettings:
    step: float  # scene-frame length of one step inside the box
    near: float = 0.05
    far: float = 200.0
    contraction: bool = True
    outer_samples: int = 48
    before_samples: int = 16
    # a perspective grid (srf/warp.py): steps inside the box uniform in ln t, this far apart, and
    # how many of them (the grid's depth span with a margin for oblique rays); 0: fixed steps
    log_step: float = 0.0
    log_steps: int = 0


def box_extent(box_min, box_max) -> tuple[float, float]:
    """(diagonal, half the largest side) of the box: the two lengths `generate_intervals` needs as
    numbers (the model passes them from its config, so a CUDA step never reads them back)."""
    size = torch.as_tensor(box_max, dtype=torch.float32, device="cpu") - torch.as_tensor(
        box_min, dtype=torch.float32, device="cpu")  # float32 as the model's box buffers
    return float(torch.linalg.norm(size)), float(size.amax()) * 0.5


def generate_intervals(origins, directions, box_min, box_max, settings: SamplerSettings, jitter=None,
                       extent: tuple[float, float] | None = None):
    """All candidate intervals (t_start, t_end) (R, K) before occupancy culling, sorted along t.

    `extent`: box_extent(box_min, box_max), when the caller has it as numbers."""
    n = origins.shape[0]
    jitter = torch.full((n,), 0.5, device=origins.device) if jitter is None else jitter
    t_enter, t_exit = ray_aabb(origins, directions, box_min, box_max)
    t0 = t_enter.clamp_min(settings.near)
    hit = t_exit > t0
    t1 = torch.where(hit, t_exit, t0)
    diagonal, scale = extent if extent is not None else box_extent(box_min.cpu(), box_max.cpu())
    if settings.log_step > 0:
        parts = [_intervals(_log_step_edges(t0, t1, settings.log_step, settings.log_steps, jitter))]
    else:
        count_in = int(math.ceil(diagonal / settings.step)) + 1
        parts = [_intervals(_fixed_step_edges(t0, t1, settings.step, count_in, jitter))]
    if settings.contraction:
        near = torch.full_like(t0, settings.near)
        before_end = torch.where(hit, t0, near)  # a ray that misses the box is all "beyond"
        if settings.before_samples > 0:
            parts.insert(0, _intervals(_uniform_edges(near, before_end, settings.before_samples, jitter)))
        after_start = torch.where(hit, t1, near)
        parts.append(_intervals(_disparity_edges(after_start, settings.far, scale, settings.outer_samples, jitter)))
    t_start = torch.cat([p[0] for p in parts], dim=1)
    t_end = torch.cat([p[1] for p in parts], dim=1)
    return t_start, t_end


def view_depth(points, camera_to_scene, intrinsics, width: int, height: int) -> torch.Tensor:
    """How deep each point (M, 3) lies inside the viewing pyramid of the camera that sees it best
    (camera_to_scene (N, 4, 4), OpenCV axes; intrinsics (N, 4) fx, fy, cx, cy): the largest, over
    the cameras, of the least signed distance to the pyramid's five planes (the image plane through
    the centre and the four planes through the centre and an image edge); negative outside all.
    A sphere of radius r meets a view when its centre's depth is >= -r, lies inside one when >= r."""
    best = torch.full((points.shape[0],), -torch.inf, dtype=points.dtype, device=points.device)
    for pose, (fx, fy, cx, cy) in zip(camera_to_scene.to(points), intrinsics.to(points).tolist()):
        x, y, z = ((points - pose[:3, 3]) @ pose[:3, :3]).unbind(-1)
        nearest = z
        # each side plane as (coordinate, tangent of the edge's angle from the axis)
        for coordinate, tangent in ((x, cx / fx), (-x, (width - cx) / fx), (y, cy / fy), (-y, (height - cy) / fy)):
            nearest = torch.minimum(nearest, (coordinate + tangent * z) / math.sqrt(1.0 + tangent * tangent))
        best = torch.maximum(best, nearest)
    return best


def spheres_in_view(centres, radii, camera_to_scene, intrinsics, width: int, height: int):
    """(meets, within) (M,) bool for spheres (centres (M, 3), radii (M,) or a float): the sphere
    meets at least one camera's viewing pyramid (conservative), and lies wholly inside one."""
    depth = view_depth(centres, camera_to_scene, intrinsics, width, height)
    radii = torch.as_tensor(radii, dtype=depth.dtype, device=depth.device)
    return depth >= -radii, depth >= radii


# the shell's seen-mark grid is this many times finer than its occupancy grid (the fox, its
# occupancy shell 32 cells: the held-out view before the space no camera saw was 11.3 dB unmarked,
# 16.0 with 128 mark cells and 20.8 with 256)
SEEN_REFINEMENT = 8


class OccupancyGrid(nn.Module):
    """Binary occupancy over the model box (level 0) and, with contraction, over the contracted
    cube [-2, 2]^3 (level 1, used only outside the box), updated from the field during training:

        occ <- max(decay * occ, sigma(x_jittered) * step)   for a subset of cells
        occupied = occ > min(mean(occ), threshold)

    (nerfacc's OccGridEstimator rule; distillation into the occupancy cache is the same operation.)

    Space that no training camera sees is empty for good (`mark_seen`, instant-ngp's "untrained
    density grid"): no training ray samples it, so nothing constrains its density there, and a
    held-out camera looking through it would see whatever the shared grid values left (on the fox,
    a dark wall in front of one held-out camera). Box cells carry the mark in `seen0` (a cell that
    any view reaches is seen). The shell's cells near the cameras are large, so its mark has a finer
    grid of its own (`seen1`), refined coarse to fine, where a cell on a view's boundary is seen
    when its centre lies in a view: the junk lies in such cells, just beside the training views (on
    the fox's `fast` weights, view 0012: 12.9 dB keeping every cell whose bounding sphere meets a
    view, 18.1 keeping those with a corner in a view (3x the time), 21.3 by the centre; the other
    views the same to 0.1 dB). `seen1` applies in eval mode (rendering, queries): training rays lie
    in the training views and never need it, so none of their samples is dropped at a view's edge.
    """

    def __init__(self, box_min, box_max, resolution, contraction: bool, outer_resolution: int = 32,
                 step: float = 0.01, threshold: float = 0.01, decay: float = 0.95,
                 warp: PerspectiveWarp | None = None, log_step: float = 0.0):
        super().__init__()
        # box_min/box_max: the grid's range (in the warp's coordinates when there is a warp)
        self.register_buffer("box_min", torch.as_tensor(box_min, dtype=torch.float32).clone())
        self.register_buffer("box_max", torch.as_tensor(box_max, dtype=torch.float32).clone())
        self.warp = warp
        self.log_step = float(log_step)
        self.resolution = tuple(int(r) for r in resolution)
        self.contraction = bool(contraction)
        self.outer_resolution = int(outer_resolution) if contraction else 1
        self.step = float(step)
        self.threshold = float(threshold)
        self.decay = float(decay)
        n0 = math.prod(self.resolution)
        n1 = self.outer_resolution**3 if self.contraction else 1
        self.register_buffer("occ0", torch.zeros(n0))
        self.register_buffer("occ1", torch.zeros(n1))
        self.register_buffer("binary0", torch.ones(n0, dtype=torch.bool))
        self.register_buffer("binary1", torch.ones(n1, dtype=torch.bool))
        self.seen_resolution = SEEN_REFINEMENT * self.outer_resolution if self.contraction else 1
        self.register_buffer("seen0", torch.ones(n0, dtype=torch.bool))
        self.register_buffer("seen1", torch.ones(self.seen_resolution**3, dtype=torch.bool))
        # on the grid's device: a tensor built from a list each call would be a host copy (which a
        # CUDA graph cannot replay)
        self.register_buffer("_res0", torch.tensor(self.resolution), persistent=False)
        self.static_shapes = False  # SRFModel.use_static_shapes: every lookup the same size (CUDA graphs)

    def _u(self, x):
        return grid_coordinates(x, self.box_min, self.box_max, self.warp)

    def _x(self, u):
        return grid_points(u, self.box_min, self.box_max, self.warp)

    def _step_length(self, x):
        """The sampler's step at scene-frame points: fixed, or in ln t with a perspective grid."""
        return self.step if self.warp is None else self.warp.depth(x) * self.log_step

    def _index0(self, u):
        res = self._res0
        cell = ((u + 1.0) * 0.5 * res).floor().long()
        cell = torch.minimum(cell.clamp_min(0), res - 1)
        return (cell[:, 0] * res[1] + cell[:, 1]) * res[2] + cell[:, 2]

    def _index1(self, v, g: int | None = None):
        g = g or self.outer_resolution
        cell = ((v + 2.0) * 0.25 * g).floor().long().clamp(0, g - 1)
        return (cell[:, 0] * g + cell[:, 1]) * g + cell[:, 2]

    @torch.no_grad()
    def occupied(self, x: torch.Tensor) -> torch.Tensor:
        """Whether scene-frame points (M, 3) lie in occupied cells (outside the field: False)."""
        u = self._u(x)
        if self.contraction and not self.static_shapes:
            return self._occupied_packed(u)
        inside = (u.abs() <= 1.0).all(dim=-1)
        result = self.binary0[self._index0(u)] & inside  # binary0 holds seen0 already
        if self.contraction:
            # both levels looked up for every point, no index of the outside ones: no shape
            # depends on the data (a CUDA graph replays it), at the cost of the shell lookups
            v = contract(u)
            outer = self.binary1[self._index1(v)]
            if not self.training:
                outer = outer & self.seen1[self._index1(v, self.seen_resolution)]
            return torch.where(inside, result, outer)
        return result

    def _occupied_packed(self, u: torch.Tensor) -> torch.Tensor:
        """`occupied` for grid coordinates u (M, 3) with a shell: each point looked up at the one
        level it lies in (the box's index is not computed for the shell's points, most of a batch)."""
        inside = (u.abs() <= 1.0).all(dim=-1)
        result = torch.empty(u.shape[0], dtype=torch.bool, device=u.device)
        box = inside.nonzero().squeeze(1)
        result[box] = self.binary0[self._index0(u[box])]  # binary0 holds seen0 already
        shell = (~inside).nonzero().squeeze(1)
        v = contract(u[shell])
        outer = self.binary1[self._index1(v)]
        if not self.training:
            outer &= self.seen1[self._index1(v, self.seen_resolution)]
        result[shell] = outer
        return result

    @torch.no_grad()
    def seen(self, x: torch.Tensor) -> torch.Tensor:
        """Whether scene-frame points (M, 3) lie where a training camera saw (see `mark_seen`)."""
        u = self._u(x)
        inside = (u.abs() <= 1.0).all(dim=-1)
        result = self.seen0[self._index0(u)]
        if self.contraction:
            outside = (~inside).nonzero().squeeze(1)
            result[outside] = self.seen1[self._index1(contract(u[outside]), self.seen_resolution)]
        return result

    @torch.no_grad()
    def mark_seen(self, camera_to_scene, intrinsics, width: int, height: int, chunk: int = 1 << 18) -> dict:
        """Mark the cells that no camera (the training views: camera_to_scene (N, 4, 4), intrinsics
        (N, 4)) sees as empty for good. Returns the fractions of box and shell cells seen."""
        device = self.occ0.device
        res = torch.tensor(self.resolution, device=device, dtype=torch.float32)
        radius0 = 0.5 * float(((self.box_max - self.box_min) / res).norm())
        for start in range(0, self.seen0.numel(), chunk):
            cells = torch.arange(start, min(start + chunk, self.seen0.numel()), device=device)
            centres = self._cell_points(0, cells)
            radius = radius0 if self.warp is None else self._cell_radii(cells, centres)
            self.seen0[cells] = spheres_in_view(centres, radius, camera_to_scene, intrinsics, width, height)[0]
        self.occ0.masked_fill_(~self.seen0, 0.0)
        self.binary0 &= self.seen0
        fractions = {"box": float(self.seen0.float().mean())}
        if self.contraction:
            fractions["shell"] = self._mark_shell_seen(camera_to_scene, intrinsics, width, height)
        return fractions

    def _mark_shell_seen(self, camera_to_scene, intrinsics, width: int, height: int) -> float:
        """seen1, coarse to fine: a cell wholly inside a camera's view is seen, one outside every
        view is not, and only the cells on a view's boundary are split in eight, down to the
        seen-mark resolution (the whole fine grid tested cell by cell took 14 s on the fox).
        Returns the fraction of the shell's cells seen."""
        device = self.seen1.device
        final = self.seen_resolution
        corners = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], device=device)
        g = self.outer_resolution
        ijk = torch.stack(torch.meshgrid(*[torch.arange(g, device=device)] * 3, indexing="ij"), -1).reshape(-1, 3)
        seen = torch.zeros((final,) * 3, dtype=torch.bool, device=device)
        while ijk.shape[0]:
            centres = self._x(uncontract((ijk + 0.5) / g * 4.0 - 2.0))
            # the bounding sphere through the cell's corners, a little wider as the cell is curved
            v = ((ijk[:, None] + corners) / g * 4.0 - 2.0).clamp(-2.0 + 1e-4, 2.0 - 1e-4)
            radii = 1.1 * (self._x(uncontract(v.reshape(-1, 3))).reshape(-1, 8, 3)
                           - centres[:, None]).norm(dim=-1).amax(dim=1)
            depth = view_depth(centres, camera_to_scene, intrinsics, width, height)
            meets, within = depth >= -radii, depth >= radii
            if g == final:  # a cell on a view's boundary goes with its centre (see the class)
                meets = depth >= 0.0
            settled = ijk[within] if g < final else ijk[meets]
            block = final // g
            for offset in torch.cartesian_prod(*[torch.arange(block, device=device)] * 3).reshape(-1, 3):
                fine = settled * block + offset
                seen[fine[:, 0], fine[:, 1], fine[:, 2]] = True
            if g == final:
                break
            ijk = (ijk[meets & ~within][:, None] * 2 + corners).reshape(-1, 3)
            g *= 2
        in_box = self._box_cells(final, device)
        self.seen1.copy_(seen.reshape(-1) | in_box)  # cells inside the box are level 0's
        return float(seen.reshape(-1)[~in_box].float().mean())

    @staticmethod
    def _box_cells(g: int, device) -> torch.Tensor:
        """(g^3,) bool: the cells of a g^3 grid over the contracted cube whose centre lies in the box."""
        centre = (torch.arange(g, device=device) + 0.5) / g * 4.0 - 2.0
        inner = centre.abs() < 1.0
        return (inner[:, None, None] & inner[None, :, None] & inner[None, None, :]).reshape(-1)

    def _cell_radii(self, cells: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
        """Scene-frame radius (M,) of the sphere round each level-0 cell's corners (a perspective
        grid's cells grow with depth)."""
        rx, ry, rz = self.resolution
        ijk = torch.stack([cells // (ry * rz), (cells // rz) % ry, cells % rz], dim=-1)
        res = torch.tensor(self.resolution, device=cells.device, dtype=torch.float32)
        corners = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], device=cells.device)
        u = ((ijk[:, None] + corners) / res * 2.0 - 1.0).reshape(-1, 3)
        return (self._x(u).reshape(-1, 8, 3) - centres[:, None]).norm(dim=-1).amax(dim=1)

    def _cell_points(self, level: int, cells: torch.Tensor, generator=None) -> torch.Tensor:
        """A jittered scene-frame point inside each of the given cells (without a generator: the
        centres)."""
        if generator is None:
            jitter = torch.full((cells.shape[0], 3), 0.5, device=cells.device)
        else:
            jitter = rand((cells.shape[0], 3), generator, cells.device)
        if level == 0:
            rx, ry, rz = self.resolution
            ijk = torch.stack([cells // (ry * rz), (cells // rz) % ry, cells % rz], dim=-1)
            res = torch.tensor(self.resolution, device=cells.device, dtype=torch.float32)
            return self._x((ijk + jitter) / res * 2.0 - 1.0)
        g = self.outer_resolution
        ijk = torch.stack([cells // (g * g), (cells // g) % g, cells % g], dim=-1)
        v = ((ijk + jitter) / g * 4.0 - 2.0).clamp(-2.0 + 1e-4, 2.0 - 1e-4)
        return self._x(uncontract(v))

    @torch.no_grad()
    def update(self, density_fn, generator, all_cells: bool, chunk: int = 1 << 18) -> None:
        """One EMA update: every cell (warm-up) or a random quarter plus a quarter of occupied cells."""
        levels = [(0, self.occ0, self.binary0)]
        if self.contraction:
            levels.append((1, self.occ1, self.binary1))
        for level, occ, binary in levels:
            n = occ.numel()
            if all_cells:
                cells = torch.arange(n, device=occ.device)
            else:
                random_cells = randint(0, n, max(n // 4, 1), generator, occ.device)
                occupied_cells = binary.nonzero().squeeze(1)
                if occupied_cells.numel() > n // 4:
                    pick = randint(0, occupied_cells.numel(), n // 4, generator, occ.device)
                    occupied_cells = occupied_cells[pick]
                # unique: index_put_ with repeated indices would keep an arbitrary one of them
                cells = torch.unique(torch.cat([random_cells, occupied_cells]))
            values = torch.empty(cells.shape[0], device=occ.device)
            for start in range(0, cells.shape[0], chunk):
                points = self._cell_points(level, cells[start:start + chunk], generator)
                values[start:start + chunk] = density_fn(points).float() * self._step_length(points)
            current = occ[cells] * self.decay
            occ.index_put_((cells,), torch.maximum(current, values))
            if level == 0:
                occ.masked_fill_(~self.seen0, 0.0)
            if level == 1:  # cells inside the box belong to level 0
                occ.masked_fill_(self._box_cells(self.outer_resolution, occ.device), 0.0)
            threshold = occ.mean().clamp_max(self.threshold)  # a 0-d tensor: no host sync on CUDA
            binary.copy_(occ > threshold)

    def occupied_fraction(self) -> float:
        return float(self.binary0.float().mean())

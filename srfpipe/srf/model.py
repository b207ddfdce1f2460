"""The SRF model: field + occupancy grid + sampler, rendering batches of rays (Eq. 1 and Eq. 3).

`build_model_config` turns the scene geometry and the `train` options into a JSON-able model
config (stored in srf.zarr); `SRFModel(config)` rebuilds the same module anywhere.
"""

from __future__ import annotations

import logging
import math

import numpy as np
import torch
import torch.nn as nn

from srfpipe.memory import check_allocation
from srfpipe.srf import rendering
from srfpipe.srf.field import SemanticField, grid_resolution
from srfpipe.srf.sampling import (OccupancyGrid, PackedSamples, RaySamples, SamplerSettings, box_extent,
                                  generate_intervals)
from srfpipe.srf.warp import build_warp, looks_one_way, perspective_fits, perspective_grid

# A sample "carries weight" above FLOATER_WEIGHT (the fog criterion of the any-capture issue); it
# is a floater when it lies more than FLOATER_CELLS grid cells (plus its own length) from the
# ray's median-weight depth, i.e. not on the surface the ray sees.
FLOATER_WEIGHT = 0.03
FLOATER_CELLS = 4.0
# Samples along a ray's path through the box at most: every ray of a batch holds this many
# candidate intervals before the occupancy grid culls them (8192 rays x 2048 = 16 M intervals in
# an evaluation chunk). The default step (one cell) gives at most 256 * sqrt(3) = 444.
MAX_STEPS_ACROSS_BOX = 2048
# Bytes one candidate interval of a ray costs while a training batch is sampled and culled
# (t_start and t_end, the keep mask, the culling points and indices, the kept samples' gather):
# an upper estimate for the check before a step's batch is allocated
CANDIDATE_BYTES = 64
# Initial opacity per step of the density grid when the bounds are trusted (config, ground truth);
# the trainer picks 0.001 for estimated bounds (srf/trainer.py, resolve_data_defaults)
TRUSTED_INITIAL_OPACITY = 0.01
# the occupancy grid's running density: new = max(decay * old, measured) at each update
OCCUPANCY_DECAY = 0.95

log = logging.getLogger(__name__)


def scene_scale(scene_from_world) -> float:
    """The uniform scale s of the similarity x_scene = s R x_world + t."""
    return float(np.cbrt(np.linalg.det(np.asarray(scene_from_world, dtype=np.float64)[:3, :3])))


def default_encoding(device) -> str:
    """The dense grid on every device.

    It measures best on both: on the CPU (see encodings.py), and on an H100 too, where the orchard
    reached 28.50 dB, object pixels 25.46, mIoU 0.80 in 90 s with the dense grid against 26.63 /
    22.36 / 0.70 with the hash grid at the same step rate (issue "srfpipe on a GPU"). The hash grid
    stays available (`train.encoding: hash`), as the paper's preset uses it.
    """
    return "dense"


TRAINING_COPIES = 4  # a trained table lives as weights, gradients and Adam's two moments


def grid_bytes(inner: dict, outer: dict | None, density_grid: bool) -> float:
    """Bytes of the float32 tables an encoding config allocates (dense levels shrink by 2 per axis)."""
    total = 0.0
    for grid in (inner, outer):
        if not grid:
            continue
        if grid["type"] == "hash":
            total += grid["levels"] * 2 ** grid["log2_table_size"] * grid["features_per_level"] * 4
            continue
        cells = sum(float(np.prod([max(int(r) >> level, 2) for r in grid["resolution"]]))
                    for level in range(int(grid.get("levels", 1))))
        total += cells * (grid["features"] + int(density_grid)) * 4
        total += int(grid.get("fine_levels", 0)) * 2 ** int(grid.get("log2_table_size", 22)) * grid["features"] * 4
    return total


# What the model uses for the train keys that have no schema default (the schema says so)
HASH_LEVELS = 16
HASH_LOG2_TABLE_SIZE = 19
BASE_CELLS = 96  # cells across the box's largest side when neither detail_size nor default_cells is set


def default_features(grid_levels: int | None) -> int:
    """Dense-grid features per cell when `train.features` is null: 16 for one level, 8 for several."""
    return 8 if int(grid_levels or 1) > 1 else 16


def scene_box(bounds_world, scene_from_world, padding: float) -> tuple[np.ndarray, np.ndarray]:
    """(box_min, box_max) in the scene frame: the world bounds' corners carried into it, and the
    box round them grown by `padding` of its extent on each side (train.box_padding)."""
    bounds_world = np.asarray(bounds_world, dtype=np.float64)
    corners = np.array(np.meshgrid(*bounds_world.T)).reshape(3, -1).T
    corners_scene = corners @ np.asarray(scene_from_world)[:3, :3].T + np.asarray(scene_from_world)[:3, 3]
    box_min, box_max = corners_scene.min(0), corners_scene.max(0)
    pad = padding * (box_max - box_min)
    return box_min - pad, box_max + pad


def build_model_config(options, bounds_world, scene_from_world, classes: list[str],
                       num_images: int, device="cpu", cameras=None) -> dict:
    """Model config from the `train` settings and the scene geometry (bounds, normalization).

    `options`: TrainSettings, or a dict of train keys (validated, the schema's defaults filled in),
    so a caller that skips the workflow (a notebook, a benchmark) builds the workflow's model.
    `cameras`: (camera_to_scene (N, 4, 4), intrinsics (N, 4), width, height) of the training views,
    which `train.grid_frame: perspective` lays its grid out from (srf/warp.py); `auto` without
    them is the box.
    """
    from srfpipe.settings import TrainSettings

    s = TrainSettings.from_options(options)
    bounds_world = np.asarray(bounds_world, dtype=np.float64)
    if bounds_world.shape != (2, 3) or not np.all(bounds_world[1] > bounds_world[0]):
        raise ValueError(f"scene bounds must be [[min xyz], [max xyz]] with min < max, got {bounds_world.tolist()}")
    scale = scene_scale(scene_from_world)
    box_min, box_max = scene_box(bounds_world, scene_from_world, float(s.box_padding))
    extent = box_max - box_min
    cap = int(s.max_resolution)
    perspective = None
    frame = s.grid_frame
    if frame == "auto":  # the trainer decides it from every view first (resolve_data_defaults)
        one_way = cameras is not None and looks_one_way(np.asarray(cameras[0]))
        frame = "perspective" if one_way and perspective_fits(*cameras, box_min, box_max) else "box"
    if frame == "perspective":
        if cameras is None:
            raise ValueError("train.grid_frame perspective lays the grid out from the training cameras; "
                             "build_model_config was given none")
        perspective = perspective_grid(*cameras, box_min, box_max, int(s.default_cells or BASE_CELLS), cap)
        resolution = perspective["resolution"]
        box_min, box_max = perspective["box_min"], perspective["box_max"]
        extent = box_max - box_min
        # the cell's width where the grid's points lie (floater tolerance, initial density)
        detail_scene = perspective["cell_across"] * perspective["median_depth"]
        log.info("perspective grid: %s points, %.2f px per cell across, cells %.3g world units wide at the "
                 "median depth", " x ".join(map(str, resolution)), perspective["pixels_per_cell"],
                 detail_scene / scale)
    elif s.detail_size is None:  # no unit known: a fixed fraction of the scene's largest extent
        detail_scene = float(extent.max()) / float(s.default_cells or BASE_CELLS)
    else:
        detail_scene = float(s.detail_size) * scale
    if perspective is None:
        resolution = [grid_resolution(float(e), detail_scene, cap) for e in extent]
        finest = float(extent.max()) / (max(resolution) - 1)  # the cell the (capped) grid really has
        if detail_scene < finest * (1 - 1e-9):
            log.warning("grid cells of %.3g world units (train.detail_size or default_cells) are finer than "
                        "max_resolution %d points can resolve over the box: cells and steps of %.3g instead",
                        detail_scene / scale, cap, finest / scale)
            detail_scene = finest
    encoding = s.encoding
    if encoding == "auto":
        encoding = default_encoding(device)
        log.info("encoding %s (auto on %s: the dense grid measured best on the CPU and on CUDA)",
                 encoding, torch.device(device).type)
    contraction = bool(s.contraction)
    features = int(s.features or default_features(s.grid_levels))
    if encoding == "dense":
        levels = int(s.grid_levels or 1)
        inner = {"type": "dense", "resolution": resolution, "features": features}
        g = int(s.outer_resolution)
        outer = {"type": "dense", "resolution": [g, g, g], "features": features} if contraction else None
        fine_levels = int(s.fine_levels or 0)
        if levels > 1 or fine_levels:
            inner["levels"] = levels
            if outer:
                outer["levels"] = levels
        if fine_levels:
            for grid in (inner, outer):
                if grid:
                    grid.update(fine_levels=fine_levels, log2_table_size=int(s.fine_log2_table_size))
    elif encoding == "hash":
        finest = max(resolution) * (2 if contraction else 1)
        inner = {"type": "hash", "levels": int(s.hash_levels or HASH_LEVELS), "features_per_level": 2,
                 "log2_table_size": int(s.hash_log2_table_size or HASH_LOG2_TABLE_SIZE),
                 "base_resolution": 16, "max_resolution": int(finest)}
        outer = None
    else:
        raise ValueError(f"train.encoding must be auto, dense or hash, got {encoding!r}")
    density_grid = bool(encoding == "dense" if s.density_grid is None else s.density_grid)
    check_allocation(TRAINING_COPIES * grid_bytes(inner, outer, density_grid),
                     "train.detail_size" if s.detail_size is not None else "train.max_resolution",
                     f"a {' x '.join(map(str, resolution))} grid of {features} features (weights, gradients and "
                     f"Adam's two moments)", device)
    step = detail_scene * float(s.step_ratio)
    diagonal = float(np.linalg.norm(extent))
    if perspective is None and diagonal / step > MAX_STEPS_ACROSS_BOX:
        finest_step = diagonal / MAX_STEPS_ACROSS_BOX
        log.warning("train.step_ratio %g gives %.3g steps across the box (memory grows with it); "
                    "step ratio %.3g instead (%d steps)", float(s.step_ratio),
                    diagonal / step, finest_step / detail_scene, MAX_STEPS_ACROSS_BOX)
        step = finest_step
    log_step, log_steps = 0.0, 0
    if perspective is not None:
        # steps uniform in ln t, one depth cell times step_ratio; the margin covers rays that
        # cross the grid's depth range obliquely (generate_intervals widens the steps of any
        # longer chord rather than leave a gap)
        log_step = perspective["log_step"] * float(s.step_ratio)
        depth_span = float(perspective["grid_max"][2] - perspective["grid_min"][2])
        log_steps = min(int(math.ceil(1.25 * depth_span / log_step)) + 1, MAX_STEPS_ACROSS_BOX)
    inside = log_steps or int(math.ceil(diagonal / step)) + 1
    candidates = inside + (s.before_samples + s.outer_samples if contraction else 0)
    check_allocation(s.rays_per_batch * candidates * CANDIDATE_BYTES, "train.rays_per_batch",
                     f"a batch of {s.rays_per_batch} rays of {candidates} candidate intervals each", device)
    # initial opacity per step of the density grid: faintly foggy, so every cell gets gradients
    # (null initial_opacity: the trainer resolves it from the bounds; a bare model config uses the
    # trusted-bounds value)
    initial_opacity = float(s.initial_opacity or TRUSTED_INITIAL_OPACITY)
    density_bias = math.log(initial_opacity / step) if density_grid else -1.0
    occupancy_resolution = [max(int(math.ceil((r - 1) / 2)), 1) for r in resolution]
    grid_frame = {} if perspective is None else {
        "warp": perspective["warp"], "grid_min": perspective["grid_min"], "grid_max": perspective["grid_max"]}
    return {
        "box_min": box_min.tolist(), "box_max": box_max.tolist(), **grid_frame,
        "contraction": contraction, "inner": inner, "outer": outer,
        "hidden": int(s.hidden), "geo_features": int(s.geo_features),
        "sh_degree": int(s.sh_degree), "background_sh_degree": int(s.background_sh_degree or s.sh_degree),
        "num_classes": len(classes),
        "appearance_dim": int(s.appearance_dim or 0), "num_images": int(num_images),
        "appearance_model": s.appearance_model,
        "novel_view_appearances": int(s.novel_view_appearances),
        "density_bias": density_bias, "density_grid": density_grid,
        "color_layers": int(s.color_layers),
        "semantic_octaves": int(s.semantic_octaves),
        "color_threshold": float(s.color_threshold),
        "detail_scene": detail_scene,
        "sampler": {
            "step": step,
            "near": float(s.near), "far": float(s.far),
            "contraction": contraction, "outer_samples": int(s.outer_samples),
            "before_samples": int(s.before_samples),
            "log_step": log_step, "log_steps": log_steps,
        },
        "occupancy": {
            "resolution": occupancy_resolution, "outer_resolution": int(s.occupancy_outer_resolution),
            "threshold": float(s.occupancy_threshold), "decay": OCCUPANCY_DECAY,
        },
    }


class SRFModel(nn.Module):
    """Renders rays given in the scene frame; returns rgb, per-class logits, depth, accumulation."""

    def __init__(self, config: dict, device="cpu"):
        super().__init__()
        self.config = config
        self.field = SemanticField(config, device)
        self.settings = SamplerSettings(**config["sampler"])
        occ = config["occupancy"]
        self.occupancy = OccupancyGrid(
            config.get("grid_min", config["box_min"]), config.get("grid_max", config["box_max"]), occ["resolution"],
            config["contraction"], occ["outer_resolution"], step=self.settings.step, threshold=occ["threshold"],
            decay=occ["decay"], warp=build_warp(config.get("warp")), log_step=self.settings.log_step,
        )
        self.color_threshold = float(config["color_threshold"])
        self.extent = box_extent(config["box_min"], config["box_max"])
        self.capacities = None  # set by use_static_shapes

    def use_static_shapes(self, capacities: tuple[int, int] | None) -> None:
        """Training steps whose every tensor has a size fixed by the batch, not by the data, so a
        CUDA graph can replay them (srf/graphed.py). `capacities` = (kept, shaded): the field's
        density is read at up to `kept` of the candidate intervals the occupancy grid keeps, the
        colour and semantic heads run at up to `shaded` significant samples, each padded to that
        size (the outputs `samples` and `shaded` count how many there were; beyond a capacity,
        the last ones count as empty, or go unshaded; the hash grid shades every kept sample, so
        `shaded` is unused there). None: back to packed, data-sized steps."""
        static = capacities is not None
        self.capacities = tuple(int(c) for c in capacities) if static else None
        self.field.static_shapes = static
        self.occupancy.static_shapes = static

    def sample(self, origins, directions, jitter=None) -> PackedSamples:
        """Candidate intervals culled by the occupancy grid, packed ray after ray."""
        t_start, t_end = generate_intervals(
            origins, directions, self.field.box_min, self.field.box_max, self.settings, jitter, self.extent
        )
        keep = t_end > t_start
        flat = keep.view(-1).nonzero().squeeze(1)
        rays = torch.div(flat, keep.shape[1], rounding_mode="floor")
        t_start, t_end = t_start.reshape(-1)[flat], t_end.reshape(-1)[flat]
        points = origins[rays] + directions[rays] * (0.5 * (t_start + t_end))[:, None]
        occupied = self.occupancy.occupied(points).nonzero().squeeze(1)
        return PackedSamples(t_start[occupied], t_end[occupied], points[occupied],
                             rendering.Segments.of(rays[occupied], keep.shape[0]), keep.sum(dim=1))

    def forward(self, origins, directions, image_index=None, jitter=None, appearances=None) -> dict:
        """Render rays (R, 3) in the scene frame. Returns rgb (R, 3), logits (R, C), depth (R,)
        (scene-frame distance along the ray), accumulation (R,), samples (number evaluated).
        `image_index` (R,): each ray's training image, whose appearance its colour takes.
        `appearances`: in place of it, pairs (image_index, weight) whose colours are blended with
        those weights (summing to 1); the rays are sampled and their density and semantics read
        once, as the appearance moves the colour alone."""
        if self.training and self.capacities is not None:
            return self._forward_static(origins, directions, image_index, jitter)
        field = self.field
        samples = self.sample(origins, directions, jitter)
        segments = samples.segments
        if field.density_grid:
            sigma = field.sigma(samples.points)
        else:
            sigma, h = field.density(samples.points)
        weights = rendering.render_weights(sigma, samples.delta, segments)
        if field.density_grid:
            # colour and semantics only where a sample can matter: w_k > threshold (occluded
            # samples and near-empty space are skipped; their contribution is below the threshold)
            shade = (weights.detach() > self.color_threshold).nonzero().squeeze(1)
            shaded, shade_weights, shade_points = segments.subset(shade), weights[shade], samples.points[shade]
            h = field.latent(shade_points)
        else:
            shaded, shade_weights, shade_points = segments, weights, samples.points
        colours = [(field.color(h, directions, index, ray_index=shaded.ray), index, weight)
                   for index, weight in (appearances if appearances is not None else [(image_index, 1.0)])]
        logits = field.semantics(h, shade_points)
        out = self._composite(directions, samples.t_start, samples.t_end, weights, segments,
                              shade_weights, shaded, colours, logits)
        out["samples"] = int(segments.ray.numel())
        out["shaded"] = int(shaded.ray.numel())
        if not self.training:
            # the floater count needs each ray's samples in order: the padded layout
            t_mid = segments.pad(0.5 * (samples.t_start + samples.t_end))
            tolerance = FLOATER_CELLS * self.config["detail_scene"] + segments.pad(samples.delta)
            out["significant"], out["floaters"] = rendering.floater_counts(
                segments.pad(weights), t_mid, tolerance, FLOATER_WEIGHT)
            # empty space skipped: the intervals the sampler placed on each ray, and those the
            # occupancy grid kept (the field is evaluated at these only)
            out["candidate_samples"] = samples.candidates.float()
            out["kept_samples"] = segments.counts().float()
        return out

    def _composite(self, directions, t_start, t_end, weights, segments, shade_weights, shaded, colours: list,
                   logits) -> dict:
        """Eq. 1 and Eq. 3: rgb, logits, depth, accumulation (and in training the distortion loss).
        The samples (t_start, t_end, weights) are padded (segments None) or packed along
        `segments`; colours and logits are given at the shaded samples (`shade_weights` along
        `shaded`; padded, all of them). `colours`: (rgb, image_index, weight) per appearance;
        Eq. 1 is linear in the samples' colours, so the blend of the rendered colours is the
        render of the blended ones."""
        field = self.field
        n, c = directions.shape[0], logits.shape[-1]
        acc = rendering.accumulation(weights, segments)
        background = field.background(directions)
        rendered = [(field.image_colour(rendering.composite_background(
            rendering.accumulate(shade_weights, rgb, shaded), acc, background), image_index), weight)
            for rgb, image_index, weight in colours]
        color = rendered[0][0] if len(rendered) == 1 else sum(rgb * weight for rgb, weight in rendered)
        # Eq. 3 with detached weights: the semantic loss reaches only F_s (and background logits)
        sem_logits = rendering.composite_background(
            rendering.accumulate(shade_weights.detach(), logits, shaded), acc.detach(),
            field.background_logits.expand(n, c),
        )
        out = {
            "rgb": color,
            "logits": sem_logits,
            "depth": rendering.expected_depth(weights, 0.5 * (t_start + t_end), segments=segments),
            "accumulation": acc,
        }
        if self.training:
            # distances normalized as s = t / (t + D), D the box's largest side: linear near the
            # box, bounded in the contracted shell, so far samples cannot dominate the loss
            d = float(max(b - a for a, b in zip(self.config["box_min"], self.config["box_max"])))
            out["distortion"] = rendering.distortion(
                weights, t_start / (t_start + d), t_end / (t_end + d), segments).mean()
        return out

    def _forward_static(self, origins, directions, image_index, jitter) -> dict:
        """`forward` in training with sizes fixed by the batch (see use_static_shapes): the same
        rendering, as culled intervals carry sigma = 0 and length 0 in place of being removed, and
        a sample below the colour threshold adds nothing either way."""
        field = self.field
        t_start, t_end = generate_intervals(
            origins, directions, field.box_min, field.box_max, self.settings, jitter, self.extent)
        n, k = t_start.shape
        end = n * k
        kept_capacity, shade_capacity = self.capacities
        points = (origins[:, None, :] + directions[:, None, :] * (0.5 * (t_start + t_end))[..., None]).reshape(-1, 3)
        mask = (t_end > t_start) & self.occupancy.occupied(points).view(n, k)
        samples = RaySamples(t_start, t_end, mask)
        # the kept intervals first, padded to the capacity with an index one past the end, whose
        # row is dropped below (a scatter needs no count read back from the device)
        kept = torch.nonzero_static(mask.reshape(-1), size=kept_capacity, fill_value=end).squeeze(1)
        kept_rows = kept.clamp_max(end - 1)
        kept_points = points[kept_rows]
        if field.density_grid:
            sigma = field.sigma(kept_points).float()
        else:  # the hash grid's MLP gives sigma and h together: every kept sample is shaded
            sigma, h = field.density(kept_points)
            sigma = sigma.float()
        sigma = torch.zeros(end + 1, device=sigma.device).index_copy(0, kept, sigma)[:end].view(n, k)
        weights = rendering.render_weights(sigma, samples.delta)
        if field.density_grid:
            significant = ((weights.detach() > self.color_threshold) & mask).reshape(-1)
            index = torch.nonzero_static(significant, size=shade_capacity, fill_value=end).squeeze(1)
            gather = index.clamp_max(end - 1)
            shade_points = points[gather]
            h = field.latent(shade_points)
        else:
            significant, index, gather, shade_points = mask.reshape(-1), kept, kept_rows, kept_points
        rgb = field.color(h, directions, image_index, ray_index=torch.div(gather, k, rounding_mode="floor"))
        logits = field.semantics(h, shade_points)
        c = logits.shape[-1]
        rgb_pad = torch.zeros(end + 1, 3, device=rgb.device).index_copy(0, index, rgb.float())[:end].view(n, k, 3)
        sem_pad = torch.zeros(end + 1, c, device=rgb.device).index_copy(0, index, logits.float())[:end].view(n, k, c)
        out = self._composite(directions, t_start, t_end, weights, None, weights, None,
                              [(rgb_pad, image_index, 1.0)], sem_pad)
        out["samples"] = mask.sum()
        out["shaded"] = significant.sum()
        return out

    @torch.no_grad()
    def render_rays_chunked(self, origins, directions, chunk: int = 8192, exclude_view: int | None = None,
                            appearance_view: int | None = None) -> dict:
        """Inference over many rays in chunks; returns CPU float32 tensors. `exclude_view`: a
        training image whose appearance embedding the rays may not borrow; `appearance_view`: a
        training image whose own appearance they take (a training view as it trained)."""
        outputs: dict[str, list] = {"rgb": [], "logits": [], "depth": [], "accumulation": [],
                                    "significant": [], "floaters": [], "candidate_samples": [],
                                    "kept_samples": []}
        # a novel view (one camera: the rays share an origin) takes the appearance of the training
        # images taken nearest to it (on the fox the nearest beat the mean embedding by 0.55 dB).
        # Its own appearance was never recorded, so with several it is rendered as the weighted
        # mean of what each of their appearances makes of it: what each image's embedding fitted
        # of that image alone (blur, a pose a little off) is then shared out, not copied whole.
        nearest = ([(int(appearance_view), 1.0)] if appearance_view is not None and self.field.appearance is not None
                   else self.field.nearest_training_views(origins.mean(dim=0), directions.mean(dim=0), exclude_view,
                                                          self.field.novel_view_appearances)) or [(None, 1.0)]
        for start in range(0, origins.shape[0], chunk):
            rays = min(chunk, origins.shape[0] - start)
            appearances = [(None if image is None else torch.full((rays,), image, dtype=torch.long,
                                                                  device=origins.device), weight)
                           for image, weight in nearest]
            out = self(origins[start:start + chunk], directions[start:start + chunk], appearances=appearances)
            for key in outputs:
                if key in out:  # the sample counts exist in eval mode only
                    outputs[key].append(out[key].float().cpu())
        return {key: torch.cat(v) for key, v in outputs.items() if v}

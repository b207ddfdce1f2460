"""Train the semantic radiance field on posed images and multi-hot labels -> srf.zarr.

Loss L = L_photo + lambda L_sem (paper Eq. 4-5), Adam (lr 1e-2, exponential decay), a random
batch of rays from the training views per step (every `evaluate.holdout_every`-th view is held
out). Checkpoints (`step-000001000.pt`, plain tensor dicts read with weights_only=True) are
written every `checkpoint_every` steps beside the output, and a re-run resumes from the latest
one whose fingerprint (options, model config, inputs) matches; `snapshot_seconds` adds the model's
weights alone (`snapshot-000000420.pt`) at the first step past each of those training seconds,
kept after success (quality against time: benchmarks/peers.py); ray sampling draws from a
generator seeded by (seed, step), so a resumed run ends with the same weights on the CPU
(bit-identical with one thread; with several, some CPU kernels order their float sums
differently from run to run, resumed or not).
With `time_budget` > 0 the run also stops when that many training seconds have passed, and the
learning-rate decay follows whichever of steps or seconds is further along; such a run depends
on the machine's speed, so the resume guarantee holds only for runs that finish by iterations.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from srfpipe import cameras
from srfpipe.settings import TrainSettings
from srfpipe.srf.hooks import (Checkpoints, DivergenceWatch, HeldoutEvaluation, MetricsLog, Snapshots, TimeBudget,
                               TrainingProgress, checkpoints_of)
from srfpipe.srf.model import BASE_CELLS, TRUSTED_INITIAL_OPACITY, default_features, scene_box
from srfpipe.srf.warp import looks_one_way, perspective_fits

log = logging.getLogger("srfpipe.train")


def add_arguments(parser) -> None:
    from srfpipe.config import add_options_arguments

    parser.add_argument("--images", required=True, metavar="ZARR", help="images.zarr (stage downscale)")
    parser.add_argument("--labels", required=True, metavar="ZARR", help="labels.zarr (stage composite)")
    parser.add_argument("--out", required=True, metavar="ZARR", help="output srf.zarr")
    parser.add_argument("--checkpoints", metavar="DIR",
                        help="checkpoint folder (default: <out without .zarr>.ckpt beside the output)")
    parser.add_argument("--metrics-log", metavar="JSONL", help="append per-step metrics here (JSON lines)")
    parser.add_argument("--holdout-every", type=int, default=None,
                        help="hold out every k-th view (default: the scene's evaluate.holdout_every)")
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    add_options_arguments(parser, "train")


def run(args) -> int:
    from srfpipe.config import stage_options, validate_scene, load_scene

    options = stage_options(args, "train")
    if args.threads is not None and args.threads < 0:
        raise ValueError(f"--threads {args.threads}: torch CPU threads must be 1 or more (0: torch's default)")
    holdout = args.holdout_every
    if holdout is None:
        scene = load_scene(args.scene) if args.scene else validate_scene({})
        holdout = scene["evaluate"]["holdout_every"]
    train(
        images=args.images, labels=args.labels, out=args.out, options=options,
        holdout_every=holdout, checkpoints=args.checkpoints, metrics_log=args.metrics_log,
        threads=args.threads,
    )
    return 0


# ----------------------------------------------------------------------------- pieces


def step_generator(seed: int, step: int, device="cpu"):
    """The random stream of one training step: a pure function of (seed, step)."""
    import torch

    digest = hashlib.sha256(f"{seed}:{step}".encode()).digest()
    return torch.Generator(device=device).manual_seed(int.from_bytes(digest[:8], "little") >> 1)


def learning_rate(progress: float, lr: float, lr_final: float, hold: float = 0.0) -> float:
    """lr until progress `hold`, then exponential decay to lr_final at progress 1.

    The hold is for short budgets: fog leaves empty cells only by many large steps on their
    log-density, and a decay that starts at once stalls it (orchard, 60 s: held-out 23.9 dB with
    the decay from step 0, 25.2 dB with none)."""
    decay = (min(max(progress, 0.0), 1.0) - hold) / max(1.0 - hold, 1e-9)
    return lr * (lr_final / lr) ** max(decay, 0.0)


def training_progress(step: int, iterations: int, seconds: float, time_budget: float) -> float:
    """How far the run is: by steps, or by the time budget when that comes first."""
    progress = step / max(iterations, 1)
    if time_budget > 0:
        progress = max(progress, seconds / time_budget)
    return progress


def parameter_groups(model, grid_lr_scale: float, cameras=None, lr: float = 1e-2,
                     camera_lr: float = 6e-4, background_lr_scale: float = 1.0,
                     background_lr_after: float = 0.0, density_decay: float = 0.0) -> list[dict]:
    """Adam groups: dense grid tables learn `grid_lr_scale` times faster (DVGO uses 1e-1 for its
    grids): one Adam step moves a grid value by at most ~lr, and a cell of fog has to fall by
    several units of log-density before the occupancy grid can skip it. The background colour
    model learns `background_lr_scale` times the field's rate (train.background_lr_scale) once the
    run's progress reaches `background_lr_after`, and at the field's rate before. The camera
    corrections (`cameras`, a CameraRefinement) learn at `camera_lr` when the field learns at `lr`,
    on its schedule. With `density_decay` > 0 the dense log-density grids form a group of their
    own whose values Adam shrinks by lr * density_decay a step towards 0, the initial opacity
    (decoupled weight decay, as Zip-NeRF decays its grids): density that the views stop
    supporting fades instead of staying where an early step put it."""
    grids = [m.table for m in model.modules() if type(m).__name__ == "DenseGrid"]
    field = model.field
    sigma = ({id(p) for grid in (field.inner_sigma, field.outer_sigma) if grid is not None for p in grid.parameters()}
             if float(density_decay) > 0 and field.density_grid else set())
    background = list(field.background_mlp.parameters()) if float(background_lr_scale) != 1.0 else []
    apart = {id(p) for p in grids + background}
    others = [p for p in model.parameters() if id(p) not in apart]
    groups = [{"params": others, "lr_scale": 1.0}]
    density = [p for p in grids if id(p) in sigma]
    grids = [p for p in grids if id(p) not in sigma]
    if grids:
        groups.append({"params": grids, "lr_scale": float(grid_lr_scale)})
    if density:
        groups.append({"params": density, "lr_scale": float(grid_lr_scale), "weight_decay": float(density_decay)})
    if background:
        groups.append({"params": background, "lr_scale": float(background_lr_scale),
                       "lr_after": float(background_lr_after)})
    if cameras is not None:
        groups.append({"params": list(cameras.parameters()), "lr_scale": camera_lr / lr})
    return groups


def group_lr_scale(group: dict, progress: float) -> float:
    """A group's multiple of the field's rate at this progress: 1 until its `lr_after`."""
    return group["lr_scale"] if progress >= group.get("lr_after", 0.0) else 1.0


def fingerprint(options: dict, model_config: dict, inputs: list[dict]) -> str:
    """Identity of a training run: resume only from checkpoints with the same one."""
    relevant = {k: v for k, v in options.items()
                if k not in ("checkpoint_every", "keep_checkpoints", "log_every", "eval_every", "snapshot_seconds")}
    blob = json.dumps([relevant, model_config, inputs], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def autocast_context(device, precision: str):
    """Mixed precision: bf16 (or fp16) autocast on CUDA by default, fp32 on the CPU unless asked."""
    import torch

    if precision == "auto":
        precision = "bf16" if device.type == "cuda" and torch.cuda.is_bf16_supported() else (
            "fp16" if device.type == "cuda" else "fp32")
    if precision == "fp32":
        return contextlib.nullcontext(), precision
    dtype = torch.bfloat16 if precision == "bf16" else torch.float16
    return torch.autocast(device.type, dtype=dtype), precision


def object_pixels(data, train_views, share: float, dilation_px: int = 2):
    """The pools of training pixels (flat (image, y, x) indices, dilated by `dilation_px`) that a
    share of each batch is drawn from, or None when the object's pixels already make up at least
    `share` of the training pixels (or there are none).

    A small object (a plant under 1 % of the frame) would get a few rays of each batch, and its
    colour, its geometry and its semantic heads almost no signal; drawing `share` of every batch
    from its pixels fixes that without touching scenes whose classes fill more of the frame.
    The first pool is what the masks mark (in the frames that have masks): the heads' positives.
    On an empty backdrop (data.backdrop) a second pool holds every frame's pixels that show
    matter, and the share is split between the two: the frames without masks (labels on a few
    frames) and the parts that partial masks miss still train the object's geometry, while the
    masked pixels keep half the share, however few frames have masks (one pool of all would
    dilute them by the share of frames without masks, and the heads learn only background).
    """
    import cv2
    import torch

    if data.multihot is None or data.multihot.shape[-1] == 0 or share <= 0:
        return None
    kernel = np.ones((2 * dilation_px + 1,) * 2, np.uint8)
    pixels = data.height * data.width
    masked, matter = [], []

    def indices(mask: np.ndarray, view) -> torch.Tensor:
        return torch.from_numpy(np.flatnonzero(cv2.dilate(mask.astype(np.uint8), kernel).ravel()) + int(view) * pixels)

    for view in train_views:
        marked = None
        if data.labelled is None or data.labelled[view]:
            marked = data.multihot[int(view)].numpy().any(axis=-1)
            if marked.any():
                masked.append(indices(marked, view))
        if data.backdrop is not None:
            shows = shows_matter(data, int(view)).numpy()
            if marked is not None:
                shows |= marked
            if shows.any():
                matter.append(indices(shows, view))
    pools = [torch.cat(found) for found in (masked, matter) if found]
    total = len(train_views) * pixels
    if not pools or max(pool.numel() for pool in pools) >= share * total:
        return None
    log.info("the masked pixels are %.2f %%%s of the training pixels: %.0f %% of each batch is drawn from them",
             100.0 * sum(t.numel() for t in masked) / total,
             f" and the pixels that show matter on the empty backdrop {100.0 * pools[-1].numel() / total:.2f} %"
             if matter else "", 100.0 * share)
    return pools


def sample_batch(data, train_views, count: int, generator, device, focus=None, focus_share: float = 0.0,
                 pixel_jitter: bool = False, supersample: int = 1):
    """A random batch of rays from the training views' pixels: rays, target rgb, multi-hot labels.

    With `focus` (object_pixels' pools), round(focus_share * count) of the pixels are drawn from
    them, an equal part from each. `pixel_jitter`: each ray passes through a random point of its
    pixel (`draw_within`), else through its centre. `supersample` s > 1: count / s^2 pixels, each
    with s x s rays in a row (`footprint_rays`); the targets repeat for each of a pixel's rays.
    """
    image, v, u, within = draw_rays(data, train_views, count, generator, focus, focus_share, pixel_jitter,
                                    supersample, data.images.device)
    origins, directions, rgb, labels = pixel_batch(data, image, v, u, within)
    return (origins.to(device), directions.to(device), image.to(device), rgb.to(device),
            None if labels is None else labels.to(device))


def draw_pixels(data, train_views, count: int, generator, focus=None, focus_share: float = 0.0):
    """(image, v, u) of `count` random pixels of the training views, on the generator's device
    (`sample_batch`'s draws, in its order)."""
    import torch

    from srfpipe.device import randint

    views = torch.as_tensor(train_views)
    focused = 0 if focus is None else int(round(focus_share * count))
    image = views[randint(0, len(views), count - focused, generator, views.device)]
    u = randint(0, data.width, count - focused, generator, data.images.device)
    v = randint(0, data.height, count - focused, generator, data.images.device)
    if focused:
        pools = list(focus)
        parts = [focused // len(pools) + (i < focused % len(pools)) for i in range(len(pools))]
        pick = torch.cat([pool[randint(0, pool.numel(), part, generator, pool.device)]
                          for pool, part in zip(pools, parts)])
        pixel = pick % (data.height * data.width)
        image = torch.cat([image, pick // (data.height * data.width)])
        v, u = torch.cat([v, pixel // data.width]), torch.cat([u, pixel % data.width])
    return image, v, u


def draw_rays(data, train_views, count: int, generator, focus=None, focus_share: float = 0.0,
              pixel_jitter: bool = False, supersample: int = 1, device="cpu"):
    """(image, v, u, within) of `count` training rays: `count` / s^2 random pixels (`draw_pixels`),
    each with s x s rays (`footprint_rays`), through random points of their cells with
    `pixel_jitter`, else through the cells' centres (0.5 for every ray when s is 1)."""
    pixels = count // (supersample * supersample)
    image, v, u = draw_pixels(data, train_views, pixels, generator, focus, focus_share)
    within = draw_within(pixels * supersample * supersample, generator, device) if pixel_jitter else None
    if supersample == 1:
        return image, v, u, 0.5 if within is None else within
    return footprint_rays(image, v, u, supersample, within)


def footprint_rays(image, v, u, supersample: int, within=None):
    """Each pixel's s x s rays in a row, through the centres of a regular grid of cells over its
    footprint (as evaluate renders a pixel, `image_rays`), or through the points `within` (R, 2) of
    the cells: (image, v, u, within) of R = pixels * s^2 rays.

    Why: a pixel holds the mean of the light over its footprint, and a ray through its centre alone
    asks the field for the centre's value. At a thin part's edge the views' pixel grids cover it
    differently, and the field fits each training view's mixed pixels with a halo of faint matter
    where new views see the backdrop; trained on the mean of its rays (`pixel_means`), the field can
    keep the edge sharp and still give each pixel its share."""
    import torch

    from srfpipe.srf.data import pixel_cells

    k = supersample * supersample
    offset = torch.full((image.shape[0] * k, 2), 0.5, device=image.device) if within is None else within
    points = (pixel_cells(supersample, image.device).repeat(image.shape[0], 1) + offset.to(image.device)) / supersample
    return (image.repeat_interleave(k), v.repeat_interleave(k), u.repeat_interleave(k), points)


def pixel_means(values, supersample: int):
    """(R, ...) per-ray values of `footprint_rays`' batches -> (R / s^2, ...) each pixel's mean."""
    k = supersample * supersample
    return values if k == 1 else values.view(-1, k, *values.shape[1:]).mean(dim=1)


def pixel_targets(values, supersample: int):
    """(R, ...) per-ray targets of `footprint_rays`' batches, a pixel's repeated on each of its
    rays -> (R / s^2, ...) one per pixel."""
    k = supersample * supersample
    return values if k == 1 else values[::k]


def draw_within(count: int, generator, device):
    """(count, 2) uniform points inside pixels, (0, 0) to (1, 1) from a pixel's corner.

    Why: a pixel holds the mean of the light over its footprint (a camera's sensor element, or
    INTER_AREA's box when images are downscaled), and evaluate renders that mean (its supersampled
    rays); a ray through the centre alone asks the field for the centre's value, which at a
    silhouette each view's pixel grid mixes differently.
    """
    from srfpipe.device import rand

    return rand((count, 2), generator, device)


def pixel_batch(data, image, v, u, within=0.5):
    """Rays through the points `within` (R, 2) of pixels (image, v, u) (0.5: their centres), target rgb
    in [0, 1] and the heads' targets in [0, 1] (the masks' probabilities where `data` holds them, else
    the multi-hot bits), on the data's device."""
    import torch

    from srfpipe.srf.data import rays_for_pixels

    origins, directions = rays_for_pixels(data.poses_scene[image], data.intrinsics[image], u, v, within)
    rgb = data.images[image, v, u].float() / 255.0
    if data.probability is not None:  # train.semantic_targets probabilities
        labels = data.probability[image, v, u].float() / 255.0
    elif data.multihot is not None:
        labels = data.multihot[image, v, u].float()
    else:
        labels = torch.zeros(image.shape[0], 0, device=data.images.device)
    return origins, directions, rgb, labels


REAL_CAPTURE_APPEARANCE_DIM = 8
# the BCE's positive weight with the masks' probabilities as targets: a point takes a class where the
# views that see it give it a mean probability of 1 / (1 + w) = 1/3 or more. Masks miss thin parts (a
# blurred stem's 0.25, a twig one view drops) more than they mark what is not there (docs/benchmarks.md)
MASK_PROBABILITY_POSITIVE_WEIGHT = 2.0
# Bounds the user or the capture's ground truth gave: a box filled with the scene's matter. Other
# bounds are estimates (frusta, points, the masks' hull plus a margin): most of the box and all
# of the contracted shell are empty there, and a field that starts as a faint fog keeps fog that
# fits the training views (built-in plant, 2 min: held-out 13.9 dB at opacity 0.01 per step,
# 26.3 dB at 0.001; the fox 19.2 vs 19.0 dB with the grid 84 % vs 23 % occupied).
TRUSTED_BOUNDS = ("config", "ground_truth")
ESTIMATED_INITIAL_OPACITY = 0.001
# weight of the background-opacity loss when the capture's background is empty (set by the plant trials).
# 0.03 clears 40 % of a faint halo beside the plant's leaves and gains 0.25-0.30 dB at 2500 steps, but at the
# panel's steps costs the plant 0.30 dB and plant-berry 0.27 (docs/benchmarks.md, "Measured, taken back: the
# empty-background loss at 0.03")
EMPTY_BACKGROUND_OPACITY = 0.01
# Mip-NeRF 360's distortion loss where the cameras stand round a subject in a scene (a room, an
# orchard): it raised held-out PSNR on every such capture of the panel, most on those that fit
# their training views only (docs/benchmarks.md, captures); it cost the forward-facing fern 0.4 dB
# and the small plant on an empty backdrop 5.5 dB, which keep 0.
SURROUNDING_SCENE_DISTORTION = 0.01


def round_a_subject_in_a_scene(poses_scene, background_empty: bool) -> bool:
    """Where the distortion loss belongs: a background that is a scene, and cameras that stand
    round their focus point (`cameras.cameras_surround`). Cameras that look one way
    (`warp.looks_one_way`) never do: with parallel axes `focus_point`'s stand-in point puts a
    symmetric rig's opposite corners exactly 90 degrees apart, and rounding decided."""
    poses = np.asarray(poses_scene, dtype=np.float64)
    return (not background_empty and not looks_one_way(poses)
            and cameras.cameras_surround(poses, cameras.focus_point(poses)))


# The grid's default cell count, and the cap of the finest level when the pixels ask for more.
# A cell should cover about one pixel where the cameras look (the box centre): the orchard and the
# built-in plant get ~1.1 px per cell from 96 cells; the fox's phone images got 7 px per cell, a
# blur no training removes. Finer single grids overfit (fox at 400 steps: 192 cells 19.5 dB vs
# 96 cells 19.9 dB); three levels up to 192 cells gave 21.7 dB. Cells smaller than a pixel overfit
# too: the plant small in the frame (0.6 px per cell at 96) fitted its 15 views with ghost leaves
# between them; 54 cells (one pixel each) raised its held-out object pixels 15.84 -> 17.02 dB and
# 15.28 -> 16.57 at two seeds; 40 cells (1.4 px each) lost 0.9 dB.
FINEST_CELLS = 192
MULTI_LEVELS = 3
MAX_PIXELS_PER_CELL = 2.0
MIN_PIXELS_PER_CELL = 1.0
COARSEST_CELLS = 24  # a box seen at a few pixels across still gets a grid that can hold a shape


def pixels_per_cell(data, cells: int) -> float:
    """Pixels one grid cell spans in a typical view: the cell size (largest box side / `cells`)
    times the median focal length over the median camera distance to the box centre."""
    bounds = np.asarray(data.bounds_world, dtype=np.float64)
    scene_from_world = np.asarray(data.scene_from_world, dtype=np.float64)
    scale = float(np.cbrt(np.linalg.det(scene_from_world[:3, :3])))
    extent = float(((bounds[1] - bounds[0]) * scale).max())
    centre = scene_from_world[:3, :3] @ bounds.mean(axis=0) + scene_from_world[:3, 3]
    distance = float(np.median(np.linalg.norm(data.poses_scene[:, :3, 3].double().numpy() - centre, axis=1)))
    focal = float(np.median(data.intrinsics[:, :2].double().numpy()))
    return extent / cells * focal / max(distance, 1e-12)


def resolve_grid_defaults(settings, data) -> dict:
    """default_cells, grid_levels and features from the images' resolution (see BASE_CELLS), as
    changes to `settings`: one grid of 96 cells when a cell then covers 1-2 pixels, fewer when it
    would cover less than a pixel (one pixel each, at least COARSEST_CELLS), else three levels whose
    finest matches a pixel (at most 192 cells). Values the scene sets are kept; a scene that sets
    its cells gets one level unless it sets grid_levels too."""
    changes = {}
    auto_cells, auto_levels = settings.default_cells is None, settings.grid_levels is None
    if settings.grid_frame == "perspective" and settings.detail_size is None:
        # the perspective grid sizes its cells in pixels itself (one each, srf/warp.py): the cap
        # and the levels of a grid whose finest level matches a pixel
        if auto_cells:
            changes["default_cells"] = FINEST_CELLS
        if auto_levels:
            changes["grid_levels"] = MULTI_LEVELS
        auto_cells = auto_levels = False
    if auto_cells or auto_levels:
        coarse = pixels_per_cell(data, BASE_CELLS)
        # a scene that sets its cells (default_cells or detail_size) chose its grid: one level
        fine = coarse > MAX_PIXELS_PER_CELL and auto_cells and settings.detail_size is None
        if auto_cells:
            one_pixel = int(round(BASE_CELLS * coarse))  # cells across at which a cell spans a pixel
            if fine:
                changes["default_cells"] = min(one_pixel, FINEST_CELLS)
            elif coarse < MIN_PIXELS_PER_CELL:
                changes["default_cells"] = max(one_pixel, COARSEST_CELLS)
            else:
                changes["default_cells"] = BASE_CELLS
        if auto_levels:
            changes["grid_levels"] = MULTI_LEVELS if fine else 1
        log.info("grid: %d cells across, %d level(s) (%.1f px per cell at %d cells)",
                 changes.get("default_cells", settings.default_cells), changes.get("grid_levels", settings.grid_levels),
                 coarse, BASE_CELLS)
    if settings.features is None:
        changes["features"] = default_features(changes.get("grid_levels", settings.grid_levels))
    return changes


# the background model's bands on an empty backdrop: the direction itself. With all four bands
# the plant's held-out backdrop was guessed 8.5 times worse (MSE) than the training views' mean
# colour, and held-out PSNR rose 3.2 dB with two; the orchard (a sky) lost 0.44 and 0.37 dB with two
EMPTY_BACKDROP_SH_DEGREE = 2
# the background model's learning rate on an empty backdrop, as a multiple of the field's, once
# background_lr_after of the run has passed: it is most of every view and, learnt, keeps fitting the
# training directions while the object gains nothing from it (the three plants, the panel's steps:
# +0.14, +0.34, +0.01 dB held out; at 2500 steps +0.03, +0.09, where a tenth from the first step lost 0.5)
EMPTY_BACKDROP_BACKGROUND_LR_SCALE = 0.1
# background_rays auto: masks that mark less than this share of the pixels not of the backdrop's
# colour miss parts of the objects (soft, partial masks: the small plant's mark 0.20 of them; the
# plant's ground-truth masks 0.90, the rest being edge pixels that blend plant and backdrop)
MIN_MASK_COVERAGE = 0.5


def shows_matter(data, index: int):
    """(H, W) bool tensor: the pixels of frame `index` that are not the empty backdrop's colour
    (data.backdrop: colour, level)."""
    import torch

    from srfpipe.srf.losses import shows_backdrop

    colour, level = data.backdrop
    return ~shows_backdrop(data.images[index].float() / 255.0, torch.tensor(colour) / 255.0, level)


def mask_coverage(data) -> float | None:
    """Of the labelled frames' pixels that are not the empty backdrop's colour (data.backdrop), the
    share some mask marks; None without a known backdrop or any such pixel."""
    if data.backdrop is None or data.multihot is None:
        return None
    frames = np.flatnonzero(np.ones(data.count, bool) if data.labelled is None else data.labelled)
    matter = marked = 0
    for i in frames:  # one frame at a time: a float copy of every frame at once is large
        shows = shows_matter(data, i)
        matter += int(shows.sum())
        marked += int((shows & (data.multihot[i].amax(dim=-1) > 0)).sum())
    return marked / matter if matter else None


def background_rays(data) -> str:
    """`train.background_rays` auto: `backdrop` when the masks mark under MIN_MASK_COVERAGE of the
    pixels that show matter (they miss parts that the unmasked rule would empty), else `unmasked`."""
    coverage = mask_coverage(data)
    if coverage is None:
        return "unmasked"
    choice = "backdrop" if coverage < MIN_MASK_COVERAGE else "unmasked"
    log.info("background_rays %s (the masks mark %.0f %% of the pixels that are not the backdrop's colour)",
             choice, 100 * coverage)
    return choice


def resolve_data_defaults(settings, data):
    """The train settings whose default depends on the capture, resolved (and recorded as such).

    `settings`: TrainSettings or a dict of train keys; returns TrainSettings.
    grid_frame auto: perspective where the cameras all look one way (`warp.looks_one_way`: the
    fern, orchard-front) and see the model box (`warp.perspective_fits`), box otherwise.
    initial_opacity: 0.01 per step when the bounds are known (config, ground truth), 0.001 when
    they were estimated (see TRUSTED_BOUNDS).
    background_opacity: when the capture says its background is empty (labels.background), a
    pixel that shows the backdrop (its colour, and none of the classes) sees empty space all
    along its ray, so opacity there is penalised; otherwise (the orchard's ground, a room) the box holds
    things the classes do not name, so it is off.
    background_rays: which of those rays (see `background_rays`).
    background_lr_scale: on an empty backdrop, EMPTY_BACKDROP_BACKGROUND_LR_SCALE (from
    background_lr_after of the run on); in a scene 1, the field's rate.
    background_sh_degree: on an empty backdrop, EMPTY_BACKDROP_SH_DEGREE: the backdrop is most of
    every view and a held-out view looks at directions between the training views', which the
    background model must interpolate, not fit; in a scene, sh_degree.
    distortion: when the background is a scene and the cameras stand round their focus point
    (`cameras.cameras_surround`), SURROUNDING_SCENE_DISTORTION; otherwise 0.
    camera_refinement: a real capture's poses were estimated (COLMAP, structure from motion) and
    are refined while training; a generated capture's are exact.
    semantic_targets: the masks' probabilities where labels.zarr holds them, and then
    semantic_positive_weight MASK_PROBABILITY_POSITIVE_WEIGHT (1, the paper's BCE, on 0/1 labels).
    appearance_dim: REAL_CAPTURE_APPEARANCE_DIM where a real capture's images form a sequence
    (`cameras.images_form_a_sequence`: a video, a walk with a camera): its frames differ in
    exposure and white balance, which a per-image embedding absorbs (Nerfacto, NeRF-W), and a
    new view borrows the appearance of the frames taken beside it, which share it (the beer
    video: 24.7 dB with, 21.1 without). Photos taken from here and there share nothing a new
    view could borrow: each embedding fits what its photo alone shows, and the field fits the
    training views, not new ones (the bottle at equal steps: held-out 26.0 dB with, 26.3
    without, its train-view gap 6.8 and 4.7 dB), so they get none (0); nor does a generated
    capture (it has ground truth), whose images have no such nuisance.
    """
    from srfpipe.settings import TrainSettings

    settings = TrainSettings.from_options(settings)
    frame = {}
    if settings.grid_frame == "auto":
        poses = data.poses_scene.detach().cpu().numpy()
        one_way = looks_one_way(poses)
        box = scene_box(data.bounds_world, data.scene_from_world, float(settings.box_padding))
        fits = one_way and perspective_fits(poses, data.intrinsics.detach().cpu().numpy(), data.width, data.height, *box)
        frame["grid_frame"] = "perspective" if fits else "box"
        if one_way and not fits:
            log.warning("grid_frame box: the cameras all look one way, but half of them see next to nothing of the "
                        "model box (bounds %s); a perspective grid covers only what they see",
                        np.asarray(data.bounds_world).tolist())
        else:
            log.info("grid_frame %s (%s)", frame["grid_frame"],
                     "the cameras all look one way" if one_way else "the cameras stand round their subject")
        settings = settings.replace(**frame)
    changes = {**frame, **resolve_grid_defaults(settings, data)}
    if settings.initial_opacity is None:
        trusted = data.bounds_source in TRUSTED_BOUNDS
        changes["initial_opacity"] = TRUSTED_INITIAL_OPACITY if trusted else ESTIMATED_INITIAL_OPACITY
        log.info("initial_opacity %g (bounds from %s)", changes["initial_opacity"], data.bounds_source)
    if settings.background_opacity is None:
        empty = data.background_empty and len(data.classes) > 0
        changes["background_opacity"] = EMPTY_BACKGROUND_OPACITY if empty else 0.0
        log.info("background_opacity %g (background %s)", changes["background_opacity"],
                 "empty" if data.background_empty else "a scene")
    if settings.background_rays == "auto":
        changes["background_rays"] = background_rays(data) if data.background_empty else "unmasked"
    if settings.background_sh_degree is None:
        changes["background_sh_degree"] = EMPTY_BACKDROP_SH_DEGREE if data.background_empty else settings.sh_degree
        log.info("background_sh_degree %d (background %s)", changes["background_sh_degree"],
                 "empty" if data.background_empty else "a scene")
    if settings.background_lr_scale is None:
        changes["background_lr_scale"] = EMPTY_BACKDROP_BACKGROUND_LR_SCALE if data.background_empty else 1.0
        log.info("background_lr_scale %g (background %s)", changes["background_lr_scale"],
                 "empty" if data.background_empty else "a scene")
    if settings.distortion is None:
        belongs = round_a_subject_in_a_scene(data.poses_scene.detach().cpu().numpy(), data.background_empty)
        changes["distortion"] = SURROUNDING_SCENE_DISTORTION if belongs else 0.0
        log.info("distortion %g (%s)", changes["distortion"],
                 "cameras round a subject in a scene" if belongs else "an empty backdrop or cameras facing one way")
    if settings.camera_refinement == "auto":
        changes["camera_refinement"] = data.gt_label is None
        log.info("camera_refinement %s (%s capture)", changes["camera_refinement"],
                 "generated" if data.gt_label is not None else "real")
    if settings.semantic_targets is None:
        changes["semantic_targets"] = "probabilities" if data.probability is not None else "labels"
        if data.classes:
            log.info("semantic_targets %s (%s)", changes["semantic_targets"],
                     "the masks' probabilities" if data.probability is not None
                     else "labels.zarr holds no probabilities: a composite of an older srfpipe")
    if settings.semantic_positive_weight is None:
        soft = (settings.semantic_targets or changes["semantic_targets"]) == "probabilities"
        changes["semantic_positive_weight"] = MASK_PROBABILITY_POSITIVE_WEIGHT if soft else 1.0
    if settings.appearance_dim is None:
        fraction = cameras.sequence_fraction(data.names, data.poses_scene.detach().cpu().numpy())
        sequence = fraction >= cameras.SEQUENCE_MIN_FRACTION
        changes["appearance_dim"] = REAL_CAPTURE_APPEARANCE_DIM if data.gt_label is None and sequence else 0
        log.info("appearance_dim %d (%s)", changes["appearance_dim"],
                 "a generated capture" if data.gt_label is not None else
                 f"{'a sequence' if sequence else 'photos in no sequence'}: {fraction:.0%} of the images "
                 "stand nearest the one before or after them")
    return settings.replace(**changes)


# ----------------------------------------------------------------------------- training


def train(images, labels, out, options, holdout_every: int = 8, checkpoints=None,
          metrics_log=None, threads: int | None = None) -> dict:
    """Train and write srf.zarr; returns a summary (steps, seconds, precision, device).

    `options`: the `train` section (TrainSettings, or a dict of its keys: validated, defaults filled in).
    """
    import torch

    from srfpipe.device import keep_freed_memory

    if threads:
        torch.set_num_threads(int(threads))
    keep_freed_memory()
    run = start_run(images, labels, Path(out), TrainSettings.from_options(options), holdout_every, checkpoints)
    progress = TrainingProgress(run.step, run.settings.iterations, run.seconds, run.settings.time_budget)
    metrics = MetricsLog(metrics_log, progress)
    run_steps(run, [progress, Snapshots(run), metrics, HeldoutEvaluation(metrics), TimeBudget(), Checkpoints()])
    write_field(run, images, labels)
    return {"iterations": run.step, "train_seconds": run.seconds, "precision": run.precision, "device": str(run.device)}


@dataclass
class TrainingRun:
    """One training run: what the loop steps, what the hooks read and save, what srf.zarr records."""

    settings: TrainSettings
    data: Any  # srf.data.PosedImages
    holdout_every: int
    train_views: Any
    heldout_views: Any
    device: Any
    model: Any
    optimizer: Any
    scaler: Any  # a GradScaler for fp16 on CUDA, else None
    autocast: Any
    precision: str
    fingerprint: str
    checkpoint_dir: Path
    out: Path
    focus: Any  # object_pixels: the pools of pixels a share of each batch is drawn from, or None
    labelled_frames: Any  # per frame, whether it had masks (None: all)
    seen_fraction: dict | None
    watch: DivergenceWatch
    step: int = 0  # steps done
    seconds: float = 0.0  # training seconds so far
    resumed_from: int = 0
    curve: dict = field(default_factory=lambda: {k: [] for k in CURVE_KEYS})
    eval_curve: dict = field(default_factory=lambda: {k: [] for k in EVAL_CURVE_KEYS})
    terms: dict = field(default_factory=dict)  # the last step's weighted loss terms, by name
    loss: Any = None  # their sum
    outputs: dict = field(default_factory=dict)  # the last step's render outputs
    graphed: Any = None  # srf.graphed.GraphedSteps when the step is replayed as a CUDA graph
    backdrop: Any = None  # (colour (3,) in [0, 1] on the device, level in 8-bit levels): data.backdrop
    cameras: Any = None  # srf.camera_refinement.CameraRefinement when train.camera_refinement is on


CURVE_KEYS = ("step", "seconds", "loss", "photometric", "semantic", "psnr", "samples_per_ray", "shaded_per_ray",
              "occupied")
EVAL_CURVE_KEYS = ("step", "seconds", "psnr", "miou", "miou_gt")


def run_steps(run: TrainingRun, hooks: list) -> None:
    """The training loop: one step, then the hooks in order; the first hook that returns True ends
    the run (srf/hooks.py). Steps are numbered from where a resumed run left off."""
    from srfpipe.device import DeviceBacklog

    backlog = DeviceBacklog(run.device)
    try:
        for step in range(run.step, run.settings.iterations):
            tick = time.perf_counter()
            run.terms, run.loss, run.outputs = training_step(run, step)
            backlog.settle()  # on CUDA: count the device's time, not only the queuing
            run.seconds += time.perf_counter() - tick
            run.step = step + 1
            if any(hook.after_step(run) for hook in hooks):
                break
        for hook in hooks:
            hook.finish(run)
    finally:
        for hook in hooks:
            hook.close()


def training_step(run: TrainingRun, step: int):
    """One optimizer step on a random batch of rays: (weighted loss terms by name, loss, outputs).

    Every random number of the step comes from one generator seeded by (seed, step), drawn in a
    fixed order (occupancy update, batch, jitter, the regularisers), so a resumed run repeats it.
    """
    from srfpipe.device import rand

    s, model = run.settings, run.model
    generator = step_generator(s.seed, step)
    if step > 0 and step % s.occupancy_update_every == 0:
        model.occupancy.update(model.field.sigma, generator, all_cells=step < s.occupancy_warmup)
        if run.graphed is not None:
            run.graphed.check_capacity()
    progress = training_progress(step, s.iterations, run.seconds, s.time_budget)
    for group in run.optimizer.param_groups:
        lr = learning_rate(progress, s.lr, s.lr_final, s.lr_hold) * group_lr_scale(group, progress)
        if hasattr(group["lr"], "fill_"):  # a CUDA graph's Adam reads it from the device (srf/graphed.py)
            group["lr"].fill_(lr)
        else:
            group["lr"] = lr
    if run.graphed is not None:
        image, v, u, within = draw_rays(run.data, run.train_views, s.rays_per_batch, generator, run.focus,
                                        s.object_rays, s.pixel_jitter, s.supersample)
        jitter = rand(s.rays_per_batch, generator, "cpu")
        try:
            terms, loss, outputs = run.graphed.step(image, v, u, jitter, within)
            run.watch.update(terms, loss)
            return terms, loss, outputs
        except RuntimeError as error:  # a capture CUDA refused: this run goes on step by step
            if not run.graphed.cuda:  # nothing was recorded: a real error
                raise
            cause = error.__cause__ or error.__context__
            log.warning("recording the training step as a CUDA graph failed (%s%s); training step by step",
                        str(error).splitlines()[0], f"; during: {str(cause).splitlines()[0]}" if cause else "")
            log.debug("the failed capture", exc_info=True)
            run.graphed.stop()
            run.graphed = None
        origins, directions, rgb, labels = (t.to(run.device) for t in pixel_batch(run.data, image, v, u, within))
        image, jitter = image.to(run.device), jitter.to(run.device)
    else:
        origins, directions, image, rgb, labels = sample_batch(run.data, run.train_views, s.rays_per_batch, generator,
                                                               run.device, run.focus, s.object_rays, s.pixel_jitter,
                                                               s.supersample)
        jitter = rand(s.rays_per_batch, generator, run.device)
    if run.cameras is not None:  # outside autocast: rays in full precision
        origins, directions = run.cameras(image, origins, directions)
    with run.autocast:
        outputs = model(origins, directions, image, jitter)
    valid = None if run.labelled_frames is None else run.labelled_frames[image]
    terms = loss_terms(s, model, outputs, rgb, labels, valid, generator, run.backdrop, run.cameras)
    loss = sum_terms(terms)
    run.watch.update(terms, loss)
    run.optimizer.zero_grad(set_to_none=True)
    if run.scaler is not None:
        run.scaler.scale(loss).backward()
        run.scaler.step(run.optimizer)
        run.scaler.update()
    else:
        loss.backward()
        run.optimizer.step()
    return terms, loss, outputs


def loss_terms(s: TrainSettings, model, outputs: dict, rgb, labels, valid, generator, backdrop=None,
               cameras=None) -> dict:
    """The step's loss terms, each times its weight from the settings, by name: L_photo (Eq. 5),
    lambda L_sem (Eq. 4, on the frames that had masks), and the regularisers the settings switch
    on (mip-NeRF 360's distortion, the empty-background opacity on the rays whose pixel shows
    the `backdrop` (colour, level), Plenoxels' total variation, the size of the `cameras`' corrections)."""
    from srfpipe.srf import losses

    # a pixel is the mean of its rays (train.supersample; each of them carries its pixel's target)
    terms = {"photometric": losses.photometric_loss(pixel_means(outputs["rgb"], s.supersample),
                                                    pixel_targets(rgb, s.supersample)),
             # settings not resolved against a capture (resolve_data_defaults) keep the paper's BCE
             "semantic": s.lambda_sem * losses.semantic_loss(outputs["logits"], labels, valid,
                                                             s.semantic_positive_weight or 1.0)}
    if s.distortion:
        terms["distortion"] = s.distortion * outputs["distortion"]
    if s.background_opacity:
        terms["background_opacity"] = s.background_opacity * losses.background_opacity_loss(
            outputs["accumulation"], labels, valid,
            None if backdrop is None else losses.shows_backdrop(rgb, *backdrop))
    if s.tv_density and model.field.density_grid:
        terms["tv_density"] = s.tv_density * losses.grid_total_variation(model.field.inner_sigma, s.tv_samples, generator)
    if s.tv_features and model.field.density_grid:
        terms["tv_features"] = s.tv_features * losses.grid_total_variation(model.field.inner, s.tv_samples, generator)
    if s.appearance_smoothness and model.field.appearance is not None and model.field.appearance_model == "latent":
        terms["appearance_smoothness"] = s.appearance_smoothness * losses.appearance_smoothness_loss(
            model.field.appearance.weight, model.field.appearance_weights(), model.field.appearance_pairs)
    if cameras is not None:
        terms["camera_penalty"] = cameras.penalty()
    return terms


def sum_terms(terms: dict):
    """L: the weighted terms summed in their order."""
    values = list(terms.values())
    loss = values[0]
    for value in values[1:]:
        loss = loss + value
    return loss


def start_run(images, labels, out: Path, settings: TrainSettings, holdout_every: int, checkpoints) -> TrainingRun:
    """Read the capture, resolve the capture-dependent defaults, build the model and its optimizer,
    and resume from the latest checkpoint of the same run (same fingerprint) if there is one."""
    import torch

    from srfpipe.artifacts import read_provenance
    from srfpipe.config import split_pixel_problem
    from srfpipe.device import choose_device
    from srfpipe.srf.data import load_posed_images, split_views
    from srfpipe.srf.graphed import GraphedSteps, graph_unavailable
    from srfpipe.srf.model import SRFModel, build_model_config

    ckpt_dir = Path(checkpoints) if checkpoints else out.with_name(out.name.removesuffix(".zarr") + ".ckpt")
    if (settings.checkpoint_every or settings.snapshot_seconds) and ckpt_dir.exists() and not ckpt_dir.is_dir():
        # found now, not at the first checkpoint (train.checkpoint_every steps of training lost)
        raise ValueError(f"{ckpt_dir}: the checkpoint folder is a file; remove it or name another folder (--checkpoints)")
    try:
        device = choose_device(settings.device)
    except RuntimeError as exc:  # no GPU, or a device torch does not know: name the key
        raise ValueError(f"train.device: {exc}") from exc
    problem = split_pixel_problem(settings.rays_per_batch, settings.supersample)
    if problem:  # callers of train() that skip the scene schema
        raise ValueError(problem)
    # the masks' probabilities are read unless the heads are asked to train on the 0/1 labels
    data = load_posed_images(images, labels, probability=settings.semantic_targets != "labels")
    if not data.classes:
        log.info("no semantic classes: training geometry and colour only")
    train_views, heldout_views = split_views(data.count, holdout_every)
    settings = resolve_data_defaults(settings, data)
    if settings.semantic_targets == "probabilities" and data.probability is None and data.classes:
        raise ValueError(f"{labels}: train.semantic_targets is probabilities, but this labels.zarr holds no "
                         "'probability' array (a composite of an older srfpipe); re-run the composite stage")
    focus = object_pixels(data, train_views, settings.object_rays)
    # frames without masks (labels.zarr `labelled`) train colour and geometry, not the heads
    labelled_frames = None if data.labelled is None else torch.from_numpy(data.labelled).to(device)
    if labelled_frames is not None:
        log.info("semantic loss on the %d labelled of %d frames", int(data.labelled.sum()), data.count)

    torch.manual_seed(settings.seed)
    config = build_model_config(settings, data.bounds_world, data.scene_from_world, data.classes, data.count, device,
                                cameras=(data.poses_scene[train_views], data.intrinsics[train_views],
                                         data.width, data.height))
    model = SRFModel(config, device).to(device)
    model.field.record_training_cameras(data.poses_scene, train_views)
    seen_fraction = None
    if settings.empty_unseen:
        seen_fraction = model.occupancy.mark_seen(data.poses_scene[train_views], data.intrinsics[train_views],
                                                  data.width, data.height)
        log.info("cells a training camera sees: %s", ", ".join(f"{k} {v:.1%}" for k, v in seen_fraction.items()))
    cameras = None
    if settings.camera_refinement is True:
        from srfpipe.srf.camera_refinement import CameraRefinement

        cameras = CameraRefinement(data.poses_scene.to(device), train_views)
    optimizer = torch.optim.Adam(parameter_groups(model, settings.grid_lr_scale, cameras, settings.lr, settings.camera_lr,
                                                  settings.background_lr_scale, settings.background_lr_after,
                                                  settings.density_decay),
                                 lr=settings.lr, eps=1e-15, decoupled_weight_decay=True,
                                 fused=device.type in ("cpu", "cuda"))
    autocast, precision = autocast_context(device, settings.precision)
    scaler = torch.amp.GradScaler("cuda") if precision == "fp16" and device.type == "cuda" else None
    inputs = [{"path": str(p), "created": read_provenance(p).get("created")} for p in (images, labels) if p is not None]
    fp = fingerprint(settings.as_dict(), config, inputs + [{"holdout_every": holdout_every}])
    run = TrainingRun(settings, data, holdout_every, train_views, heldout_views, device, model, optimizer, scaler, autocast, precision,
                      fp, ckpt_dir, out, focus, labelled_frames, seen_fraction, watch=None, cameras=cameras)
    if settings.background_opacity and settings.background_rays == "backdrop":
        if data.backdrop is None:
            log.warning("background_rays backdrop: %s records no backdrop colour (labels.zarr of an older "
                        "composite, or a background that is not empty); every unmasked ray is emptied", labels)
        else:
            colour, level = data.backdrop
            run.backdrop = (torch.tensor(colour, device=device) / 255.0, level)
    resumed = False
    for path, state in checkpoints_of(ckpt_dir, fp):
        if resume(run, state, path):
            resumed = True
            break
    if resumed:
        log.info("resuming from %s at step %d", ckpt_dir, run.step)
    elif ckpt_dir.is_dir():
        # a fresh run: snapshots of an earlier run in this folder would mix into its curve
        for path in ckpt_dir.glob("snapshot-*.pt"):
            path.unlink()
    run.watch = DivergenceWatch(run.step, device)
    model.train()
    unavailable = graph_unavailable(run)
    if unavailable is None:
        run.graphed = GraphedSteps(run)
    elif device.type == "cuda":
        log.info("training step by step, not as a CUDA graph: %s", unavailable)
    return run


def resume(run: TrainingRun, state: dict, path: Path) -> bool:
    """Load a checkpoint of this run's fingerprint into the run; False, with a warning naming the
    file and the run's fresh state kept, when it does not fit (tensors of other shapes, a missing
    key: written by another version of srfpipe, or damaged)."""
    import copy

    model, cameras, optimizer = run.model, run.cameras, run.optimizer
    fresh = [copy.deepcopy(part.state_dict()) for part in (model, cameras, optimizer) if part is not None]
    try:
        model.load_state_dict(state["model"])
        if cameras is not None:
            cameras.load_state_dict(state["cameras"])
        optimizer.load_state_dict(state["optimizer"])
        step, seconds = int(state["step"]), float(state["train_seconds"])
        curve = {k: list(v) for k, v in state["curve"].items()}
        eval_curve = {k: list(v) for k, v in state["eval_curve"].items()}
    except (RuntimeError, ValueError, KeyError, TypeError, AttributeError, IndexError) as exc:
        log.warning("ignoring checkpoint %s: it does not fit this run (%s: %s)", path, type(exc).__name__,
                    str(exc).splitlines()[0] if str(exc) else "")
        for part, saved in zip([p for p in (model, cameras, optimizer) if p is not None], fresh):
            part.load_state_dict(saved)
        return False
    for group in optimizer.param_groups:  # a CUDA graph's run saved its device-side settings
        group["lr"], group["capturable"] = float(group["lr"]), False
    run.step, run.seconds, run.resumed_from = step, seconds, step
    run.curve, run.eval_curve = curve, eval_curve
    return True


def camera_record(run: TrainingRun) -> dict:
    """What srf.zarr records of the refined cameras: each image's correction (the training
    views' are what the training views were rendered through) and their size, logged."""
    if run.cameras is None:
        return {}
    from srfpipe.srf.model import scene_scale

    summary = run.cameras.summary(run.train_views, scene_scale(run.data.scene_from_world))
    log.info("cameras refined: rotation %.3g deg median (%.3g largest), translation %.3g world units median "
             "(%.3g largest) over %d training images", summary["rotation_deg_median"], summary["rotation_deg_max"],
             summary["translation_world_median"], summary["translation_world_max"], summary["images"])
    return {"camera_adjustment": run.cameras.corrections().detach().cpu().double().numpy(),
            "camera_refinement": summary}


def write_field(run: TrainingRun, images, labels) -> None:
    """srf.zarr from the trained run, then the run's checkpoints removed (snapshots stay)."""
    from srfpipe.srf import io
    from srfpipe.srf.model import scene_scale

    run.model.eval()
    data, curve, eval_curve = run.data, run.curve, run.eval_curve
    io.write_srf(
        run.out, run.model, config=run.settings.as_dict(), inputs=[p for p in (images, labels) if p is not None],
        curve=curve, eval_curve={k: v for k, v in eval_curve.items() if v} if eval_curve["step"] else None,
        classes=data.classes, scene_from_world=data.scene_from_world, world_from_scene=data.world_from_scene,
        bounds_world=data.bounds_world, semantic_bounds_world=data.semantic_bounds_world,
        scene_scale=scene_scale(data.scene_from_world), holdout_every=run.holdout_every,
        train_views=run.train_views, heldout_views=run.heldout_views, train_seconds=run.seconds,
        precision=run.precision, device=str(run.device), fingerprint=run.fingerprint, iterations_done=run.step,
        resumed_from_step=run.resumed_from, final=({k: curve[k][-1] for k in curve} if curve["step"] else {}),
        seen_fraction=run.seen_fraction, **camera_record(run),
    )
    if not run.settings.keep_checkpoints and run.checkpoint_dir.is_dir():
        # with the temporary file of a checkpoint whose writing a kill cut short
        for path in [*run.checkpoint_dir.glob("step-*.pt"), *run.checkpoint_dir.glob("step-*.pt.tmp")]:
            path.unlink()
        with contextlib.suppress(OSError):
            run.checkpoint_dir.rmdir()

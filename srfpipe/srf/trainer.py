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
import errno
import hashlib
import json
import logging
import shutil
import time
from pathlib import Path

import numpy as np

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


def parameter_groups(model, options: dict) -> list[dict]:
    """Adam groups: dense grid tables learn `grid_lr_scale` times faster (DVGO uses 1e-1 for its
    grids): one Adam step moves a grid value by at most ~lr, and a cell of fog has to fall by
    several units of log-density before the occupancy grid can skip it."""
    import torch

    grids = [m.table for m in model.modules() if type(m).__name__ == "DenseGrid"]
    grid_ids = {id(p) for p in grids}
    others = [p for p in model.parameters() if id(p) not in grid_ids]
    scale = float(options.get("grid_lr_scale", 10.0))
    groups = [{"params": others, "lr_scale": 1.0}]
    if grids:
        groups.append({"params": grids, "lr_scale": scale})
    return groups


def fingerprint(options: dict, model_config: dict, inputs: list[dict]) -> str:
    """Identity of a training run: resume only from checkpoints with the same one."""
    relevant = {k: v for k, v in options.items()
                if k not in ("checkpoint_every", "log_every", "eval_every", "snapshot_seconds")}
    blob = json.dumps([relevant, model_config, inputs], sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def latest_checkpoint(folder: Path, fp: str):
    """The checkpoint with the highest step written by a run with fingerprint `fp`, or None."""
    import torch

    if not folder.is_dir():
        return None
    for path in sorted(folder.glob("step-*.pt"), reverse=True):
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # a checkpoint cut short by a kill: try the one before
            log.warning("ignoring unreadable checkpoint %s (%s)", path, exc)
            continue
        if state.get("fingerprint") == fp:
            return state
        log.info("ignoring checkpoint %s from a run with different settings", path)
    return None


def save_checkpoint(folder: Path, state: dict, keep: int = 2) -> None:
    """Write step-XXXXXXXXX.pt atomically, keeping the newest `keep`."""
    import torch

    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"step-{state['step']:09d}.pt"
    tmp = path.with_suffix(".pt.tmp")
    try:
        torch.save(state, tmp)
        tmp.replace(path)
    except BaseException as exc:  # a full disk: no half-written checkpoint left behind
        tmp.unlink(missing_ok=True)
        if isinstance(exc, (OSError, RuntimeError)):  # torch reports a full disk as an iostream error
            free = shutil.disk_usage(folder).free
            raise OSError(getattr(exc, "errno", None) or errno.EIO,
                          f"cannot write the checkpoint ({exc}; {free} bytes free on its disk)", str(path)) from exc
        raise
    for old in sorted(folder.glob("step-*.pt"))[:-keep]:
        old.unlink(missing_ok=True)


def save_snapshot(folder: Path, step: int, seconds: float, marks: list[float], model, fp: str) -> Path:
    """The model's weights (no optimizer state) at `step`, after `seconds` of training, as
    snapshot-XXXXXXXXX.pt: written for the `snapshot_seconds` marks the step passed. Never pruned
    and never resumed from; the trainer's clean-up leaves them (and so the folder) in place."""
    import torch

    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"snapshot-{step:09d}.pt"
    tmp = path.with_suffix(".pt.tmp")
    torch.save({"step": step, "train_seconds": seconds, "marks": list(marks), "fingerprint": fp,
                "model": model.state_dict()}, tmp)
    tmp.replace(path)
    return path


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
    """Flat (image, y, x) indices of the training pixels that show a class (dilated by `dilation_px`),
    or None when they already make up at least `share` of the training pixels (or there are none).

    A small object (a plant under 1 % of the frame) would get a few rays of each batch, and its
    colour, its geometry and its semantic heads almost no signal; drawing `share` of every batch
    from its pixels fixes that without touching scenes whose classes fill more of the frame.
    Frames without masks contribute none.
    """
    import cv2
    import torch

    if data.multihot is None or data.multihot.shape[-1] == 0 or share <= 0:
        return None
    kernel = np.ones((2 * dilation_px + 1,) * 2, np.uint8)
    pixels = data.height * data.width
    found = []
    for view in train_views:
        if data.labelled is not None and not data.labelled[view]:
            continue
        marked = data.multihot[int(view)].numpy().any(axis=-1).astype(np.uint8)
        flat = np.flatnonzero(cv2.dilate(marked, kernel).ravel())
        found.append(torch.from_numpy(flat + int(view) * pixels))
    indices = torch.cat(found) if found else torch.zeros(0, dtype=torch.int64)
    total = len(train_views) * pixels
    if indices.numel() == 0 or indices.numel() >= share * total:
        return None
    log.info("the classes' pixels are %.2f %% of the training pixels: %.0f %% of each batch is drawn from them",
             100.0 * indices.numel() / total, 100.0 * share)
    return indices


def sample_batch(data, train_views, count: int, generator, device, focus=None, focus_share: float = 0.0):
    """A random batch of pixels from the training views: rays, target rgb, multi-hot labels.

    With `focus` (object_pixels), round(focus_share * count) of the pixels are drawn from it.
    """
    import torch

    from srfpipe.device import randint
    from srfpipe.srf.data import rays_for_pixels

    views = torch.as_tensor(train_views)
    focused = 0 if focus is None else int(round(focus_share * count))
    image = views[randint(0, len(views), count - focused, generator, views.device)]
    u = randint(0, data.width, count - focused, generator, data.images.device)
    v = randint(0, data.height, count - focused, generator, data.images.device)
    if focused:
        pick = focus[randint(0, focus.numel(), focused, generator, focus.device)]
        pixel = pick % (data.height * data.width)
        image = torch.cat([image, pick // (data.height * data.width)])
        v, u = torch.cat([v, pixel // data.width]), torch.cat([u, pixel % data.width])
    origins, directions = rays_for_pixels(data.poses_scene[image], data.intrinsics[image], u, v)
    rgb = data.images[image, v, u].float() / 255.0
    labels = (data.multihot[image, v, u].float() if data.multihot is not None
              else torch.zeros(count, 0))
    return (origins.to(device), directions.to(device), image.to(device), rgb.to(device),
            None if labels is None else labels.to(device))


def render_view(model, data, index: int, device, chunk: int = 8192) -> dict:
    """Render one view of `data` (scene-frame pose) into numpy images."""
    from srfpipe.srf.data import image_rays

    origins, directions = image_rays(data.poses_scene[index], data.intrinsics[index], data.width, data.height)
    out = model.render_rays_chunked(origins.to(device), directions.to(device), chunk)
    h, w = data.height, data.width
    return {
        "rgb": out["rgb"].clamp(0, 1).numpy().reshape(h, w, 3),
        "probabilities": out["logits"].sigmoid().numpy().reshape(h, w, -1),
        "depth": out["depth"].numpy().reshape(h, w),
        "accumulation": out["accumulation"].numpy().reshape(h, w),
    }


def quick_eval(model, data, views, device, max_views: int = 4) -> dict:
    """Held-out PSNR and mIoU (vs composited labels, and ground truth when present) on a few views."""
    from srfpipe.srf import metrics
    from srfpipe.srf.data import remap_ground_truth

    mses, conf, conf_gt = [], None, None
    c = len(data.classes)
    for index in list(views)[:max_views]:
        out = render_view(model, data, int(index), device)
        target = data.images[index].numpy() / 255.0
        mses.append(float(((out["rgb"] - target) ** 2).mean()))
        pred = metrics.label_from_probabilities(out["probabilities"])
        if data.label is not None and (data.labelled is None or data.labelled[index]):
            m = metrics.confusion(pred, data.label[index], c + 1)
            conf = m if conf is None else conf + m
        if data.gt_label is not None:
            gt = remap_ground_truth(data.gt_label[index], data.gt_classes, data.classes)
            m = metrics.confusion(pred, gt, c + 1)
            conf_gt = m if conf_gt is None else conf_gt + m
    result = {"psnr": metrics.psnr_from_mse(np.mean(mses))}
    if conf is not None:
        result["miou"] = float(np.nanmean(metrics.iou_from_confusion(conf)))
    if conf_gt is not None:
        result["miou_gt"] = float(np.nanmean(metrics.iou_from_confusion(conf_gt)))
    return result


REAL_CAPTURE_APPEARANCE_DIM = 8
# Bounds the user or the capture's ground truth gave: a box filled with the scene's matter. Other
# bounds are estimates (frusta, points, the masks' hull plus a margin): most of the box and all
# of the contracted shell are empty there, and a field that starts as a faint fog keeps fog that
# fits the training views (built-in plant, 2 min: held-out 13.9 dB at opacity 0.01 per step,
# 26.3 dB at 0.001; the fox 19.2 vs 19.0 dB with the grid 84 % vs 23 % occupied).
TRUSTED_BOUNDS = ("config", "ground_truth")
# weight of the background-opacity loss when the capture's background is empty (set by the plant trials)
EMPTY_BACKGROUND_OPACITY = 0.01


# The grid's default cell count, and the cap of the finest level when the pixels ask for more.
# A cell should cover about one pixel where the cameras look (the box centre): the orchard and the
# built-in plant get ~1.1 px per cell from 96 cells; the fox's phone images got 7 px per cell, a
# blur no training removes. Finer single grids overfit (fox at 400 steps: 192 cells 19.5 dB vs
# 96 cells 19.9 dB); three levels up to 192 cells gave 21.7 dB.
BASE_CELLS = 96
FINEST_CELLS = 192
MULTI_LEVELS = 3
MAX_PIXELS_PER_CELL = 2.0


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


def resolve_grid_defaults(options: dict, data) -> None:
    """default_cells, grid_levels and features from the images' resolution (see BASE_CELLS):
    one grid of 96 cells when a cell then covers <= 2 pixels, else three levels whose finest
    matches a pixel (at most 192 cells). Values the scene sets are kept; a scene that sets its
    cells gets one level unless it sets grid_levels too."""
    auto_cells, auto_levels = options.get("default_cells") is None, options.get("grid_levels") is None
    if auto_cells or auto_levels:
        coarse = pixels_per_cell(data, BASE_CELLS)
        # a scene that sets its cells (default_cells or detail_size) chose its grid: one level
        fine = coarse > MAX_PIXELS_PER_CELL and auto_cells and options.get("detail_size") is None
        if auto_cells:
            options["default_cells"] = min(int(round(BASE_CELLS * coarse)), FINEST_CELLS) if fine else BASE_CELLS
        if auto_levels:
            options["grid_levels"] = MULTI_LEVELS if fine else 1
        log.info("grid: %d cells across, %d level(s) (%.1f px per cell at %d cells)",
                 options["default_cells"], options["grid_levels"], coarse, BASE_CELLS)
    if options.get("features") is None:
        options["features"] = 8 if int(options["grid_levels"]) > 1 else 16


def resolve_data_defaults(options: dict, data) -> dict:
    """The options whose default depends on the capture, resolved (and recorded as such).

    initial_opacity: 0.01 per step when the bounds are known (config, ground truth), 0.001 when
    they were estimated (see TRUSTED_BOUNDS).
    background_opacity: when the capture says its background is empty (labels.background), a
    pixel that shows none of the classes sees empty space through the box, so opacity there is
    penalised; otherwise (the orchard's ground, a room) the box holds things the classes do not
    name, so it is off.
    appearance_dim: a real capture's images differ in exposure and white balance, which a
    per-image embedding absorbs (Nerfacto, NeRF-W); a generated capture (it has ground truth)
    has none, and the embedding would only add parameters.
    """
    options = dict(options)
    resolve_grid_defaults(options, data)
    if options.get("initial_opacity") is None:
        trusted = data.bounds_source in TRUSTED_BOUNDS
        options["initial_opacity"] = 0.01 if trusted else 0.001
        log.info("initial_opacity %g (bounds from %s)", options["initial_opacity"], data.bounds_source)
    if options.get("background_opacity") is None:
        empty = data.background_empty and len(data.classes) > 0
        options["background_opacity"] = EMPTY_BACKGROUND_OPACITY if empty else 0.0
        log.info("background_opacity %g (background %s)", options["background_opacity"],
                 "empty" if data.background_empty else "a scene")
    if options.get("appearance_dim") is None:
        options["appearance_dim"] = 0 if data.gt_label is not None else REAL_CAPTURE_APPEARANCE_DIM
        log.info("appearance_dim %d (%s capture)", options["appearance_dim"],
                 "generated" if data.gt_label is not None else "real")
    return options


class TrainingDiverged(RuntimeError):
    """A loss term or the model's parameters became NaN or infinite, or a loss term exploded:
    nothing is written."""


# A loss term this many times the run's first loss (at least 0.1) has exploded. A healthy run's loss
# falls from its first value (photometric <= 3, semantic about 0.7 per class at logits 0); train.lr
# 1e6 on the tiny test scene gave a semantic loss of 1e5 to 6e14 that never became NaN.
EXPLODED_FACTOR = 1e3


class DivergenceWatch:
    """Notices a loss term that becomes NaN or infinite, without a host-device sync per step.

    Every step `update` records on the device, per loss term, the first step at which it was not
    finite (a few tiny kernels, nothing read back); `check`, called where the loop reads the loss
    to the host anyway (each `log_every` steps, before a checkpoint, at the end), reads those
    steps, the terms of the latest step and whether every parameter is still finite, and raises
    TrainingDiverged naming the step, the term and the learning rate. A term above
    EXPLODED_FACTOR times the run's first loss counts as diverged too.
    """

    def __init__(self, names: list[str], start_step: int, device):
        import torch

        self.names = list(names)
        self.start = start_step + 1
        self.step = torch.full((), start_step + 1, dtype=torch.int64, device=device)  # the step `update` sees
        self.first = torch.full((len(self.names),), -1, dtype=torch.int64, device=device)
        self.initial = None  # the first step's loss (device)
        self.last = None  # the latest step's terms (device)

    def update(self, terms, loss) -> None:
        import torch

        self.last = torch.stack([t.detach().float().reshape(()) for t in terms])
        if self.initial is None:
            self.initial = loss.detach().float().reshape(1)
        self.first = torch.where(~torch.isfinite(self.last) & (self.first < 0), self.step, self.first)
        self.step += 1

    def check(self, done: int, model, lr: float, out) -> None:
        import math

        import torch

        params_finite = torch.stack([torch.isfinite(p.detach()).all() for p in model.parameters()]).all()
        found = torch.cat([self.first.double(), self.last.double(), self.initial.double(),
                           (~params_finite).double().reshape(1)]).tolist()
        n = len(self.names)
        first, last, initial, params_bad = found[:n], found[n:2 * n], found[2 * n], bool(found[-1])
        went = [(int(step), name) for step, name in zip(first, self.names) if step >= 0]
        limit = EXPLODED_FACTOR * max(initial, 0.1) if math.isfinite(initial) else math.inf
        exploded = [(value, name) for value, name in zip(last, self.names) if math.isfinite(value) and value > limit]
        if not went and not params_bad and not exploded:
            return
        from srfpipe.config import load_schema

        default = load_schema()["properties"]["train"]["properties"]["lr"].get("default")
        hint = f"lower train.lr (the default is {default:g})" if default is not None else "lower train.lr"
        if went:
            step = min(s for s, _ in went)
            terms = " and ".join(name for s, name in went if s == step)
            what = f"at step {step} the {terms} loss became NaN or infinite"
        elif params_bad:
            name = next(n for n, p in model.named_parameters() if not bool(torch.isfinite(p.detach()).all()))
            what = f"by step {done} the parameter {name} became NaN or infinite"
        else:
            value, name = max(exploded)
            what = (f"at step {done} the {name} loss is {value:.3g}, over {EXPLODED_FACTOR:g} times the loss "
                    f"at step {self.start} ({initial:.3g})")
        raise TrainingDiverged(f"{out}: training diverged, {what} (train.lr {lr:g}); {hint}; nothing written")


class TrainingProgress:
    """The training progress bar. With a time budget the run ends on the clock (usually long
    before `iterations`), so the bar counts training seconds towards the budget and shows the
    step beside it; without one it counts steps towards `iterations`."""

    def __init__(self, start_step: int, iterations: int, seconds: float, time_budget: float):
        from tqdm import tqdm

        self.by_time = time_budget > 0
        if self.by_time:
            self.bar = tqdm(total=round(time_budget), initial=min(round(seconds), round(time_budget)),
                            desc="train", unit="s", dynamic_ncols=True, mininterval=1.0,
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s [{elapsed}{postfix}]")
        else:
            self.bar = tqdm(total=iterations, initial=start_step, desc="train", unit="step",
                            dynamic_ncols=True, mininterval=1.0)
        self.postfix: dict = {}

    def advance(self, step: int, seconds: float) -> None:
        if self.by_time:
            self.bar.update(min(seconds, self.bar.total) - self.bar.n)
            self.postfix["step"] = step
            self.bar.set_postfix(self.postfix, refresh=False)
        else:
            self.bar.update(step - self.bar.n)

    def set_postfix(self, **values) -> None:
        self.postfix.update(values)
        self.bar.set_postfix(self.postfix, refresh=False)

    def close(self) -> None:
        self.bar.close()


# ----------------------------------------------------------------------------- training


def train(images, labels, out, options: dict, holdout_every: int = 8, checkpoints=None,
          metrics_log=None, threads: int | None = None) -> dict:
    """Train and write srf.zarr; returns a summary (steps, seconds, final metrics)."""
    import torch
    from tqdm import tqdm

    from srfpipe.artifacts import read_provenance
    from srfpipe.device import choose_device, keep_freed_memory, rand
    from srfpipe.srf import io, losses, metrics
    from srfpipe.srf.data import load_posed_images, split_views
    from srfpipe.srf.model import SRFModel, build_model_config, scene_scale

    if threads:
        torch.set_num_threads(int(threads))
    keep_freed_memory()
    out = Path(out)
    device = choose_device(options.get("device", "auto"))
    data = load_posed_images(images, labels)
    if not data.classes:
        log.info("no semantic classes: training geometry and colour only")
    train_views, heldout_views = split_views(data.count, holdout_every)
    options = resolve_data_defaults(options, data)
    seed = int(options.get("seed", 0))
    iterations = int(options["iterations"])
    batch = int(options["rays_per_batch"])
    lambda_sem = float(options.get("lambda_sem", 1.0))
    tv_density = float(options.get("tv_density", 0.0))
    distortion_weight = float(options.get("distortion", 0.0))
    background_opacity = float(options.get("background_opacity") or 0.0)
    tv_features = float(options.get("tv_features", 0.0))
    tv_samples = options.get("tv_samples")
    tv_samples = None if tv_samples is None else int(tv_samples)
    object_share = float(options.get("object_rays", 0.0))
    focus = object_pixels(data, train_views, object_share)

    # frames without masks (labels.zarr `labelled`) train colour and geometry, not the heads
    labelled_frames = None if data.labelled is None else torch.from_numpy(data.labelled).to(device)
    if labelled_frames is not None:
        log.info("semantic loss on the %d labelled of %d frames", int(data.labelled.sum()), data.count)

    torch.manual_seed(seed)
    config = build_model_config(options, data.bounds_world, data.scene_from_world, data.classes,
                                data.count, device)
    model = SRFModel(config, device).to(device)
    model.field.record_training_cameras(data.poses_scene, train_views)
    seen_fraction = None
    if options.get("empty_unseen", True):
        seen_fraction = model.occupancy.mark_seen(data.poses_scene[train_views], data.intrinsics[train_views],
                                                  data.width, data.height)
        log.info("cells a training camera sees: %s", ", ".join(f"{k} {v:.1%}" for k, v in seen_fraction.items()))
    fused = device.type in ("cpu", "cuda")
    optimizer = torch.optim.Adam(parameter_groups(model, options), lr=float(options["lr"]), eps=1e-15, fused=fused)
    scaler_needed = False
    autocast, precision = autocast_context(device, options.get("precision", "auto"))
    if precision == "fp16" and device.type == "cuda":
        scaler = torch.amp.GradScaler("cuda")
        scaler_needed = True

    inputs = [{"path": str(p), "created": read_provenance(p).get("created")} for p in (images, labels) if p is not None]
    fp = fingerprint(options, config, inputs + [{"holdout_every": holdout_every}])
    ckpt_dir = Path(checkpoints) if checkpoints else out.with_name(out.name.removesuffix(".zarr") + ".ckpt")
    curve = {k: [] for k in ("step", "seconds", "loss", "photometric", "semantic", "psnr", "samples_per_ray", "shaded_per_ray", "occupied")}
    eval_curve = {k: [] for k in ("step", "seconds", "psnr", "miou", "miou_gt")}
    start_step, train_seconds = 0, 0.0
    state = latest_checkpoint(ckpt_dir, fp)
    resumed_from = 0
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        start_step, train_seconds = int(state["step"]), float(state["train_seconds"])
        resumed_from = start_step
        curve = {k: list(v) for k, v in state["curve"].items()}
        eval_curve = {k: list(v) for k, v in state["eval_curve"].items()}
        log.info("resuming from %s at step %d", ckpt_dir, start_step)
    elif ckpt_dir.is_dir():
        # a fresh run: snapshots of an earlier run in this folder would mix into its curve
        for path in ckpt_dir.glob("snapshot-*.pt"):
            path.unlink()

    log_file = open(metrics_log, "a") if metrics_log else None
    update_every = int(options.get("occupancy_update_every", 16))
    warmup = int(options.get("occupancy_warmup", 256))
    checkpoint_every = int(options.get("checkpoint_every", 500))
    log_every = int(options.get("log_every", 25))
    eval_every = int(options.get("eval_every", 0))
    time_budget = float(options.get("time_budget", 0))
    # marks already passed by a resumed run are not saved again
    snapshot_marks = sorted(float(m) for m in options.get("snapshot_seconds") or [] if float(m) > train_seconds)
    lr, lr_final = float(options["lr"]), float(options.get("lr_final", options["lr"] * 0.1))
    lr_hold = float(options.get("lr_hold", 0.0))
    scale = scene_scale(data.scene_from_world)
    iterations_done = iterations

    def record_heldout(done: int, seconds: float) -> dict:
        """Evaluate the held-out views and append them to the quality-vs-time curve."""
        model.eval()
        result = quick_eval(model, data, heldout_views, device)
        model.train()
        eval_curve["step"].append(done)
        eval_curve["seconds"].append(seconds)
        for key in ("psnr", "miou", "miou_gt"):
            eval_curve[key].append(result.get(key, float("nan")))
        return result

    model.train()
    bar = TrainingProgress(start_step, iterations, train_seconds, time_budget)
    watch = None
    try:
        for step in range(start_step, iterations):
            tick = time.perf_counter()
            generator = step_generator(seed, step)
            if step > 0 and step % update_every == 0:
                model.occupancy.update(model.field.sigma, generator, all_cells=step < warmup)
            for group in optimizer.param_groups:
                progress = training_progress(step, iterations, train_seconds, time_budget)
                group["lr"] = learning_rate(progress, lr, lr_final, lr_hold) * group["lr_scale"]
            origins, directions, image, rgb, labels_batch = sample_batch(data, train_views, batch, generator, device,
                                                                         focus, object_share)
            jitter = rand(batch, generator, device)
            with autocast:
                outputs = model(origins, directions, image, jitter,
                                box_accumulation=bool(background_opacity and labels_batch is not None))
            valid = None if labelled_frames is None else labelled_frames[image]
            parts = losses.total_loss(outputs["rgb"], rgb, outputs["logits"], labels_batch, lambda_sem, valid)
            extra = {}  # the weighted regularisers, by name (a divergence names the term)
            if distortion_weight:
                extra["distortion"] = distortion_weight * outputs["distortion"]
            if background_opacity and labels_batch is not None:
                extra["background_opacity"] = background_opacity * losses.background_opacity_loss(
                    outputs["box_accumulation"], labels_batch, valid)
            if tv_density and model.field.density_grid:
                extra["tv_density"] = tv_density * losses.grid_total_variation(
                    model.field.inner_sigma, tv_samples, generator)
            if tv_features and model.field.density_grid:
                extra["tv_features"] = tv_features * losses.grid_total_variation(
                    model.field.inner, tv_samples, generator)
            for term in extra.values():
                parts["loss"] = parts["loss"] + term
            if watch is None:
                watch = DivergenceWatch(["photometric", "semantic", *extra], start_step, device)
            watch.update([parts["photometric"], parts["semantic"], *extra.values()], parts["loss"])
            optimizer.zero_grad(set_to_none=True)
            if scaler_needed:
                scaler.scale(parts["loss"]).backward()
                scaler.step(optimizer)
                scaler.update()
            else:
                parts["loss"].backward()
                optimizer.step()
            train_seconds += time.perf_counter() - tick
            done = step + 1
            bar.advance(done, train_seconds)
            if snapshot_marks and train_seconds >= snapshot_marks[0]:
                passed = [m for m in snapshot_marks if m <= train_seconds]
                snapshot_marks = snapshot_marks[len(passed):]
                save_snapshot(ckpt_dir, done, train_seconds, passed, model, fp)
            if done % log_every == 0 or done == iterations:
                # the loop reads the loss to the host here anyway: the one place to look for NaN
                watch.check(done, model, lr, out)
                photo = float(parts["photometric"].detach())
                record = {
                    "step": done, "seconds": round(train_seconds, 3), "loss": float(parts["loss"].detach()),
                    "photometric": photo, "semantic": float(parts["semantic"].detach()),
                    "psnr": metrics.psnr_from_mse(photo / 3.0),
                    "samples_per_ray": outputs["samples"] / batch,
                    "shaded_per_ray": outputs.get("shaded", outputs["samples"]) / batch,
                    "occupied": model.occupancy.occupied_fraction(),
                }
                for key, value in record.items():
                    curve[key].append(value)
                bar.set_postfix(loss=f"{record['loss']:.4f}", psnr=f"{record['psnr']:.2f}",
                                spr=f"{record['samples_per_ray']:.1f}")
                log.debug("step %d: %s", done, record)
                if log_file:
                    log_file.write(json.dumps(record) + "\n")
                    log_file.flush()
            if eval_every and (done % eval_every == 0 or done == iterations):
                result = record_heldout(done, train_seconds)
                log.info("step %d held-out %s", done, result)
                if log_file:
                    log_file.write(json.dumps({"step": done, "seconds": train_seconds, "heldout": result}) + "\n")
            if time_budget and train_seconds >= time_budget and done < iterations:
                log.info("time budget of %.0f s reached at step %d", time_budget, done)
                if eval_every and (not eval_curve["step"] or eval_curve["step"][-1] != done):
                    record_heldout(done, train_seconds)
                iterations_done = done
                break
            if checkpoint_every and done % checkpoint_every == 0 and done < iterations:
                watch.check(done, model, lr, out)  # never a checkpoint of a diverged run
                save_checkpoint(ckpt_dir, {
                    "step": done, "fingerprint": fp, "model": model.state_dict(),
                    "optimizer": optimizer.state_dict(), "train_seconds": train_seconds,
                    "curve": curve, "eval_curve": eval_curve,
                })
        if watch is not None:
            watch.check(iterations_done, model, lr, out)  # a run cut by its time budget between two logs
    finally:
        bar.close()
        if log_file:
            log_file.close()

    model.eval()
    summary = {"iterations": iterations_done, "train_seconds": train_seconds, "precision": precision,
               "device": str(device)}
    io.write_srf(
        out, model, config=options, inputs=[p for p in (images, labels) if p is not None], curve=curve,
        eval_curve={k: v for k, v in eval_curve.items() if v} if eval_curve["step"] else None,
        classes=data.classes, scene_from_world=data.scene_from_world, world_from_scene=data.world_from_scene,
        bounds_world=data.bounds_world, semantic_bounds_world=data.semantic_bounds_world, scene_scale=scale, holdout_every=holdout_every,
        train_views=train_views, heldout_views=heldout_views, train_seconds=train_seconds,
        precision=precision, device=str(device), fingerprint=fp, iterations_done=iterations_done, resumed_from_step=resumed_from,
        final=({k: curve[k][-1] for k in curve} if curve["step"] else {}), seen_fraction=seen_fraction,
    )
    if not options.get("keep_checkpoints", False) and ckpt_dir.is_dir():
        for path in ckpt_dir.glob("step-*.pt"):
            path.unlink()
        with contextlib.suppress(OSError):
            ckpt_dir.rmdir()
    return summary

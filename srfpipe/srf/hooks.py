"""What the training loop calls after each step (srf/trainer.py, `run_steps`).

Each hook looks at the run after a step and may end it: the progress bar, snapshots at given
training seconds, the metrics log (which is also where divergence is checked, since the loss is
read to the host there anyway), held-out evaluation, the time budget and checkpoints. They run in
that order; the first that returns True ends the run, and the later ones do not see that step
(a run cut by its time budget writes no checkpoint at its last step). Checkpoints and snapshots
are plain tensor dicts, read with weights_only=True.
"""

from __future__ import annotations

import errno
import json
import logging
import math
import shutil
from pathlib import Path

import numpy as np

log = logging.getLogger("srfpipe.train")


# ----------------------------------------------------------------------------- checkpoints


def latest_checkpoint(folder: Path, fp: str):
    """The checkpoint with the highest step written by a run with fingerprint `fp`, or None."""
    return next((state for _, state in checkpoints_of(folder, fp)), None)


def checkpoints_of(folder: Path, fp: str):
    """(path, state) of each readable checkpoint written by a run with fingerprint `fp`, the
    highest step first (a caller that cannot use one goes on to the one before)."""
    import torch

    if not folder.is_dir():
        return
    for path in sorted(folder.glob("step-*.pt"), reverse=True):
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # a checkpoint cut short by a kill: try the one before
            log.warning("ignoring unreadable checkpoint %s (%s)", path, exc)
            continue
        if isinstance(state, dict) and state.get("fingerprint") == fp:
            yield path, state
        else:
            log.info("ignoring checkpoint %s from a run with different settings", path)


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
    # the newest `keep` up to this step: a checkpoint of a later step is another run's (other settings,
    # same folder), and counting it would delete this run's own before the next could replace them
    for old in sorted(p for p in folder.glob("step-*.pt") if p.name <= path.name)[:-keep]:
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


# ----------------------------------------------------------------------------- divergence


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

    def __init__(self, start_step: int, device):
        self.start = start_step + 1
        self.device = device
        self.names: list[str] = []  # the loss terms, from the first step
        self.step = None  # the step `update` sees (device)
        self.first = None  # per term, the first step it was not finite, else -1 (device)
        self.initial = None  # the first step's loss (device)
        self.last = None  # the latest step's terms (device)

    def update(self, terms: dict, loss) -> None:
        import torch

        if self.step is None:
            self.names = list(terms)
            self.step = torch.full((), self.start, dtype=torch.int64, device=self.device)
            self.first = torch.full((len(self.names),), -1, dtype=torch.int64, device=self.device)
            self.initial = loss.detach().float().reshape(1)
        self.last = torch.stack([t.detach().float().reshape(()) for t in terms.values()])
        self.first = torch.where(~torch.isfinite(self.last) & (self.first < 0), self.step, self.first)
        self.step += 1

    def check(self, done: int, model, lr: float, out) -> None:
        import torch

        if self.step is None:  # no step yet
            return
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
        from srfpipe.settings import TrainSettings

        hint = f"lower train.lr (the default is {TrainSettings.lr:g})"
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


# ----------------------------------------------------------------------------- hooks


class Hook:
    """Called by the loop after every step (`after_step`; True ends the run), after the last step of
    a run that was not stopped by an error (`finish`), and at the very end in any case (`close`)."""

    def after_step(self, run) -> bool:
        return False

    def finish(self, run) -> None:
        pass

    def close(self) -> None:
        pass


class TrainingProgress(Hook):
    """The training progress bar. With a time budget the run ends on the clock (usually long
    before `iterations`), so the bar counts training seconds towards the budget and shows the
    step beside it; without one it counts steps towards `iterations`."""

    def __init__(self, start_step: int, iterations: int, seconds: float, time_budget: float):
        from tqdm import tqdm

        self.by_time = 0 < time_budget < math.inf  # an infinite budget (`.inf`, 1e400) never ends the run
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

    def after_step(self, run) -> bool:
        self.advance(run.step, run.seconds)
        return False

    def close(self) -> None:
        self.bar.close()


class Snapshots(Hook):
    """The model's weights at the first step past each of `train.snapshot_seconds` (marks a resumed
    run already passed are not saved again)."""

    def __init__(self, run):
        self.marks = sorted(float(m) for m in run.settings.snapshot_seconds if float(m) > run.seconds)

    def after_step(self, run) -> bool:
        if self.marks and run.seconds >= self.marks[0]:
            passed = [m for m in self.marks if m <= run.seconds]
            self.marks = self.marks[len(passed):]
            save_snapshot(run.checkpoint_dir, run.step, run.seconds, passed, run.model, run.fingerprint)
        return False


class MetricsLog(Hook):
    """Every `train.log_every` steps and at the last: the divergence check, one record of the
    training batch in the run's curve (srf.zarr) and the JSONL metrics log, and the bar's text."""

    def __init__(self, path, progress: TrainingProgress):
        self.file = open(path, "a") if path else None
        self.progress = progress

    def write(self, record: dict) -> None:
        if self.file:
            self.file.write(json.dumps(record) + "\n")
            self.file.flush()

    def after_step(self, run) -> bool:
        from srfpipe.srf import metrics

        if run.step % run.settings.log_every and run.step != run.settings.iterations:
            return False
        run.watch.check(run.step, run.model, run.settings.lr, run.out)
        photo = float(run.terms["photometric"].detach())
        batch = run.settings.rays_per_batch
        record = {
            "step": run.step, "seconds": round(run.seconds, 3), "loss": float(run.loss.detach()),
            "photometric": photo, "semantic": float(run.terms["semantic"].detach()),
            "psnr": metrics.psnr_from_mse(photo / 3.0),
            "samples_per_ray": float(run.outputs["samples"]) / batch,
            "shaded_per_ray": float(run.outputs.get("shaded", run.outputs["samples"])) / batch,
            "occupied": run.model.occupancy.occupied_fraction(),
        }
        for key, value in record.items():
            run.curve[key].append(value)
        self.progress.set_postfix(loss=f"{record['loss']:.4f}", psnr=f"{record['psnr']:.2f}",
                                  spr=f"{record['samples_per_ray']:.1f}")
        log.debug("step %d: %s", run.step, record)
        self.write(record)
        return False

    def finish(self, run) -> None:
        run.watch.check(run.step, run.model, run.settings.lr, run.out)  # a run cut between two logs

    def close(self) -> None:
        if self.file:
            self.file.close()


class HeldoutEvaluation(Hook):
    """Every `train.eval_every` steps (0: never) and at the last: a few held-out views rendered and
    scored into the run's quality-against-time curve and the metrics log."""

    def __init__(self, metrics_log: MetricsLog):
        self.metrics_log = metrics_log

    def after_step(self, run) -> bool:
        every = run.settings.eval_every
        if every and (run.step % every == 0 or run.step == run.settings.iterations):
            result = record_heldout(run)
            log.info("step %d held-out %s", run.step, result)
            self.metrics_log.write({"step": run.step, "seconds": run.seconds, "heldout": result})
        return False


class TimeBudget(Hook):
    """Ends the run once `train.time_budget` training seconds have passed (0: no budget), with a
    last held-out evaluation when the run keeps that curve."""

    def after_step(self, run) -> bool:
        budget = run.settings.time_budget
        if not (budget and run.seconds >= budget and run.step < run.settings.iterations):
            return False
        log.info("time budget of %.0f s reached at step %d", budget, run.step)
        pixels = len(run.train_views) * run.data.width * run.data.height
        # train.supersample: a pixel's s x s rays count once
        passes = run.step * run.settings.rays_per_batch / run.settings.supersample ** 2 / max(pixels, 1)
        if passes < 1:
            # the budget is wall time: a machine whose cores other work shares trains fewer steps
            # (the orchard's quick start: 223 steps and 22.7 dB beside another training, 2706 and 28.6 alone)
            log.warning("the time budget ended training after %d steps, %.2f passes over the %d training "
                        "pixels: the field saw most pixels less than once. A machine whose cores were shared "
                        "(or a slow one) trains fewer steps; raise train.time_budget, or set train.iterations "
                        "with train.time_budget 0", run.step, passes, pixels)
        if run.settings.eval_every and (not run.eval_curve["step"] or run.eval_curve["step"][-1] != run.step):
            record_heldout(run)
        return True


class Checkpoints(Hook):
    """Every `train.checkpoint_every` steps (0: never) before the last: the run's whole state, after
    the divergence check (never a checkpoint of a diverged run)."""

    def after_step(self, run) -> bool:
        every = run.settings.checkpoint_every
        if every and run.step % every == 0 and run.step < run.settings.iterations:
            run.watch.check(run.step, run.model, run.settings.lr, run.out)
            save_checkpoint(run.checkpoint_dir, {
                "step": run.step, "fingerprint": run.fingerprint, "model": run.model.state_dict(),
                "optimizer": run.optimizer.state_dict(), "train_seconds": run.seconds,
                "curve": run.curve, "eval_curve": run.eval_curve,
                **({"cameras": run.cameras.state_dict()} if run.cameras is not None else {}),
            })
        return False


def record_heldout(run) -> dict:
    """Evaluate the held-out views and append them to the run's quality-vs-time curve."""
    run.model.eval()
    result = quick_eval(run.model, run.data, run.heldout_views, run.device)
    run.model.train()
    for key, value in (("step", run.step), ("seconds", run.seconds)):
        run.eval_curve[key].append(value)
    for key in ("psnr", "miou", "miou_gt"):
        run.eval_curve[key].append(result.get(key, float("nan")))
    return result


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

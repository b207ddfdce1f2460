"""Side by side with nerfstudio's nerfacto: the same data, held-out views, image size and machine.

For each scene (the orchard and ../shared/data/fox), one after the other on this machine:

1. srfpipe builds the scene through the workflow (its preset, `train.time_budget` = the largest
   budget) up to `eval`; `train.snapshot_seconds` keeps the field's weights at every budget and on a
   finer grid of training seconds (10 s steps up to a fifth of the largest budget, then 30 s).
2. nerfacto gets the very images srfpipe trains on: images.zarr (undistorted, downscaled, and for the
   fox with the COLMAP-refined poses) written as lossless PNGs named frame_<index>.png, so that
   nerfstudio's file-name order is srfpipe's order, with a pinhole transforms.json (OpenGL axes).
   `ns-train nerfacto` (nerfstudio 1.1.5 in its own environment, ../shared/peers/nerfstudio-setup.sh;
   the light configuration of that script's notes) trains with `--eval-mode interval
   --eval-interval <evaluate.holdout_every>`, a checkpoint every NERFACTO_SAVE_EVERY steps, all kept,
   and no evaluation during training; it is stopped once its clock has passed the largest budget.
3. Both are scored by the same code (srfpipe.srf.metrics): PSNR of the mean squared error over all
   held-out pixels of all held-out views (as `srfpipe evaluate`), mean SSIM per view, on the
   held-out views of srfpipe's split (every `holdout_every`-th image, starting with image 0; the
   script checks that nerfstudio's eval set is exactly those images and pixels).

The clock of both methods is training time without start-up: srfpipe's `train_seconds` (the sum of
its training steps; loading the data, building the model, checkpoints and snapshots are not
counted) and, for nerfacto, the sum of its training iterations (`Train Iter (time)` in its
tensorboard log, a running mean over `logging.max_buffer_size` steps, summed window by window;
its data loading, model set-up, logging and checkpoint writing are not counted; the wall-clock of
its training loop, which counts them, is reported beside it). At each budget the snapshot or
checkpoint nearest in that clock is evaluated. nerfacto's schedules do not depend on its iteration
count (learning rates decay over 200k steps), so stopping it changes nothing before the stop;
srfpipe's learning rate follows its clock towards the largest budget, so its earlier points are
what one run of the largest budget has reached by then, not what a run of that budget would reach.

Time to nerfacto's quality: T = nerfacto's PSNR at --target-budget (300 s). For each method, the
first moment its PSNR-against-clock curve reaches T, by linear interpolation between evaluated
points, found by bisection over its snapshots/checkpoints (a few more evaluations, assuming the
curve rises). `time_to_nerfacto300_ratio` = nerfacto's time / srfpipe's time.

    python benchmarks/peers.py                # orchard and fox, budgets 1, 2, 5, 10 min (~2.5 h)
    python benchmarks/peers.py --quick        # fox only (no COLMAP refinement), budgets 1, 2, 4 min (~25 min)
    python benchmarks/peers.py --nsvenv DIR   # nerfstudio's environment (default $NSVENV or /tmp/nsvenv)
    python benchmarks/peers.py --scenes fox --preset fast       # as peers.json's entries (each scene measured on its own, --preset fast)
    python benchmarks/peers.py --panel bottle beer  # nerfacto alone on captures.py's builds of panel captures
                                                    # (1, 2, 5, 10 min; peers.json `panel`; ~20 min a capture),
                                                    # and its training views at 10 min (`training_views`: its gap)

Writes benchmarks/results/peers.json (`peers_quick.json`) and peers.png (PSNR against the clock).
Opt-in and never part of CI: nerfstudio is no dependency of srfpipe (a 3.5 GB environment).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from captures import FOX, PANEL, scene_configs
from common import REPO, earlier_measurements, holdout_every, machine_info, result_path, rule_seconds, run_workflow, write_result, write_workdir

SCENES = ["orchard", "fox"]
BUDGETS = [60, 120, 300, 600]
QUICK_BUDGETS = [60, 120, 240]
QUICK_SCENES = ["fox"]
TARGET_BUDGET = 300
PANEL_BUDGETS = [60.0, 120.0, 300.0, 600.0]  # the panel's nerfacto_psnr_{1,2,5,10}min
NERFACTO_SAVE_EVERY = 20  # steps (~10 s at 0.5 s a step)
PRUNED_GAP_SECONDS = 60.0  # a budget this far from every checkpoint: the run was pruned for other budgets
# The light nerfacto of ../shared/peers/nerfstudio-setup.sh (fits minutes on 2 cores), with the
# evaluation during training switched off (its time would count against nerfacto's clock).
NERFACTO_ARGS = [
    "--machine.device-type", "cpu", "--vis", "tensorboard", "--pipeline.model.implementation", "torch",
    "--pipeline.datamanager.train-num-rays-per-batch", "1024",
    "--pipeline.model.num-proposal-samples-per-ray", "64", "32",
    "--pipeline.model.num-nerf-samples-per-ray", "24", "--pipeline.model.log2-hashmap-size", "16",
    "--pipeline.model.num-levels", "12", "--pipeline.model.camera-optimizer.mode", "off",
    "--steps-per-eval-batch", "0", "--steps-per-eval-image", "0", "--steps-per-eval-all-images", "0",
    "--save-only-latest-checkpoint", "False", "--max-num-iterations", "1000000",
]
ITER_TAG = "Train Iter (time)"


# ----------------------------------------------------------------------------- pure helpers


def snapshot_marks(budgets: list[float]) -> list[float]:
    """srfpipe's snapshot times: the budgets, every 1/60 of the largest up to a fifth of it
    (10 s steps for 600 s) and every 1/20 after (30 s steps), no closer than 5 s."""
    top = float(max(budgets))
    fine, coarse = max(5.0, top / 60), max(5.0, top / 20)
    marks = set(float(b) for b in budgets)
    marks |= {round(fine * i, 3) for i in range(1, int(top / 5 / fine + 1e-9) + 1)}
    marks |= {round(coarse * i, 3) for i in range(1, int(top / coarse + 1e-9) + 1)}
    return sorted(marks)


def nearest(available: dict[str, float], seconds: float) -> str:
    """The key of `available` (key -> clock seconds) whose clock is nearest `seconds`."""
    return min(available, key=lambda key: (abs(available[key] - seconds), available[key]))


def image_metrics(renders, targets) -> dict:
    """PSNR over all pixels of all views (pooled squared error, as `srfpipe evaluate`) and mean SSIM;
    renders float in [0, 1], targets uint8, both (H, W, 3) per view."""
    from srfpipe.srf import metrics

    squared, values, per_view = 0.0, 0, []
    for render, target in zip(renders, targets, strict=True):
        if render.shape != target.shape:
            raise ValueError(f"render {render.shape} and image {target.shape} differ")
        truth = target.astype(np.float64) / 255.0
        squared += float(((render.astype(np.float64) - truth) ** 2).sum())
        values += truth.size
        per_view.append({"psnr": metrics.psnr(render, truth), "ssim": metrics.ssim(render, truth)})
    return {"psnr": metrics.psnr_from_mse(squared / values),
            "ssim": float(np.mean([v["ssim"] for v in per_view])), "per_view": per_view}


def crossing_time(points: dict[float, float], target: float) -> tuple[float | None, str]:
    """When a curve (clock -> PSNR) first reaches `target`: linear interpolation between the last
    point below it and the first at or above it; ("upper bound") when the first point is already
    there, (None, "not reached") when no point is."""
    times = sorted(points)
    for i, t in enumerate(times):
        if points[t] >= target:
            if i == 0:
                return t, "upper bound: the first evaluated point"
            t0, p0 = times[i - 1], points[times[i - 1]]
            return t0 + (target - p0) / (points[t] - p0) * (t - t0), "interpolated"
    return None, "not reached"


def refine_crossing(available: list[float], points: dict[float, float], target: float, evaluate,
                    max_evaluations: int) -> int:
    """Bisection for `crossing_time`: evaluate (clock -> PSNR, added to `points`) the available clock
    in the middle of those between the last point below `target` and the first at or above it;
    returns the number of evaluations."""
    done = 0
    while done < max_evaluations:
        times = sorted(points)
        above = [t for t in times if points[t] >= target]
        if not above:
            break
        high = above[0]
        below = [t for t in times if t < high]
        low = below[-1] if below else -np.inf
        between = sorted(t for t in available if low < t < high and t not in points)
        if not between:
            break
        middle = between[len(between) // 2]
        points[middle] = evaluate(middle)
        done += 1
    return done


def iteration_clock(steps: list[int], means: list[float], window: int) -> dict[int, float]:
    """Seconds of training up to and including each step, from nerfstudio's running mean of the
    last `window` iteration times logged at every step (`means[k]` at `steps[k]`, steps 0, 1, ...):
    the sum of steps 0..s is the sum over windows of `window` steps ending at s, s - window, ...,
    each window's mean times its length."""
    mean = dict(zip(steps, means))
    if sorted(mean) != list(range(len(mean))):
        raise ValueError("the iteration times must be logged at every step from step 0")
    clock = {}
    for step in mean:
        total, end = 0.0, step
        while end >= 0:
            total += mean[end] * min(end + 1, window)
            end -= window
        clock[step] = total
    return clock


def opengl_from_opencv(camera_to_world: np.ndarray) -> np.ndarray:
    """camera_to_world with OpenCV camera axes (+y down, +z forward) -> nerfstudio's (OpenGL: +y up, +z back)."""
    return np.asarray(camera_to_world, np.float64) @ np.diag([1.0, -1.0, -1.0, 1.0])


# ----------------------------------------------------------------------------- srfpipe


def scene_config(name: str, budgets: list[float], quick: bool, preset: str | None,
                 downscale: float | None = None) -> dict:
    """The shipped scene file, as benchmarks/captures.py reads it (the fox from ../shared/data/fox;
    quick: without its ~20-minute COLMAP refinement), with the budget and the snapshots."""
    scene = scene_configs([name], quick)[name]
    if downscale:
        scene.setdefault("images", {})["downscale"] = downscale
    if preset:
        scene["preset"] = preset
    train = scene.setdefault("train", {})
    train["time_budget"] = float(max(budgets))
    train["snapshot_seconds"] = snapshot_marks(budgets)
    return scene


def read_views(images_zarr: Path) -> dict:
    """Images (uint8), world camera_to_world (OpenCV axes) and intrinsics (fx, fy, cx, cy) of images.zarr."""
    from srfpipe.artifacts import meta, open_artifact

    group = open_artifact(images_zarr, stage="downscale")
    return {"images": np.asarray(group["images"][...]), "poses": np.asarray(group["camera_to_world"][...]),
            "intrinsics": np.asarray(group["intrinsics"][...]), "names": [str(n) for n in meta(group).get("names", [])]}


class Evaluations:
    """Metrics of evaluated snapshots/checkpoints, cached in a JSON file by path and size."""

    def __init__(self, path: Path):
        self.path = path
        self.cache = json.loads(path.read_text()) if path.exists() else {}

    def get(self, file: Path, compute) -> dict:
        key = f"{file}:{file.stat().st_size}:{file.stat().st_mtime_ns}"
        if key not in self.cache:
            self.cache[key] = compute()
            self.path.write_text(json.dumps(self.cache))
        return self.cache[key]


class SrfRenderer:
    """The trained field with a snapshot's weights, rendering srfpipe's held-out views."""

    def __init__(self, srf: Path, views: dict, heldout: np.ndarray):
        import torch

        from srfpipe.srf.query import SemanticRadianceField

        torch.set_num_threads(2)
        self.torch = torch
        self.field = SemanticRadianceField.load(srf, "cpu")
        self.final = {k: v.clone() for k, v in self.field.model.state_dict().items()}
        self.views, self.heldout = views, heldout

    def metrics(self, snapshot: Path | None) -> dict:
        state = self.final if snapshot is None else self.torch.load(snapshot, map_location="cpu", weights_only=True)["model"]
        self.field.model.load_state_dict(state)
        started = time.perf_counter()
        renders = []
        for index in self.heldout:
            out = self.field.render(self.views["poses"][index], self.views["intrinsics"][index],
                                    self.views["images"].shape[2], self.views["images"].shape[1])
            renders.append(out["rgb"])
        result = image_metrics(renders, [self.views["images"][i] for i in self.heldout])
        result["render_seconds"] = time.perf_counter() - started
        return result


def srf_snapshots(folder: Path, fingerprint: str | None) -> dict[str, float]:
    """snapshot file -> its training seconds, for the snapshots of the run with `fingerprint`
    (the one that wrote srf.zarr; a snapshot of an earlier run in the folder is left out)."""
    import torch

    out = {}
    for path in sorted(folder.glob("snapshot-*.pt")):
        state = torch.load(path, map_location="cpu", weights_only=True)
        if fingerprint is None or state.get("fingerprint") == fingerprint:
            out[str(path)] = float(state["train_seconds"])
    return out


# ----------------------------------------------------------------------------- nerfacto


def export_nerfstudio(views: dict, folder: Path) -> str:
    """srfpipe's images as a nerfstudio capture: frame_<index>.png (lossless) and a pinhole
    transforms.json in srfpipe's order; returns a hash of the content."""
    import cv2

    (folder / "images").mkdir(parents=True, exist_ok=True)
    n, height, width, _ = views["images"].shape
    frames, digest = [], hashlib.sha256()
    for index in range(n):
        name = f"images/frame_{index:05d}.png"
        image = views["images"][index]
        digest.update(image.tobytes())
        path = folder / name
        if not path.exists() or not np.array_equal(cv2.imread(str(path))[..., ::-1], image):
            cv2.imwrite(str(path), image[..., ::-1])
        fx, fy, cx, cy = (float(v) for v in views["intrinsics"][index])
        frames.append({"file_path": name, "transform_matrix": opengl_from_opencv(views["poses"][index]).tolist(),
                       "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": width, "h": height})
    transforms = {"camera_model": "PINHOLE", "frames": frames}
    text = json.dumps(transforms, indent=1)
    digest.update(text.encode())
    (folder / "transforms.json").write_text(text)
    return digest.hexdigest()[:16]


def nerfstudio_env(nsvenv: Path) -> dict:
    return dict(os.environ, TORCH_HOME=str(nsvenv / "torchhome"), TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD="1",
                PATH=str(nsvenv / "bin") + os.pathsep + os.environ.get("PATH", ""), PYTHONUNBUFFERED="1")


def train_nerfacto(nsvenv: Path, data: Path, folder: Path, holdout: int, budget: float, content: str) -> Path:
    """ns-train nerfacto in `folder` until its clock passes `budget`; returns the run folder.
    A finished run of the same command on the same images is reused."""
    run = folder / "outputs" / "nerfacto" / "nerfacto" / "run"
    command = [str(nsvenv / "bin" / "ns-train"), "nerfacto", *NERFACTO_ARGS,
               "--steps-per-save", str(NERFACTO_SAVE_EVERY), "--output-dir", str(folder / "outputs"),
               "--experiment-name", "nerfacto", "--timestamp", "run",
               "nerfstudio-data", "--data", str(data), "--downscale-factor", "1",
               "--eval-mode", "interval", "--eval-interval", str(holdout)]
    record = {"command": command, "content": content, "budget": budget}
    done = folder / "done.json"
    if done.exists() and json.loads(done.read_text()).get("record") == record:
        print(f"nerfacto: reusing the finished run in {run}")
        return run
    done.unlink(missing_ok=True)
    if run.exists():
        import shutil

        shutil.rmtree(run)
    log = folder / "ns-train.log"
    print("$", " ".join(command), flush=True)
    launched = time.time()
    with open(log, "w") as handle:
        process = subprocess.Popen(command, cwd=folder, env=nerfstudio_env(nsvenv), stdout=handle,
                                   stderr=subprocess.STDOUT, start_new_session=True)
    # Stop rule, from file times (the exact clock is read from the log afterwards): the training
    # loop starts when dataparser_transforms.json is written. The tensorboard log, which holds the
    # clock, reaches the disk every 120 s (SummaryWriter's flush_secs) and may lose its tail when
    # the process is stopped, so stop once the log *on disk* is past the budget plus a margin for
    # logging and checkpoint writes (up to two minutes more training than needed).
    margin = 1.05 * budget + 30
    start = run / "dataparser_transforms.json"
    try:
        while process.poll() is None:
            time.sleep(2)
            events = list(run.glob("events.out.tfevents.*"))
            if start.exists() and events and max(e.stat().st_mtime for e in events) - start.stat().st_mtime > margin:
                break
            if time.time() - launched > 4 * budget + 900:
                raise RuntimeError(f"nerfacto did not reach {budget} s of training in time: see {log}")
    finally:
        # the session started above: ns-train and its data worker; Ctrl-C first (nerfstudio ends cleanly)
        for sig, wait in ((signal.SIGINT, 60), (signal.SIGTERM, 30), (signal.SIGKILL, None)):
            if process.poll() is not None:
                break
            os.killpg(process.pid, sig)
            try:
                process.wait(timeout=wait)
            except subprocess.TimeoutExpired:
                pass
    if not (run / "dataparser_transforms.json").exists():
        raise RuntimeError(f"ns-train ended before training (exit {process.returncode}): see {log}")
    done.write_text(json.dumps({"record": record, "launched": launched}))
    return run


def nerfacto_tool(nsvenv: Path, *args: str) -> dict:
    """Run this script's nerfstudio side (below) with the nerfstudio environment's Python."""
    out = subprocess.run([str(nsvenv / "bin" / "python"), str(Path(__file__).resolve()), *args],
                         env=nerfstudio_env(nsvenv), check=True, stdout=subprocess.PIPE, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def nerfacto_clock(nsvenv: Path, run: Path) -> dict:
    """Per step: clock (sum of iteration times) and loop wall-clock since training started."""
    info = nerfacto_tool(nsvenv, "_nerfacto", "clock", str(run))
    window = info["window"]
    steps, means, walls = info["steps"], info["means"], info["walls"]
    clock = iteration_clock(steps, means, window)
    start = walls[0] - means[0]  # step 0's event is written when step 0 ends; its mean is its time
    return {"clock": clock, "wall": {s: w - start for s, w in zip(steps, walls)}, "start_time": start, "window": window}


def nerfacto_checkpoints(run: Path, clock: dict[int, float]) -> dict[str, float]:
    out = {}
    for path in sorted((run / "nerfstudio_models").glob("step-*.ckpt")):
        step = int(path.stem.split("-")[1])
        if step in clock:
            out[str(path)] = clock[step]
    return out


# ----------------------------------------------------------------------------- the nerfstudio side
# (runs with the nerfstudio environment's Python: no srfpipe import)


class _PlainTagsLoader(yaml.SafeLoader):
    """A safe loader that reads nerfstudio's config.yml (Python object tags such as
    !!python/object:nerfstudio...TrainerConfig) as plain mappings, lists and strings:
    nothing is imported or constructed."""


def _plain(loader: yaml.SafeLoader, _suffix: str, node: yaml.Node):
    if isinstance(node, yaml.MappingNode):
        return loader.construct_mapping(node, deep=True)
    if isinstance(node, yaml.SequenceNode):
        return loader.construct_sequence(node, deep=True)
    return loader.construct_scalar(node)


_PlainTagsLoader.add_multi_constructor("", _plain)


def read_tagged_yaml(path: Path):
    loader = _PlainTagsLoader(path.read_text())
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def nerfstudio_side(argv: list[str]) -> int:
    action, run = argv[0], Path(argv[1])
    if action == "clock":
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

        config = read_tagged_yaml(run / "config.yml")
        events = []
        for path in sorted(run.glob("events.out.tfevents.*")):
            accumulator = EventAccumulator(str(path), size_guidance={"scalars": 0})
            accumulator.Reload()
            if ITER_TAG in accumulator.Tags()["scalars"]:
                events += accumulator.Scalars(ITER_TAG)
        events.sort(key=lambda e: e.step)
        print(json.dumps({"window": int(config["logging"]["max_buffer_size"]), "steps": [e.step for e in events],
                          "means": [e.value for e in events], "walls": [e.wall_time for e in events]}))
        return 0
    if action in ("render", "render_train"):
        # render FOLDER NPZ CHECKPOINT: the eval views with a checkpoint's weights;
        # render_train FOLDER NPZ CHECKPOINT NAME,...: those training views, each twice (below)
        import torch
        from nerfstudio.utils.eval_utils import eval_setup

        out, checkpoint = Path(argv[2]), Path(argv[3])
        _, pipeline, _, _ = eval_setup(run / "config.yml", test_mode="test")
        import numpy
        from numpy.core.multiarray import scalar  # the name nerfstudio's checkpoints refer to

        # still weights_only (no code runs from the file): nerfstudio's checkpoints hold numpy
        # scalars, so the plain-data numpy types they are rebuilt from are allowed, as torch advises
        dtypes = [type(numpy.dtype(t)) for t in numpy.typecodes["All"]]  # Float64DType, ...
        with torch.serialization.safe_globals([scalar, numpy.dtype, *dtypes]):
            state = torch.load(checkpoint, map_location="cpu", weights_only=True)
        pipeline.load_pipeline(state["pipeline"], state["step"])
        pipeline.eval()
        if action == "render_train":
            return _render_training_views(pipeline, out, argv[4].split(","), int(state["step"]))
        dataset = pipeline.datamanager.eval_dataset
        started = time.perf_counter()
        renders, images = [], []
        for i in range(len(dataset)):
            renders.append(_rgb(pipeline, dataset.cameras[i : i + 1]))
            images.append(dataset.get_numpy_image(i)[..., :3])
        names = [Path(f).name for f in dataset.image_filenames]
        np.savez(out, renders=np.stack(renders), images=np.stack(images), names=np.array(names))
        print(json.dumps({"step": int(state["step"]), "views": len(names),
                          "render_seconds": time.perf_counter() - started}))
        return 0
    raise SystemExit(f"unknown action {action}")


def _rgb(pipeline, camera) -> np.ndarray:
    """nerfacto's colour render of one camera, float32 (H, W, 3)."""
    return pipeline.model.get_outputs_for_camera(camera.to(pipeline.device))["rgb"].cpu().numpy().astype(np.float32)


def _render_training_views(pipeline, out: Path, names: list[str], step: int) -> int:
    """Training views of nerfacto, each rendered twice: as nerfacto renders any view in eval mode
    (the mean of the training images' appearance embeddings) and with the view's own embedding, the
    one it trained with (nerfacto's field reads `embedding_appearance.mean` in eval mode: that
    method is pointed at the view's row while it renders). Camera refinement is off
    (NERFACTO_ARGS), so the training cameras are the ones it trained with."""
    dataset = pipeline.datamanager.train_dataset
    files = [Path(f).name for f in dataset.image_filenames]
    embedding = pipeline.model.field.embedding_appearance
    started = time.perf_counter()
    own, average, images = [], [], []
    for name in names:
        index = files.index(name)  # the row of the embedding: the position in the training set
        camera = dataset.cameras[index : index + 1]
        average.append(_rgb(pipeline, camera))
        embedding.mean = lambda dim=0, row=index: embedding.embedding.weight[row]
        try:
            own.append(_rgb(pipeline, camera))
        finally:
            del embedding.mean  # the class's method again
        images.append(dataset.get_numpy_image(index)[..., :3])
    np.savez(out, own=np.stack(own), average=np.stack(average), images=np.stack(images), names=np.array(names))
    print(json.dumps({"step": step, "views": len(names), "render_seconds": time.perf_counter() - started}))
    return 0


class NerfactoRenderer:
    def __init__(self, nsvenv: Path, run: Path, views: dict, heldout: np.ndarray, scratch: Path):
        self.nsvenv, self.run, self.views, self.heldout, self.scratch = nsvenv, run, views, heldout, scratch

    def metrics(self, checkpoint: Path) -> dict:
        self.scratch.mkdir(parents=True, exist_ok=True)
        npz = self.scratch / f"{checkpoint.stem}.npz"
        info = nerfacto_tool(self.nsvenv, "_nerfacto", "render", str(self.run), str(npz), str(checkpoint))
        data = np.load(npz)
        expected = [f"frame_{i:05d}.png" for i in self.heldout]
        if list(data["names"]) != expected:
            raise RuntimeError(f"nerfstudio's eval views {list(data['names'])} are not srfpipe's {expected}")
        targets = [self.views["images"][i] for i in self.heldout]
        if not all(np.array_equal(a, b) for a, b in zip(data["images"], targets)):
            raise RuntimeError("nerfstudio's eval images differ from srfpipe's images.zarr")
        result = image_metrics(list(data["renders"]), targets)
        result["render_seconds"] = info["render_seconds"]
        npz.unlink()
        return result

    def training_views(self, checkpoint: Path, indices: list[int]) -> dict:
        """nerfacto's `train_view_psnr` (each view with its own appearance embedding, as srfpipe's)
        and `train_view_psnr_average_appearance` (with the mean embedding it renders new views with)
        on srfpipe's training views `indices`, at `checkpoint`."""
        self.scratch.mkdir(parents=True, exist_ok=True)
        npz = self.scratch / f"{checkpoint.stem}-train.npz"
        names = [f"frame_{i:05d}.png" for i in indices]
        info = nerfacto_tool(self.nsvenv, "_nerfacto", "render_train", str(self.run), str(npz), str(checkpoint),
                             ",".join(names))
        data = np.load(npz)
        targets = [self.views["images"][i] for i in indices]
        if not all(np.array_equal(a, b) for a, b in zip(data["images"], targets, strict=True)):
            raise RuntimeError("nerfstudio's training images differ from srfpipe's images.zarr")
        own, average = image_metrics(list(data["own"]), targets), image_metrics(list(data["average"]), targets)
        npz.unlink()
        return {"train_view_indices": list(indices), "train_view_psnr": own["psnr"],
                "train_view_psnr_average_appearance": average["psnr"], "file": checkpoint.name,
                "render_seconds": info["render_seconds"]}


# ----------------------------------------------------------------------------- one scene


def budget_key(budget: float) -> str:
    """A budget's key in the reports: "300", or "20.5" where it is not whole."""
    return str(int(budget) if float(budget).is_integer() else budget)


def by_name(files: dict[str, float], name: str) -> str:
    """The path of `files` (path -> clock seconds) whose file name is `name`."""
    return next(path for path in files if Path(path).name == name)


def evaluate_method(label: str, files: dict[str, float], render, cache: Evaluations, budgets) -> dict:
    """Metrics at each budget (the nearest file by clock); returns budgets, points and the evaluator."""
    points: dict[float, dict] = {}
    by_clock = {seconds: path for path, seconds in files.items()}

    def at(seconds: float) -> dict:
        path = Path(by_clock[seconds])
        if seconds not in points:
            print(f"{label}: evaluating {path.name} ({seconds:.1f} s)", flush=True)
            points[seconds] = dict(cache.get(path, lambda: render(path)), file=path.name, seconds=seconds)
        return points[seconds]

    per_budget = {}
    for budget in budgets:
        seconds = files[nearest(files, budget)]
        per_budget[budget_key(budget)] = at(seconds)
    return {"budgets": per_budget, "points": points, "at": at, "available": sorted(by_clock)}


def time_to(method: dict, target: float, refine: int) -> dict:
    psnr = {t: p["psnr"] for t, p in method["points"].items()}
    extra = refine_crossing(method["available"], psnr, target, lambda t: method["at"](t)["psnr"], refine)
    seconds, how = crossing_time(psnr, target)
    return {"seconds": seconds, "how": how, "extra_evaluations": extra}


def run_scene(name: str, args, cache_dir: Path) -> dict:
    workdir = args.workdir
    print(f"=== {name}: srfpipe", flush=True)
    scene = scene_config(name, args.budgets, args.quick, args.preset, args.downscale)
    holdout = holdout_every(scene)
    write_workdir(workdir, {name: scene}, "occupancy")
    run_workflow(workdir, [f"results/{name}/eval"], log=workdir / "snakemake.log")
    results = workdir / "results" / name
    from srfpipe.artifacts import read_provenance
    from srfpipe.srf.data import split_views

    srf_info = read_provenance(results / "srf.zarr")
    if int(srf_info["holdout_every"]) != holdout:
        raise RuntimeError(f"srfpipe held out every {srf_info['holdout_every']}th view, expected {holdout}")
    views = read_views(results / "images.zarr")
    _, heldout = split_views(len(views["images"]), holdout)
    if list(srf_info["heldout_views"]) != heldout.tolist():
        raise RuntimeError("srf.zarr's held-out views differ from split_views")
    cache = Evaluations(cache_dir / f"{name}-evaluations.json")
    srf_renderer = SrfRenderer(results / "srf.zarr", views, heldout)
    final = srf_renderer.metrics(None)
    workflow_eval = json.loads((results / "eval" / "metrics.json").read_text())
    snapshots = srf_snapshots(results / "srf.ckpt", srf_info.get("fingerprint"))

    print(f"=== {name}: nerfacto", flush=True)
    folder = workdir / "nerfacto" / name
    content = export_nerfstudio(views, folder / "data")
    run = train_nerfacto(args.nsvenv, folder / "data", folder, holdout, max(args.budgets), content)
    timing = nerfacto_clock(args.nsvenv, run)
    checkpoints = nerfacto_checkpoints(run, timing["clock"])
    nerf_renderer = NerfactoRenderer(args.nsvenv, run, views, heldout, folder / "renders")

    if max(checkpoints.values()) < max(args.budgets):
        print(f"WARNING: nerfacto's log covers {max(checkpoints.values()):.0f} s, less than the budget")
    srf = evaluate_method(f"{name} srfpipe", snapshots, srf_renderer.metrics, cache, args.budgets)
    nerf = evaluate_method(f"{name} nerfacto", checkpoints, nerf_renderer.metrics, cache, args.budgets)
    target_key = str(int(args.target_budget))
    target = nerf["budgets"][target_key]["psnr"]
    srf_time = time_to(srf, target, args.refine)
    nerf_time = time_to(nerf, target, args.refine)
    ratio = (nerf_time["seconds"] / srf_time["seconds"]
             if srf_time["seconds"] and nerf_time["seconds"] else None)

    def curve(method):
        return [{k: p[k] for k in ("seconds", "psnr", "ssim", "file")} for _, p in sorted(method["points"].items())]

    def strip(metrics_at):
        return {b: {k: v for k, v in m.items() if k != "per_view"} for b, m in metrics_at.items()}

    start_file = run / "dataparser_transforms.json"
    launched = json.loads((folder / "done.json").read_text())["launched"]
    last_step = max(timing["clock"])
    t = int(args.target_budget)
    return {
        f"srf_psnr_at_{t}s": srf["budgets"][target_key]["psnr"],
        f"nerfacto_psnr_at_{t}s": target,
        f"time_to_nerfacto{t}_ratio": ratio,
        f"srf_seconds_to_nerfacto{t}": srf_time,
        f"nerfacto_seconds_to_nerfacto{t}": nerf_time,
        "budgets": {b: {"srf": strip({b: srf["budgets"][b]})[b], "nerfacto": strip({b: nerf["budgets"][b]})[b]}
                    for b in srf["budgets"]},
        "curves": {"srf": curve(srf), "nerfacto": curve(nerf)},
        "heldout": {"indices": heldout.tolist(), "names": [views["names"][i] for i in heldout] if views["names"] else None,
                    "width": int(views["images"].shape[2]), "height": int(views["images"].shape[1])},
        "srf": {
            "train_seconds": srf_info.get("train_seconds"), "steps": srf_info.get("iterations_done"),
            "train_rule_wall_seconds": rule_seconds(workdir, name, "train"),
            "final_psnr_here": final["psnr"], "final_psnr_workflow_eval": workflow_eval.get("psnr"),
            "final_ssim_here": final["ssim"], "final_ssim_workflow_eval": workflow_eval.get("ssim"),
            "snapshots": len(snapshots), "resolved_train_config": srf_info.get("config"),
        },
        "nerfacto": {
            "steps": last_step + 1, "clock_seconds": timing["clock"][last_step],
            "loop_wall_seconds": timing["wall"][last_step],
            "startup_seconds": timing["start_time"] - launched,
            "dataparser_written_after_launch": start_file.stat().st_mtime - launched,
            "checkpoints": len(checkpoints), "save_every_steps": NERFACTO_SAVE_EVERY, "run": str(run),
            "command_args": NERFACTO_ARGS,
        },
    }


def run_panel_capture(name: str, args, cache_dir: Path) -> dict:
    """nerfacto alone on a panel capture that benchmarks/captures.py built: the very images.zarr and
    held-out split srfpipe trained and was scored on (its numbers do not change when srfpipe does,
    so each capture is measured once and captures.py re-runs srfpipe alone)."""
    from srfpipe.artifacts import read_provenance
    from srfpipe.srf.data import split_views

    results = args.captures_workdir / "results" / name
    if (results / "srf.zarr").exists():
        holdout = int(read_provenance(results / "srf.zarr")["holdout_every"])
    elif (results / "images.zarr").exists():  # nerfacto needs srfpipe's images only: the split from the scene file
        scene = yaml.safe_load((args.captures_workdir / "config" / "scenes" / f"{name}.yaml").read_text())
        holdout = holdout_every(scene)
    else:
        raise SystemExit(f"{results}: build the capture's images first (python benchmarks/captures.py --scenes {name} "
                         f"builds it whole; `snakemake results/{name}/images.zarr` in {args.captures_workdir} "
                         "is enough for nerfacto)")
    views = read_views(results / "images.zarr")
    _, heldout = split_views(len(views["images"]), holdout)
    print(f"=== {name}: nerfacto on {len(views['images'])} views of {views['images'].shape[2]}x"
          f"{views['images'].shape[1]}, held out {heldout.tolist()}", flush=True)
    folder = args.workdir / "nerfacto" / name
    content = export_nerfstudio(views, folder / "data")
    run = train_nerfacto(args.nsvenv, folder / "data", folder, holdout, max(args.budgets), content)
    timing = nerfacto_clock(args.nsvenv, run)
    checkpoints = nerfacto_checkpoints(run, timing["clock"])
    if not checkpoints:
        raise SystemExit(f"{run}: no checkpoints left; delete {folder} to train nerfacto again")
    if max(checkpoints.values()) < max(args.budgets):
        print(f"WARNING: nerfacto's log covers {max(checkpoints.values()):.0f} s, less than the budget")
    if far := [b for b in args.budgets if abs(checkpoints[nearest(checkpoints, b)] - b) > PRUNED_GAP_SECONDS]:
        raise SystemExit(f"{run}: no checkpoint within {PRUNED_GAP_SECONDS:.0f} s of the budgets {far} (an earlier "
                         f"measurement kept only the ones it evaluated); delete {folder} to train nerfacto again")
    renderer = NerfactoRenderer(args.nsvenv, run, views, heldout, folder / "renders")
    nerf = evaluate_method(f"{name} nerfacto", checkpoints, renderer.metrics,
                           Evaluations(cache_dir / f"{name}-evaluations.json"), args.budgets)
    # its generalization gap beside srfpipe's: the training views srfpipe's evaluate scores
    # (evaluate.train_views, evenly spaced), at the checkpoint of the largest budget
    from srfpipe.evaluate import train_view_choice
    from srfpipe.settings import EvaluateSettings

    train, _ = split_views(len(views["images"]), holdout)
    final = nerf["budgets"][budget_key(max(args.budgets))]
    print(f"{name} nerfacto: training views at {final['file']}", flush=True)
    training = renderer.training_views(Path(by_name(checkpoints, final["file"])),
                                       train_view_choice(train, EvaluateSettings().train_views).tolist())
    training["generalization_gap_db"] = training["train_view_psnr"] - final["psnr"]
    training["budget_seconds"] = float(max(args.budgets))
    kept = prune_checkpoints(checkpoints, {p["file"] for p in nerf["points"].values()})
    last_step = max(timing["clock"])
    return {
        "training_views": training,
        "budgets": {b: {"nerfacto": {k: v for k, v in m.items() if k != "per_view"}} for b, m in nerf["budgets"].items()},
        "heldout": {"indices": heldout.tolist(), "names": [views["names"][i] for i in heldout] if views["names"] else None,
                    "width": int(views["images"].shape[2]), "height": int(views["images"].shape[1])},
        "images": str(results / "images.zarr"),
        "nerfacto": {"steps": last_step + 1, "clock_seconds": timing["clock"][last_step],
                     "loop_wall_seconds": timing["wall"][last_step], "checkpoints": len(checkpoints),
                     "save_every_steps": NERFACTO_SAVE_EVERY, "run": str(run), "command_args": NERFACTO_ARGS,
                     "checkpoints_kept": kept},
    }


def prune_checkpoints(checkpoints: dict[str, float], keep: set[str]) -> list[str]:
    """Delete the run's checkpoints whose file names are not in `keep` (the evaluated ones): a
    checkpoint every NERFACTO_SAVE_EVERY steps finds each budget's step by its clock, but at ~60 MB
    each a 10-minute run holds 6-11 GB, and three captures filled a 28 GB disk. Returns the kept names."""
    for path in checkpoints:
        if Path(path).name not in keep:
            Path(path).unlink(missing_ok=True)
    return sorted(keep)


def panel_main(args) -> int:
    """--panel: nerfacto on captures.py's builds, merged into peers.json's `panel` object."""
    cache_dir = args.workdir / "evaluations"
    cache_dir.mkdir(parents=True, exist_ok=True)
    path = result_path("peers", False)
    report = json.loads(path.read_text()) if path.exists() else {}
    panel = report.setdefault("panel", {})
    for name in args.panel:
        entry = run_panel_capture(name, args, cache_dir)
        panel[name] = dict(entry, budgets_seconds=args.budgets, machine=machine_info(quick=False))
        write_result(path, report)  # after each capture: a long run keeps what it measured
        for budget, pair in entry["budgets"].items():
            print(f"{name:14} {budget:>5} s | nerfacto {pair['nerfacto']['psnr']:6.2f} dB, SSIM {pair['nerfacto']['ssim']:.3f}")
        views = entry["training_views"]
        print(f"{name:14} training views: {views['train_view_psnr']:.2f} dB with their own appearance, "
              f"{views['train_view_psnr_average_appearance']:.2f} with the mean; gap {views['generalization_gap_db']:.2f} dB")
    return 0


# ----------------------------------------------------------------------------- report


def plot(report: dict, scenes: list[str], path: Path, size=(480, 360)) -> None:
    """PSNR against the clock, one panel per scene (OpenCV drawing: no plotting library needed)."""
    import cv2

    colours = {"srf": (200, 80, 0), "nerfacto": (0, 120, 240)}
    panels = []
    for name in scenes:
        width, height = size
        panel = np.full((height, width, 3), 255, np.uint8)
        scene = report.get(name)
        if not scene:
            continue
        curves = {m: [(p["seconds"], p["psnr"]) for p in scene["curves"][m]] for m in colours}
        xs = [x for c in curves.values() for x, _ in c]
        ys = [y for c in curves.values() for _, y in c]
        x1 = max(xs) * 1.05
        y0, y1 = min(ys) - 0.5, max(ys) + 0.5
        left, bottom, w, h = 50, height - 40, width - 70, height - 75

        def at(x, y):
            return int(left + x / x1 * w), int(bottom - (y - y0) / (y1 - y0) * h)

        cv2.rectangle(panel, (left, bottom - h), (left + w, bottom), (0, 0, 0), 1)
        target = [v for k, v in scene.items() if k.startswith("nerfacto_psnr_at_")][0]
        for x in range(left, left + w, 8):
            cv2.line(panel, (x, at(0, target)[1]), (x + 4, at(0, target)[1]), (120, 120, 120), 1)
        for method, points in curves.items():
            pixels = [at(x, y) for x, y in points]
            for a, b in zip(pixels, pixels[1:]):
                cv2.line(panel, a, b, colours[method], 2, cv2.LINE_AA)
            for p in pixels:
                cv2.circle(panel, p, 3, colours[method], -1)
        for value in np.linspace(y0, y1, 5):
            cv2.putText(panel, f"{value:.1f}", (4, at(0, value)[1] + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        for value in np.linspace(0, x1, 5):
            cv2.putText(panel, f"{value:.0f}", (at(value, y0)[0] - 8, bottom + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
        cv2.putText(panel, f"{name}: held-out PSNR (dB)", (left, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1)
        cv2.putText(panel, "srfpipe", (left + 5, 36), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colours["srf"], 1)
        cv2.putText(panel, "nerfacto", (left + 80, 36), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colours["nerfacto"], 1)
        cv2.putText(panel, "training seconds, start-up excluded (2 CPU cores)", (left, height - 8),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1)
        panels.append(panel)
    if panels:
        cv2.imwrite(str(path), np.concatenate(panels, axis=1))
        print(f"wrote {path}")


def print_table(report: dict, scenes: list[str], target_budget: int) -> None:
    print(f"{'scene':8} {'budget s':>8} | {'srf psnr':>8} {'ssim':>6} {'clock':>6} | {'nerfacto':>8} {'ssim':>6} {'clock':>6}")
    for name in scenes:
        scene = report.get(name)
        if not scene:
            continue
        for budget, pair in scene["budgets"].items():
            s, n = pair["srf"], pair["nerfacto"]
            print(f"{name:8} {budget:>8} | {s['psnr']:8.2f} {s['ssim']:6.3f} {s['seconds']:6.0f} | "
                  f"{n['psnr']:8.2f} {n['ssim']:6.3f} {n['seconds']:6.0f}")
        t = target_budget
        srf_t, nerf_t = scene[f"srf_seconds_to_nerfacto{t}"], scene[f"nerfacto_seconds_to_nerfacto{t}"]
        ratio = scene[f"time_to_nerfacto{t}_ratio"]
        fmt = lambda v: "-" if v is None else f"{v:.0f} s"  # noqa: E731
        print(f"{name:8} to nerfacto's {t} s PSNR ({scene[f'nerfacto_psnr_at_{t}s']:.2f} dB): srfpipe "
              f"{fmt(srf_t['seconds'])} ({srf_t['how']}), nerfacto {fmt(nerf_t['seconds'])} ({nerf_t['how']}), "
              f"ratio {'-' if ratio is None else f'{ratio:.1f}x'}")


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "_nerfacto":
        return nerfstudio_side(sys.argv[2:])
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help=f"fox only, budgets {QUICK_BUDGETS} s, no COLMAP refinement (~25 min)")
    parser.add_argument("--scenes", nargs="+", default=None, choices=SCENES)
    parser.add_argument("--nsvenv", type=Path, default=Path(os.environ.get("NSVENV", "/tmp/nsvenv")),
                        help="nerfstudio's environment (../shared/peers/nerfstudio-setup.sh DIR)")
    parser.add_argument("--preset", default=None, help="srfpipe preset for every scene (default: the scene's own)")
    parser.add_argument("--refine", type=int, default=None,
                        help="extra evaluations per method to find when it reaches nerfacto's target (default 3, quick 2)")
    parser.add_argument("--workdir", type=Path, default=None)
    parser.add_argument("--panel", nargs="+", default=None, choices=PANEL,
                        help="nerfacto alone on these captures of benchmarks/captures.py's panel, on the images "
                             "and split it built (--captures-workdir): held-out PSNR at 1, 2, 5 and 10 minutes "
                             "unless --budgets, and its training views at the last (its generalization gap)")
    parser.add_argument("--captures-workdir", type=Path, default=REPO / "benchmarks" / "work" / "captures")
    parser.add_argument("--budgets", default=None, help=argparse.SUPPRESS)  # e.g. 20,40: a test of the script
    parser.add_argument("--target-budget", type=float, default=None, help=argparse.SUPPRESS)
    # images.downscale for every scene (a test of the script: small images render fast)
    parser.add_argument("--downscale", type=float, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    args.nsvenv = args.nsvenv.resolve()
    if not (args.nsvenv / "bin" / "ns-train").exists():
        parser.error(f"{args.nsvenv}: no nerfstudio here; build it with bash ../shared/peers/nerfstudio-setup.sh {args.nsvenv}")
    if args.panel:
        args.budgets = [float(b) for b in args.budgets.split(",")] if args.budgets else PANEL_BUDGETS
        args.workdir = (args.workdir or REPO / "benchmarks" / "work" / "peers").resolve()
        args.captures_workdir = args.captures_workdir.resolve()
        return panel_main(args)
    scenes = args.scenes or (QUICK_SCENES if args.quick else SCENES)
    if "fox" in scenes and not (FOX / "transforms.json").exists():
        parser.error(f"{FOX}: the fox capture is not there (../shared/data/fox beside the repository)")
    args.budgets = ([float(b) for b in args.budgets.split(",")] if args.budgets
                    else (QUICK_BUDGETS if args.quick else BUDGETS))
    short = args.budgets not in (BUDGETS, QUICK_BUDGETS) or args.downscale is not None
    args.target_budget = args.target_budget or (TARGET_BUDGET if TARGET_BUDGET in args.budgets else max(args.budgets))
    if args.target_budget not in args.budgets:
        parser.error("the target budget must be one of the budgets")
    args.refine = args.refine if args.refine is not None else (2 if args.quick or short else 3)
    quick = args.quick = args.quick or short  # short budgets: a test of the script, quick's settings
    args.workdir = (args.workdir or REPO / "benchmarks" / "work" / ("peers-quick" if quick else "peers")).resolve()
    cache_dir = args.workdir / "evaluations"
    cache_dir.mkdir(parents=True, exist_ok=True)

    report: dict = {}
    for name in scenes:
        report[name] = run_scene(name, args, cache_dir)
    report.update({
        "budgets_seconds": args.budgets, "target_budget_seconds": args.target_budget, "scenes": scenes,
        "clock": "training seconds without start-up: srfpipe's train_seconds (sum of its steps), nerfacto's "
                 "summed iteration times (tensorboard 'Train Iter (time)'); loading, set-up, logging, "
                 "checkpoints and evaluation excluded for both",
        "metrics": "PSNR of the pooled squared error over all held-out pixels, mean SSIM per view "
                   "(srfpipe.srf.metrics), srfpipe's held-out views (every holdout_every-th image from 0) "
                   "at srfpipe's downscaled resolution, for both methods",
        "config": {"srfpipe_scene_configs": {n: scene_config(n, args.budgets, args.quick, args.preset, args.downscale)
                                             for n in scenes},
                   "nerfacto_args": NERFACTO_ARGS, "nerfacto_save_every_steps": NERFACTO_SAVE_EVERY,
                   "nerfstudio": "1.1.5 (../shared/peers/nerfstudio-setup.sh)", "refine_evaluations": args.refine,
                   "quick": args.quick, "short_budgets": short},
        "machine": machine_info(quick=quick),
    })
    report["measured_now"] = list(scenes)
    previous_file = result_path("peers", quick)
    if previous_file.exists():  # a run of some scenes keeps the others' last measurement
        previous = json.loads(previous_file.read_text())
        if previous.get("budgets_seconds") == args.budgets:
            earlier = earlier_measurements({n: previous[n] for n in previous.get("scenes", []) if n in previous},
                                           scenes)
            report.update(earlier)
            earlier_configs = previous.get("config", {}).get("srfpipe_scene_configs", {})
            report["config"]["srfpipe_scene_configs"].update({n: earlier_configs.get(n) for n in earlier})
            scenes = report["scenes"] = [n for n in SCENES if n in report]
    suffix = "_quick" if quick else ""
    plot(report, scenes, REPO / "benchmarks" / "results" / f"peers{suffix}.png")
    write_result(result_path("peers", quick), report)
    print_table(report, scenes, int(args.target_budget))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

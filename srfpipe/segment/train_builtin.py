"""Train the built-in orchard segmenter and export it to srfpipe/models/ (reproducible, CPU).

    python -m srfpipe.segment.train_builtin --workdir /tmp/seg-train

1. Builds training scenes through the Snakemake workflow itself (orchard seeds 101-116, never the
   demo's seed 0; 24-48 apples), up to images.zarr, so the network sees exactly what the demo's segment rule
   sees: 640x480 renders downscaled by 4 with INTER_AREA, labels from `ground_truth/labels`.
2. Trains a small U-Net (`TinyUNet`, ~1 M parameters) with one sigmoid output per class
   (multi-label, as the paper's independent heads) towards images.zarr's `ground_truth/labels`
   (the class covering most of each pixel, see `load_images_zarr`): BCE plus a soft-Dice term,
   which keeps thin branches and few-pixel apples from drowning in background.
3. Exports ONNX (dynamic batch and size; sizes padded to a multiple of 8) with metadata_props
   classes / activation / pad_multiple, and writes a JSON card beside it with the data, the
   settings and the IoU on a held-out training seed.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

log = logging.getLogger("srfpipe.segment.train_builtin")

CLASSES = ["apple", "branch", "leaf"]  # ground-truth label values 1, 2, 3
TRAIN_SEEDS = list(range(101, 117))
VALIDATION_SEED = 117
APPLES_PER_SEED = (24, 36, 48)  # more apples than the demo's 24 on some trees: apples are <1% of pixels
PAD_MULTIPLE = 8
REPO = Path(__file__).resolve().parents[2]


def build_model(width: int = 32):
    """A tiny U-Net: three 2x downsamplings, skip connections at every scale, 3 logit maps."""
    import torch
    from torch import nn

    def block(cin, cout):
        return nn.Sequential(
            nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True),
        )

    class TinyUNet(nn.Module):
        def __init__(self, c: int, classes: int):
            super().__init__()
            self.enc = nn.ModuleList([block(3, c), block(c, 2 * c), block(2 * c, 3 * c), block(3 * c, 4 * c)])
            self.up = nn.ModuleList([nn.ConvTranspose2d(k * c, k * c, 2, stride=2) for k in (4, 3, 2)])
            self.dec = nn.ModuleList([block(7 * c, 3 * c), block(5 * c, 2 * c), block(3 * c, c)])
            self.head = nn.Conv2d(c, classes, 1)
            self.pool = nn.MaxPool2d(2)

        def forward(self, x):  # x: RGB in [0, 1], (B, 3, H, W) with H, W multiples of 8
            x = (x - 0.5) / 0.25
            skips = []
            for i, enc in enumerate(self.enc):
                x = enc(x if i == 0 else self.pool(x))
                skips.append(x)
            x = skips.pop()
            for up, dec in zip(self.up, self.dec):
                x = dec(torch.cat([up(x), skips.pop()], dim=1))
            return self.head(x)

    return TinyUNet(width, len(CLASSES))


# ------------------------------------------------------------------------------------------ data


def build_training_scenes(workdir: Path, seeds: list[int], views: int) -> list[Path]:
    """Run the Snakemake workflow up to images.zarr for one orchard scene per seed."""
    import yaml

    scenes = workdir / "config" / "scenes"
    scenes.mkdir(parents=True, exist_ok=True)
    names = [f"orchard_s{seed}" for seed in seeds]
    for seed, name in zip(seeds, names):
        apples = APPLES_PER_SEED[seed % len(APPLES_PER_SEED)]
        scene = {"source": {"format": "orchard"}, "orchard": {"seed": seed, "views": views, "n_apples": apples},
                 "images": {"downscale": 4}}
        (scenes / f"{name}.yaml").write_text(yaml.safe_dump(scene))
    (workdir / "config" / "config.yaml").write_text(yaml.safe_dump(
        {"scenes_dir": "config/scenes", "scenes": names, "results_dir": "results", "final_artifact": "images"}))
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(workdir), "--cores", "2"]
    log.info("building training scenes: %s", " ".join(cmd))
    # the rules call the `srfpipe` script: the one installed beside this interpreter
    env = dict(os.environ, PATH=str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""))
    subprocess.run(cmd, check=True, env=env)
    return [workdir / "results" / name / "images.zarr" for name in names]


def load_images_zarr(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Images (N, H, W, 3) uint8 and per-class targets (N, C, H, W) uint8 in {0, 1} of one scene.

    The targets are images.zarr's `ground_truth/labels`: each working-resolution pixel takes the
    class covering most of its full-resolution footprint (`srfpipe.images.downscale_labels`,
    background on a tie), the same labels every benchmark scores against. The network thus learns
    p = P(the pixel's label is the class), and p >= 0.5 is its best guess of that label.
    """
    from srfpipe.artifacts import open_artifact

    group = open_artifact(path, stage="downscale")
    if "ground_truth" not in group or "labels" not in group["ground_truth"]:
        raise ValueError(f"{path}: no ground_truth/labels (not an orchard scene?)")
    images = np.asarray(group["images"][:])
    labels = np.asarray(group["ground_truth/labels"][:])
    values = np.arange(1, len(CLASSES) + 1, dtype=np.uint8).reshape(1, -1, 1, 1)
    return images, (labels[:, None] == values).astype(np.uint8)


def _pad(x, multiple: int = PAD_MULTIPLE):
    import torch.nn.functional as F

    h, w = x.shape[-2:]
    return F.pad(x, (0, -w % multiple, 0, -h % multiple), mode="replicate")


# ------------------------------------------------------------------------------------- training


def soft_dice_loss(logits, targets, eps: float = 1.0):
    """1 - Dice per class over the batch, averaged: counters the classes' tiny pixel shares."""
    probs = logits.sigmoid()
    dims = (0, 2, 3)
    inter = (probs * targets).sum(dims)
    return (1.0 - (2 * inter + eps) / (probs.sum(dims) + targets.sum(dims) + eps)).mean()


def iou_per_class(model, images: np.ndarray, targets: np.ndarray, threshold: float = 0.5) -> dict[str, float]:
    """IoU of (sigmoid >= threshold) against the ground truth, pooled over all images."""
    import torch

    inter = np.zeros(len(CLASSES))
    union = np.zeros(len(CLASSES))
    model.eval()
    with torch.no_grad():
        for start in range(0, len(images), 16):
            x = torch.from_numpy(images[start:start + 16]).permute(0, 3, 1, 2).float() / 255.0
            h, w = x.shape[-2:]
            pred = (model(_pad(x)).sigmoid()[..., :h, :w] >= threshold).numpy()
            truth = targets[start:start + 16].astype(bool)
            inter += (pred & truth).sum(axis=(0, 2, 3))
            union += (pred | truth).sum(axis=(0, 2, 3))
    return {c: float(i / u) if u else 1.0 for c, i, u in zip(CLASSES, inter, union)}


def train(images: np.ndarray, targets: np.ndarray, val_images, val_targets, epochs: int, batch_size: int,
          lr: float, width: int, seed: int):
    import torch
    from tqdm import tqdm

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    model = build_model(width)
    log.info("TinyUNet(width=%d): %d parameters", width, sum(p.numel() for p in model.parameters()))
    optimizer = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
    steps_per_epoch = int(np.ceil(len(images) / batch_size))
    scheduler = torch.optim.lr_scheduler.OneCycleLR(optimizer, max_lr=lr, total_steps=epochs * steps_per_epoch,
                                                    pct_start=0.15)
    bce = torch.nn.BCEWithLogitsLoss()
    x_all = torch.from_numpy(images).permute(0, 3, 1, 2).contiguous()
    y_all = torch.from_numpy(targets)
    history = []
    for epoch in range(epochs):
        model.train()
        order = rng.permutation(len(images))
        total = 0.0
        for start in tqdm(range(0, len(order), batch_size), desc=f"epoch {epoch + 1}/{epochs}", unit="batch",
                          leave=False):
            idx = torch.from_numpy(order[start:start + batch_size])
            x = x_all[idx].float() / 255.0
            y = y_all[idx].float()
            if rng.random() < 0.5:  # mirror views: the tree has no preferred handedness
                x, y = x.flip(-1), y.flip(-1)
            # small exposure/white-balance jitter: other captures are not rendered with our sun
            x = (x * torch.empty(len(x), 3, 1, 1).uniform_(0.85, 1.15)).clamp(0, 1)
            h, w = x.shape[-2:]
            logits = model(_pad(x))[..., :h, :w]
            loss = bce(logits, y) + soft_dice_loss(logits, y)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            scheduler.step()
            total += loss.item() * len(idx)
        ious = iou_per_class(model, val_images, val_targets)
        history.append({"epoch": epoch + 1, "loss": total / len(images), **{f"iou_{k}": v for k, v in ious.items()}})
        log.info("epoch %d: loss %.4f, validation IoU %s", epoch + 1, total / len(images),
                 {k: round(v, 3) for k, v in ious.items()})
    return model.eval(), history


def with_flip_averaging(proto, image: str = "image", logits: str = "logits"):
    """Wrap an exported segmenter so it returns the mean of its logits for x and mirrored x.

    The mirrored copy rides in the same batch (Concat, one pass, Split), so the weights are
    stored once. Mirroring is a symmetry of the task (see the training augmentation); averaging
    the two answers removes some of the network's left/right idiosyncrasies at object edges.
    """
    import onnx
    from onnx import TensorProto, helper

    graph = proto.graph
    for node in graph.node:
        node.input[:] = ["tta_pair" if n == image else n for n in node.input]
        node.output[:] = ["tta_raw" if n == logits else n for n in node.output]
    flip = {"starts": [-1], "ends": [-(2**63)], "axes": [3], "steps": [-1]}
    consts = [helper.make_tensor(f"tta_{k}", TensorProto.INT64, [1], v) for k, v in flip.items()]
    half = helper.make_tensor("tta_half", TensorProto.FLOAT, [], [0.5])
    slice_inputs = [f"tta_{k}" for k in flip]
    before = [
        helper.make_node("Slice", [image, *slice_inputs], ["tta_mirrored"]),
        helper.make_node("Concat", [image, "tta_mirrored"], ["tta_pair"], axis=0),
    ]
    after = [
        helper.make_node("Split", ["tta_raw"], ["tta_a", "tta_b"], axis=0),
        helper.make_node("Slice", ["tta_b", *slice_inputs], ["tta_b_back"]),
        helper.make_node("Add", ["tta_a", "tta_b_back"], ["tta_sum"]),
        helper.make_node("Mul", ["tta_sum", "tta_half"], [logits]),
    ]
    nodes = before + list(graph.node) + after
    del graph.node[:]
    graph.node.extend(nodes)
    graph.initializer.extend([*consts, half])
    onnx.checker.check_model(proto)
    return proto


def export_onnx(model, path: Path, metadata: dict, flip_average: bool = True) -> None:
    import warnings

    import onnx
    import torch

    path.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the legacy exporter needs no onnxscript
        torch.onnx.export(
            model, (torch.zeros(1, 3, 120, 160),), str(path), dynamo=False, opset_version=17,
            input_names=["image"], output_names=["logits"],
            dynamic_axes={"image": {0: "batch", 2: "height", 3: "width"},
                          "logits": {0: "batch", 2: "height", 3: "width"}},
        )
    proto = onnx.load(str(path))
    if flip_average:
        proto = with_flip_averaging(proto)
    onnx.helper.set_model_props(proto, {k: v if isinstance(v, str) else json.dumps(v) for k, v in metadata.items()})
    onnx.checker.check_model(proto)
    onnx.save(proto, str(path))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--workdir", type=Path, required=True, help="Snakemake work directory for the training scenes")
    parser.add_argument("--out", type=Path, default=REPO / "srfpipe" / "models", help="folder for the .onnx and .json")
    parser.add_argument("--views", type=int, default=40, help="views per training scene")
    parser.add_argument("--epochs", type=int, default=14)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--lr", type=float, default=4e-3)
    parser.add_argument("--width", type=int, default=32, help="channels at full resolution")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")

    import torch

    torch.set_num_threads(args.threads)
    started = time.time()
    paths = build_training_scenes(args.workdir.resolve(), TRAIN_SEEDS + [VALIDATION_SEED], args.views)
    data = [load_images_zarr(p) for p in paths]
    images = np.concatenate([d[0] for d in data[:-1]])
    targets = np.concatenate([d[1] for d in data[:-1]])
    val_images, val_targets = data[-1]
    log.info("training on %d images %s, validating on %d (seed %d)", len(images), images.shape[1:3],
             len(val_images), VALIDATION_SEED)
    model, history = train(images, targets, val_images, val_targets, args.epochs, args.batch_size, args.lr,
                           args.width, args.seed)
    torch.save(model.state_dict(), args.workdir / "orchard_segmenter.pt")  # for re-exports; not shipped
    onnx_path = args.out / "orchard_segmenter.onnx"
    export_onnx(model, onnx_path, {"classes": CLASSES, "activation": "sigmoid", "pad_multiple": PAD_MULTIPLE,
                                   "producer": "srfpipe.segment.train_builtin"})
    card = {
        "file": onnx_path.name,
        "description": "Built-in orchard segmenter: tiny U-Net, one sigmoid logit map per class "
                       "(multi-label), logits averaged over the image and its mirror image. Input 'image' (B, 3, H, W) float RGB in [0, 1], H and W padded "
                       "to a multiple of 8; output 'logits' (B, 3, H, W).",
        "classes": CLASSES,
        "parameters": int(sum(p.numel() for p in model.parameters())),
        "training": {"seeds": TRAIN_SEEDS, "validation_seed": VALIDATION_SEED, "views_per_seed": args.views,
                     "images": int(len(images)), "resolution": list(images.shape[1:3]),
                     "data": "orchard 640x480 renders, downscale 4 (INTER_AREA) via the Snakemake workflow; "
                             "targets: images.zarr ground_truth/labels (area majority of the full-resolution labels)",
                     "apples_per_seed": list(APPLES_PER_SEED),
                     "epochs": args.epochs, "batch_size": args.batch_size, "lr": args.lr, "width": args.width,
                     "seed": args.seed, "loss": "BCE with logits + soft Dice", "seconds": round(time.time() - started)},
        # against images.zarr's ground_truth/labels of the validation seed, threshold 0.5
        "validation_iou": {k: round(v, 4) for k, v in history[-1].items() if k.startswith("iou_")},
        "history": history,
        "reproduce": "python -m srfpipe.segment.train_builtin --workdir /tmp/seg-train",
        "versions": {"torch": torch.__version__},
    }
    (args.out / "orchard_segmenter.json").write_text(json.dumps(card, indent=1) + "\n")
    log.info("wrote %s (%.1f kB) and its card; validation IoU %s", onnx_path, onnx_path.stat().st_size / 1e3,
             card["validation_iou"])
    return 0


if __name__ == "__main__":
    sys.exit(main())

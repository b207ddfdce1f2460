"""Per-prompt masks: run one prompt over every image of images.zarr -> masks/{prompt}.zarr.

Back ends (scene key `segmentation.backend`): `onnx` (a class-channel or a text-prompted ONNX
model; `model: builtin` is the orchard model shipped with srfpipe) and `import` (masks computed
elsewhere, read from a folder). The artifact holds `probability` (N, H, W) uint8 = round(255 p),
one chunk per image, and the threshold the composite stage applies.
"""

from __future__ import annotations

import argparse
import copy
import logging
from pathlib import Path

import numpy as np

from srfpipe.config import add_options_arguments, stage_options

log = logging.getLogger(__name__)

# Keys whose value is a per-prompt table: each prompt's rule sees only its own entry.
_PER_PROMPT = ("prompt_text", "thresholds")


def prompt_options(section: dict, prompt: str) -> dict:
    """The segmentation keys that matter for one prompt (the params of its Snakemake rule).

    Drops the prompt list and the other prompts' entries of per-prompt tables, and resolves the
    prompt's threshold, so adding or changing another prompt leaves this prompt's params unchanged.
    """
    options = copy.deepcopy(section)
    options.pop("prompts", None)
    thresholds = options.pop("thresholds", {}) or {}
    options["threshold"] = thresholds.get(prompt, options["threshold"])
    for key in _PER_PROMPT:
        if key in options:
            options[key] = {k: v for k, v in (options[key] or {}).items() if k == prompt}
    if options.get("backend") == "import":
        for key in ("model", "kind", "classes", "activation", "input_size", "fit", "tile_overlap",
                    "pad_multiple", "mean", "std", "image_input", "text_input", "attention_mask_input",
                    "output", "tokenizer", "text_length", "batch_size", "device"):
            options.pop(key, None)
        spec = options.get("import") or {}
        if "values" in spec:
            spec["values"] = {k: v for k, v in spec["values"].items() if k == prompt}
    else:
        options.pop("import", None)
    return options


def segment_images(images_path: str | Path, prompt: str, options: dict, out: str | Path,
                   threads: int | None = None, progress: bool = True) -> Path:
    """Run `prompt` over images.zarr and write masks/{prompt}.zarr; returns the artifact path."""
    from srfpipe.artifacts import create_artifact, meta, open_artifact, update_attrs

    images_group = open_artifact(images_path, stage="downscale")
    images = images_group["images"]
    n, height, width, _ = images.shape
    image_meta = meta(images_group)
    names = list(image_meta.get("names") or [f"{i:05d}" for i in range(n)])
    if n == 0:
        raise ValueError(f"{images_path}: holds no images")

    frames = (np.asarray(images[i]) for i in range(n))
    backend = options["backend"]
    mask_values: dict = {}  # the imported masks' bit depth and value range (filled by import_masks)
    if backend == "onnx":
        from srfpipe.segment.onnx_backend import OnnxSegmenter

        segmenter = OnnxSegmenter(options, prompt, threads=threads)
        maps = segmenter.predict(frames, total=n, progress=progress)
        source = {"model": segmenter.describe()}
        inputs = [images_path, segmenter.path]
    elif backend == "import":
        from tqdm import tqdm

        from srfpipe.segment.import_backend import import_masks

        downscale = float(image_meta.get("downscale", 1) or 1)
        maps = tqdm(import_masks(names, (width, height), prompt, options, downscale, found=mask_values), total=n,
                    desc=f"import {prompt}", unit="img", disable=not progress)
        source = {"import": options["import"]}
        inputs = [images_path, options["import"]["path"]]
    else:
        raise ValueError(f"segmentation.backend {backend!r}: expected onnx or import")

    with create_artifact(out, stage="segment", config=options, inputs=inputs) as group:
        probability = group.create_array(
            "probability", shape=(n, height, width), chunks=(1, height, width), dtype="uint8",
            dimension_names=("image", "y", "x"), fill_value=0,
        )
        coverage, labelled, highest = [], [], 0.0
        for i, prob in enumerate(maps):
            labelled.append(prob is not None)
            if prob is None:  # no mask for this frame (import): unlabelled, left at the fill value
                coverage.append(None)
                continue
            if prob.shape != (height, width):
                raise ValueError(f"{backend} back end returned a {prob.shape} mask for image {names[i]}, "
                                 f"expected {(height, width)}")
            probability[i] = np.round(np.clip(prob, 0.0, 1.0) * 255.0).astype(np.uint8)
            coverage.append(float(np.mean(prob >= options["threshold"])))
            highest = max(highest, float(prob.max(initial=0.0)))
        if mask_values:
            mask_values["highest_probability"] = highest
            source["mask_values"] = mask_values
        update_attrs(group, prompt=prompt, threshold=options["threshold"], backend=backend, names=names,
                     width=width, height=height, coverage=coverage, labelled=labelled,
                     unlabelled_frames=[name for name, known in zip(names, labelled) if not known], **source)
    known = [c for c in coverage if c is not None]
    if mask_values and not any(known):
        from srfpipe.segment.composite import SOFT_MASK_FLOOR
        from srfpipe.segment.import_backend import describe_range

        log.warning("prompt %r: no pixel of its masks reaches the threshold %.2f (highest probability %.3g; %s); the "
                    "composite reads a class whose masks peak at %g or more on its own scale (labels.rescale_soft_masks)",
                    prompt, options["threshold"], highest, describe_range(mask_values), SOFT_MASK_FLOOR)
    log.info("%s: %d masks (%d frames unlabelled), mean coverage %.3f at threshold %.2f", out, len(known),
             n - len(known), float(np.mean(known)), options["threshold"])
    return Path(out)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--images", required=True, metavar="ZARR", help="images.zarr (stage downscale)")
    parser.add_argument("--prompt", required=True, help="the prompt (class) to segment, e.g. apple")
    parser.add_argument("--out", required=True, metavar="ZARR", help="output masks/{prompt}.zarr")
    parser.add_argument("--threads", type=int, default=None, help="onnxruntime intra-op threads (unset: all cores)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_options_arguments(parser, "segmentation")


def run(args) -> int:
    options = prompt_options(stage_options(args, "segmentation"), args.prompt)
    segment_images(args.images, args.prompt, options, args.out, threads=args.threads,
                   progress=not args.no_progress)
    return 0

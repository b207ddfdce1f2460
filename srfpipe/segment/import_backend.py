"""Import back end: precomputed masks from a folder (e.g. SAM 3 run on a GPU box).

Two layouts (`segmentation.import.format`):

* `masks`: one grayscale image per frame and prompt, named by `pattern` (default
  `{stem}_{prompt}.png`). Binary masks may be 0/255 or 0/1 (an image whose values are all 0 or 1 is
  read as binary); anything else is a soft probability, value / 255 (8-bit) or / 65535 (16-bit).
* `labels`: one label image per frame (default `{stem}.png`); a prompt's mask is the pixels whose
  value is one of `values[prompt]`.

A mask must have the size of images.zarr, or the capture's full resolution (the downscale factor
times it, to within a pixel); full-resolution masks are area-averaged down, so a binary mask
becomes a soft one at the edges, as the downscaled image blends colours there.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator

import logging

import numpy as np

log = logging.getLogger(__name__)

DEFAULT_PATTERNS = {"masks": "{stem}_{prompt}.png", "labels": "{stem}.png"}


def mask_filename(pattern: str, name: str, prompt: str) -> str:
    stem = Path(name).stem if Path(name).suffix else name
    try:
        return pattern.format(name=name, stem=stem, prompt=prompt)
    except (KeyError, IndexError, AttributeError, TypeError, ValueError) as exc:
        raise ValueError(
            f"segmentation.import.pattern {pattern!r}: unknown field {exc} (use {{name}}, {{stem}}, {{prompt}})"
        ) from None


def _read_single_channel(path: Path) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise FileNotFoundError(f"{path}: mask file does not exist")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"{path}: cannot read the mask image (not an image file?)")
    if image.ndim == 3:
        colour = image[..., :3]
        if not (np.array_equal(colour[..., 0], colour[..., 1]) and np.array_equal(colour[..., 0], colour[..., 2])):
            raise ValueError(f"{path}: expected a single-channel (grayscale) mask, got a colour image")
        image = colour[..., 0]
    if image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{path}: expected an 8- or 16-bit mask, got {image.dtype}")
    return image


def _fit_size(mask: np.ndarray, path: Path, size: tuple[int, int], downscale: float) -> np.ndarray:
    """Probability mask (H, W) float32 at `size` (width, height), from the working or full resolution."""
    import cv2

    width, height = size
    mh, mw = mask.shape
    if (mw, mh) == (width, height):
        return mask
    if downscale > 1 and abs(mw / downscale - width) <= 1 and abs(mh / downscale - height) <= 1:
        return cv2.resize(mask, (width, height), interpolation=cv2.INTER_AREA)
    full = f" or {round(width * downscale)}x{round(height * downscale)} (full resolution)" if downscale > 1 else ""
    raise ValueError(f"{path}: mask is {mw}x{mh}, expected {width}x{height} (the size of images.zarr){full}")


def _soft(mask: np.ndarray) -> np.ndarray:
    if mask.max(initial=0) <= 1:
        return mask.astype(np.float32)  # a 0/1 binary mask
    scale = 65535.0 if mask.dtype == np.uint16 else 255.0
    return mask.astype(np.float32) / scale


def import_masks(
    names: list[str], size: tuple[int, int], prompt: str, options: dict, downscale: float = 1.0
) -> Iterator[np.ndarray]:
    """Probability maps (H, W) float32 in [0, 1] for `prompt`, one per image name, in order.

    A frame whose mask file is missing yields None (unlabelled); all of them missing is an error.
    """
    spec = options.get("import") or {}
    if not spec.get("path"):
        raise ValueError("segmentation.backend is 'import' but segmentation.import.path is not set")
    folder = Path(spec["path"])
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: mask folder does not exist (segmentation.import.path)")
    layout = spec.get("format", "masks")
    pattern = spec.get("pattern") or DEFAULT_PATTERNS[layout]
    if layout == "labels":
        values = (spec.get("values") or {}).get(prompt)
        if values is None:
            raise ValueError(f"unknown prompt {prompt!r}: segmentation.import.values has no label value for it "
                             f"(it maps {sorted((spec.get('values') or {}))})")
        values = np.asarray([values] if isinstance(values, int) else values)
    paths = [folder / mask_filename(pattern, name, prompt) for name in names]
    missing = [name for name, path in zip(names, paths) if not path.is_file()]
    if len(missing) == len(names):
        raise FileNotFoundError(f"{paths[0]}: mask file does not exist, nor does any other of the {len(names)} "
                                f"frames' masks for prompt {prompt!r} (segmentation.import.pattern {pattern!r})")
    if missing:
        # a frame without a mask is unlabelled, not empty: it trains colour and geometry only
        log.warning("prompt %r: %d of %d frames have no mask in %s (unlabelled: %s%s)", prompt, len(missing),
                    len(names), folder, ", ".join(missing[:8]), " ..." if len(missing) > 8 else "")
    for path in paths:
        if not path.is_file():
            yield None
            continue
        raw = _read_single_channel(path)
        if layout == "labels":
            # select the class at full resolution, then area-average: soft edges like the image's
            probability = np.isin(raw, values).astype(np.float32)
            yield np.clip(_fit_size(probability, path, size, downscale), 0.0, 1.0)
        else:
            yield np.clip(_fit_size(_soft(raw), path, size, downscale), 0.0, 1.0)

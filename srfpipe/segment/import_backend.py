"""Import back end: precomputed masks from a folder (e.g. SAM 3 run on a GPU box).

Two layouts (`segmentation.import.format`):

* `masks`: one grayscale image per frame and prompt, named by `pattern` (default
  `{stem}_{prompt}.png`). How values map to probabilities is decided once per prompt, over all its
  masks (a first pass reads each mask's depth and value range, see `value_range`): when every mask
  holds only 0 and 1 they are binary 0/1; 8-bit masks are value / 255 (binary 0/255 or soft);
  16-bit masks whose values all lie in 0..255 are 8-bit masks stored in 16 bits, value / 255;
  other 16-bit masks are value / 65535. 8- and 16-bit masks mixed in one prompt are refused. A
  per-frame decision read a soft mask whose maximum is 1 as certain and 16-bit 0/255 masks as
  nearly empty.
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
import os

import numpy as np

log = logging.getLogger(__name__)

DEFAULT_PATTERNS = {"masks": "{stem}_{prompt}.png", "labels": "{stem}.png"}


# image names in images.zarr are the image files' stems already; {stem} drops only an image
# extension, so a name like `shot.0001` keeps its frame number
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", ".exr")


def mask_filename(pattern: str, name: str, prompt: str) -> str:
    stem = name[: -len(Path(name).suffix)] if Path(name).suffix.lower() in IMAGE_SUFFIXES else name
    try:
        return pattern.format(name=name, stem=stem, prompt=prompt)
    except (KeyError, IndexError, AttributeError, TypeError, ValueError) as exc:
        raise ValueError(
            f"segmentation.import.pattern {pattern!r}: unknown field {exc} (use {{name}}, {{stem}}, {{prompt}})"
        ) from None


def _inside(folder: str, path: str) -> bool:
    return os.path.commonpath([folder, path]) == folder


def mask_path(folder: Path, filename: str, pattern: str) -> Path:
    """`folder / filename`, refused unless it names a location inside the mask folder, lexically
    (`..`, absolute paths in the pattern) and with symlinks resolved (a symlinked mask folder is
    fine: the check is against where the folder itself resolves to)."""
    folder_abs = os.path.normpath(os.path.abspath(folder))
    full = os.path.normpath(os.path.join(folder_abs, filename))
    if not _inside(folder_abs, full) or full == folder_abs:
        raise ValueError(f"{folder}: mask file {filename!r} (segmentation.import.pattern {pattern!r}) points "
                         f"outside the mask folder {folder_abs}")
    real = os.path.realpath(full)
    if not _inside(os.path.realpath(folder_abs), real):
        raise ValueError(f"{full}: mask file is a symlink to {real}, outside the mask folder {folder_abs}")
    return Path(full)


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


def value_range(paths: list[Path], prompt: str) -> dict:
    """Pass 1 over one prompt's mask files: bit depth and values, and how they are read.

    Returns {"masks", "bits", "min", "max", "binary01", "binary0255", "scale", "read_as"}: every
    mask of the prompt is divided by `scale` (1: binary 0/1, 255, or 65535). Refuses 8- and 16-bit
    masks mixed in one prompt, naming one file of each.
    """
    first_of: dict[int, Path] = {}
    low, high, within01, within0255 = None, 0, True, True
    some01 = None  # a mask holding only 0 and 1 (with others reaching higher: read as nearly empty)
    for path in paths:
        raw = _read_single_channel(path)
        bits = 16 if raw.dtype == np.uint16 else 8
        first_of.setdefault(bits, path)
        lo, hi = (int(raw.min()), int(raw.max())) if raw.size else (0, 0)
        low, high = lo if low is None else min(low, lo), max(high, hi)
        only01 = hi <= 1
        within01 &= only01
        if only01 and hi == 1 and some01 is None:
            some01 = path
        if within0255:  # 0/255 binary (a 0/1 mask among them holds a 1 of 255)
            within0255 = hi == 0 if only01 else bool(np.isin(raw, (0, 255)).all())
    if len(first_of) > 1:
        raise ValueError(f"prompt {prompt!r}: masks of mixed bit depth, {first_of[8]} is 8-bit and {first_of[16]} "
                         "is 16-bit; export every mask of a prompt with the same depth")
    bits = next(iter(first_of), 8)
    low = 0 if low is None else low
    found = {"masks": len(paths), "bits": bits, "min": low, "max": high, "binary01": within01,
             "binary0255": within0255 and not within01}
    if within01:
        found.update(scale=1.0, read_as="binary 0/1")
    elif bits == 8:
        found.update(scale=255.0, read_as="probability value/255" + (" (binary 0/255)" if within0255 else ""))
    elif high <= 255:
        found.update(scale=255.0, read_as="probability value/255 (8-bit masks stored in 16 bits"
                     + (", binary 0/255)" if within0255 else ")"))
    else:
        found.update(scale=65535.0, read_as="probability value/65535")
    if not within01 and some01 is not None:
        log.warning("prompt %r: %s holds only 0 and 1 while other masks of the prompt reach %d: read as "
                    "value/%d like them (nearly empty), not as a binary mask", prompt, some01, high,
                    int(found["scale"]))
    return found


def describe_range(found: dict) -> str:
    """'40 masks, 8-bit, values 0..255, read as probability value/255'."""
    return (f"{found['masks']} masks, {found['bits']}-bit, values {found['min']}..{found['max']}, "
            f"read as {found['read_as']}")


def import_masks(
    names: list[str], size: tuple[int, int], prompt: str, options: dict, downscale: float = 1.0,
    found: dict | None = None,
) -> Iterator[np.ndarray]:
    """Probability maps (H, W) float32 in [0, 1] for `prompt`, one per image name, in order.

    A frame whose mask file is missing yields None (unlabelled); all of them missing is an error.
    `found`, when given, receives the prompt's value range (`value_range`, `masks` layout) before
    the first map is yielded.
    """
    spec = options.get("import") or {}
    if not spec.get("path"):
        raise ValueError("segmentation.backend is 'import' but segmentation.import.path is not set")
    folder = Path(spec["path"])
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: mask folder does not exist (segmentation.import.path)")
    layout = spec["format"]
    pattern = spec.get("pattern") or DEFAULT_PATTERNS[layout]
    if layout == "labels":
        values = (spec.get("values") or {}).get(prompt)
        if values is None:
            raise ValueError(f"unknown prompt {prompt!r}: segmentation.import.values has no label value for it "
                             f"(it maps {sorted((spec.get('values') or {}))})")
        values = np.asarray([values] if isinstance(values, int) else values)
    paths = [mask_path(folder, mask_filename(pattern, name, prompt), pattern) for name in names]
    for path in paths:
        if path.exists() and not path.is_file():  # a folder: no frame is meant to be left without its mask
            raise ValueError(f"{path}: mask path is not a file (segmentation.import.pattern {pattern!r})")
    missing = [name for name, path in zip(names, paths) if not path.is_file()]
    if len(missing) == len(names):
        raise FileNotFoundError(f"{paths[0]}: mask file does not exist, nor does any other of the {len(names)} "
                                f"frames' masks for prompt {prompt!r} (segmentation.import.pattern {pattern!r})")
    if missing:
        # a frame without a mask is unlabelled, not empty: it trains colour and geometry only
        log.warning("prompt %r: %d of %d frames have no mask in %s (unlabelled: %s%s)", prompt, len(missing),
                    len(names), folder, ", ".join(missing[:8]), " ..." if len(missing) > 8 else "")
    scale = None
    if layout != "labels":
        # pass 1: one decision for all the prompt's masks, not one per frame
        values_found = value_range([path for path in paths if path.is_file()], prompt)
        scale = values_found["scale"]
        log.info("prompt %r: %s", prompt, describe_range(values_found))
        if found is not None:
            found.update(values_found)
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
            yield np.clip(_fit_size(raw.astype(np.float32) / scale, path, size, downscale), 0.0, 1.0)

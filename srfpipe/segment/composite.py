"""Composite the per-prompt masks into labels.zarr: a label image and multi-hot bits per frame.

Class values follow the prompt order of the scene (the paper's: background 0, apple 1, branch 2,
leaf 3); the masks are passed in that order. A pixel is in class c when p_c >= t_c (the prompt's
threshold). The label image, which holds one class per pixel, resolves overlaps by taking the class
with the highest probability among those above their thresholds (the earlier prompt wins a tie);
a pixel above no threshold is background (0). The multi-hot bits keep every class a pixel is in,
for the C independent semantic heads; `probability` keeps each kept class's mask probability
(round(255 p)), which the heads train against by default (train.semantic_targets): a pixel half
covered by a thin stem, or a soft mask's blurred rim, is neither in nor out.

Soft masks are read on each class's own scale (`labels.rescale_soft_masks`): a class whose masks
peak at h < 1 over the whole capture (a blurred stem, a segmenter never sure of a small part) has
its probabilities divided by h, so its most certain pixel counts as certain and the threshold
applies to the share of that certainty. A class that peaks under SOFT_MASK_FLOOR is read as given.

A class that no frame contains (at most `labels.min_pixels` pixels over all frames) is reported,
recorded in `dropped_classes` and left out of the label image, the multi-hot channels and
`classes`, unless `labels.keep_empty_classes` is true. Kept classes keep their values, so a label
value means the same thing in every scene with the same prompt list.

The frames (names, size) come from images.zarr, and every mask must match them. With no prompts
at all (a capture without masks) the labels have zero classes: `classes` [], an all-background
label image and a multi-hot array of 0 channels.
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from srfpipe.config import add_options_arguments, stage_options

if TYPE_CHECKING:
    import zarr

log = logging.getLogger(__name__)

# RGBA for the NGFF image-label table; classes not listed get a tab10 colour.
DEFAULT_COLORS = {
    "background": [0, 0, 0, 0],
    "apple": [214, 39, 40, 255],
    "branch": [140, 86, 75, 255],
    "leaf": [44, 160, 44, 255],
}
_PALETTE = [[31, 119, 180], [255, 127, 14], [148, 103, 189], [227, 119, 194], [127, 127, 127],
            [188, 189, 34], [23, 190, 207], [214, 39, 40], [44, 160, 44], [140, 86, 75]]


def class_members(probabilities: np.ndarray, thresholds) -> np.ndarray:
    """Multi-hot bits (C, ...) bool: p_c >= t_c, from probabilities (C, ...) in [0, 1]."""
    t = np.asarray(thresholds, dtype=np.float32).reshape((-1,) + (1,) * (probabilities.ndim - 1))
    return probabilities >= t


def label_image(probabilities: np.ndarray, thresholds, values) -> np.ndarray:
    """Label image (...) uint8: values[c*] where c* = argmax of p_c over the classes above threshold.

    `probabilities` is (C, ...); a pixel above no threshold gets 0 (background). np.argmax returns
    the first maximum, so the earlier class wins a tie.
    """
    members = class_members(probabilities, thresholds)
    scores = np.where(members, probabilities, -1.0)
    winner = np.argmax(scores, axis=0)
    lut = np.asarray(values, dtype=np.uint8)
    return np.where(members.any(axis=0), lut[winner], 0).astype(np.uint8)


def _color(name: str, index: int, colors: dict) -> list[int]:
    if name in colors:
        return list(colors[name])
    if name in DEFAULT_COLORS:
        return DEFAULT_COLORS[name]
    return _PALETTE[index % len(_PALETTE)] + [255]


def image_label_table(classes: list[str], values: list[int], counts: dict[str, int], colors: dict,
                      source: str | None = None) -> dict:
    """NGFF `image-label` metadata: colours and properties per label value (0 = background)."""
    names = ["background", *classes]
    all_values = [0, *values]
    table = {
        "version": "0.5",
        "colors": [{"label-value": v, "rgba": _color(n, i, colors)} for i, (n, v) in enumerate(zip(names, all_values))],
        "properties": [{"label-value": v, "class": n, "pixel_count": int(counts.get(n, 0))}
                       for n, v in zip(names, all_values)],
    }
    if source:
        table["source"] = {"image": source}
    return table


@dataclass(frozen=True)
class Frames:
    """The posed frames of images.zarr that the labels describe: one label image per frame."""

    path: Path
    group: zarr.Group  # the open images.zarr (stage downscale)
    names: list[str]
    height: int
    width: int

    @property
    def count(self) -> int:
        return len(self.names)


def read_frames(images_path: str | Path) -> Frames:
    """Open images.zarr and read its frame names and image size."""
    from srfpipe.artifacts import meta, open_artifact

    group = open_artifact(images_path, stage="downscale")
    if "images" not in group:
        raise ValueError(f"{images_path}: missing array 'images'")
    n, height, width = group["images"].shape[:3]
    # the same fallback as the segment stage, so unnamed frames still match their masks
    names = [str(name) for name in (meta(group).get("names") or [f"{i:05d}" for i in range(n)])]
    if len(names) != n:
        raise ValueError(f"{images_path}: {n} images but {len(names)} names")
    return Frames(Path(images_path), group, names, int(height), int(width))


def _check_mask_frames(path, shape, names, frames: Frames) -> None:
    """A mask must hold one (H, W) map per frame of images.zarr, for the same frames in order."""
    expected = (frames.count, frames.height, frames.width)
    if tuple(shape) != expected:
        raise ValueError(f"{path}: masks of shape {tuple(shape)} (frames, height, width) do not match "
                         f"{frames.path}: {frames.count} frames of {frames.width}x{frames.height}")
    if names is None or [str(n) for n in names] == frames.names:
        return
    if len(names) != frames.count:
        raise ValueError(f"{path}: masks name {len(names)} frames, {frames.path} has {frames.count}")
    first = next(i for i, (a, b) in enumerate(zip(names, frames.names)) if str(a) != b)
    raise ValueError(f"{path}: masks are for other frames than {frames.path}: frame {first} is "
                     f"{names[first]!r} in the masks, {frames.names[first]!r} in the images")


def _open_masks(paths: list[str | Path], frames: Frames):
    from srfpipe.artifacts import meta, open_artifact, require_input

    arrays, prompts, thresholds, value_ranges, counts = [], [], [], [], []
    labelled = np.ones(frames.count, dtype=bool)
    for path in paths:
        group = open_artifact(path, stage="segment")
        info = meta(group)
        if "probability" not in group or group["probability"].dtype != np.uint8:
            found = group["probability"].dtype if "probability" in group else "no array"
            raise ValueError(f"{path}: 'probability' must be uint8 (round(255 p)), found {found}")
        _check_mask_frames(path, group["probability"].shape, info.get("names"), frames)
        require_input(path, frames.path, "downscale")  # masks of this images.zarr, not of a sibling's
        if info["prompt"] in prompts:
            raise ValueError(f"{path}: prompt {info['prompt']!r} is given twice")
        arrays.append(group["probability"])
        prompts.append(info["prompt"])
        thresholds.append(float(info["threshold"]))
        value_ranges.append(info.get("mask_values"))  # imported masks: bit depth, values, how read
        if info.get("labelled") is not None:  # masks of some frames only (import)
            labelled &= np.asarray(info["labelled"], dtype=bool)
            counts.append(f"{path}: {int(np.sum(info['labelled']))} of {frames.count}")
    if paths and not labelled.any():  # every frame unlabelled: the semantic heads would learn nothing
        raise ValueError(f"composite: no frame has a mask of every prompt {prompts} (frames with a mask: "
                         f"{'; '.join(counts)}); a frame is labelled only where every prompt's masks cover it")
    return arrays, prompts, thresholds, labelled, value_ranges


def _probabilities(arrays, index: int, channels, scale: np.ndarray | None = None) -> np.ndarray:
    """(C, H, W) float32 probabilities of one frame for the given mask channels, each multiplied by
    its `scale` (per mask, all of them; see class_scales) and clipped at 1."""
    probabilities = np.stack([np.asarray(arrays[k][index]) for k in channels]).astype(np.float32) / 255.0
    if scale is None:
        return probabilities
    factor = np.asarray(scale, dtype=np.float32)[list(channels)].reshape(-1, 1, 1)
    return np.minimum(probabilities * factor, np.float32(1.0))


# A segmenter's soft masks need not reach 1 where it finds a class: a stem a pixel wide blurred by the
# masks' soft edges peaks at 0.51 in the plant small in the frame (2 of its pixels reach the threshold
# 0.5, where the truth has 256 in the 18 views); a text-prompted segmenter scores some prompts lower than
# others. Read on the class's own scale, its best pixel counts as certain. A class whose masks peak
# under this floor is read as given (so dropped as empty): noise of a prompt the images do not show,
# or masks read on the wrong scale (16-bit values read as 8-bit), which the error must still name.
SOFT_MASK_FLOOR = 0.25


def class_scales(highest: np.ndarray, rescale: bool) -> np.ndarray:
    """(C,) float32: 1 / each class's highest mask probability where that lies in [SOFT_MASK_FLOOR,
    1) and `rescale` is on (labels.rescale_soft_masks), else 1."""
    highest = np.asarray(highest, dtype=np.float32)
    soft = rescale & (highest >= SOFT_MASK_FLOOR) & (highest < 1.0)
    # np.where evaluates both branches: the floor keeps an empty class (highest 0) from dividing by 0
    return np.where(soft, 1.0 / np.maximum(highest, SOFT_MASK_FLOOR), 1.0).astype(np.float32)


def _why_empty(prompt: str, highest: float, threshold: float, value_range: dict | None) -> str:
    """'apple: highest probability 0.39 (threshold 0.5), imported 8-bit masks, values 0..100, ...'."""
    why = f"{prompt}: highest probability {highest:.3g} (threshold {threshold:g})"
    if value_range:
        from srfpipe.segment.import_backend import describe_range

        why += f", imported {describe_range(value_range)}"
    return why


def _kept_classes(arrays, prompts: list[str], t: np.ndarray, settings, n: int, progress: bool,
                  value_ranges: list | None = None):
    """Pass 1: which prompts' classes the scene contains; returns (kept indices, empty prompts,
    each prompt's scale: class_scales).

    An empty class is reported with the highest probability its masks reach and, for imported
    masks, the bit depth and value range found (a 16-bit or soft export read on the wrong scale
    shows there)."""
    from tqdm import tqdm

    # each prompt's histogram of its 8-bit mask values: the pixels over the threshold follow for any scale
    histograms = np.zeros((len(prompts), 256), dtype=np.int64)
    for i in tqdm(range(n), desc="count classes", unit="img", disable=not progress):
        for k in range(len(prompts)):
            histograms[k] += np.bincount(np.asarray(arrays[k][i]).ravel(), minlength=256)
    levels = np.arange(256, dtype=np.float32) / np.float32(255.0)
    highest = np.array([levels[np.flatnonzero(h).max(initial=0)] for h in histograms], dtype=np.float32)
    scale = class_scales(highest, settings.rescale_soft_masks)
    counts = np.array([h[class_members(np.minimum(levels * s, np.float32(1.0))[None], [tk])[0]].sum()
                       for h, s, tk in zip(histograms, scale, t)], dtype=np.int64)
    rescaled = [f"{p} (highest {h:.3g})" for p, h, s in zip(prompts, highest, scale) if s != 1.0]
    if rescaled:
        log.info("soft masks read on their own scale (labels.rescale_soft_masks): %s", ", ".join(rescaled))
    min_pixels, keep_empty = settings.min_pixels, settings.keep_empty_classes
    empty = [p for p, c in zip(prompts, counts) if c <= min_pixels]
    kept = [k for k, p in enumerate(prompts) if keep_empty or p not in empty]
    value_ranges = value_ranges or [None] * len(prompts)
    why = "; ".join(_why_empty(p, float(highest[k]), float(t[k]), value_ranges[k])
                    for k, p in enumerate(prompts) if p in empty)
    if empty:
        action = "kept (labels.keep_empty_classes)" if keep_empty else "dropped from the heads"
        log.warning("classes %s: at most %d pixels in all %d frames, %s (%s)", empty, min_pixels, n, action, why)
    if not kept:
        raise ValueError(f"composite: no frame contains any of the classes {prompts} ({why}); nothing to learn "
                         "(set labels.keep_empty_classes: true to keep them anyway)")
    return kept, empty, scale, highest


def composite_masks(images_path: str | Path, mask_paths: list[str | Path], options: dict, out: str | Path,
                    progress: bool = True) -> Path:
    """Read images.zarr and masks/{prompt}.zarr (in class order, maybe none) and write labels.zarr."""
    from tqdm import tqdm

    from srfpipe.artifacts import create_artifact, update_attrs
    from srfpipe.settings import LabelsSettings

    settings = LabelsSettings.from_options(options)
    frames = read_frames(images_path)
    arrays, prompts, thresholds, labelled, value_ranges = _open_masks(list(mask_paths), frames)
    n, height, width, names = frames.count, frames.height, frames.width, frames.names
    all_values = list(range(1, len(prompts) + 1))
    t = np.asarray(thresholds, dtype=np.float32)
    keep_empty = settings.keep_empty_classes
    if prompts:
        kept, empty, scale, highest = _kept_classes(arrays, prompts, t, settings, n, progress, value_ranges)
    else:
        kept, empty, scale, highest = [], [], np.ones(0, np.float32), np.ones(0, np.float32)
        log.info("no prompts (segmentation.prompts is empty): labels with zero classes for %d frames", n)
    classes = [prompts[k] for k in kept]
    values = [all_values[k] for k in kept]

    config = {**settings.as_dict(), "prompts": prompts, "thresholds": dict(zip(prompts, thresholds))}
    with create_artifact(out, stage="composite", config=config, inputs=[images_path, *mask_paths]) as group:
        label = group.create_array("label", shape=(n, height, width), chunks=(1, height, width), dtype="uint8",
                                   dimension_names=("image", "y", "x"), fill_value=0)
        multihot = group.create_array("multihot", shape=(n, height, width, len(kept)),
                                      chunks=(1, height, width, max(1, len(kept))), dtype="uint8",
                                      dimension_names=("image", "y", "x", "class"), fill_value=0)
        probability = group.create_array("probability", shape=(n, height, width, len(kept)),
                                         chunks=(1, height, width, max(1, len(kept))), dtype="uint8",
                                         dimension_names=("image", "y", "x", "class"), fill_value=0)
        label_counts = np.zeros(len(kept) + 1, dtype=np.int64)
        member_counts = np.zeros(len(kept), dtype=np.int64)
        for i in tqdm(range(n), desc="composite", unit="img", disable=not progress):
            if kept:
                probs = _probabilities(arrays, i, kept, scale)
                frame = label_image(probs, t[kept], values)
                bits = class_members(probs, t[kept])
            else:  # zero classes: every pixel is background
                frame = np.zeros((height, width), dtype=np.uint8)
                bits = np.zeros((0, height, width), dtype=bool)
            label[i] = frame
            multihot[i] = np.moveaxis(bits, 0, -1).astype(np.uint8)
            if kept:
                probability[i] = np.round(np.moveaxis(probs, 0, -1) * 255.0).astype(np.uint8)
            label_counts += np.bincount(np.searchsorted([0, *values], frame.ravel()), minlength=len(kept) + 1)
            member_counts += bits.sum(axis=(1, 2))
        pixel_counts = {c: int(m) for c, m in zip(classes, member_counts)}
        label_pixel_counts = {n_: int(c) for n_, c in zip(["background", *classes], label_counts)}
        table = image_label_table(classes, values, label_pixel_counts, settings.colors)
        label.attrs["image-label"] = table
        hull_mask = partial(_hull_mask, arrays, kept, scale)
        background = resolve_background(frames, hull_mask, settings.background, bool(classes), labelled)
        update_attrs(group, **background)
        carving, carve_mask = labelled, hull_mask
        if background["background"] == "empty" and classes:
            backdrop = ((background["background_spread"], background["backdrop_colour"])
                        if background.get("backdrop_colour") is not None  # measured by labels.background auto
                        else backdrop_statistics(frames, hull_mask, labelled))
            if backdrop is not None:
                spread, colour = backdrop
                level = backdrop_level(spread)
                carving, carve_mask = None, silhouette_hull_mask(frames, hull_mask, labelled, colour, level)
                log.info("every frame carves the hull by its silhouette against the empty backdrop (colour %s, "
                         "more than %.0f levels away) and its masks: masks of some parts leave the rest of the "
                         "object (%d of %d frames without masks)", np.round(colour).astype(int).tolist(), level,
                         int((~labelled).sum()), n)
                update_attrs(group, hull_silhouettes={"frames": n, "frames_without_masks": int((~labelled).sum()),
                                                      "backdrop_colour": colour, "level": level})
        update_attrs(group, **scene_bounds(frames, carve_mask, settings.bounds, bool(classes),
                                           background["background"], carving))
        update_attrs(group, classes=classes, class_values=dict(zip(classes, values)), names=names,
                     pixel_counts=pixel_counts, label_pixel_counts=label_pixel_counts,
                     dropped_classes=[] if keep_empty else empty, empty_classes=empty,
                     thresholds=dict(zip(prompts, thresholds)), width=width, height=height,
                     highest_probability={p: float(h) for p, h in zip(prompts, highest)},
                     mask_scale={prompts[k]: float(scale[k]) for k in kept},
                     labelled=labelled.tolist(),
                     unlabelled_frames=[name for name, known in zip(names, labelled) if not known],
                     **{"image-label": table})
    log.info("%s: classes %s, pixel counts %s, dropped %s", out, classes, pixel_counts,
             [] if keep_empty else empty)
    return Path(out)


def _hull_mask(arrays, channels, scale, index: int) -> np.ndarray:
    """(H, W) bool: the pixels of frame `index` where any of the classes reaches HULL_MIN_PROBABILITY
    (on its own scale: class_scales)."""
    from srfpipe.segment.hull import HULL_MIN_PROBABILITY

    if not channels:
        return np.zeros(arrays[0].shape[1:], bool) if arrays else np.zeros((0, 0), bool)
    return _probabilities(arrays, index, channels, scale).max(axis=0) >= HULL_MIN_PROBABILITY


# labels.background auto: the pixels no mask marks (2.5 % of the widest side away from any mask)
# are an empty backdrop when 90 % of them lie within this many 8-bit levels of their median colour.
# Measured: the built-in plant's near-black backdrop 3 levels, a living room (../shared/data/bottle) 55.
EMPTY_BACKGROUND_SPREAD = 12
BACKGROUND_MARGIN = 0.025
BACKGROUND_SAMPLES = 200_000


def backdrop_statistics(frames: Frames, hull_mask, labelled: np.ndarray | None) -> tuple[float, list[float]] | None:
    """Over the labelled frames' pixels that no mask marks (nor comes near): the 90th percentile of
    each pixel's largest channel difference from their median colour (8-bit levels), and that
    median colour; None without any such pixel."""
    import cv2

    margin = max(1, int(round(BACKGROUND_MARGIN * max(frames.height, frames.width))))
    kernel = np.ones((2 * margin + 1,) * 2, np.uint8)
    known = np.flatnonzero(np.ones(frames.count, bool) if labelled is None else labelled)
    step = max(1, int(len(known) * frames.height * frames.width // BACKGROUND_SAMPLES))
    samples = []
    for i in known:
        near = cv2.dilate(hull_mask(i).astype(np.uint8), kernel).astype(bool)
        samples.append(np.asarray(frames.group["images"][i])[~near][::step])
    pixels = np.concatenate(samples).astype(np.int16) if samples else np.zeros((0, 3), np.int16)
    if len(pixels) == 0:
        return None
    median = np.median(pixels, axis=0)
    return float(np.percentile(np.abs(pixels - median).max(axis=1), 90)), median.tolist()


# A frame on an empty backdrop shows where matter is, whatever its masks cover: every pixel that is
# not backdrop. Such a pixel differs from the backdrop's median colour by more than this many times the
# backdrop's spread (and at least EMPTY_BACKGROUND_SPREAD levels) in some channel.
SILHOUETTE_SPREADS = 3


def silhouette_hull_mask(frames: Frames, hull_mask, labelled: np.ndarray, colour, level: float):
    """Frame i's pixels that show matter on an empty backdrop: those farther than `level` (8-bit
    levels, in some channel) from the backdrop's `colour`, and those its masks mark (`hull_mask`,
    labelled frames).

    The masks cover the prompted parts only: the berries' masks of a plant leave its stem and
    leaves, whose hull would then be a box round the berries (issue 30: a thin plant's masks of
    its organs, 0.1 % of each image, carved its stem away). The silhouette shows all of it; the
    masks add what is too dark to stand out. With masks on a few frames only, the silhouettes of
    the others carve as well: two or three views leave a cone of space behind the object that
    agrees with every mask (on the built-in plant, 2 views give a box 71x the object's).
    """
    colour = np.asarray(colour, dtype=np.int16)

    def mask(index: int) -> np.ndarray:
        image = np.asarray(frames.group["images"][index]).astype(np.int16)
        shows = np.abs(image - colour).max(axis=-1) > level
        return shows | hull_mask(index) if labelled[index] else shows

    return mask


def resolve_background(frames: Frames, hull_mask, asked: str, has_classes: bool,
                       labelled: np.ndarray | None) -> dict:
    """labels.background resolved: `empty` or `scene`, where it came from, and the spread measured.

    `auto` looks at what the masks leave: a uniform backdrop (a plant rendered on black, an object
    on a studio sweep or against a clear sky) is empty; a room, a table or the ground is a scene.
    Without classes nothing marks the objects: a scene.
    """
    if asked == "scene" or (asked == "empty" and not has_classes):
        return {"background": asked, "background_from": "config"}
    if not has_classes:
        return {"background": "scene", "background_from": "no classes"}
    found = backdrop_statistics(frames, hull_mask, labelled)
    spread = None if found is None else found[0]
    colour = None if found is None else found[1]
    if asked == "empty":  # the scene says so; the backdrop's colour is still measured (backdrop_level)
        return {"background": "empty", "background_from": "config", "background_spread": spread,
                "backdrop_colour": colour, "backdrop_level": backdrop_level(spread)}
    empty = spread is not None and spread <= EMPTY_BACKGROUND_SPREAD
    log.info("background %s: the unmasked pixels lie within %s levels of their median colour (90 %%; empty "
             "at most %d)", "empty" if empty else "a scene", "?" if spread is None else f"{spread:.0f}",
             EMPTY_BACKGROUND_SPREAD)
    return {"background": "empty" if empty else "scene", "background_from": "images", "background_spread": spread,
            "backdrop_colour": colour, "backdrop_level": backdrop_level(spread) if empty else None}


def backdrop_level(spread: float | None) -> float | None:
    """8-bit levels (largest channel difference) within which a pixel shows the empty backdrop's
    colour; farther, it shows matter (SILHOUETTE_SPREADS times the backdrop's spread, at least
    EMPTY_BACKGROUND_SPREAD)."""
    return None if spread is None else max(EMPTY_BACKGROUND_SPREAD, SILHOUETTE_SPREADS * spread)


def scene_bounds(frames: Frames, hull_mask, policy: str, has_classes: bool, background: str = "scene",
                 labelled: np.ndarray | None = None) -> dict:
    """The model's bounds every later stage uses, and the semantic region inside them.

    The model's box is the poses' (config, ground truth, sparse points or frusta): what the
    images show, whatever the masks cover. Only a capture whose background is empty (`background`
    "empty": a pixel no mask marks looks through empty space) may shrink it to the masks' visual
    hull, under `auto` when the poses' bounds were only estimated, or always under `masks`.

    The semantic region (`semantic_bounds_world`) is where the classes are: the hull's box when
    the masks carve one and the poses' bounds were estimated, else the model's box. It bounds the
    occupancy cache and the simulator, so that modelling a whole room does not grow them. Only
    the `labelled` frames (those with masks; default all) carve; `hull_mask(i)` gives frame i's
    pixels that mark the hull (on an empty backdrop, every frame marks it by its silhouette as
    well: silhouette_hull_mask).
    """
    from srfpipe.artifacts import meta
    from srfpipe.segment.hull import bounds_from_masks

    info = meta(frames.group)
    if info.get("bounds_world") is None:  # images.zarr without a scene box: nothing to refine
        return {}
    poses_bounds = np.asarray(info["bounds_world"], dtype=np.float64)
    poses_source = info.get("bounds_source") or "poses"
    kept = {"bounds_world": poses_bounds, "bounds_source": poses_source, "bounds_poses": poses_bounds,
            "semantic_bounds_world": poses_bounds}
    trusted = poses_source in ("config", "ground_truth")
    if policy == "poses" or not has_classes or (policy == "auto" and trusted):
        return kept
    # only frames with masks carve: an unlabelled frame's empty label would carve everything
    known = np.flatnonzero(np.ones(frames.count, bool) if labelled is None else labelled)
    found = bounds_from_masks(
        np.asarray(frames.group["camera_to_world"][...])[known], np.asarray(frames.group["intrinsics"][...])[known],
        lambda: (hull_mask(i) for i in known), poses_bounds)
    if found is None:
        return {**kept, "bounds_hull": None}
    box, record = found
    kept.update(semantic_bounds_world=box, bounds_hull=record)
    if background != "empty" and policy == "auto":
        log.info("semantic region from the masks' visual hull: %s (%.3g of the volume of the %s bounds, "
                 "which the model keeps: the background is not empty)",
                 np.round(box, 4).tolist(), record["volume_vs_poses_bounds"], poses_source)
        return kept
    log.info("bounds from the visual hull: %s (%.3g of the volume of the %s bounds)",
             np.round(box, 4).tolist(), record["volume_vs_poses_bounds"], poses_source)
    return {**kept, "bounds_world": box, "bounds_source": "mask_hull"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--images", required=True, metavar="ZARR",
                        help="images.zarr (stage downscale): the frames the labels describe")
    parser.add_argument("--masks", nargs="*", default=[], metavar="ZARR",
                        help="masks/{prompt}.zarr in class order (label values 1, 2, ... follow it); "
                             "none: labels with zero classes")
    parser.add_argument("--out", required=True, metavar="ZARR", help="output labels.zarr")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_options_arguments(parser, "labels")


def run(args) -> int:
    composite_masks(args.images, args.masks, stage_options(args, "labels"), args.out, progress=not args.no_progress)
    return 0

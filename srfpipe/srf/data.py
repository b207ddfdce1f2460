"""Posed images and labels for training and evaluation, read from images.zarr and labels.zarr.

Poses are moved into the scene frame once here (`transform_poses(scene_from_world, ...)`), so the
model only ever sees scene-frame rays; depth and density are converted back with the scene scale.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from srfpipe.artifacts import meta, open_artifact, require_input
from srfpipe.cameras import scene_from_world_transform, transform_poses

ORCHARD_GT_CLASSES = ["background", "apple", "branch", "leaf"]  # label value = index


@dataclass
class PosedImages:
    images: torch.Tensor  # (N, H, W, 3) uint8
    multihot: torch.Tensor | None  # (N, H, W, C) uint8, or None without labels
    label: np.ndarray | None  # (N, H, W) uint8 composited label image
    gt_label: np.ndarray | None  # (N, H, W) uint8 ground-truth classes (generated captures only)
    gt_classes: list[str] | None  # name of each gt_label value
    poses_scene: torch.Tensor  # (N, 4, 4) float32 camera_to_scene
    intrinsics: torch.Tensor  # (N, 4) float32
    width: int
    height: int
    names: list[str]
    classes: list[str]
    scene_from_world: np.ndarray
    world_from_scene: np.ndarray
    bounds_world: np.ndarray
    provenance: dict
    bounds_source: str | None = None  # where bounds_world came from (config, ground_truth, mask_hull, ...)
    # where the classes are (labels.zarr: the masks' visual hull, else bounds_world): bounds the
    # occupancy cache and the simulator
    semantic_bounds_world: np.ndarray | None = None
    background_empty: bool = False  # labels.background: pixels no mask marks look through empty space
    # on an empty background: its colour (RGB, 8-bit levels) and the largest channel difference
    # within which a pixel shows it (labels.zarr backdrop_colour, backdrop_level); None when unknown
    backdrop: tuple[list[float], float] | None = None
    labelled: np.ndarray | None = None  # (N,) bool: frames with masks (None: every frame, or no labels)
    # (N, H, W, C) uint8 round(255 p): each class's mask probability (labels.zarr `probability`); None
    # without labels, in labels.zarr written before the composite kept it, or unless the loader was asked for it
    probability: torch.Tensor | None = None

    @property
    def count(self) -> int:
        return int(self.images.shape[0])


def split_views(count: int, holdout_every: int) -> tuple[np.ndarray, np.ndarray]:
    """(train, held-out) view indices: every `holdout_every`-th view, starting with view 0, is held out.

    The trainer and the evaluation use this one function, so the split can never disagree.
    """
    if holdout_every < 2:
        raise ValueError(f"holdout_every must be >= 2, got {holdout_every}")
    index = np.arange(count)
    held_out = index % holdout_every == 0
    if held_out.all() or count < 2:
        raise ValueError(f"{count} views leave nothing to train on with holdout_every={holdout_every}")
    return index[~held_out], index[held_out]


def remap_ground_truth(gt: np.ndarray, gt_classes: list[str], classes: list[str]) -> np.ndarray:
    """Ground-truth label image in the trained class order (1 + index in `classes`, 0 otherwise).

    `gt` holds values that index `gt_classes` (PosedImages.gt_label / gt_classes); the trainer's
    held-out check and the evaluation both score against this.
    """
    lookup = np.zeros(256, dtype=np.uint8)
    for value, name in enumerate(gt_classes):
        if name in classes:
            lookup[value] = classes.index(name) + 1
    return lookup[gt]


def _check_matrix(value, name: str, path: Path) -> np.ndarray:
    matrix = np.asarray(value, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise ValueError(f"{path}: attribute {name} must be a finite 4x4 matrix")
    return matrix


def load_posed_images(images_path, labels_path=None, probability: bool = False) -> PosedImages:
    """Read images.zarr (+ labels.zarr) into memory, checking shapes against each other and that
    labels.zarr was composited from this images.zarr (the fingerprint it records; `require_input`).

    `probability`: also read labels.zarr's per-class mask probabilities (N, H, W, C), which only
    training against them needs; `PosedImages.probability` stays None without it, or when the
    labels.zarr (an older composite) holds none."""
    images_path = Path(images_path)
    group = open_artifact(images_path, stage="downscale")
    attrs = meta(group)
    for key in ("images", "intrinsics", "camera_to_world"):
        if key not in group:
            raise ValueError(f"{images_path}: missing array '{key}'")
    images = np.asarray(group["images"][...])
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(f"{images_path}: images must be (N, H, W, 3) uint8, got {images.shape} {images.dtype}")
    n, h, w, _ = images.shape
    intrinsics = np.asarray(group["intrinsics"][...], dtype=np.float64)
    poses = np.asarray(group["camera_to_world"][...], dtype=np.float64)
    if intrinsics.shape != (n, 4) or poses.shape != (n, 4, 4):
        raise ValueError(
            f"{images_path}: {n} images but intrinsics {intrinsics.shape} and camera_to_world {poses.shape}"
        )
    if not (np.all(np.isfinite(intrinsics)) and np.all(np.isfinite(poses))):
        raise ValueError(f"{images_path}: intrinsics or camera_to_world contain NaN/inf")
    scene_from_world = _check_matrix(attrs.get("scene_from_world"), "scene_from_world", images_path)
    world_from_scene = _check_matrix(attrs.get("world_from_scene", np.linalg.inv(scene_from_world)),
                                     "world_from_scene", images_path)
    bounds = np.asarray(attrs.get("bounds_world"), dtype=np.float64)
    if bounds.shape != (2, 3):
        raise ValueError(f"{images_path}: attribute bounds_world must be [[min xyz], [max xyz]]")
    bounds_source = attrs.get("bounds_source")
    gt_label = gt_classes = None
    if "ground_truth" in group and "labels" in group["ground_truth"]:
        gt_label = np.asarray(group["ground_truth"]["labels"][...])
        if gt_label.shape != (n, h, w) or gt_label.dtype != np.uint8:
            raise ValueError(f"{images_path}: ground_truth/labels must be ({n}, {h}, {w}) uint8 like its {n} images of "
                             f"{w}x{h}, got {gt_label.shape} {gt_label.dtype}")
        # images.zarr written before the downscale stage recorded the names are all orchards
        gt_classes = [str(c) for c in attrs.get("ground_truth_classes") or ORCHARD_GT_CLASSES]
    multihot = label = mask_probability = None
    classes: list[str] = []
    semantic_bounds = None
    background_empty = False
    backdrop = None
    labelled = None
    if labels_path is not None:
        labels_path = Path(labels_path)
        lgroup = open_artifact(labels_path, stage="composite")
        lattrs = meta(lgroup)
        classes = [str(c) for c in lattrs.get("classes", [])]
        if "multihot" not in lgroup:
            raise ValueError(f"{labels_path}: missing array 'multihot'")
        multihot = np.asarray(lgroup["multihot"][...]).astype(np.uint8)
        if multihot.shape[:3] != (n, h, w) or multihot.shape[3] != len(classes):
            raise ValueError(
                f"{labels_path}: multihot {multihot.shape} does not match {n} images of {w}x{h} "
                f"and {len(classes)} classes {classes}"
            )
        if probability and "probability" in lgroup:
            mask_probability = np.asarray(lgroup["probability"][...]).astype(np.uint8)
            if mask_probability.shape != multihot.shape:
                raise ValueError(f"{labels_path}: probability {mask_probability.shape} does not match multihot "
                                 f"{multihot.shape}")
        require_input(labels_path, images_path, "downscale")
        if lattrs.get("bounds_world") is not None:
            # the labels stage refines the bounds (visual hull of the masks): from here on they
            # are the scene's bounds, and the scene frame is normalized to them
            bounds = np.asarray(lattrs["bounds_world"], dtype=np.float64)
            if bounds.shape != (2, 3) or not np.all(bounds[1] > bounds[0]):
                raise ValueError(f"{labels_path}: attribute bounds_world must be [[min xyz], [max xyz]] with min < max")
            scene_from_world = scene_from_world_transform(bounds[0], bounds[1])
            bounds_source = lattrs.get("bounds_source", bounds_source)
            world_from_scene = np.linalg.inv(scene_from_world)
        if lattrs.get("semantic_bounds_world") is not None:
            semantic_bounds = np.asarray(lattrs["semantic_bounds_world"], dtype=np.float64)
            if semantic_bounds.shape != (2, 3) or not np.all(semantic_bounds[1] > semantic_bounds[0]):
                raise ValueError(f"{labels_path}: attribute semantic_bounds_world must be [[min xyz], [max xyz]] "
                                 "with min < max")
        if lattrs.get("labelled") is not None:
            labelled = np.asarray(lattrs["labelled"], dtype=bool)
            if labelled.shape != (n,):
                raise ValueError(f"{labels_path}: attribute labelled has {labelled.size} entries for {n} images")
            if labelled.all():
                labelled = None
        # labels.zarr written before labels.background existed: a hull box meant an empty background
        background_empty = lattrs.get("background", "empty" if bounds_source == "mask_hull" else "scene") == "empty"
        colour, level = lattrs.get("backdrop_colour"), lattrs.get("backdrop_level")
        if background_empty and colour is not None and level is not None:
            if len(colour) != 3 or not float(level) >= 0:
                raise ValueError(f"{labels_path}: attributes backdrop_colour {colour} / backdrop_level {level} must be "
                                 "an RGB colour and a level >= 0")
            backdrop = ([float(c) for c in colour], float(level))
        if "label" in lgroup:
            label = np.asarray(lgroup["label"][...])
            if label.shape != (n, h, w) or label.dtype != np.uint8:
                raise ValueError(f"{labels_path}: label must be ({n}, {h}, {w}) uint8 like the {n} images of {w}x{h} "
                                 f"({images_path}), got {label.shape} {label.dtype}")
            # label values follow the config's prompt order (a dropped class leaves a gap):
            # renumber them 1..C in the order of `classes`, like the SRF's heads
            values = lattrs.get("class_values") or {name: i + 1 for i, name in enumerate(classes)}
            lookup = np.zeros(256, dtype=np.uint8)
            for i, name in enumerate(classes):
                if name in values:
                    lookup[int(values[name])] = i + 1
            label = lookup[label]
    return PosedImages(
        images=torch.from_numpy(images),
        multihot=None if multihot is None else torch.from_numpy(multihot),
        probability=None if mask_probability is None else torch.from_numpy(mask_probability),
        label=label, gt_label=gt_label, gt_classes=gt_classes,
        poses_scene=torch.from_numpy(transform_poses(scene_from_world, poses)).float(),
        intrinsics=torch.from_numpy(intrinsics).float(),
        width=w, height=h, names=[str(x) for x in attrs.get("names", [str(i) for i in range(n)])],
        classes=classes, scene_from_world=scene_from_world, world_from_scene=world_from_scene,
        bounds_world=bounds, provenance=attrs, bounds_source=bounds_source,
        semantic_bounds_world=bounds if semantic_bounds is None else semantic_bounds,
        background_empty=background_empty, backdrop=backdrop, labelled=labelled,
    )


def rays_for_pixels(poses: torch.Tensor, intrinsics: torch.Tensor, u: torch.Tensor, v: torch.Tensor,
                    within: torch.Tensor | float = 0.5):
    """Rays through the points (u + a, v + b) of pixels (u, v) of cameras (R, 4, 4) with intrinsics (R, 4):
    `within` (R, 2) holds (a, b) in [0, 1), the point inside each pixel; 0.5 is its centre.

    OpenCV camera frame (see srfpipe.cameras). Returns origins and unit directions (R, 3).
    """
    fx, fy, cx, cy = intrinsics.unbind(-1)
    a, b = (within, within) if isinstance(within, float) else within.unbind(-1)
    d_cam = torch.stack([(u.float() + a - cx) / fx, (v.float() + b - cy) / fy, torch.ones_like(fx)], -1)
    d = torch.einsum("rij,rj->ri", poses[:, :3, :3], d_cam)
    d = d / torch.linalg.norm(d, dim=-1, keepdim=True)
    return poses[:, :3, 3].clone(), d


def image_rays(pose: torch.Tensor, intrinsics: torch.Tensor, width: int, height: int, supersample: int = 1):
    """Rays through every pixel of one camera, row-major: (H*W, 3), or with `supersample` s > 1 the
    s x s points of a regular grid inside each pixel, (H*W*s*s, 3) with a pixel's s*s rays in a row
    (their mean is the pixel: a pixel integrates the light over its footprint)."""
    s = int(supersample)
    v, u = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    u, v = u.reshape(-1).repeat_interleave(s * s), v.reshape(-1).repeat_interleave(s * s)
    within = ((pixel_cells(s) + 0.5) / s).repeat(height * width, 1)
    n = u.shape[0]
    return rays_for_pixels(pose.expand(n, 4, 4), intrinsics.expand(n, 4), u, v, within)


def pixel_cells(supersample: int, device="cpu") -> torch.Tensor:
    """(s*s, 2) the (column, row) of each cell of a pixel's regular s x s grid, row by row: the
    order of a pixel's rays in `image_rays` and in training's footprint rays (a point within the
    pixel, from its corner, is (cell + offset) / s for an offset in [0, 1)^2)."""
    cells = torch.arange(supersample * supersample, device=device)
    return torch.stack([cells % supersample, cells // supersample], -1).float()

"""A tiny analytic scene for tests and quick experiments: coloured spheres on a textured ground.

Rendered exactly by ray-sphere / ray-plane intersection (numpy), written as images.zarr and
labels.zarr in the documented layouts (docs/artifacts.md), with ground-truth labels and depth
like the orchard. Classes follow the default table: 0 background, 1 apple, 2 branch, 3 leaf.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from srfpipe.artifacts import create_artifact
from srfpipe.cameras import look_at, pixel_rays, scene_from_world_transform

CLASSES = ["apple", "branch", "leaf"]
# centre (x, y, z), radius, class value, base colour
SPHERES = [
    ((0.0, 0.0, 0.5), 0.35, 3, (0.20, 0.55, 0.15)),
    ((0.35, 0.2, 0.35), 0.12, 1, (0.85, 0.10, 0.10)),
    ((-0.3, -0.25, 0.3), 0.10, 1, (0.90, 0.60, 0.10)),
    ((0.05, -0.05, 0.05), 0.08, 2, (0.45, 0.30, 0.15)),
]


def render(origins, directions):
    """Exact rgb (…, 3), label (…,), depth along the ray (…,; inf for sky) of the scene."""
    shape = origins.shape[:-1]
    o, d = origins.reshape(-1, 3), directions.reshape(-1, 3)
    best = np.full(o.shape[0], np.inf)
    label = np.zeros(o.shape[0], np.uint8)
    rgb = np.zeros((o.shape[0], 3))
    light = np.array([0.4, -0.3, 0.85])
    light /= np.linalg.norm(light)
    for centre, radius, value, colour in SPHERES:
        oc = o - np.asarray(centre)
        b = (oc * d).sum(-1)
        disc = b * b - ((oc * oc).sum(-1) - radius * radius)
        t = -b - np.sqrt(np.maximum(disc, 0))
        hit = (disc > 0) & (t > 1e-6) & (t < best)
        best = np.where(hit, t, best)
        label = np.where(hit, value, label)
        normal = (oc + t[:, None] * d) / radius
        p = oc + t[:, None] * d
        stripes = 0.85 + 0.15 * np.sin(25 * p[:, 0]) * np.sin(25 * p[:, 2])
        shade = (0.35 + 0.65 * np.clip(normal @ light, 0, 1)) * stripes
        rgb = np.where(hit[:, None], np.asarray(colour) * shade[:, None], rgb)
    # ground plane z = 0, checkerboard, label background
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = -o[:, 2] / d[:, 2]
    ground = (tg > 1e-6) & (tg < best) & np.isfinite(tg)
    p = o + np.nan_to_num(tg)[:, None] * d
    checker = ((np.floor(p[:, 0] * 4) + np.floor(p[:, 1] * 4)) % 2)
    ground_rgb = (0.35 + 0.2 * checker)[:, None] * np.array([0.8, 0.7, 0.5])
    rgb = np.where(ground[:, None], ground_rgb, rgb)
    label = np.where(ground, 0, label)
    best = np.where(ground, tg, best)
    sky = ~np.isfinite(best)
    sky_rgb = np.array([0.55, 0.7, 0.95]) * (0.7 + 0.3 * np.clip(d[:, 2:3], 0, 1))
    rgb = np.where(sky[:, None], sky_rgb, rgb)
    return rgb.reshape(*shape, 3), label.reshape(shape), best.reshape(shape)


def write_scene(folder, views: int = 16, width: int = 48, height: int = 36, radius: float = 2.2,
                heights=(0.4, 1.2), fov_deg: float = 50.0, pose_errors: dict | None = None,
                arc_deg: float = 360.0) -> tuple[Path, Path]:
    """Render the scene from rings of cameras; write folder/images.zarr and folder/labels.zarr.

    `arc_deg` < 360: the cameras span that arc of the ring round +x, all looking one way (a
    forward-facing capture).
    `pose_errors` {view: (3,) axis-angle in radians}: those views are rendered from their true
    camera but recorded turned by that rotation in their camera frame, as a calibration that got
    them wrong (for camera refinement); `pose_errors` is recorded in images.zarr."""
    folder = Path(folder)
    bounds = np.array([[-0.6, -0.6, 0.0], [0.6, 0.6, 0.9]])
    scene_from_world = scene_from_world_transform(*bounds)
    fx = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    intrinsics = np.array([fx, fx, width / 2, height / 2])
    poses, images, labels, depths = [], [], [], []
    for i in range(views):
        angle = (2 * np.pi * i / views if arc_deg >= 360.0
                 else np.radians(arc_deg) * (i / max(views - 1, 1) - 0.5))
        z = heights[i % len(heights)]
        pose = look_at((radius * np.cos(angle), radius * np.sin(angle), z), (0.0, 0.0, 0.35))
        origins, directions = pixel_rays(pose, intrinsics, width, height)
        rgb, label, depth = render(origins, directions)
        z_depth = depth * (directions @ pose[:3, 2])
        if pose_errors and i in pose_errors:
            import cv2

            pose = pose.copy()
            pose[:3, :3] = pose[:3, :3] @ cv2.Rodrigues(np.asarray(pose_errors[i], dtype=np.float64))[0]
        poses.append(pose)
        images.append(np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8))
        labels.append(label)
        depths.append(np.where(np.isfinite(z_depth), z_depth, 0).astype(np.float32))
    images, labels, poses = np.stack(images), np.stack(labels), np.stack(poses)
    names = [f"frame_{i:05d}" for i in range(views)]
    images_path = folder / "images.zarr"
    with create_artifact(images_path, "downscale", names=names, width=width, height=height, downscale=1,
                         scene_from_world=scene_from_world, world_from_scene=np.linalg.inv(scene_from_world),
                         bounds_world=bounds, ground_truth="synthetic",
                         pose_errors={int(k): list(map(float, v)) for k, v in (pose_errors or {}).items()}) as g:
        g.create_array("images", shape=images.shape, chunks=(1, height, width, 3), dtype=np.uint8)[...] = images
        g.create_array("intrinsics", shape=(views, 4), dtype=np.float64)[...] = np.tile(intrinsics, (views, 1))
        g.create_array("camera_to_world", shape=poses.shape, dtype=np.float64)[...] = poses
        gt = g.create_group("ground_truth")
        gt.create_array("labels", shape=labels.shape, chunks=(1, height, width), dtype=np.uint8)[...] = labels
        gt.create_array("depth", shape=labels.shape, chunks=(1, height, width), dtype=np.float32)[...] = np.stack(depths)
    labels_path = write_labels(folder / "labels.zarr", labels, CLASSES, names, inputs=[images_path])
    return images_path, labels_path


def write_labels(path, label: np.ndarray, classes: list[str], names: list[str], inputs=(),
                 probability: np.ndarray | None = None) -> Path:
    """labels.zarr (stage composite) from a label image (N, H, W): value v is classes[v - 1], 0 none.
    `probability` (N, H, W, C) uint8, round(255 p): the masks' probabilities, and the multi-hot bits
    where they reach 0.5 (the composite's default threshold); without it, no probabilities."""
    n, height, width = label.shape
    multihot = (label[..., None] == np.arange(1, len(classes) + 1)).astype(np.uint8)
    if probability is not None:
        multihot = (probability >= 128).astype(np.uint8)
    with create_artifact(path, "composite", inputs=list(inputs), classes=list(classes), names=names) as g:
        g.create_array("label", shape=label.shape, chunks=(1, height, width), dtype=np.uint8)[...] = label
        for name, array in (("multihot", multihot), ("probability", probability)):
            if array is not None:
                g.create_array(name, shape=array.shape, chunks=(1, height, width, max(len(classes), 1)),
                               dtype=np.uint8)[...] = array
    return Path(path)

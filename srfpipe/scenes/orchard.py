"""Generate the built-in procedural orchard: one apple tree rendered from rings of views, with ground truth.

World frame: metres, right-handed, z up; the ground is the plane z = 0 and the trunk base is at
the origin. Cameras stand on horizontal rings of radius `ring_radius` around the trunk at the
heights `ring_heights` and look at the canopy centre, like a person walking round the tree.

Output (a nerfstudio capture folder plus ground truth, see docs/artifacts.md)::

    OUT/transforms.json            nerfstudio (OpenGL camera: looks down -z, +y up), camera_model OPENCV
    OUT/images/frame_00000.png     RGB renders
    OUT/ground_truth/labels/frame_00000.png   uint8: 0 background (sky, ground), 1 apple, 2 branch, 3 leaf
    OUT/ground_truth/depth/frame_00000.npy    float32 z-depth along the camera +z (metres), 0 = no hit
    OUT/ground_truth/meshes/{apple,branch,leaf,ground}.ply
    OUT/ground_truth/apples.json   [{"centre": [x, y, z], "radius": r}, ...]
    OUT/ground_truth/scene.json    classes, units, bounds_world of the tree, parameters, intrinsics, poses
    OUT/video.avi                  with `video: true`: the views as a Motion-JPEG video (frame i = view i),
                                   along one continuous turn (`orbit_poses`) instead of the rings

The shared layout and the camera rings are in `srfpipe.scenes.capture`. Rendering is CPU ray
casting (open3d RaycastingScene) with Lambert shading, sun shadows, a sky gradient and 3D
value-noise textures; see `srfpipe.scenes.raycast`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from srfpipe.config import ConfigError, stage_options, validate_scene
from srfpipe.scenes.capture import (
    add_generator_arguments, check_views, intrinsics_for, orbit_poses, ring_poses, write_capture,
)
from srfpipe.scenes.raycast import light_direction

log = logging.getLogger(__name__)

CLASSES = ["background", "apple", "branch", "leaf"]
VIDEO_FPS = 10.0  # orchard.video: the frame rate written (timestamps only: every view is one frame)
BOUNDS_MARGIN = 0.1  # metres around the tree's mesh in bounds_world
SUN_ELEVATION_DEG = (40.0, 65.0)  # range over seeds


# ----------------------------------------------------------------------------- cameras and bounds


def sun_direction(rng: np.random.Generator) -> np.ndarray:
    """Unit vector toward the sun: any azimuth, a mid-day elevation (varies by seed, for training variety)."""
    return light_direction(rng, SUN_ELEVATION_DEG)


def _tree_bounds(tree) -> list[list[float]]:
    points = np.concatenate([tree.branch.vertices, tree.leaf.vertices, tree.apple.vertices])
    lo = points.min(0) - BOUNDS_MARGIN
    hi = points.max(0) + BOUNDS_MARGIN
    lo[2] = max(lo[2], -BOUNDS_MARGIN)  # the trunk base sinks a few cm into the ground
    return [lo.tolist(), hi.tolist()]


# ----------------------------------------------------------------------------- entry points


def generate_orchard(out_dir: str | Path, progress: bool = True, **options) -> Path:
    """Build the tree, render every view and write the capture folder atomically; returns its path.

    `options` are the scene schema's `orchard` keys (seed, n_apples, branch_depth, leaf_density,
    tree_height, views, width, height, fov_deg, ring_heights, ring_radius, arc_deg); missing keys take the
    schema defaults, unknown or invalid ones raise ValueError.
    """
    from srfpipe.scenes.raycast import OrchardRenderer
    from srfpipe.scenes.tree import build_tree

    params = validate_scene({"orchard": dict(options)}, "generate_orchard options")["orchard"]
    out = Path(out_dir)
    started = time.perf_counter()
    rng = np.random.default_rng([params["seed"], 1])  # views and sun: independent of the tree stream
    tree = build_tree(params["seed"], params["n_apples"], params["branch_depth"],
                      params["leaf_density"], params["tree_height"])
    if len(tree.apple_centres) < params["n_apples"]:
        log.warning("placed %d of %d apples (no more free space on the branches)",
                    len(tree.apple_centres), params["n_apples"])
    sun = sun_direction(rng)
    target = np.array([0.0, 0.0, 0.55 * params["tree_height"]])
    try:
        if params.get("video"):
            poses = orbit_poses(params["views"], params["ring_heights"], params["ring_radius"], target)
        else:
            poses = ring_poses(params["views"], params["ring_heights"], params["ring_radius"], target, rng,
                               arc_deg=params.get("arc_deg"))
    except ValueError as exc:  # look_at: a camera straight below or above the canopy centre, or overflowing
        raise ConfigError(f"orchard (ring_radius {params['ring_radius']:g}, ring_heights {params['ring_heights']}): "
                          f"a camera cannot be aimed at the tree ({exc})") from None
    width, height = params["width"], params["height"]
    check_views("orchard", poses, intrinsics_for(width, height, params["fov_deg"]), width, height,
                params.get("distortion"))
    scene = {
        "world_frame": "metres, z up, ground plane z = 0, trunk base at the origin",
        "units": "metre",
        "bounds_world": _tree_bounds(tree),
        "parameters": params,
        "look_at_target": target.tolist(),
        "sun_direction": sun.tolist(),
        "tree": tree.info,
    }
    written = write_capture(
        out, OrchardRenderer(tree, params["seed"], sun), poses, intrinsics_for(width, height, params["fov_deg"]),
        width, height, CLASSES, {name: getattr(tree, name) for name in ("apple", "branch", "leaf", "ground")},
        scene, files={"apples.json": [{"centre": c.tolist(), "radius": tree.apple_radius}
                                      for c in tree.apple_centres]},
        progress=progress, desc="orchard views", distortion=params.get("distortion"),
        video_fps=VIDEO_FPS if params.get("video") else None,
        subject_keys="orchard.tree_height, ring_radius, ring_heights, fov_deg",
    )
    log.info(
        "orchard seed %d: %d segments, %d leaves, %d apples; %d views of %dx%d in %.1f s -> %s",
        params["seed"], tree.info["n_segments"], tree.info["n_leaves"], tree.info["n_apples"],
        len(poses), width, height, time.perf_counter() - started, out,
    )
    log.info("pixels per class over all views: %s", written["class_pixel_counts"])
    return out


def add_arguments(parser) -> None:
    add_generator_arguments(parser, "orchard")


def run(args) -> int:
    generate_orchard(args.out, progress=not args.no_progress, **stage_options(args, "orchard"))
    return 0

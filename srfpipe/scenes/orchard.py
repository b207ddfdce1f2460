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
    OUT/ground_truth/scene.json    classes, bounds_world of the tree, parameters, intrinsics, poses

Rendering is CPU ray casting (open3d RaycastingScene) with Lambert shading, sun shadows, a sky
gradient and 3D value-noise textures; see `srfpipe.scenes.raycast`.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from srfpipe.artifacts import atomic_directory
from srfpipe.config import add_options_arguments, section_defaults, stage_options, validate_scene

log = logging.getLogger(__name__)

CLASSES = ["background", "apple", "branch", "leaf"]
BOUNDS_MARGIN = 0.1  # metres around the tree's mesh in bounds_world
SUN_ELEVATION_DEG = (40.0, 65.0)  # range over seeds


# ----------------------------------------------------------------------------- cameras


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """camera_to_world (4x4, OpenCV camera: +x right, +y down, +z forward) at `eye` looking at `target`."""
    eye = np.asarray(eye, np.float64)
    forward = np.asarray(target, np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, np.float64))
    if np.linalg.norm(right) < 1e-9:
        raise ValueError(f"look_at: viewing direction {forward} is parallel to up {up}")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose


def ring_poses(
    views: int, ring_heights: list[float], ring_radius: float, target: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """(views, 4, 4) camera_to_world on rings; views split evenly, rings offset by half a step.

    A little jitter in azimuth, radius and height keeps the views from being exactly symmetric
    (as a person walking would be), which also helps SfM and held-out evaluation.
    """
    n_rings = len(ring_heights)
    counts = [views // n_rings + (1 if r < views % n_rings else 0) for r in range(n_rings)]
    poses = []
    for r, (height, count) in enumerate(zip(ring_heights, counts)):
        if count == 0:
            continue
        step = 2 * np.pi / count
        azimuths = np.arange(count) * step + (r / n_rings) * step + rng.normal(0, 0.08 * step, count)
        radii = ring_radius * (1.0 + rng.normal(0, 0.02, count))
        heights = height + rng.normal(0, 0.03, count)
        for a, rad, h in zip(azimuths, radii, heights):
            eye = np.array([rad * np.cos(a), rad * np.sin(a), h])
            poses.append(look_at(eye, target))
    return np.stack(poses)


def intrinsics_for(width: int, height: int, fov_deg: float) -> np.ndarray:
    """(fx, fy, cx, cy): square pixels, horizontal field of view `fov_deg`, centred principal point."""
    fx = 0.5 * width / np.tan(np.radians(fov_deg) / 2.0)
    return np.array([fx, fx, width / 2.0, height / 2.0])


def sun_direction(rng: np.random.Generator) -> np.ndarray:
    """Unit vector toward the sun: any azimuth, a mid-day elevation (varies by seed, for training variety)."""
    azimuth = rng.uniform(0, 2 * np.pi)
    elevation = np.radians(rng.uniform(*SUN_ELEVATION_DEG))
    horizontal = np.cos(elevation)
    return np.array([horizontal * np.cos(azimuth), horizontal * np.sin(azimuth), np.sin(elevation)])


# ----------------------------------------------------------------------------- output


EMPTY_PLY = (
    "ply\nformat ascii 1.0\ncomment srfpipe orchard: no geometry of this class\n"
    "element vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
    "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
)


def _write_mesh(path: Path, mesh) -> None:
    import open3d as o3d

    if len(mesh.triangles) == 0:
        # open3d refuses to write an empty mesh, but n_apples=0 or leaf_density=0 are valid scenes
        path.write_text(EMPTY_PLY)
        return
    legacy = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh.vertices.astype(np.float64)),
        o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)),
    )
    if not o3d.io.write_triangle_mesh(str(path), legacy):
        raise RuntimeError(f"{path}: open3d could not write the mesh")


def _transforms_json(poses_cv: np.ndarray, intrinsics: np.ndarray, width: int, height: int, names) -> dict:
    from srfpipe.cameras import opencv_to_opengl

    fx, fy, cx, cy = (float(v) for v in intrinsics)
    frames = [
        {"file_path": f"images/{name}.png", "transform_matrix": opencv_to_opengl(pose).tolist()}
        for name, pose in zip(names, poses_cv)
    ]
    return {
        "camera_model": "OPENCV",
        "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": int(width), "h": int(height),
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "frames": frames,
    }


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
    tree_height, views, width, height, fov_deg, ring_heights, ring_radius); missing keys take the
    schema defaults, unknown or invalid ones raise ValueError.
    """
    import cv2
    from tqdm import tqdm

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
    poses = ring_poses(params["views"], params["ring_heights"], params["ring_radius"], target, rng)
    width, height = params["width"], params["height"]
    intrinsics = intrinsics_for(width, height, params["fov_deg"])
    names = [f"frame_{i:05d}" for i in range(len(poses))]
    renderer = OrchardRenderer(tree, params["seed"], sun)

    with atomic_directory(out) as tmp:
        gt = tmp / "ground_truth"
        for folder in (tmp / "images", gt / "labels", gt / "depth", gt / "meshes"):
            folder.mkdir(parents=True)
        class_pixels = np.zeros(len(CLASSES), np.int64)
        views = tqdm(list(zip(names, poses)), desc="orchard views", unit="view", disable=not progress)
        for name, pose in views:
            view = renderer.render(pose, intrinsics, width, height)
            if not cv2.imwrite(str(tmp / "images" / f"{name}.png"), view.rgb[..., ::-1]):
                raise RuntimeError(f"{tmp / 'images' / name}.png: OpenCV could not write the image")
            cv2.imwrite(str(gt / "labels" / f"{name}.png"), view.label)
            np.save(gt / "depth" / f"{name}.npy", view.depth)
            class_pixels += np.bincount(view.label.ravel(), minlength=len(CLASSES))
        for mesh_name in ("apple", "branch", "leaf", "ground"):
            _write_mesh(gt / "meshes" / f"{mesh_name}.ply", getattr(tree, mesh_name))
        apples = [{"centre": c.tolist(), "radius": tree.apple_radius} for c in tree.apple_centres]
        (gt / "apples.json").write_text(json.dumps(apples, indent=1))
        (tmp / "transforms.json").write_text(
            json.dumps(_transforms_json(poses, intrinsics, width, height, names), indent=1)
        )
        fx, fy, cx, cy = intrinsics.tolist()
        scene = {
            "classes": CLASSES,
            "world_frame": "metres, z up, ground plane z = 0, trunk base at the origin",
            "bounds_world": _tree_bounds(tree),
            "parameters": params,
            "intrinsics": {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": width, "height": height},
            "camera_convention": "camera_to_world below is OpenCV (+x right, +y down, +z forward)",
            "names": names,
            "camera_to_world": poses.tolist(),
            "look_at_target": target.tolist(),
            "sun_direction": sun.tolist(),
            "tree": tree.info,
            "class_pixel_counts": dict(zip(CLASSES, class_pixels.tolist())),
        }
        (gt / "scene.json").write_text(json.dumps(scene, indent=1))
    seconds = time.perf_counter() - started
    log.info(
        "orchard seed %d: %d segments, %d leaves, %d apples; %d views of %dx%d in %.1f s -> %s",
        params["seed"], tree.info["n_segments"], tree.info["n_leaves"], tree.info["n_apples"],
        len(names), width, height, seconds, out,
    )
    log.info("pixels per class over all views: %s", dict(zip(CLASSES, class_pixels.tolist())))
    return out


def add_arguments(parser) -> None:
    defaults = section_defaults("orchard")
    parser.epilog = "orchard keys (schema defaults): " + ", ".join(f"{k}={v}" for k, v in defaults.items())
    add_options_arguments(parser, "orchard")
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="capture folder to write (replaced atomically)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def run(args) -> int:
    options = stage_options(args, "orchard")
    generate_orchard(args.out, progress=not args.no_progress, **options)
    return 0

"""What the built-in capture generators (orchard, plant) share: cameras on rings, and writing a capture.

A generator builds its geometry and a renderer (`srfpipe.scenes.raycast`), chooses poses and
intrinsics, and hands them to `write_capture`, which renders every view and writes the folder
atomically in the layout of docs/artifacts.md::

    OUT/transforms.json                        nerfstudio (OpenGL camera), camera_model OPENCV
    OUT/images/frame_00000.png                 RGB renders
    OUT/ground_truth/labels/frame_00000.png    uint8 class values (index into scene.json `classes`)
    OUT/ground_truth/depth/frame_00000.npy     float32 z-depth along the camera +z, 0 = no hit
    OUT/ground_truth/meshes/<name>.ply         one mesh per surface
    OUT/ground_truth/scene.json                classes, the generator's own keys, intrinsics, poses
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from srfpipe.artifacts import atomic_directory
from srfpipe.cameras import look_at

CAMERA_CONVENTION = "camera_to_world below is OpenCV (+x right, +y down, +z forward)"
VIDEO_FILE = "video.avi"  # write_capture(video_fps=...): the views as one video


# ----------------------------------------------------------------------------- cameras


def ring_poses(
    views: int, ring_heights: list[float], ring_radius, target: np.ndarray, rng: np.random.Generator,
    height_jitter: float = 0.03, arc_deg: float | None = None,
) -> np.ndarray:
    """(views, 4, 4) camera_to_world on rings; views split evenly, rings offset by half a step.

    `ring_radius` is one radius or one per ring; `height_jitter` is in world units (the default
    suits the orchard's metres). `arc_deg`: the views of each ring spread over this arc of azimuth
    centred on +x (a forward-facing capture: every camera on one side, looking the same way) instead
    of the whole turn. A little jitter in azimuth, radius and height keeps the views from
    being exactly symmetric (as a person walking would be), which also helps SfM and held-out
    evaluation.
    """
    n_rings = len(ring_heights)
    radius_of_ring = np.broadcast_to(np.asarray(ring_radius, np.float64), (n_rings,))
    counts = [views // n_rings + (1 if r < views % n_rings else 0) for r in range(n_rings)]
    poses = []
    for r, (height, count) in enumerate(zip(ring_heights, counts)):
        if count == 0:
            continue
        if arc_deg is None:
            step = 2 * np.pi / count
            azimuths = np.arange(count) * step + (r / n_rings) * step + rng.normal(0, 0.08 * step, count)
        else:
            step = np.radians(arc_deg) / count
            azimuths = ((np.arange(count) + (r + 0.5) / n_rings) * step - np.radians(arc_deg) / 2
                        + rng.normal(0, 0.08 * step, count))
        radii = radius_of_ring[r] * (1.0 + rng.normal(0, 0.02, count))
        heights = height + rng.normal(0, height_jitter, count)
        for a, rad, h in zip(azimuths, radii, heights):
            eye = np.array([rad * np.cos(a), rad * np.sin(a), h])
            poses.append(look_at(eye, target))
    return np.stack(poses)


def orbit_poses(views: int, heights: list[float], radius: float, target: np.ndarray) -> np.ndarray:
    """(views, 4, 4) camera_to_world along one continuous turn round `target` (a video's walk):
    the azimuth steps evenly, the height climbs from the lowest to the highest of `heights`, so
    consecutive frames overlap and the last one comes back beside the first (a loop to close)."""
    azimuths = np.linspace(0.0, 2.0 * np.pi, views, endpoint=False)
    climb = np.linspace(min(heights), max(heights), views)
    return np.stack([look_at(np.array([radius * np.cos(a), radius * np.sin(a), h]), target)
                     for a, h in zip(azimuths, climb)])


def check_views(section: str, poses: np.ndarray, intrinsics: np.ndarray, width: int, height: int,
                distortion=None, ring_keys: str = "ring_radius, ring_heights") -> None:
    """Raise ConfigError, naming the generator's keys, for cameras whose capture the poses stage
    would refuse (`srfpipe.poses.geometry`): a focal length no camera has (fov_deg near 0 or 180),
    a lens mapping most of the frame outside it, every camera at one point (`ring_keys` place them).
    Called before rendering, so that nothing is written."""
    from srfpipe.config import ConfigError
    from srfpipe.poses.geometry import check_camera_model, check_camera_spread

    lens = np.zeros(4) if distortion is None else np.asarray(distortion, np.float64)
    keys = "fov_deg, width, height" + (", distortion" if distortion is not None else "")
    try:
        check_camera_model(intrinsics, lens, (width, height), f"{section} ({keys})")
        check_camera_spread(poses, f"{section} ({ring_keys})")
    except ValueError as exc:
        raise ConfigError(f"{exc}; the poses stage would refuse this capture") from None


def write_video(frames: list[Path], path: Path, fps: float) -> None:
    """The image files `frames`, in order, as a Motion-JPEG AVI (OpenCV's own encoder, present in
    every build; quality 95): what a phone's video gives the `video` source format."""
    import cv2

    first = cv2.imread(str(frames[0]))
    writer = cv2.VideoWriter(str(path), cv2.CAP_OPENCV_MJPEG, cv2.VideoWriter_fourcc(*"MJPG"), fps,
                             (first.shape[1], first.shape[0]), [cv2.VIDEOWRITER_PROP_QUALITY, 95])
    if not writer.isOpened():
        raise RuntimeError(f"{path}: OpenCV cannot write a Motion-JPEG video")
    try:
        for frame in frames:
            writer.write(cv2.imread(str(frame)))
    finally:
        writer.release()


def intrinsics_for(width: int, height: int, fov_deg: float) -> np.ndarray:
    """(fx, fy, cx, cy): square pixels, horizontal field of view `fov_deg`, centred principal point."""
    fx = 0.5 * width / np.tan(np.radians(fov_deg) / 2.0)
    return np.array([fx, fx, width / 2.0, height / 2.0])


def frame_names(count: int) -> list[str]:
    return [f"frame_{i:05d}" for i in range(count)]


# ----------------------------------------------------------------------------- command line


def add_generator_arguments(parser, section: str) -> None:
    """A generator subcommand's arguments: its scene section's keys (--scene/--options) and --out."""
    from srfpipe.config import add_options_arguments, section_defaults

    defaults = section_defaults(section)
    parser.epilog = f"{section} keys (schema defaults): " + ", ".join(f"{k}={v}" for k, v in defaults.items())
    add_options_arguments(parser, section)
    parser.add_argument("--out", required=True, metavar="DIR",
                        help="capture folder to write (replaced atomically)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


# ----------------------------------------------------------------------------- files


EMPTY_PLY = (
    "ply\nformat ascii 1.0\ncomment srfpipe scenes: no geometry of this class\n"
    "element vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
    "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
)


def write_mesh(path: Path, mesh) -> None:
    import open3d as o3d

    if len(mesh.triangles) == 0:
        # open3d refuses to write an empty mesh, but a scene without apples or leaves is valid
        path.write_text(EMPTY_PLY)
        return
    legacy = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh.vertices.astype(np.float64)),
        o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)),
    )
    if not o3d.io.write_triangle_mesh(str(path), legacy):
        raise RuntimeError(f"{path}: open3d could not write the mesh")


def transforms_json(poses_cv: np.ndarray, intrinsics: np.ndarray, width: int, height: int, names,
                    distortion=None) -> dict:
    from srfpipe.cameras import opencv_to_opengl

    fx, fy, cx, cy = (float(v) for v in intrinsics)
    frames = [
        {"file_path": f"images/{name}.png", "transform_matrix": opencv_to_opengl(pose).tolist()}
        for name, pose in zip(names, poses_cv)
    ]
    return {
        "camera_model": "OPENCV",
        "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": int(width), "h": int(height),
        **dict(zip(("k1", "k2", "p1", "p2"), (float(c) for c in (distortion if distortion is not None else [0] * 4)))),
        "frames": frames,
    }


def add_sensor_noise(rgb: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise of `sigma` 8-bit levels on an encoded uint8 image, like a camera's read noise."""
    noisy = rgb.astype(np.float32) + rng.normal(0.0, sigma, rgb.shape).astype(np.float32)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def _render_views(renderer, poses, intrinsics, width: int, height: int, names, folder: Path, n_classes: int,
                  progress: bool, desc: str, sensor_noise: float, noise_seed: int, distortion=None) -> np.ndarray:
    """Render and write every view's image, label and depth; returns the pixel count of each class."""
    import cv2
    from tqdm import tqdm

    gt = folder / "ground_truth"
    class_pixels = np.zeros(n_classes, np.int64)
    views = tqdm(list(enumerate(zip(names, poses))), desc=desc, unit="view", disable=not progress)
    for index, (name, pose) in views:
        view = renderer.render(pose, intrinsics, width, height, distortion)
        rgb = view.rgb
        if sensor_noise > 0:
            rgb = add_sensor_noise(rgb, sensor_noise, np.random.default_rng([noise_seed, 2, index]))
        if not cv2.imwrite(str(folder / "images" / f"{name}.png"), rgb[..., ::-1]):
            raise RuntimeError(f"{folder / 'images' / name}.png: OpenCV could not write the image")
        cv2.imwrite(str(gt / "labels" / f"{name}.png"), view.label)
        np.save(gt / "depth" / f"{name}.npy", view.depth)
        class_pixels += np.bincount(view.label.ravel(), minlength=n_classes)
    return class_pixels


def write_capture(
    out: str | Path, renderer, poses: np.ndarray, intrinsics: np.ndarray, width: int, height: int,
    classes: list[str], meshes: dict, scene: dict, files: dict | None = None, progress: bool = True,
    desc: str = "views", sensor_noise: float = 0.0, noise_seed: int = 0, distortion=None,
    video_fps: float | None = None, subject_keys: str = "",
) -> dict:
    """Render every pose and write the capture folder atomically; returns scene.json as written.

    `meshes` maps a file name (without .ply) to a `tree.Mesh`; `scene` holds the generator's own
    scene.json keys (world frame, bounds, parameters, ...); `files` maps further ground-truth file
    names to JSON-able values (e.g. apples.json). `sensor_noise` (8-bit levels, 0 = none) is drawn
    per view from `noise_seed`. `distortion` (k1, k2, p1, p2) renders through an OpenCV lens, and
    transforms.json records it. With `video_fps`, the views (in order) are also written as the
    video `VIDEO_FILE` at that frame rate, frame i being view i. A capture in which no view shows
    anything but the background class is refused (ValueError naming `subject_keys`, the keys that
    size and frame the subject), and nothing is written.
    """
    out = Path(out)
    names = frame_names(len(poses))
    with atomic_directory(out) as tmp:
        gt = tmp / "ground_truth"
        for folder in (tmp / "images", gt / "labels", gt / "depth", gt / "meshes"):
            folder.mkdir(parents=True)
        class_pixels = _render_views(renderer, poses, intrinsics, width, height, names, tmp, len(classes),
                                     progress, desc, sensor_noise, noise_seed, distortion)
        if not class_pixels[1:].any():
            raise ValueError(f"{out}: no pixel of the {len(poses)} views shows the subject (all {classes[0]}): "
                             f"it is too small, or out of view; check {subject_keys or 'the options'}")
        for mesh_name, mesh in meshes.items():
            write_mesh(gt / "meshes" / f"{mesh_name}.ply", mesh)
        for file_name, value in (files or {}).items():
            (gt / file_name).write_text(json.dumps(value, indent=1))
        (tmp / "transforms.json").write_text(
            json.dumps(transforms_json(poses, intrinsics, width, height, names, distortion), indent=1)
        )
        fx, fy, cx, cy = np.asarray(intrinsics, np.float64).tolist()
        full = {
            "classes": list(classes),
            **scene,
            "intrinsics": {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": width, "height": height},
            "camera_convention": CAMERA_CONVENTION,
            "names": names,
            "camera_to_world": np.asarray(poses).tolist(),
            "class_pixel_counts": dict(zip(classes, class_pixels.tolist())),
        }
        if video_fps is not None:
            write_video([tmp / "images" / f"{name}.png" for name in names], tmp / VIDEO_FILE, video_fps)
            full["video"] = {"file": VIDEO_FILE, "fps": video_fps, "frames": len(names)}
        (gt / "scene.json").write_text(json.dumps(full, indent=1))
    return full

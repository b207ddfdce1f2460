"""Import camera poses (nerfstudio | blender | colmap | llff | orchard), or recover them by structure from
motion (images | video), optionally refine them with COLMAP.

Writes `poses.zarr` (see docs/artifacts.md): world-frame `camera_to_world` in the project's OpenCV
camera convention (`srfpipe.cameras`), full-resolution intrinsics and OpenCV distortion, optional
sparse points, and the scene normalization `scene_from_world` that maps the scene bounds into
[-1, 1]^3. The importers live beside this module (one per format); this is the stage that
dispatches to them, and the only module of the package that the CLI runs.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from srfpipe import cameras
from srfpipe.config import ConfigError, add_options_arguments, json_object_flag, stage_options, validate_scene
from srfpipe.poses.align import perturb_poses, up_alignment
from srfpipe.poses.blender import read_blender
from srfpipe.poses.bounds import resolve_bounds
from srfpipe.poses.capture import Capture, validate_capture
from srfpipe.poses.colmap import read_colmap
from srfpipe.poses.colmap_refine import refine_poses
from srfpipe.poses.geometry import check_cameras_see_bounds, check_scene_bounds
from srfpipe.poses.ground_truth import attach_ground_truth
from srfpipe.poses.llff import read_llff
from srfpipe.poses.nerfstudio import read_nerfstudio
from srfpipe.settings import SourceSettings

log = logging.getLogger(__name__)

FORMATS = ("orchard", "plant", "nerfstudio", "blender", "colmap", "llff", "images", "video")
UNPOSED_FORMATS = ("images", "video")  # posed here, by structure from motion (srfpipe.poses.sfm)


def load_capture(source: dict, capture_dir: str | Path | None = None, options: dict | None = None,
                 threads: int = -1, workdir: str | Path | None = None) -> Capture:
    """Import the capture described by a scene's `source` section; `capture_dir` overrides `source.path`.

    Unposed captures (images, video) are posed by structure from motion with the `poses` section
    `options`; its scratch files, and a video's extracted frames (`frames/`), go to `workdir`.
    """
    fmt = source.get("format")
    path = capture_dir if capture_dir is not None else source.get("path")
    if fmt not in FORMATS:
        raise ValueError(f"{path}: unknown capture format {fmt!r} (expected one of {', '.join(FORMATS)})")
    if path is None:
        raise ValueError(f"source: format {fmt} needs a capture path")
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: capture does not exist")
    allowed = source.get("allowed_roots") or ()
    if fmt in ("nerfstudio", "orchard", "plant"):
        capture = read_nerfstudio(path, source_format=fmt, allowed_roots=allowed)
    elif fmt == "blender":
        capture = read_blender(path, allowed_roots=allowed)
    elif fmt == "llff":
        capture = read_llff(path, source.get("images_dir"), allowed_roots=allowed)
    elif fmt == "colmap":
        capture = read_colmap(path, source.get("images_dir"), source.get("model_dir"), allowed_roots=allowed)
    else:
        from srfpipe.poses.sfm import read_images, read_video

        options = options or {}
        if fmt == "images":
            capture = read_images(path, source, options, threads=threads, workdir_parent=workdir)
        else:
            frames_dir = Path(workdir if workdir is not None else path.parent) / "frames"
            capture = read_video(path, source, options, threads=threads, workdir_parent=workdir,
                                 frames_dir=frames_dir)
    if fmt not in UNPOSED_FORMATS:
        # a generator's ground truth lies in its world frame, not in the arbitrary one of SfM
        capture = attach_ground_truth(capture)
    validate_capture(capture)
    return capture


def check_enough_images(capture: Capture, min_images: int) -> None:
    """Raise ValueError, naming the poses file, when fewer than `min_images` frames kept their image."""
    if len(capture) >= min_images:
        return
    missing = capture.extra.get("missing_images") or []
    listed = capture.extra.get("n_frames_listed", len(capture))
    raise ValueError(
        f"{capture.source_file}: only {len(capture)} of {listed} frames have an image ({len(missing)} missing), "
        f"fewer than poses.min_images={min_images}" + (f"; missing: {', '.join(missing)}" if missing else ""))


def import_poses(source: dict, capture_dir: str | Path | None, options: dict, out: str | Path,
                 threads: int = -1, progress: bool = True) -> Path:
    """Import, optionally perturb and refine, normalize, and write `poses.zarr` atomically.

    `source` and `options` are the scene's `source` and `poses` sections (defaults are filled in
    by validation here); `capture_dir` overrides `source.path`.
    """
    from srfpipe.artifacts import create_artifact

    source = dict(source)
    where = capture_dir if capture_dir is not None else source.get("path") or "source"
    if source.get("format", SourceSettings.format) not in FORMATS:
        raise ValueError(f"{where}: unknown capture format {source.get('format')!r} "
                         f"(expected one of {', '.join(FORMATS)})")
    if capture_dir is not None:
        source.setdefault("path", str(capture_dir))
    source = validate_scene({"source": source}, "source")["source"]
    options = validate_scene({"poses": dict(options)}, "poses options")["poses"]
    if options["refine"] == "colmap" and options["matcher"] == "retrieval":
        raise ConfigError("poses.matcher: retrieval is for structure from motion (source.format images or video); "
                          "COLMAP refinement matches with auto, exhaustive, poses, sequential or spatial")
    capture = load_capture(source, capture_dir, options=options, threads=threads, workdir=Path(out).parent)
    check_enough_images(capture, options["min_images"])
    log.info("imported %d images (%s) from %s", len(capture), capture.source_format, capture.source_file)
    up_rotation = None
    if options.get("up") == "auto":  # no default: absent is off
        if capture.ground_truth is not None:
            raise ConfigError(f"{capture.source_file}: poses.up auto would turn the world away from the frame of "
                              f"its ground truth ({capture.ground_truth})")
        up_rotation = up_alignment(capture.camera_to_world)
        capture = replace(capture, camera_to_world=cameras.transform_poses(up_rotation, capture.camera_to_world),
                          points_world=None if capture.points_world is None
                          else cameras.transform_points(up_rotation, capture.points_world))
        log.info("poses.up auto: turned the world by %.1f degrees so the cameras' mean up is +z",
                 np.degrees(np.arccos(np.clip((np.trace(up_rotation[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))

    poses = capture.camera_to_world
    points = capture.points_world
    bounds, bounds_source = resolve_bounds(capture, poses, points, options["bounds"], options["points_box"])
    scene_size = float(np.max(bounds[1] - bounds[0]))
    perturbed = options["perturb_rot_deg"] > 0 or options["perturb_trans_frac"] > 0
    if perturbed:
        poses = perturb_poses(poses, options["perturb_rot_deg"], options["perturb_trans_frac"] * scene_size,
                              options["perturb_seed"])
        log.info("perturbed poses by %.3g deg and %.3g world units", options["perturb_rot_deg"],
                 options["perturb_trans_frac"] * scene_size)

    refinement = None
    if options["refine"] == "colmap":
        result = refine_poses(capture, poses, matcher=options["matcher"], workdir_parent=Path(out).parent,
                              threads=threads, refine_distortion=options.get("refine_distortion") or False)
        poses, points, refinement = result.camera_to_world, result.points_world, result.stats
        if result.distortion is not None:  # the lens the images' own matches measured, which downscaling undoes
            capture = replace(capture, distortion=result.distortion)
        if bounds_source in ("points", "frusta"):
            bounds, bounds_source = resolve_bounds(capture, poses, points, None, options["points_box"])

    check_scene_bounds(bounds, capture.source_file, bounds_source)
    blind_cameras = check_cameras_see_bounds(poses, capture.intrinsics, capture.image_size, bounds, capture.names,
                                             capture.source_file, bounds_source)
    scene_from_world = cameras.scene_from_world_transform(bounds[0], bounds[1])
    config = {"source": source, "poses": options}
    inputs = [str(Path(capture.root).resolve())]
    with create_artifact(out, "poses", config=config, inputs=inputs) as group:
        n = len(capture)
        group.create_array("camera_to_world", data=poses.astype(np.float64), dimension_names=("image", "row", "col"))
        group.create_array("intrinsics", data=capture.intrinsics.astype(np.float64), dimension_names=("image", "k"))
        group.create_array("image_size", data=capture.image_size.astype(np.int32), dimension_names=("image", "wh"))
        group.create_array("distortion", data=capture.distortion.astype(np.float64), dimension_names=("image", "k"))
        if points is not None and len(points):
            group.create_array("points_world", data=points.astype(np.float32), dimension_names=("point", "xyz"))
        from srfpipe.artifacts import update_attrs

        update_attrs(
            group,
            capture_root=str(Path(capture.root).resolve()),
            image_paths=capture.image_paths,
            names=capture.names,
            n_images=n,
            scene_from_world=scene_from_world,
            world_from_scene=np.linalg.inv(scene_from_world),
            bounds_world=bounds,
            bounds_source=bounds_source,
            source_format=capture.source_format,
            source_file=str(capture.source_file),
            ground_truth=str(capture.ground_truth) if capture.ground_truth else None,
            perturbed=perturbed,
            refinement=refinement,
            cameras_seeing_no_bounds=blind_cameras,
            up_rotation=up_rotation,
            **capture.extra,
        )
    log.info("wrote %s: %d cameras, bounds %s (%s)", out, len(capture), bounds.round(3).tolist(), bounds_source)
    return Path(out)


def add_arguments(parser) -> None:
    add_options_arguments(parser, "poses")
    parser.add_argument(
        "--source", metavar="JSON", default=None,
        help="JSON object: the scene's 'source' section (format nerfstudio|blender|colmap|llff|orchard|"
        "images|video, path, images_dir, model_dir, max_frames); overrides the --scene file's",
    )
    parser.add_argument("--capture", metavar="DIR", default=None,
                        help="capture folder (overrides source.path; the orchard's generated capture, a video's "
                        "frames folder written by `srfpipe frames`)")
    parser.add_argument("--out", required=True, metavar="ZARR", help="poses.zarr to write (atomically)")
    parser.add_argument("--threads", type=int, default=-1, help="COLMAP threads (-1: all cores)")


def run(args) -> int:
    from srfpipe.config import load_scene

    options = stage_options(args, "poses")
    source = dict(load_scene(args.scene)["source"]) if args.scene else {}
    if args.source:
        source.update(json_object_flag(args.source, "--source"))
    import_poses(source, args.capture, options, args.out, threads=args.threads)
    return 0

"""Refine imported camera poses with COLMAP (pycolmap): SIFT, matching, triangulation, bundle adjustment.

The poses are taken as given (a COLMAP reconstruction is built from them, with the capture's
intrinsics held fixed), so this is "point triangulator + bundle adjuster", not SfM from scratch:

1. SIFT features for every image (`pycolmap.extract_features`) into a temporary database that
   already holds our cameras, rigs, frames and images with the reconstruction's ids.
2. Matching: exhaustive for small captures, otherwise the pairs that the known poses say can
   match (`pairs_from_poses`: nearest cameras whose views point the same way, as hloc's
   pairs_from_poses), or spatial (nearest camera centres only, written as pose priors) or
   sequential (neighbours in capture order) when asked for.
3. Triangulation from the given poses (`pycolmap.triangulate_points`). Thresholds are loose in
   the first pass, because the given poses may be off by a degree or more.
4. Bundle adjustment of poses and points (robust Cauchy loss, intrinsics fixed), outlier
   filtering, a second triangulation with COLMAP's default thresholds from the refined poses, and
   a final bundle adjustment. With `refine_distortion` (`stated`, the stage's default: the
   calibrations that state a distortion; `true`: every one) every adjustment also fits the
   calibration's OpenCV distortion (shared by the images taken with it; focal lengths and principal point stay):
   a phone's COLMAP model can carry tangential terms that undistortion would turn into pixels
   several px off at the frame's corners, and the images' own matches measure the lens.
5. Bundle adjustment leaves the gauge (scale, rotation, position of the world) free, so the result
   is mapped back by the similarity that best aligns the refined cameras (centres and axes) to the
   given ones: the world frame (and its units) of the capture is kept.
6. An image that ends up observing fewer than `MIN_OBSERVATIONS` points keeps its given pose:
   on the orchard, such images (a few dozen points on one branch) come out of bundle adjustment
   worse than they went in, while images with a few hundred points come out several times better.

Reprojection errors (pixels) after step 3 ("before", poses as given) and after step 4 ("after")
are reported in `stats`, with the numbers of points and observations.
"""

from __future__ import annotations

import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from srfpipe import cameras
from srfpipe.poses.align import align_poses
from srfpipe.poses.capture import Capture

log = logging.getLogger(__name__)

EXHAUSTIVE_MAX_IMAGES = 20  # 'auto' matcher: all pairs up to this many images (190 pairs)
SPATIAL_NEIGHBOURS = 20
POSES_NEIGHBOURS = 20  # 'poses' matcher: nearest cameras per image ...
POSES_MAX_ANGLE_DEG = 30.0  # ... whose optical axes differ by less: SIFT seldom matches across more
POSES_MIN_PAIRS = 3  # an image with fewer cameras inside the angle takes the closest in angle
SEQUENTIAL_OVERLAP = 15
LOOSE_ANGLE_DEG = 8.0  # first triangulation: the given poses may be this far off
LOOSE_REPROJ_PX = 24.0
FILTER_REPROJ_PX = 4.0  # COLMAP's default outlier threshold
FILTER_MIN_TRI_ANGLE_DEG = 1.5
MIN_OBSERVATIONS = 100  # fewer observed points than this: the image keeps its given pose (see refine_poses)
MIN_REFINED_IMAGES = 3  # images with MIN_OBSERVATIONS points each that the gauge alignment needs


@dataclass
class RefinementResult:
    camera_to_world: np.ndarray  # (N, 4, 4) refined, in the input's world frame
    points_world: np.ndarray  # (M, 3) triangulated points, same frame
    stats: dict
    distortion: np.ndarray | None = None  # (N, 4) k1, k2, p1, p2 when they were refined, else None


def choose_matcher(matcher: str, n_images: int) -> str:
    """'auto' -> exhaustive for small captures, pairs from the known poses otherwise."""
    if matcher != "auto":
        return matcher
    return "exhaustive" if n_images <= EXHAUSTIVE_MAX_IMAGES else "poses"


def pairs_from_poses(camera_to_world: np.ndarray, neighbours: int = POSES_NEIGHBOURS,
                     max_angle_deg: float = POSES_MAX_ANGLE_DEG, min_pairs: int = POSES_MIN_PAIRS) -> list[tuple[int, int]]:
    """Image pairs (i < j) worth matching, chosen from known poses (OpenCV cameras, +z looks forward).

    Each image pairs with its `neighbours` nearest camera centres among the cameras whose optical
    axis is within `max_angle_deg` of its own; an image with fewer than `min_pairs` such cameras
    takes the `min_pairs` closest in angle instead. Exhaustive matching spends most of its time
    on pairs that look at the scene from too far apart for SIFT to match: on the fox capture
    (50 images), 416 of its 1225 pairs are within 30 degrees.
    """
    n = len(camera_to_world)
    centres = camera_to_world[:, :3, 3]
    axes = camera_to_world[:, :3, 2] / np.linalg.norm(camera_to_world[:, :3, 2], axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip(axes @ axes.T, -1.0, 1.0)))
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(angle, np.inf)
    pairs: set[tuple[int, int]] = set()
    for i in range(n):
        within = np.flatnonzero(angle[i] <= max_angle_deg)
        if len(within) < min_pairs:
            chosen = np.argsort(angle[i])[:min(min_pairs, n - 1)]
        else:
            chosen = within[np.argsort(distance[i, within], kind="stable")[:neighbours]]
        pairs.update((min(i, int(j)), max(i, int(j))) for j in chosen)
    return sorted(pairs)


def _camera_model(intrinsics, distortion, size, opencv: bool = False):
    """pycolmap camera: PINHOLE, or OPENCV when there is distortion or `opencv` (a lens to refine)
    (COLMAP pixels also centre at +0.5)."""
    import pycolmap

    fx, fy, cx, cy = (float(v) for v in intrinsics)
    width, height = (int(v) for v in size)
    if opencv or np.any(np.asarray(distortion) != 0):
        camera = pycolmap.Camera.create_from_model_name(0, "OPENCV", fx, width, height)
        camera.params = [fx, fy, cx, cy, *(float(v) for v in distortion)]
    else:
        camera = pycolmap.Camera.create_from_model_name(0, "PINHOLE", fx, width, height)
        camera.params = [fx, fy, cx, cy]
    return camera


def build_reconstruction(image_paths, camera_to_world, intrinsics, image_size, distortion, opencv: bool = False):
    """A posed pycolmap.Reconstruction (no points): one camera per distinct calibration, image i has id i+1.
    `opencv`: every camera OPENCV, so that its distortion can be refined."""
    import pycolmap

    reconstruction = pycolmap.Reconstruction()
    camera_ids: dict[tuple, int] = {}
    for index, (name, pose) in enumerate(zip(image_paths, camera_to_world)):
        key = (*np.round(intrinsics[index], 9), *np.round(distortion[index], 12), *image_size[index])
        if key not in camera_ids:
            camera = _camera_model(intrinsics[index], distortion[index], image_size[index], opencv)
            camera.camera_id = len(camera_ids) + 1
            reconstruction.add_camera_with_trivial_rig(camera)
            camera_ids[key] = camera.camera_id
        world_to_camera = np.linalg.inv(pose)
        cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(world_to_camera[:3, :3]), world_to_camera[:3, 3])
        image = pycolmap.Image(name=name, camera_id=camera_ids[key], image_id=index + 1)
        reconstruction.add_image_with_trivial_frame(image, cam_from_world)
    return reconstruction


def _write_database(database_path: Path, reconstruction, with_pose_priors: bool) -> None:
    """Cameras, rigs, frames and images into a new database, keeping the reconstruction's ids,
    so that feature extraction attaches its keypoints to exactly these images."""
    import pycolmap

    database = pycolmap.Database.open(str(database_path))
    try:
        for camera in reconstruction.cameras.values():
            database.write_camera(camera, use_camera_id=True)
        for rig in reconstruction.rigs.values():
            database.write_rig(rig, use_rig_id=True)
        for frame in reconstruction.frames.values():
            database.write_frame(frame, use_frame_id=True)
        for image in reconstruction.images.values():
            database.write_image(image, use_image_id=True)
            if with_pose_priors:  # spatial matching reads camera positions from pose priors
                prior = pycolmap.PosePrior(
                    position=image.projection_center(),
                    coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN,
                )
                prior.corr_data_id = image.data_id
                database.write_pose_prior(prior)
    finally:
        database.close()


def _write_pairs(path: Path, image_names: list[str], pairs: list[tuple[int, int]]) -> None:
    with open(path, "w") as f:
        for i, j in pairs:
            f.write(f"{image_names[i]} {image_names[j]}\n")


def _match(database_path: Path, matcher: str, camera_to_world: np.ndarray, image_names: list[str],
           threads: int) -> None:
    import pycolmap

    n_images = len(image_names)
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = threads
    # after RANSAC, match again along the epipolar geometry: doubles the inliers on foliage
    options.guided_matching = True
    device = pycolmap.Device.cpu
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(str(database_path), matching_options=options, device=device)
    elif matcher == "poses":
        pairs = pairs_from_poses(camera_to_world)
        pairs_path = database_path.with_name("pairs.txt")
        _write_pairs(pairs_path, image_names, pairs)
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pairs_path)
        pycolmap.match_image_pairs(str(database_path), matching_options=options, pairing_options=pairing, device=device)
    elif matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = min(SEQUENTIAL_OVERLAP, n_images - 1)
        pycolmap.match_sequential(str(database_path), matching_options=options, pairing_options=pairing, device=device)
    elif matcher == "spatial":
        pairing = pycolmap.SpatialPairingOptions()
        pairing.ignore_z = False  # positions are 3D camera centres, not GPS
        pairing.max_num_neighbors = min(SPATIAL_NEIGHBOURS, n_images - 1)
        camera_spread = max(float(np.ptp(camera_to_world[:, :3, 3], axis=0).max()), 1e-6)
        pairing.max_distance = 10.0 * camera_spread
        pycolmap.match_spatial(str(database_path), matching_options=options, pairing_options=pairing, device=device)
    else:
        raise ValueError(f"poses.matcher: unknown matcher {matcher!r}")


def _triangulation_options(threads: int, loose: bool):
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.ba_global_max_refinements = 1
    options.extract_colors = False
    if loose:
        tri = options.triangulation
        tri.create_max_angle_error = LOOSE_ANGLE_DEG
        tri.continue_max_angle_error = LOOSE_ANGLE_DEG
        tri.re_max_angle_error = LOOSE_ANGLE_DEG
        tri.merge_max_reproj_error = LOOSE_REPROJ_PX
        tri.complete_max_reproj_error = LOOSE_REPROJ_PX
        options.mapper.filter_max_reproj_error = LOOSE_REPROJ_PX
    return options


def _bundle_adjust(reconstruction, threads: int, refine_distortion: bool = False) -> None:
    import pycolmap

    options = pycolmap.BundleAdjustmentOptions()
    # the capture's focal lengths and principal point are trusted (freed, a box corner's focal drifted
    # 1 % with the poses' depth, and the principal point slides along what a capture barely constrains)
    options.refine_focal_length = False
    options.refine_principal_point = False
    options.refine_extra_params = refine_distortion  # else the distortion is trusted too
    options.refine_sensor_from_rig = False
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    options.ceres.loss_function_scale = 2.0  # pixels: matches off by more count less
    options.ceres.solver_options.num_threads = threads
    options.ceres.solver_options.max_num_iterations = 100
    pycolmap.bundle_adjustment(reconstruction, options)


def _filter_outliers(reconstruction) -> int:
    import pycolmap

    manager = pycolmap.ObservationManager(reconstruction)
    return int(manager.filter_all_points3D(FILTER_REPROJ_PX, FILTER_MIN_TRI_ANGLE_DEG))


def _poses_in_order(reconstruction, n_images: int) -> np.ndarray:
    poses = np.empty((n_images, 4, 4))
    for index in range(n_images):
        cam_from_world = reconstruction.images[index + 1].cam_from_world().matrix()
        poses[index] = np.linalg.inv(np.vstack([cam_from_world, [0.0, 0.0, 0.0, 1.0]]))
    return poses


def _points(reconstruction) -> np.ndarray:
    return np.array([p.xyz for p in reconstruction.points3D.values()], dtype=np.float64).reshape(-1, 3)


def _summary(reconstruction) -> dict:
    return {
        "reprojection_error_px": float(reconstruction.compute_mean_reprojection_error()),
        "num_points3D": int(reconstruction.num_points3D()),
        "num_observations": int(reconstruction.compute_num_observations()),
    }


def _refined_distortion(reconstruction, capture: Capture) -> tuple[np.ndarray, list[dict]]:
    """(N, 4) OpenCV k1, k2, p1, p2 of each image's camera (zeros for a pinhole), and per camera
    that has a distortion its first image with the given and the refined coefficients (for
    poses.zarr's stats)."""
    distortion, records, seen = [], [], set()
    for index, name in enumerate(capture.image_paths):
        camera_id = reconstruction.images[index + 1].camera_id
        params = np.asarray(reconstruction.cameras[camera_id].params, dtype=np.float64)
        distortion.append(params[4:8] if params.size >= 8 else np.zeros(4))
        if camera_id not in seen and params.size >= 8:
            seen.add(camera_id)
            records.append({"first_image": name, "given": capture.distortion[index].tolist(),
                            "refined": distortion[-1].tolist()})
    return np.stack(distortion), records


def refine_poses(capture: Capture, camera_to_world: np.ndarray, matcher: str = "auto",
                 workdir_parent: str | Path | None = None, threads: int = -1,
                 max_features: int = 8192, refine_distortion: bool | str = False) -> RefinementResult:
    """Refine `camera_to_world` (N, 4, 4) for the images of `capture`; with `refine_distortion`, also
    the calibrations' distortion (the result's `distortion`): True every calibration's (a pinhole
    gains the OpenCV terms), "stated" those that state one (a pinhole stays one), False none.

    Intermediate files (database, models) go to a temporary folder under `workdir_parent`.
    """
    import pycolmap

    n = len(capture.image_paths)
    if n < MIN_REFINED_IMAGES:  # the gauge is aligned back on the refined cameras: 2 could never pass
        raise ValueError(f"{capture.source_file}: poses.refine colmap needs at least {MIN_REFINED_IMAGES} images "
                         f"(the refined cameras are aligned back onto the given ones), got {n}")
    matcher = choose_matcher(matcher, n)
    if matcher == "poses" and any(len(name.split()) != 1 for name in capture.image_paths):
        # COLMAP's pair list is split at spaces
        log.warning("COLMAP: image names with spaces cannot go into a pair list; spatial matching instead")
        matcher = "spatial"
    reconstruction = build_reconstruction(capture.image_paths, camera_to_world, capture.intrinsics,
                                          capture.image_size, capture.distortion, opencv=refine_distortion is True)
    # a pinhole camera has no extra parameters: under "stated" only the stated lenses are freed
    stated = bool(np.any(np.asarray(capture.distortion) != 0))
    free_distortion = refine_distortion is True or (refine_distortion == "stated" and stated)
    if workdir_parent is not None:
        Path(workdir_parent).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".colmap-refine-", dir=workdir_parent) as tmp:
        tmp = Path(tmp)
        database = tmp / "database.db"
        _write_database(database, reconstruction, with_pose_priors=(matcher == "spatial"))

        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = threads
        extraction.sift.max_num_features = max_features
        log.info("COLMAP: SIFT on %d images", n)
        pycolmap.extract_features(str(database), str(capture.root), image_names=list(capture.image_paths),
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        db = pycolmap.Database.open(str(database))
        try:
            no_features = [image.name for image in db.read_all_images() if db.num_keypoints_for_image(image.image_id) == 0]
        finally:
            db.close()
        if len(no_features) == n:
            raise RuntimeError(f"{capture.root}: COLMAP found no SIFT features in any image")
        log.info("COLMAP: %s matching", matcher)
        _match(database, matcher, camera_to_world, list(capture.image_paths), threads)
        db = pycolmap.Database.open(str(database))
        try:
            pairs = {"pairs_matched": int(db.num_matched_image_pairs()),
                     "pairs_verified": int(db.num_verified_image_pairs())}
        finally:
            db.close()
        log.info("COLMAP: %s", pairs)

        (tmp / "tri1").mkdir()
        reconstruction = pycolmap.triangulate_points(
            reconstruction, str(database), str(capture.root), str(tmp / "tri1"),
            clear_points=True, options=_triangulation_options(threads, loose=True),
        )
        before = _summary(reconstruction)
        if before["num_points3D"] == 0:
            raise RuntimeError(f"{capture.root}: COLMAP triangulated no points from the given poses")
        log.info("COLMAP: triangulated from the given poses: %s", before)

        _bundle_adjust(reconstruction, threads, free_distortion)
        filtered = _filter_outliers(reconstruction)
        _bundle_adjust(reconstruction, threads, free_distortion)
        (tmp / "tri2").mkdir()
        reconstruction = pycolmap.triangulate_points(
            reconstruction, str(database), str(capture.root), str(tmp / "tri2"),
            clear_points=True, options=_triangulation_options(threads, loose=False),
        )
        _bundle_adjust(reconstruction, threads, free_distortion)
        filtered += _filter_outliers(reconstruction)
        if free_distortion:  # the lens fitted once more without the outliers it was first fitted with
            _bundle_adjust(reconstruction, threads, free_distortion)
        after = _summary(reconstruction)
        log.info("COLMAP: after bundle adjustment: %s", after)

    refined = _poses_in_order(reconstruction, n)
    observed = np.array([reconstruction.images[i + 1].num_points3D for i in range(n)])
    constrained = observed >= MIN_OBSERVATIONS
    if constrained.sum() < MIN_REFINED_IMAGES:
        raise RuntimeError(
            f"{capture.root}: COLMAP refinement constrained only {int(constrained.sum())} of {n} images "
            f"(>= {MIN_OBSERVATIONS} points each); too few matches to refine the poses"
        )
    # Bundle adjustment drifts the gauge: map the refined cameras back onto the given ones,
    # using only the cameras that bundle adjustment could actually constrain.
    world_from_refined = align_poses(refined[constrained], camera_to_world[constrained])
    refined = cameras.transform_poses(world_from_refined, refined)
    refined[~constrained] = camera_to_world[~constrained]  # a pose seen through a handful of points is noise
    points = cameras.transform_points(world_from_refined, _points(reconstruction))
    stats = {
        "method": "colmap",
        "matcher": matcher,
        **pairs,
        "num_images": n,
        "num_images_refined": int(constrained.sum()),
        "images_kept_as_given": [capture.image_paths[i] for i in np.flatnonzero(~constrained)],
        "images_without_features": no_features,
        "reprojection_error_before_px": before["reprojection_error_px"],
        "reprojection_error_after_px": after["reprojection_error_px"],
        "num_points3D_before": before["num_points3D"],
        "num_points3D": after["num_points3D"],
        "num_observations": after["num_observations"],
        "observations_filtered": filtered,
        "gauge_alignment_scale": float(np.cbrt(np.linalg.det(world_from_refined[:3, :3]))),
        "pycolmap": pycolmap.__version__,
    }
    if not free_distortion:
        return RefinementResult(camera_to_world=refined, points_world=points, stats=stats)
    distortion, stats["distortion"] = _refined_distortion(reconstruction, capture)
    for record in stats["distortion"]:
        log.info("COLMAP: distortion of %s's camera refined: %s -> %s",
                 record["first_image"], record["given"], record["refined"])
    return RefinementResult(camera_to_world=refined, points_world=points, stats=stats, distortion=distortion)

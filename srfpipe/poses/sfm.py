"""Poses from unposed captures by structure from motion (pycolmap): `source.format: images | video`.

`images`: the photos of a folder (`source.path`, or its `source.images_dir` subfolder; the
folder's `images/` when its top level holds none). `video`: the frames `srfpipe.poses.video`
chose from a video file (a frames folder with `frames.json`, or the video itself, whose frames
are then extracted next to poses.zarr).

1. SIFT features for every image into a scratch database (one shared camera for a video's
   frames, and for photos of one size; else one per size and EXIF focal length, COLMAP's `AUTO`). The camera
   model is `poses.camera_model` (RADIAL when absent: one focal length, the principal point, k1,
   k2; a phone's lens needs k2: the fox's k1 0.058, k2 -0.081), mapped to the project's OpenCV
   (fx, fy, cx, cy) and (k1, k2, p1, p2).
2. Matching suited to the source (`poses.matcher: auto`): a video's frames with their
   `SEQUENTIAL_OVERLAP` successors (and quadratic ones), and, for loop closure, with the frames
   that look most alike further along (`retrieval_pairs`); photos exhaustively below
   `EXHAUSTIVE_MAX_IMAGES`, otherwise each with the `RETRIEVAL_NEIGHBOURS` photos that look most
   alike. Retrieval here needs no downloaded vocabulary tree: a bag of visual words clustered
   from the capture's own SIFT descriptors (k-means), weighted by tf-idf, compared by cosine.
3. Incremental mapping (`pycolmap.incremental_mapping`); when it registers fewer than
   `RELAX_BELOW` of the images, once more with relaxed thresholds (fewer inliers to start and to
   register an image with), and the model with the most registered images is kept. The images
   it did not register are left out of the capture, listed in a warning and in poses.zarr
   (`unregistered_images`); fewer registered than `poses.min_images` is an error naming the
   folder.
4. The principal point, fixed at the image centre while mapping, is freed in one global bundle
   adjustment and moved along the directions that adjustment determines (`poses.principal_point:
   auto`, `refine_principal_point`).

The world frame and scale are COLMAP's (arbitrary); `poses.up: auto` turns the world so the
cameras' mean up vector is +z (`srfpipe.poses.stage`). `Capture.extra["sfm"]` records the
matcher, the registered fraction, the mean reprojection error, the cameras and the seconds spent.
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from srfpipe.images import read_image
from srfpipe.poses.capture import Capture, check_image_file, orthonormalize, read_image_size, resolve_inside
from srfpipe.poses.colmap import colmap_camera_parameters
from srfpipe.settings import PosesSettings

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp")
EXHAUSTIVE_MAX_IMAGES = 100  # photos: every pair below this many images (4950 pairs)
RETRIEVAL_NEIGHBOURS = 25  # photos above it: each with this many most alike
SEQUENTIAL_OVERLAP = 10  # a video's frames: each with this many successors (and 2^k ones)
LOOP_NEIGHBOURS = 5  # ... and with this many most alike frames further than the overlap away
VOCABULARY_WORDS = 512
VOCABULARY_SAMPLES = 60000  # descriptors the words are clustered from
CAMERA_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")
DEFAULT_CAMERA_MODEL = "RADIAL"
MAX_FEATURES = 8192
# COLMAP's 0.0067 keeps too few features on foliage and bark, which are low in contrast: the
# orchard's 36-view turn at 320 x 240 registered 25 of 36 images with it, all 36 with 0.004
SIFT_PEAK_THRESHOLD = 0.004
RELAX_BELOW = 0.9  # fewer images registered than this fraction: mapping again with relaxed thresholds
# Guided matching (after RANSAC, match again along each pair's epipolar geometry) costs about the
# square of the features per image. Measured on 2 cores: the orchard video's 640 x 480 frames (2800
# features) 0.12 s a pair with it; the fox's 1080 x 1920 photos (10 100 features) 2.7 s a pair
# with it, 0.28 s without, 1500 inliers a pair even then (its 1225 pairs: 6 minutes measured
# without it, about 55 at the rate with it). Images with more features than this on average are
# matched without it.
GUIDED_MAX_FEATURES = 4096
MIN_PAIR_INLIERS = 15  # a pair 'verified' in the stats: this many matches fit its two-view geometry
# After mapping, the principal point moves from the image centre along each principal direction of
# its covariance (from the bundle adjustment that frees it) where its standard deviation is at most
# PRINCIPAL_POINT_MAX_SIGMA_DEG (over the focal length) and the shift found there is significant: at
# least PRINCIPAL_POINT_MIN_SIGNIFICANCE standard deviations (a normal two-sided test at 99.9 %).
# A test on the whole 2-d shift is not enough: the orchard video's turn determines the horizontal
# to 0.01 deg and the vertical only to 0.17 deg, and a 1 px horizontal shift made a 5.3 px vertical
# slide (noise) significant as a whole, costing 0.10 -> 0.52 deg. Measured (details docs/benchmarks.md):
#   the fox's 50 photos: both directions to 0.012 deg: moved (10.3, 10.0) px, 0.43 -> 0.18 deg;
#   the orchard video's turn: vertical 0.17 deg: kept at the centre there;
#   the tests' 36-view turn at 320 x 240: 2.3 deg: kept (moved by the whole shift, 1.3 -> 9.2 deg).
PRINCIPAL_POINT_MIN_SIGNIFICANCE = 3.29
PRINCIPAL_POINT_MAX_SIGMA_DEG = 0.1
SFM_MATCHERS = ("auto", "exhaustive", "sequential", "retrieval")


@dataclass
class SfmResult:
    indices: list[int]  # registered images, indices into the input list, in input order
    camera_to_world: np.ndarray  # (R, 4, 4)
    intrinsics: np.ndarray  # (R, 4)
    distortion: np.ndarray  # (R, 4)
    image_size: np.ndarray  # (R, 2)
    points_world: np.ndarray  # (M, 3)
    stats: dict


# ----------------------------------------------------------------------------- listing


def list_images(root: Path, images_dir: str | None = None, allowed_roots=()) -> tuple[Path, list[str]]:
    """(folder the paths are relative to, sorted image paths) of an `images` capture.

    The photos of `root/images_dir` when given, else of `root`, else of `root/images`; hidden files
    are skipped; every path (symlinks resolved) must stay inside `root` or `allowed_roots`; every
    photo must decode (`srfpipe.images.read_image`: a truncated one is refused naming it).
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: images folder does not exist")

    def photos(folder: Path) -> list[str]:
        return sorted(p.name for p in folder.iterdir()
                      if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and p.is_file())

    if images_dir is not None:
        folder = resolve_inside(root, images_dir, f"{root}: source.images_dir", allowed_roots)
        if not (root / folder).is_dir():
            raise FileNotFoundError(f"{root / folder}: source.images_dir is not a folder")
        candidates = [folder]
    else:
        candidates = [".", "images"]
    for folder in candidates:
        if not (root / folder).is_dir():
            continue
        names = photos(root / folder)
        if names:
            paths = [resolve_inside(root, f"{folder}/{name}" if folder != "." else name, root, allowed_roots)
                     for name in names]
            for path in paths:
                check_image_file(root / path, root)
                # decoded once here: COLMAP reads a truncated JPEG or PNG without an error (the rows
                # it lacks grey) and would pose it; the downscale stage would refuse it only after SfM
                read_image(root / path)
            return root, paths
    raise ValueError(f"{root}: no photos ({', '.join(IMAGE_SUFFIXES)}) in the folder"
                     + ("" if images_dir else " or its images/ subfolder"))


# ----------------------------------------------------------------------------- retrieval


def bag_of_words(descriptors: list[np.ndarray], words: int = VOCABULARY_WORDS, samples: int = VOCABULARY_SAMPLES,
                 seed: int = 0) -> np.ndarray:
    """(N, words) tf-idf weighted, L2-normalized visual-word histograms of N images' SIFT descriptors.

    The words are k-means centres of (RootSIFT) descriptors sampled from these images: no
    vocabulary file to download, and words fitted to the scene itself.
    """
    import cv2

    def root_sift(d: np.ndarray) -> np.ndarray:
        d = d.astype(np.float32)
        d /= np.maximum(d.sum(1, keepdims=True), 1e-9)
        return np.sqrt(d)

    rng = np.random.default_rng(seed)
    per_image = max(1, samples // max(len(descriptors), 1))
    pool = [root_sift(d[rng.choice(len(d), min(per_image, len(d)), replace=False)]) for d in descriptors if len(d)]
    if not pool:
        return np.zeros((len(descriptors), 1), np.float32)
    pool = np.concatenate(pool)
    words = int(max(2, min(words, len(pool) // 10)))
    cv2.setRNGSeed(seed)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 15, 1e-4)
    _, _, centres = cv2.kmeans(pool, words, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
    centre_norms = (centres ** 2).sum(1)
    counts = np.zeros((len(descriptors), words), np.float32)
    for i, d in enumerate(descriptors):
        if not len(d):
            continue
        for block in range(0, len(d), 4096):
            x = root_sift(d[block:block + 4096])
            nearest = np.argmin(centre_norms[None] - 2.0 * x @ centres.T, axis=1)
            counts[i] += np.bincount(nearest, minlength=words)
    idf = np.log(len(descriptors) / np.maximum((counts > 0).sum(0), 1)).astype(np.float32)
    histograms = counts / np.maximum(counts.sum(1, keepdims=True), 1.0) * idf
    return histograms / np.maximum(np.linalg.norm(histograms, axis=1, keepdims=True), 1e-12)


def retrieval_pairs(histograms: np.ndarray, neighbours: int, min_index_distance: int = 0) -> list[tuple[int, int]]:
    """Pairs (i < j): each image with its `neighbours` most alike (cosine of the histograms) among
    the images at least `min_index_distance` away from it in capture order (beyond a video's
    sequential overlap, for loop closure)."""
    n = len(histograms)
    similarity = histograms @ histograms.T
    index = np.arange(n)
    similarity[np.abs(index[:, None] - index[None]) < max(min_index_distance, 1)] = -np.inf
    pairs = set()
    for i in range(n):
        candidates = np.flatnonzero(np.isfinite(similarity[i]))
        best = candidates[np.argsort(-similarity[i, candidates], kind="stable")[:neighbours]]
        pairs.update((min(i, int(j)), max(i, int(j))) for j in best)
    return sorted(pairs)


# ----------------------------------------------------------------------------- matching


def choose_sfm_matcher(matcher: str, n_images: int, video: bool, where) -> str:
    """'auto' -> sequential for a video, exhaustive below EXHAUSTIVE_MAX_IMAGES photos, retrieval above."""
    if matcher not in SFM_MATCHERS:
        raise ValueError(f"{where}: poses.matcher {matcher!r} needs known poses; structure from motion "
                         f"matches with {', '.join(SFM_MATCHERS)}")
    if matcher != "auto":
        return matcher
    if video:
        return "sequential"
    return "exhaustive" if n_images < EXHAUSTIVE_MAX_IMAGES else "retrieval"


def _descriptors(database_path: Path, names: list[str]) -> list[np.ndarray]:
    import pycolmap

    with pycolmap.Database.open(str(database_path)) as db:
        ids = {image.name: image.image_id for image in db.read_all_images()}
        return [np.asarray(db.read_descriptors(ids[name]).data) if name in ids else np.zeros((0, 128), np.uint8)
                for name in names]


def _match(database_path: Path, matcher: str, names: list[str], threads: int, features: float) -> dict:
    """Run the matcher on images with `features` SIFT features on average; returns what it matched
    ({'loop_pairs': ...} for a video)."""
    import pycolmap

    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = threads
    # more inliers on foliage's few features (see GUIDED_MAX_FEATURES), affordable only with few
    options.guided_matching = features <= GUIDED_MAX_FEATURES
    log.info("SfM: %.0f features per image: %s", features,
             "guided matching" if options.guided_matching else
             f"no guided matching (over {GUIDED_MAX_FEATURES}: its cost grows with their square)")
    device = pycolmap.Device.cpu
    n = len(names)
    info: dict = {"mean_features": round(features, 1), "guided_matching": bool(options.guided_matching)}
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(str(database_path), matching_options=options, device=device)
        return info
    if matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = min(SEQUENTIAL_OVERLAP, n - 1)
        pairing.quadratic_overlap = True
        pairing.loop_detection = False  # COLMAP's needs a vocabulary tree file: our retrieval instead
        pycolmap.match_sequential(str(database_path), matching_options=options, pairing_options=pairing,
                                  device=device)
        pairs = []
        if n > SEQUENTIAL_OVERLAP + 1:
            histograms = bag_of_words(_descriptors(database_path, names))
            pairs = retrieval_pairs(histograms, LOOP_NEIGHBOURS, min_index_distance=SEQUENTIAL_OVERLAP + 1)
        info["loop_pairs"] = len(pairs)
    elif matcher == "retrieval":
        histograms = bag_of_words(_descriptors(database_path, names))
        pairs = retrieval_pairs(histograms, RETRIEVAL_NEIGHBOURS)
        info["retrieval_pairs"] = len(pairs)
    else:
        raise ValueError(f"poses.matcher: unknown structure-from-motion matcher {matcher!r}")
    if pairs:
        pairs_path = database_path.with_name("pairs.txt")
        pairs_path.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pairs_path)
        pycolmap.match_image_pairs(str(database_path), matching_options=options, pairing_options=pairing,
                                   device=device)
    return info


# ----------------------------------------------------------------------------- mapping


def _link_name(index: int) -> str:
    return f"{index:06d}"


def _link_images(root: Path, image_paths: list[str], folder: Path) -> list[str]:
    """Symlinks folder/<index><suffix> -> the images: COLMAP's names carry no spaces or subfolders."""
    folder.mkdir()
    names = []
    for i, path in enumerate(image_paths):
        name = _link_name(i) + Path(path).suffix.lower()
        os.symlink(os.path.abspath(root / path), folder / name)
        names.append(name)
    return names


def _mapping_options(threads: int, relaxed: bool):
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = threads
    options.random_seed = 0
    options.mapper.random_seed = 0
    options.triangulation.random_seed = 0
    options.extract_colors = False
    options.min_model_size = 3
    if relaxed:  # small or weakly textured images: fewer inliers to start and to register with
        options.mapper.init_min_num_inliers = 30
        options.mapper.abs_pose_min_num_inliers = 15
        options.mapper.init_min_tri_angle = 8.0
        options.min_num_matches = 10
    return options


def _largest(models: dict):
    return max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), default=None)


def _final_adjustment(model, refine_principal_point: bool):
    """One global bundle adjustment of every registered image (COLMAP's defaults otherwise); the
    adjuster is returned for the covariance estimate."""
    import pycolmap

    options = pycolmap.BundleAdjustmentOptions()
    options.refine_principal_point = refine_principal_point
    config = pycolmap.BundleAdjustmentConfig()
    for image_id, image in model.images.items():
        if image.has_pose:
            config.add_image(image_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, model)
    summary = adjuster.solve()
    return adjuster, summary


def _principal_point_shift(camera) -> np.ndarray:
    """The camera's principal point minus the image centre, in pixels."""
    return np.array([camera.principal_point_x - camera.width / 2, camera.principal_point_y - camera.height / 2])


def principal_point_uncertainty(model, adjuster, summary) -> dict[int, dict]:
    """Per camera: the principal point's shift from the image centre, and along each principal
    direction of its covariance (the bundle adjustment's: the inverse of its Gauss-Newton Hessian,
    scaled by the residuals' variance) the shift, its standard deviation (pixels, and degrees at
    the focal length) and its significance (shift over standard deviation). None where the
    covariance cannot be estimated."""
    import pycolmap

    ceres = summary.ceres_summary
    variance = 2.0 * ceres.final_cost / max(summary.num_residuals, 1)  # Ceres' cost is half the squared sum
    covariance = pycolmap.estimate_ba_covariance(pycolmap.BACovarianceOptions(), model, adjuster)
    out = {}
    for camera_id, camera in model.cameras.items():
        block = None if covariance is None else covariance.get_other_params_cov(camera.params)
        if block is None:
            out[camera_id] = None
            continue
        pp = list(camera.principal_point_idxs())
        values, vectors = np.linalg.eigh(variance * np.asarray(block)[np.ix_(pp, pp)])
        shift = _principal_point_shift(camera)
        directions = []
        for value, vector in zip(values, vectors.T):
            sigma = float(np.sqrt(max(value, 1e-24)))
            along = float(vector @ shift)
            directions.append({"direction": vector.tolist(), "shift_px": along, "sigma_px": sigma,
                               "sigma_deg": float(np.degrees(sigma / camera.mean_focal_length())),
                               "significance": abs(along) / sigma})
        out[camera_id] = {"shift_px": shift.tolist(), "directions": directions}
    return out


def determined_shift(uncertainty: dict | None) -> np.ndarray:
    """The part of a camera's principal point shift that its views determine: the components along
    the covariance's directions whose standard deviation is at most `PRINCIPAL_POINT_MAX_SIGMA_DEG`
    and whose shift is significant (`PRINCIPAL_POINT_MIN_SIGNIFICANCE`)."""
    kept = np.zeros(2)
    for d in (uncertainty or {}).get("directions", []):
        if d["sigma_deg"] <= PRINCIPAL_POINT_MAX_SIGMA_DEG and d["significance"] >= PRINCIPAL_POINT_MIN_SIGNIFICANCE:
            kept += d["shift_px"] * np.asarray(d["direction"])
    return kept


def refine_principal_point(model, mode: str = "auto"):
    """The mapped model (principal point fixed at the image centre while mapping: refined there it
    collapses weak captures) and one global bundle adjustment with the principal point free.

    `centre` keeps the model as mapped; `refine` takes the adjusted one; `auto` moves each camera's
    principal point from the centre only along the directions its views determine
    (`determined_shift`): the centre is a camera's likeliest principal point, and views that
    barely constrain a direction (a level orbit lets it slide vertically with a common tilt of
    every camera) move it there by noise. A partial move is followed by one more adjustment with
    the principal point fixed there. Returns (model, record for poses.zarr)."""
    import pycolmap

    if mode == "centre":
        return model, {"mode": mode, "refined": False}
    trial = pycolmap.Reconstruction(model)
    adjuster, summary = _final_adjustment(trial, refine_principal_point=True)
    uncertainty = principal_point_uncertainty(trial, adjuster, summary)
    trial.update_point_3d_errors()
    found = {c: _principal_point_shift(camera) for c, camera in trial.cameras.items()}
    applied = found if mode == "refine" else {c: determined_shift(uncertainty[c]) for c in trial.cameras}
    if all(np.allclose(applied[c], found[c], rtol=0.0, atol=1e-6) for c in found):  # the whole shift
        result = trial
    elif not any(np.any(applied[c]) for c in applied):
        result = model
    else:
        result = pycolmap.Reconstruction(model)
        for camera_id, shift in applied.items():
            camera = result.cameras[camera_id]
            camera.principal_point_x = camera.width / 2 + shift[0]
            camera.principal_point_y = camera.height / 2 + shift[1]
            result.cameras[camera_id] = camera
        _final_adjustment(result, refine_principal_point=False)
        result.update_point_3d_errors()
    refined = any(np.any(shift) for shift in applied.values())
    record = {"mode": mode, "refined": refined, "min_significance": PRINCIPAL_POINT_MIN_SIGNIFICANCE,
              "max_sigma_deg": PRINCIPAL_POINT_MAX_SIGMA_DEG,
              "cameras": {str(c): None if u is None else {**u, "applied_shift_px": applied[c].tolist()}
                          for c, u in uncertainty.items()}}
    log.info("SfM: principal point %s (%s)", "moved" if refined else "kept at the image centre",
             "; ".join(f"camera {c}: " + ("covariance unavailable" if u is None else
                       f"shift found ({u['shift_px'][0]:+.1f}, {u['shift_px'][1]:+.1f}) px, applied "
                       f"({applied[c][0]:+.1f}, {applied[c][1]:+.1f}); " + ", ".join(
                           f"{d['shift_px']:+.1f} px +- {d['sigma_deg']:.3f} deg ({d['significance']:.1f} sigma)"
                           for d in u["directions"]))
                       for c, u in uncertainty.items()))
    return result, record


def run_sfm(root: Path, image_paths: list[str], *, video: bool = False, matcher: str = "auto",
            camera_model: str | None = None, threads: int = -1, workdir_parent: str | Path | None = None,
            min_images: int = 2, max_features: int = MAX_FEATURES, principal_point: str = "auto") -> SfmResult:
    """Structure from motion on the images `root/image_paths` (see the module); errors name `root`."""
    import pycolmap

    start = time.perf_counter()
    pycolmap.set_random_seed(0)  # RANSAC in matching and mapping: the same capture gives the same poses
    n = len(image_paths)
    camera_model = camera_model or DEFAULT_CAMERA_MODEL
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"poses.camera_model: {camera_model!r} is not one of {', '.join(CAMERA_MODELS)}")
    if n < max(min_images, 2):
        raise ValueError(f"{root}: {n} images, fewer than poses.min_images={max(min_images, 2)} "
                         "for structure from motion")
    matcher = choose_sfm_matcher(matcher, n, video, root)
    if workdir_parent is not None:
        Path(workdir_parent).mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".colmap-sfm-", dir=workdir_parent) as tmp:
        tmp = Path(tmp)
        links = _link_images(root, image_paths, tmp / "images")
        database = tmp / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        # one camera for all the images when they share a size (a phone's photos, as nerfstudio's
        # ns-process-data assumes; without EXIF, COLMAP would give each its own), else COLMAP's
        # AUTO (per size and EXIF focal length)
        shared = video or len({read_image_size(root / p, root) for p in image_paths}) == 1
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = threads
        extraction.sift.max_num_features = max_features
        extraction.sift.peak_threshold = SIFT_PEAK_THRESHOLD
        log.info("SfM: SIFT on %d images of %s (%s, %s camera)", n, root, camera_model,
                 "one shared" if shared else "one per size and focal length")
        pycolmap.extract_features(str(database), str(tmp / "images"), image_names=links,
                                  camera_mode=pycolmap.CameraMode.SINGLE if shared else pycolmap.CameraMode.AUTO,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        with pycolmap.Database.open(str(database)) as db:
            keypoints = {image.name: db.num_keypoints_for_image(image.image_id) for image in db.read_all_images()}
        featureless = [name for name, count in keypoints.items() if count == 0]
        if len(featureless) == n:
            raise ValueError(f"{root}: structure from motion found no SIFT features in any of the {n} images")
        log.info("SfM: %s matching", matcher)
        matched = _match(database, matcher, links, threads, float(np.mean(list(keypoints.values()))))
        with pycolmap.Database.open(str(database)) as db:
            _, inliers = db.read_two_view_geometry_num_inliers()
            pairs = {"pairs_matched": int(db.num_matched_image_pairs()),
                     "pairs_verified": int(np.sum(np.asarray(inliers) >= MIN_PAIR_INLIERS))}
        log.info("SfM: %s", {**pairs, **matched})
        models, relaxed = {}, False
        if pairs["pairs_verified"]:
            (tmp / "sparse").mkdir()
            models = pycolmap.incremental_mapping(str(database), str(tmp / "images"), str(tmp / "sparse"),
                                                  _mapping_options(threads, relaxed=False))
            best = _largest(models)
            if best is None or best.num_reg_images() < RELAX_BELOW * n:
                log.info("SfM: %d of %d images registered; again with relaxed thresholds",
                         0 if best is None else best.num_reg_images(), n)
                (tmp / "sparse-relaxed").mkdir()
                again = pycolmap.incremental_mapping(str(database), str(tmp / "images"), str(tmp / "sparse-relaxed"),
                                                     _mapping_options(threads, relaxed=True))
                if again and (best is None or _largest(again).num_reg_images() > best.num_reg_images()):
                    models, relaxed = again, True
        model = _largest(models)
        if model is None or model.num_reg_images() == 0:
            raise ValueError(f"{root}: structure from motion registered none of the {n} images "
                             f"({pairs['pairs_verified']} of {pairs['pairs_matched']} image pairs verified): "
                             + ("too little overlap or texture between them" if not pairs["pairs_verified"] else
                                "the pairs that match show too little parallax to start from (the camera stood "
                                "still or only turned: it must move between views)"))
        model, principal_point_record = refine_principal_point(model, principal_point)

        index_of = {_link_name(i): i for i in range(n)}
        registered = sorted((index_of[Path(image.name).stem], image) for image in model.images.values()
                            if image.has_pose)
        indices = [i for i, _ in registered]
        poses, intrinsics, distortion, sizes = [], [], [], []
        for i, image in registered:
            camera = model.cameras[image.camera_id]
            k, dist = colmap_camera_parameters(camera, f"{root}: SfM camera {image.camera_id}")
            poses.append(np.linalg.inv(np.vstack([image.cam_from_world().matrix(), [0.0, 0.0, 0.0, 1.0]])))
            intrinsics.append(k)
            distortion.append(dist)
            sizes.append((int(camera.width), int(camera.height)))
        points = np.array([p.xyz for p in model.points3D.values()], np.float64).reshape(-1, 3)
        unregistered = [image_paths[i] for i in range(n) if i not in set(indices)]
        cameras_used = sorted({image.camera_id for _, image in registered})
        stats = {
            "method": "pycolmap incremental mapping",
            "matcher": matcher,
            **pairs,
            **matched,
            "camera_model": camera_model,
            "shared_camera": bool(shared),
            "cameras": [{"model": model.cameras[c].model.name, "width": int(model.cameras[c].width),
                         "height": int(model.cameras[c].height),
                         "params": [float(v) for v in model.cameras[c].params]} for c in cameras_used],
            "n_images": n,
            "n_registered": len(indices),
            "registered_fraction": len(indices) / n,
            "n_models": len(models),
            "model_sizes": sorted((int(m.num_reg_images()) for m in models.values()), reverse=True),
            "relaxed_thresholds": relaxed,
            "principal_point": principal_point_record,
            "reprojection_error_px": float(model.compute_mean_reprojection_error()),
            "num_points3D": int(model.num_points3D()),
            "num_observations": int(model.compute_num_observations()),
            "images_without_features": [image_paths[index_of[Path(name).stem]] for name in featureless],
            "seconds": round(time.perf_counter() - start, 2),
            "pycolmap": pycolmap.__version__,
        }
    if unregistered:
        log.warning("%s: structure from motion registered %d of %d images; left out: %s", root, len(indices), n,
                    ", ".join(unregistered))
    if len(indices) < min_images:
        raise ValueError(f"{root}: structure from motion registered only {len(indices)} of {n} images, fewer than "
                         f"poses.min_images={min_images}; not registered: {', '.join(unregistered)}")
    log.info("SfM: %d of %d images registered, %d points, reprojection error %.3f px, %.1f s", len(indices), n,
             stats["num_points3D"], stats["reprojection_error_px"], stats["seconds"])
    return SfmResult(indices=indices, camera_to_world=orthonormalize(np.stack(poses)),
                     intrinsics=np.asarray(intrinsics, np.float64), distortion=np.asarray(distortion, np.float64),
                     image_size=np.asarray(sizes, np.int32), points_world=points, stats=stats)


# ----------------------------------------------------------------------------- importers


def _capture(root: Path, image_paths: list[str], result: SfmResult, source_format: str, source_file: Path,
             extra: dict) -> Capture:
    kept = [image_paths[i] for i in result.indices]
    unregistered = [p for i, p in enumerate(image_paths) if i not in set(result.indices)]
    return Capture(
        root=root, image_paths=kept, camera_to_world=result.camera_to_world, intrinsics=result.intrinsics,
        image_size=result.image_size, distortion=result.distortion, source_format=source_format,
        source_file=source_file, points_world=result.points_world if len(result.points_world) else None,
        extra={"sfm": result.stats, "unregistered_images": unregistered, "n_frames_listed": len(image_paths),
               **extra},
    )


def read_images(path: str | Path, source: dict, options: dict, threads: int = -1,
                workdir_parent: str | Path | None = None) -> Capture:
    """`source.format: images`: the folder's photos, posed by structure from motion."""
    root, image_paths = list_images(Path(path), source.get("images_dir"), source.get("allowed_roots") or ())
    poses = PosesSettings.from_options(options)
    result = run_sfm(root, image_paths, video=False, matcher=poses.matcher, camera_model=poses.camera_model,
                     threads=threads, workdir_parent=workdir_parent, min_images=poses.min_images,
                     principal_point=poses.principal_point)
    return _capture(root, image_paths, result, "images", root, {})


def read_video(path: str | Path, source: dict, options: dict, threads: int = -1,
               workdir_parent: str | Path | None = None, frames_dir: str | Path | None = None) -> Capture:
    """`source.format: video`: a frames folder written by `srfpipe frames` (holding frames.json), or
    a video file whose frames are first extracted into `frames_dir`; posed by structure from motion
    with one shared camera."""
    from srfpipe.poses.video import FRAMES_FILE, extract_frames, read_frames

    path = Path(path)
    if path.is_file():
        if frames_dir is None:
            raise ValueError(f"{path}: a video needs a folder to write its frames to")
        path = extract_frames(path, frames_dir, source.get("max_frames"))
    elif not (path / FRAMES_FILE).is_file():
        raise FileNotFoundError(f"{path}: neither a video file nor a frames folder (no {FRAMES_FILE})")
    image_paths, record = read_frames(path, source.get("allowed_roots") or ())
    poses = PosesSettings.from_options(options)
    result = run_sfm(path, image_paths, video=True, matcher=poses.matcher, camera_model=poses.camera_model,
                     threads=threads, workdir_parent=workdir_parent, min_images=poses.min_images,
                     principal_point=poses.principal_point)
    frames = [record["frames"][i] for i in result.indices]
    extra = {
        "video": {key: record.get(key) for key in ("video", "fps", "frame_size", "n_video_frames", "max_frames",
                                                   "selection", "blurred_frames")},
        "frame_indices": [int(f.get("index", -1)) for f in frames],
        "frame_timestamps_s": [float(f.get("timestamp_s", float("nan"))) for f in frames],
        "n_frames_listed": record["n_frames_listed"],
        "missing_images": record["missing_images"],
    }
    return _capture(path, image_paths, result, "video", path / FRAMES_FILE, extra)

"""Unposed captures: a video's frames chosen by sharpness, structure from motion (pycolmap) on photos
and on a video, `poses.up: auto`, and the errors when nothing can be posed.

The SfM captures are the built-in orchard at a small size, walked round in one turn
(`orchard.video: true`), whose generator poses are known: the recovered poses are compared with
them after a similarity alignment (`srfpipe.poses.align.pose_errors`).
"""

from __future__ import annotations

import json
import time

import cv2
import numpy as np
import pytest

from srfpipe import cameras
from srfpipe.artifacts import meta, open_artifact
from srfpipe.poses import import_poses
from srfpipe.poses import sfm
from srfpipe.poses.align import pose_errors, up_alignment
from srfpipe.poses.video import choose_frames, extract_frames, read_frames

# 36 views of 320 x 240 round the tree, 10 degrees apart: SfM in about 10 s on 2 cores. At this
# size the tree gives a few hundred SIFT features a view; the recovered turn bends by a degree or
# two (1.3 to 1.7 degrees mean rotation error measured), far more than at a phone's resolution.
ORBIT = {"seed": 0, "views": 36, "width": 320, "height": 240, "video": True, "n_apples": 12}


@pytest.fixture(scope="module")
def orbit(tmp_path_factory):
    from srfpipe.scenes.orchard import generate_orchard

    root = generate_orchard(tmp_path_factory.mktemp("orbit") / "capture", progress=False, **ORBIT)
    scene = json.loads((root / "ground_truth" / "scene.json").read_text())
    return root, np.array(scene["camera_to_world"]), np.array(scene["bounds_world"])


def _check_recovered(group, truth: np.ndarray, scene_size: float, names: list[str]) -> dict:
    info = meta(group)
    sfm = info["sfm"]
    registered = [int(name.rsplit("_", 1)[1]) for name in info["names"]]
    assert info["names"] == [n for n in names if n in info["names"]]  # in capture order
    errors = pose_errors(group["camera_to_world"][:], truth[registered], scene_size)
    assert sfm["registered_fraction"] >= 0.9, sfm
    assert errors["rot_err_deg"] < 3.0, errors
    assert errors["trans_err"] < 0.08, errors
    assert sfm["reprojection_error_px"] < 1.0 and sfm["num_points3D"] > 500
    assert len(info["unregistered_images"]) == sfm["n_images"] - sfm["n_registered"]
    return {**errors, "registered_fraction": sfm["registered_fraction"], "seconds": sfm["seconds"]}


def test_photos_are_posed_by_structure_from_motion(orbit, tmp_path):
    root, truth, bounds = orbit
    started = time.perf_counter()
    out = import_poses({"format": "images", "path": str(root)}, None, {"up": "auto"}, tmp_path / "poses.zarr",
                       threads=2)
    group = open_artifact(out, stage="poses")
    info = meta(group)
    assert info["source_format"] == "images" and info["sfm"]["matcher"] == "exhaustive"
    # small frames, few features: guided matching is affordable and on
    assert info["sfm"]["guided_matching"] and info["sfm"]["mean_features"] <= sfm.GUIDED_MAX_FEATURES
    assert all(p.startswith("images/frame_") for p in info["image_paths"])  # the capture's images/ subfolder
    assert info["ground_truth"] is None  # the generator's frame is not SfM's
    # the default camera has k1 and k2 (a phone's lens needs both); this pinhole's are near zero
    camera_fit = info["sfm"]["cameras"][0]
    assert info["sfm"]["camera_model"] == "RADIAL" and camera_fit["model"] == "RADIAL"
    assert np.all(np.abs(camera_fit["params"][3:]) < 0.05), camera_fit
    principal_point = info["sfm"]["principal_point"]
    # this small turn barely constrains its principal point vertically (2-3 deg): the slide found
    # there (tens of pixels; the camera is centred) is not applied
    assert principal_point["mode"] == "auto"
    camera = principal_point["cameras"]["1"]
    assert max(d["sigma_deg"] for d in camera["directions"]) > sfm.PRINCIPAL_POINT_MAX_SIGMA_DEG
    assert np.linalg.norm(camera["applied_shift_px"]) < 2.0
    result = _check_recovered(group, truth, float(np.max(bounds[1] - bounds[0])),
                              [f"frame_{i:05d}" for i in range(len(truth))])
    # up: auto turned the world so that the cameras' mean up (-y) is +z
    up = -group["camera_to_world"][:][:, :3, 1].mean(0)
    assert up[2] / np.linalg.norm(up) > 0.999
    assert np.allclose(np.array(info["up_rotation"])[:3, :3] @ np.array(info["up_rotation"])[:3, :3].T, np.eye(3))
    assert group["points_world"].shape[0] == info["sfm"]["num_points3D"]
    print(f"\nphotos: {result}, {time.perf_counter() - started:.1f} s in all")


def test_images_with_many_features_are_matched_without_guidance_and_still_posed(orbit, tmp_path, monkeypatch):
    # the orbit's frames standing in for large photos (the fox's 10 000 features): over the limit,
    # matching skips the guided pass (its cost grows with the square of the features)
    monkeypatch.setattr(sfm, "GUIDED_MAX_FEATURES", 10)
    root, truth, bounds = orbit
    out = import_poses({"format": "images", "path": str(root)}, None, {}, tmp_path / "poses.zarr", threads=2)
    group = open_artifact(out, stage="poses")
    assert meta(group)["sfm"]["guided_matching"] is False
    _check_recovered(group, truth, float(np.max(bounds[1] - bounds[0])),
                     [f"frame_{i:05d}" for i in range(len(truth))])


def test_video_is_posed_through_its_chosen_frames(orbit, tmp_path):
    root, truth, bounds = orbit
    video = root / "video.avi"
    assert video.is_file()
    # one thread: with two, pycolmap's matching and mapping order follow the threads' timing, and on a
    # loaded host the map registered 56 % of the frames
    out = import_poses({"format": "video", "path": str(video), "max_frames": len(truth)}, None, {},
                       tmp_path / "scene" / "poses.zarr", threads=1)
    group = open_artifact(out, stage="poses")
    info = meta(group)
    sfm = info["sfm"]
    assert sfm["matcher"] == "sequential" and sfm["shared_camera"] and len(sfm["cameras"]) == 1
    # the frames were written next to poses.zarr, and the capture's images lie inside that folder
    frames = tmp_path / "scene" / "frames"
    assert info["capture_root"] == str(frames.resolve()) and (frames / "frames.json").is_file()
    assert all((frames / p).is_file() for p in info["image_paths"])
    assert info["frame_indices"] == [int(n.rsplit("_", 1)[1]) for n in info["names"]]
    assert np.allclose(np.diff(info["frame_timestamps_s"]), np.diff(info["frame_indices"]) / 10.0, atol=1e-3)
    result = _check_recovered(group, truth, float(np.max(bounds[1] - bounds[0])),
                              [f"frame_{i:05d}" for i in range(len(truth))])
    print(f"\nvideo: {result}")


def test_retrieval_finds_the_neighbouring_views(orbit):
    """The bag of words clustered from the capture's own SIFT features: each view of the turn is most
    like a view next to it (what the retrieval matcher and a video's loop closure rely on)."""
    from srfpipe.poses.sfm import bag_of_words, retrieval_pairs

    root, truth, _ = orbit
    sift = cv2.SIFT_create()
    descriptors = []
    for i in range(len(truth)):
        _, d = sift.detectAndCompute(cv2.imread(str(root / "images" / f"frame_{i:05d}.png"), cv2.IMREAD_GRAYSCALE), None)
        descriptors.append((512 * d / np.linalg.norm(d, axis=1, keepdims=True)).clip(0, 255).astype(np.uint8))
    histograms = bag_of_words(descriptors)
    similarity = histograms @ histograms.T
    np.fill_diagonal(similarity, -1.0)
    n = len(truth)
    steps = np.abs(similarity.argmax(1) - np.arange(n))
    steps = np.minimum(steps, n - steps)  # round the turn
    assert np.mean(steps <= 2) >= 0.8, steps
    # beyond a video's overlap: only pairs at least 11 frames apart
    assert all(j - i >= 11 for i, j in retrieval_pairs(histograms, 5, min_index_distance=11))


def _textured(rng, width=160, height=120) -> np.ndarray:
    small = rng.uniform(0, 255, (height // 8, width // 8, 3)).astype(np.float32)
    return cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC).clip(0, 255).astype(np.uint8)


def _write_video(path, frames, fps=25.0):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (frames[0].shape[1], frames[0].shape[0]))
    assert writer.isOpened()
    for frame in frames:
        writer.write(frame)
    writer.release()


def test_video_frames_are_chosen_by_sharpness_and_spacing(tmp_path):
    rng = np.random.default_rng(0)
    texture = _textured(rng, 480, 120)
    frames = [np.ascontiguousarray(texture[:, 4 * i:4 * i + 160]) for i in range(24)]
    blurred = [3, 8, 15]
    for i in blurred:
        frames[i] = cv2.GaussianBlur(frames[i], (0, 0), 4.0)
    video = tmp_path / "walk.avi"
    _write_video(video, frames)

    # 12 windows of 2 frames: each window's sharper frame, never a blurred one
    out = extract_frames(video, tmp_path / "frames", max_frames=12)
    paths, record = read_frames(out)
    indices = [f["index"] for f in record["frames"]]
    assert len(indices) == 12 and not set(indices) & set(blurred)
    assert [i // 2 for i in indices] == list(range(12))  # one per window: spread over the video
    assert all((out / p).is_file() for p in paths) and paths[0] == f"images/frame_{indices[0]:05d}.png"
    assert record["n_video_frames"] == 24 and record["fps"] == pytest.approx(25.0)
    assert [f["timestamp_s"] for f in record["frames"]] == pytest.approx([i / 25.0 for i in indices], abs=1e-3)
    sharp = [f["sharpness"] for f in record["frames"]]
    assert min(sharp) > 3 * max(cv2.Laplacian(cv2.cvtColor(frames[i], cv2.COLOR_BGR2GRAY), cv2.CV_64F).var()
                                for i in blurred)
    # every frame may be kept: a shaken one is still dropped, against its neighbours
    paths, record = read_frames(extract_frames(video, tmp_path / "all", max_frames=100))
    assert record["blurred_frames"] == blurred and len(paths) == 24 - len(blurred)


@pytest.mark.bad_input
def test_truncated_video_is_refused_naming_it(tmp_path):
    # an AVI cut in half (a copy interrupted): OpenCV decodes its first half without an error
    rng = np.random.default_rng(0)
    texture = _textured(rng, 480, 120)
    video = tmp_path / "walk.avi"
    _write_video(video, [np.ascontiguousarray(texture[:, 4 * i:4 * i + 160]) for i in range(24)])
    data = video.read_bytes()
    video.write_bytes(data[:len(data) // 2])
    out = tmp_path / "frames"
    with pytest.raises(ValueError, match=r"walk.avi: OpenCV decoded \d+ of the 24 frames the video's header lists "
                                         r"\(truncated"):
        extract_frames(video, out, max_frames=12)
    assert not out.exists() and not list(tmp_path.glob(".frames.partial-*"))


def _frames_folder(root, n=4):
    (root / "images").mkdir(parents=True)
    frames = []
    for i in range(n):
        cv2.imwrite(str(root / "images" / f"frame_{i:05d}.png"), _textured(np.random.default_rng(i)))
        frames.append({"file_path": f"images/frame_{i:05d}.png", "index": i, "timestamp_s": i / 25.0})
    return frames


def _write_frames_json(root, frames):
    (root / "frames.json").write_text(json.dumps({"frames": frames}))
    return root / "frames.json"


@pytest.mark.bad_input
def test_frames_folder_entries_are_checked_naming_the_frame(tmp_path):
    # a frames folder (srfpipe frames) edited by hand: every entry is checked before SfM
    cases = [
        (lambda f, root: f.__setitem__(2, dict(f[1])), r"frame 2: file_path 'images/frame_00001.png' is listed twice"),
        (lambda f, root: f[1].update(index="abc"), r"frame 1: index must be a frame number .* got 'abc'"),
        (lambda f, root: f[1].update(index=True), r"frame 1: index must be a frame number"),
        (lambda f, root: f[3].update(timestamp_s=[1]), r"frame 3: timestamp_s must be a number, got list"),
        (lambda f, root: f[2].update(file_path="images"), r"frame 2: image .*images does not exist"),
        (lambda f, root: ((root / "images" / "notes.png").write_text("not an image"),
                          f[0].update(file_path="images/notes.png")), r"notes.png: corrupt or unsupported image"),
    ]
    for k, (edit, message) in enumerate(cases):
        root = tmp_path / f"case{k}"
        frames = _frames_folder(root)
        edit(frames, root)
        path = _write_frames_json(root, frames)
        with pytest.raises((ValueError, FileNotFoundError), match=message) as info:
            read_frames(root)
        assert str(root) in str(info.value), info.value
        assert "frames.json" in str(info.value) or "notes.png" in str(info.value)
        assert path.is_file()
    # a frame whose image was deleted (weeded out by hand) is skipped, recorded, and the record's
    # frames stay aligned with the paths
    root = tmp_path / "weeded"
    frames = _frames_folder(root)
    _write_frames_json(root, frames)
    (root / "images" / "frame_00002.png").unlink()
    paths, record = read_frames(root)
    assert paths == ["images/frame_00000.png", "images/frame_00001.png", "images/frame_00003.png"]
    assert [f["index"] for f in record["frames"]] == [0, 1, 3]
    assert record["missing_images"] == ["images/frame_00002.png"] and record["n_frames_listed"] == 4


def test_choose_frames_windows():
    scores = np.array([1.0, 5.0, 2.0, 2.5, 9.0, 1.0, 3.0])
    assert choose_frames(scores, 3) == ([1, 4, 6], [])  # windows [0, 2), [2, 5), [5, 7)
    assert choose_frames(np.ones(5), 10) == ([0, 1, 2, 3, 4], [])


def test_nothing_registered_is_an_error_naming_the_folder(tmp_path):
    rng = np.random.default_rng(1)
    folder = tmp_path / "noise photos"
    folder.mkdir()
    for i in range(5):
        cv2.imwrite(str(folder / f"IMG {i}.jpg"), rng.integers(0, 256, (96, 128, 3), dtype=np.uint8))
    out = tmp_path / "poses.zarr"
    with pytest.raises(ValueError, match=r"noise photos.*structure from motion registered none of the 5 images"):
        import_poses({"format": "images", "path": str(folder)}, None, {}, out, threads=2)
    assert not out.exists() and not list(tmp_path.glob(".colmap-sfm-*"))


@pytest.mark.bad_input
def test_photos_without_parallax_are_an_error_that_says_so(tmp_path):
    # the same view over and over (a camera on a tripod): every pair matches, nothing triangulates
    folder = tmp_path / "tripod"
    folder.mkdir()
    view = _textured(np.random.default_rng(3), 160, 120)
    for i in range(5):
        cv2.imwrite(str(folder / f"{i}.png"), view)
    out = tmp_path / "poses.zarr"
    with pytest.raises(ValueError, match=r"tripod: structure from motion registered none of the 5 images "
                                         r"\(10 of 10 image pairs verified\): .*too little parallax"):
        import_poses({"format": "images", "path": str(folder)}, None, {}, out, threads=1)
    assert not out.exists() and not list(tmp_path.glob(".colmap-sfm-*"))


def test_empty_folder_and_pose_matchers_are_refused(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"empty: no photos"):
        import_poses({"format": "images", "path": str(tmp_path / "empty")}, None, {}, tmp_path / "p.zarr")
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        cv2.imwrite(str(photos / f"{i}.png"), _textured(np.random.default_rng(i)))
    with pytest.raises(ValueError, match=r"poses.matcher 'poses' needs known poses"):
        import_poses({"format": "images", "path": str(photos)}, None, {"matcher": "poses"}, tmp_path / "p.zarr")
    with pytest.raises(FileNotFoundError, match="neither a video file nor a frames folder"):
        import_poses({"format": "video", "path": str(photos)}, None, {}, tmp_path / "p.zarr")


@pytest.mark.bad_input
@pytest.mark.parametrize("suffix, message", [(".jpg", "truncated JPEG"), (".png", "corrupt or unreadable image")])
def test_truncated_photo_is_refused_before_structure_from_motion(tmp_path, suffix, message):
    # COLMAP reads either without an error (the missing rows grey) and posed it
    photos = tmp_path / "photos"
    photos.mkdir()
    for i in range(3):
        cv2.imwrite(str(photos / f"{i}{suffix}"), _textured(np.random.default_rng(i)))
    data = (photos / f"1{suffix}").read_bytes()
    (photos / f"1{suffix}").write_bytes(data[:len(data) // 2])
    with pytest.raises(ValueError, match=rf"photos/1\{suffix}: {message}"):
        sfm.list_images(photos)
    out = tmp_path / "poses.zarr"
    with pytest.raises(ValueError, match=rf"photos/1\{suffix}: {message}"):
        import_poses({"format": "images", "path": str(photos)}, None, {}, out, threads=1)
    assert not out.exists() and not list(tmp_path.glob(".poses.zarr.partial-*"))


def _observed_model(elevations_deg, pp_shift, views_per_ring=12, n_points=800, noise_px=0.5, seed=0):
    """A reconstruction as incremental mapping leaves it: cameras on rings at `elevations_deg`
    round a cloud of points, each point observed where a camera whose principal point lies
    `pp_shift` px off centre sees it (plus noise), the model's camera still centred."""
    import pycolmap

    rng = np.random.default_rng(seed)
    width, height, focal = 640, 480, 500.0
    principal_point = np.array([width / 2 + pp_shift[0], height / 2 + pp_shift[1]])
    points = rng.uniform(-1.0, 1.0, (n_points, 3))
    model = pycolmap.Reconstruction()
    model.add_camera_with_trivial_rig(pycolmap.Camera(model="SIMPLE_RADIAL", width=width, height=height,
                                                      params=[focal, width / 2, height / 2, 0.0], camera_id=1))
    tracks = [pycolmap.Track() for _ in range(n_points)]
    image_id = 0
    for elevation in np.radians(elevations_deg):
        for azimuth in np.linspace(0, 2 * np.pi, views_per_ring, endpoint=False):
            centre = 5.0 * np.array([np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation),
                                     np.sin(elevation)])
            camera_to_world = cameras.look_at(centre, np.zeros(3))
            world_to_camera = np.linalg.inv(camera_to_world)
            in_camera = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
            pixels = focal * in_camera[:, :2] / in_camera[:, 2:] + principal_point
            pixels += rng.normal(0.0, noise_px, pixels.shape)
            seen = np.flatnonzero(np.all((pixels > 0) & (pixels < [width, height]), axis=1))
            image_id += 1
            image = pycolmap.Image(name=f"{image_id:03d}.png", camera_id=1, image_id=image_id,
                                   points2D=[pycolmap.Point2D(pixels[i]) for i in seen])
            model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(world_to_camera[:3]))
            for k, i in enumerate(seen):
                tracks[i].add_element(image_id, k)
    for point, track in zip(points, tracks):
        model.add_point3D(point, track)
    return model


def _principal_point(model) -> np.ndarray:
    camera = model.cameras[1]
    return np.array([camera.principal_point_x - camera.width / 2, camera.principal_point_y - camera.height / 2])


def test_principal_point_moves_only_along_what_the_views_determine():
    # two rings of views determine the principal point: a camera 12, -8 px off centre is found
    model, record = sfm.refine_principal_point(_observed_model([0, 35], (12, -8)), "auto")
    assert record["refined"]
    assert all(d["sigma_deg"] <= sfm.PRINCIPAL_POINT_MAX_SIGMA_DEG for d in record["cameras"]["1"]["directions"])
    np.testing.assert_allclose(_principal_point(model), [12, -8], atol=1.0)
    # a centred camera: the shift found is noise, and the centre is kept exactly
    for rings in ([0, 35], [0]):
        model, record = sfm.refine_principal_point(_observed_model(rings, (0, 0)), "auto")
        assert not record["refined"]
        np.testing.assert_array_equal(_principal_point(model), [0, 0])
    # one level ring determines the horizontal, not the vertical (a common tilt of every camera
    # moves it): the camera 12 px off horizontally is found, the vertical stays at the centre
    model, record = sfm.refine_principal_point(_observed_model([0], (12, -8)), "auto")
    vertical = max(record["cameras"]["1"]["directions"], key=lambda d: abs(d["direction"][1]))
    assert vertical["sigma_px"] > 5.0 and vertical["sigma_deg"] > sfm.PRINCIPAL_POINT_MAX_SIGMA_DEG
    assert record["refined"]
    np.testing.assert_allclose(_principal_point(model), [12, 0], atol=1.0)
    # the setting overrides the test both ways
    model, record = sfm.refine_principal_point(_observed_model([0, 35], (12, -8)), "centre")
    assert not record["refined"] and np.all(_principal_point(model) == 0)
    model, record = sfm.refine_principal_point(_observed_model([0], (0, 0)), "refine")
    assert record["refined"] and np.any(_principal_point(model) != 0)


def test_up_alignment_turns_the_mean_up_to_z():
    from srfpipe.scenes.capture import look_at

    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ring = np.stack([look_at([3 * np.cos(a), 3 * np.sin(a), 1.0], [0, 0, 0.5]) for a in angles])
    np.testing.assert_allclose(up_alignment(ring), np.eye(4), atol=1e-9)  # upright already: left alone
    tilt = np.eye(4)
    tilt[:3, :3] = cv2.Rodrigues(np.array([0.7, -1.9, 0.4]))[0]
    tilted = cameras.transform_poses(tilt, ring)
    turned = cameras.transform_poses(up_alignment(tilted), tilted)
    up = -turned[:, :3, 1].mean(0)
    assert up[2] / np.linalg.norm(up) == pytest.approx(1.0, abs=1e-9)
    upside_down = cameras.transform_poses(np.diag([1.0, -1.0, -1.0, 1.0]), ring)
    flipped = cameras.transform_poses(up_alignment(upside_down), upside_down)
    assert (-flipped[:, :3, 1].mean(0))[2] > 0.9


def test_workflow_extracts_a_video_before_its_poses(workflow, tmp_path):
    video = tmp_path / "walk.avi"
    _write_video(video, [_textured(np.random.default_rng(i)) for i in range(4)])
    workflow.write_scene("walk", {"source": {"format": "video", "path": str(video), "max_frames": 3},
                                  "segmentation": {"prompts": []}})
    workflow.write_config({"scenes_dir": "config/scenes", "scenes": ["walk"], "results_dir": "results",
                           "final_artifact": "poses"})
    jobs = workflow.dry_run_jobs()
    assert jobs.get("video_frames") == 1 and jobs.get("poses") == 1

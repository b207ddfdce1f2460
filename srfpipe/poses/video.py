"""Frames of a video for structure from motion (`source.format: video`).

A phone video holds far more frames than SfM needs, many of them blurred by motion. As
nerfstudio's `ns-process-data` does, frames are chosen by spacing and sharpness:

1. Every frame's sharpness is the variance of its Laplacian (on a grey copy whose longer side is
   at most `SHARPNESS_SIDE` px, so that the measure does not depend on the video's resolution).
2. The video is cut into `max_frames` windows of equal length (all frames when it has fewer); the
   sharpest frame of each window is kept: the frames stay spread over the whole walk.
3. A kept frame blurrier than `BLUR_RATIO` times the median sharpness of the frames around it
   (`BLUR_NEIGHBOURS` either side) is dropped: every frame near it was sharp, it was shaken.

The chosen frames are written as `images/frame_<index>.png` (index = the frame's position in the
video, so a generator's ground truth named by view matches) into a frames folder, with
`frames.json` recording the video, its frame rate and frame count, and every chosen frame's
index, timestamp and sharpness. `extract_frames` writes that folder atomically (the workflow's
`video_frames` rule, `srfpipe frames`); `read_frames` reads it back for the poses stage.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from srfpipe.poses.capture import (check_image_file, check_unique, load_json, number, record_missing_images,
                                   resolve_inside)

log = logging.getLogger(__name__)

DEFAULT_MAX_FRAMES = 150  # source.max_frames when absent
SHARPNESS_SIDE = 640
BLUR_RATIO = 0.5
BLUR_NEIGHBOURS = 8
# A video that decodes to much fewer frames than its header lists is cut short (a copy interrupted:
# the decoder stops halfway without an error): refused under this share. A few frames short is only
# warned about: a container without a frame count (WebM, Matroska) gets one estimated from its
# duration and mean frame rate, which a phone's variable frame rate puts off by a few frames.
MIN_DECODED_SHARE = 0.9
FRAMES_FILE = "frames.json"
IMAGES_DIR = "images"


def sharpness(bgr: np.ndarray) -> float:
    """Variance of the Laplacian of the frame in grey, at most SHARPNESS_SIDE px on its longer side."""
    import cv2

    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) if bgr.ndim == 3 else bgr
    scale = SHARPNESS_SIDE / max(grey.shape[:2])
    if scale < 1.0:
        grey = cv2.resize(grey, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def choose_frames(scores: np.ndarray, max_frames: int) -> tuple[list[int], list[int]]:
    """(chosen, dropped as blurred): frame indices, by windows of equal length and sharpness."""
    scores = np.asarray(scores, np.float64)
    n = len(scores)
    edges = np.linspace(0, n, min(max_frames, n) + 1).round().astype(int)
    chosen = [int(a + np.argmax(scores[a:b])) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    kept, blurred = [], []
    for index in chosen:
        around = np.r_[scores[max(0, index - BLUR_NEIGHBOURS):index], scores[index + 1:index + 1 + BLUR_NEIGHBOURS]]
        if len(around) and scores[index] < BLUR_RATIO * float(np.median(around)):
            blurred.append(index)
        else:
            kept.append(index)
    return kept, blurred


def _open(video: Path):
    import cv2

    if not video.is_file():
        raise FileNotFoundError(f"{video}: video file does not exist")
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        raise ValueError(f"{video}: OpenCV cannot open the video (corrupt, or a codec it lacks)")
    return capture


def scan_video(video: Path) -> tuple[np.ndarray, np.ndarray, float, tuple[int, int]]:
    """(sharpness, timestamps in seconds) of every frame, the frame rate and the frame size (w, h)."""
    import cv2

    capture = _open(video)
    fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
    listed = int(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    scores, times, size = [], [], None
    try:
        while True:
            ok, frame = capture.read()
            if not ok or frame is None:
                break
            if size is None:
                size = (frame.shape[1], frame.shape[0])
            elif (frame.shape[1], frame.shape[0]) != size:
                raise ValueError(f"{video}: frame {len(scores)} is {frame.shape[1]}x{frame.shape[0]}, the first "
                                 f"{size[0]}x{size[1]}; a video's frames must share one size")
            msec = capture.get(cv2.CAP_PROP_POS_MSEC)
            index = len(scores)
            times.append(msec / 1000.0 if msec > 0 or index == 0 else (index / fps if fps > 0 else float(index)))
            scores.append(sharpness(frame))
    finally:
        capture.release()
    if not scores:
        raise ValueError(f"{video}: OpenCV decoded no frame from the video")
    if len(scores) < MIN_DECODED_SHARE * listed:
        raise ValueError(f"{video}: OpenCV decoded {len(scores)} of the {listed} frames the video's header lists "
                         "(truncated, or a frame it cannot decode)")
    if listed > len(scores):
        log.warning("%s: OpenCV decoded %d of the %d frames the video's header lists", video, len(scores), listed)
    return np.asarray(scores), np.asarray(times), fps, size


def extract_frames(video: str | Path, out: str | Path, max_frames: int | None = None) -> Path:
    """Choose frames of `video` (see the module) and write the frames folder `out` atomically."""
    import cv2

    from srfpipe.artifacts import atomic_directory

    video, out = Path(video), Path(out)
    max_frames = DEFAULT_MAX_FRAMES if max_frames is None else int(max_frames)
    if max_frames < 2:
        raise ValueError(f"{video}: source.max_frames must be at least 2, got {max_frames}")
    scores, times, fps, size = scan_video(video)
    chosen, blurred = choose_frames(scores, max_frames)
    if blurred:
        log.info("%s: dropped %d blurred frames (sharpness under %g x their neighbours'): %s", video,
                 len(blurred), BLUR_RATIO, blurred)
    digits = max(5, len(str(len(scores) - 1)))
    names = {index: f"{IMAGES_DIR}/frame_{index:0{digits}d}.png" for index in chosen}
    wanted = set(chosen)
    with atomic_directory(out) as tmp:
        (tmp / IMAGES_DIR).mkdir()
        capture = _open(video)
        try:
            for index in range(max(chosen) + 1):
                if index not in wanted:
                    if not capture.grab():
                        raise ValueError(f"{video}: the video ended at frame {index} on the second read")
                    continue
                ok, frame = capture.read()
                if not ok:
                    raise ValueError(f"{video}: the video ended at frame {index} on the second read")
                if not cv2.imwrite(str(tmp / names[index]), frame):
                    raise OSError(f"{out / names[index]}: OpenCV could not write the frame")
        finally:
            capture.release()
        record = {
            "video": str(video.resolve()),
            "video_bytes": video.stat().st_size,
            "fps": fps,
            "frame_size": list(size),
            "n_video_frames": len(scores),
            "max_frames": max_frames,
            "selection": f"sharpest of {min(max_frames, len(scores))} equal windows (variance of the Laplacian); "
                         f"dropped when under {BLUR_RATIO} x the median of {BLUR_NEIGHBOURS} neighbours either side",
            "blurred_frames": blurred,
            "sharpness_median": float(np.median(scores)),
            "frames": [{"file_path": names[i], "index": i, "timestamp_s": float(times[i]),
                        "sharpness": float(scores[i])} for i in chosen],
        }
        (tmp / FRAMES_FILE).write_text(json.dumps(record, indent=1))
    log.info("%s: chose %d of %d frames (%dx%d, %.3g fps) -> %s", video, len(chosen), len(scores), size[0], size[1],
             fps, out)
    return out


def read_frames(folder: str | Path, allowed_roots=()) -> tuple[list[str], dict]:
    """The frames folder's image paths (relative, checked to stay inside it and to be images) and its
    frames.json, whose `frames` are those kept: a frame whose image was deleted (a user weeding out
    blurred frames) is skipped with a warning and listed in `missing_images` (with `n_frames_listed`);
    a frame listed twice, an `index` or `timestamp_s` that is not a number, a file that is not an
    image are refused, naming the frame."""
    folder = Path(folder)
    path = folder / FRAMES_FILE
    record = load_json(path)
    frames = record.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{path}: 'frames' must be a non-empty list")
    paths, kept, missing = [], [], []
    for i, frame in enumerate(frames):
        where = f"{path}: frame {i}"
        if not isinstance(frame, dict):
            raise ValueError(f"{where} is not an object")
        relative = resolve_inside(folder, frame.get("file_path"), where, allowed_roots)
        check_unique(paths + missing, relative, where)
        if "index" in frame and (isinstance(frame["index"], bool) or not isinstance(frame["index"], int)
                                 or frame["index"] < 0):
            raise ValueError(f"{where}: index must be a frame number (an integer >= 0), got {frame['index']!r}")
        if "timestamp_s" in frame:
            number(frame["timestamp_s"], "timestamp_s", where)
        if not (folder / relative).exists():
            missing.append(relative)
            continue
        check_image_file(folder / relative, where)
        paths.append(relative)
        kept.append(frame)
    extra = record_missing_images(path, len(frames), missing)
    if not paths:
        raise FileNotFoundError(f"{path}: none of the {len(frames)} frames has an image file")
    return paths, {**record, "frames": kept, **extra}


def add_arguments(parser) -> None:
    from srfpipe.config import add_options_arguments

    add_options_arguments(parser, "source")
    parser.add_argument("--video", metavar="FILE", default=None, help="the video (overrides source.path)")
    parser.add_argument("--out", required=True, metavar="DIR", help="frames folder to write (replaced atomically)")


def run(args) -> int:
    from srfpipe.config import stage_options

    source = stage_options(args, "source")
    video = args.video or source.get("path")
    if not video:
        raise ValueError("frames: no video (give --video or source.path)")
    extract_frames(video, args.out, source.get("max_frames"))
    return 0

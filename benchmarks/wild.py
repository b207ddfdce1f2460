"""Benchmark: unposed captures (issue 34 part 1), posed by structure from motion in the poses stage.

* orchard_video  the built-in orchard walked round in one turn and written as a video by the
                 generator (`orchard.video: true`); its frames chosen by `srfpipe frames`
                 (source.max_frames), posed by SfM, compared with the generator's poses.
* fox_sfm        the photos of ../shared/data/fox with its transforms.json ignored, compared with
                 the poses that file holds (COLMAP's, from nerfstudio's ns-process-data).

Both comparisons are after a similarity alignment (`srfpipe.poses.align.pose_errors`): SfM's
world frame and scale are its own. Keys of benchmarks/results/wild.json: orchard_video_registered
(fraction of the chosen frames registered), orchard_video_rot_err_deg, orchard_video_trans_err_pct
(of the tree's bounding-box size), fox_sfm_registered, fox_sfm_rot_err_deg, sfm_seconds (poses
stage wall time for each), and per capture the SfM statistics poses.zarr records. The PSNR, mIoU
and sparse-label keys of the issue need the whole pipeline and are not measured here.

    python benchmarks/wild.py [--quick] [--only orchard_video|fox_sfm] [--workdir DIR]

`--quick` (results/wild_quick.json): a 72-view turn at 320 x 240 with every frame kept, and no fox.
The full run renders 300 views of 640 x 480 and keeps the default 150 frames, then poses the fox's
50 photos of 1080 x 1920 (several minutes each on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from common import REPO, machine_info, result_path, write_result

SHARED = (REPO / ".." / "shared" / "data").resolve()
FOX = SHARED / "fox"
FULL_ORBIT = {"seed": 0, "views": 300, "width": 640, "height": 480, "video": True}
QUICK_ORBIT = {"seed": 0, "views": 72, "width": 320, "height": 240, "video": True}


def _frame_number(name: str) -> int:
    return int(name.rsplit("_", 1)[1])


def orchard_video(workdir: Path, quick: bool, threads: int) -> dict:
    from srfpipe.artifacts import meta, open_artifact
    from srfpipe.poses import import_poses
    from srfpipe.poses.align import pose_errors
    from srfpipe.poses.video import extract_frames
    from srfpipe.scenes.orchard import generate_orchard

    options = QUICK_ORBIT if quick else FULL_ORBIT
    capture = generate_orchard(workdir / "orchard_video" / "generated", progress=False, **options)
    scene = json.loads((capture / "ground_truth" / "scene.json").read_text())
    truth = np.array(scene["camera_to_world"])
    bounds = np.array(scene["bounds_world"])
    source = {"format": "video", "path": str(capture / "video.avi")}
    if quick:
        source["max_frames"] = options["views"]
    started = time.perf_counter()
    frames = extract_frames(source["path"], workdir / "orchard_video" / "capture", source.get("max_frames"))
    extracted = time.perf_counter() - started
    out = import_poses(source, frames, {}, workdir / "orchard_video" / "poses.zarr", threads=threads)
    seconds = time.perf_counter() - started
    info = meta(open_artifact(out, stage="poses"))
    poses = open_artifact(out)["camera_to_world"][:]
    registered = [_frame_number(name) for name in info["names"]]
    errors = pose_errors(poses, truth[registered], float(np.max(bounds[1] - bounds[0])))
    return {
        "orchard_video_registered": info["sfm"]["registered_fraction"],
        "orchard_video_rot_err_deg": errors["rot_err_deg"],
        "orchard_video_trans_err_pct": 100.0 * errors["trans_err"],
        "seconds": seconds,
        "frames_seconds": extracted,
        "orbit": options,
        "frames_chosen": info["sfm"]["n_images"],
        "errors": errors,
        "sfm": info["sfm"],
    }


def fox_sfm(workdir: Path, threads: int) -> dict:
    from srfpipe.artifacts import meta, open_artifact
    from srfpipe.poses import import_poses, load_capture
    from srfpipe.poses.align import pose_errors

    known = load_capture({"format": "nerfstudio", "path": str(FOX)})
    started = time.perf_counter()
    out = import_poses({"format": "images", "path": str(FOX)}, None, {}, workdir / "fox_sfm" / "poses.zarr",
                       threads=threads)
    seconds = time.perf_counter() - started
    info = meta(open_artifact(out, stage="poses"))
    poses = open_artifact(out)["camera_to_world"][:]
    index = {path: i for i, path in enumerate(known.image_paths)}
    matched = [k for k, path in enumerate(info["image_paths"]) if path in index]
    reference = known.camera_to_world[[index[info["image_paths"][k]] for k in matched]]
    centres = reference[:, :3, 3]
    scene_size = float(np.max(np.ptp(centres, axis=0)))
    errors = pose_errors(poses[matched], reference, scene_size)
    return {
        "fox_sfm_registered": info["sfm"]["registered_fraction"],
        "fox_sfm_rot_err_deg": errors["rot_err_deg"],
        "fox_sfm_trans_err_pct_of_camera_spread": 100.0 * errors["trans_err"],
        "seconds": seconds,
        "errors": errors,
        "sfm": info["sfm"],
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="a small turn, every frame kept, no fox")
    parser.add_argument("--only", choices=["orchard_video", "fox_sfm"], default=None)
    parser.add_argument("--workdir", type=Path, default=REPO / "benchmarks" / "work" / "wild")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()

    report: dict = {"machine": machine_info(threads=args.threads), "quick": args.quick, "sfm_seconds": {}}
    if args.only in (None, "orchard_video"):
        entry = orchard_video(args.workdir, args.quick, args.threads)
        report.update({k: v for k, v in entry.items() if k.startswith("orchard_video_")})
        report["sfm_seconds"]["orchard_video"] = entry["seconds"]
        report["orchard_video"] = entry
    if args.only in (None, "fox_sfm") and not args.quick:
        entry = fox_sfm(args.workdir, args.threads)
        report.update({k: v for k, v in entry.items() if k.startswith("fox_sfm_")})
        report["sfm_seconds"]["fox"] = entry["seconds"]
        report["fox_sfm"] = entry
    write_result(result_path("wild", args.quick), report)
    print(json.dumps({k: v for k, v in report.items() if k.endswith(("_registered", "_deg", "_pct", "seconds"))},
                     indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Benchmark: a capture whose calibration misstates its lens, built as given and with its distortion
refined by COLMAP (`poses.refine: colmap` + `poses.refine_distortion: true`).

Issue 30's fruit capture came with a phone's COLMAP model (k1 -0.0024, k2 -0.021, p1 0.011, p2 0.0096)
that undistortion made worse than no undistortion at all. captures.py's orchard-lens renders the
orchard through exactly that lens and states it exactly, and comes within 0.5 dB of the pinhole
orchard: the undistortion is right for a lens stated right. What is left is a lens stated wrong. Here the same
generated orchard (80 views of 605 x 806 through the phone lens) claims the lens without its
tangential terms (p1 = p2 = 0, transforms.json rewritten after the capture is generated), and is
built three ways, every other setting the orchard-lens's:

* `as given`: the claimed lens undistorts the images (pixels up to 25 px off at the frame's corners);
* `poses refined`: COLMAP triangulates from the given poses and bundle-adjusts them, the claimed
  lens held fixed (`poses.refine_distortion: false`; a turn of a camera can absorb part of a
  tangential error);
* `distortion refined`: the same with the lens's distortion freed (`poses.refine_distortion: true`,
  which for a stated lens is what `refine: colmap` does by default, `stated`); downscaling
  undistorts with what it measured.

`--lens right` builds the same three ways with the lens stated right (transforms.json as generated,
all four coefficients): does COLMAP's refinement keep a strong tangential lens that is right, and what
does freeing the distortion cost when nothing was wrong? It writes lens_stated_right.json.
`--iterations N` trains every build for N steps (time budget off), so that the builds compare at
equal steps on any host.

    python benchmarks/lens.py [--quick] [--lens misstated|right] [--iterations N] [--workdir DIR]
                              [--train-seconds S] [--snakemake-args ...]

Writes benchmarks/results/lens.json: per build `psnr`, `psnr_object`, `miou_gt_classes`, `ssim`,
`train_view_psnr`, `steps`, the distortion the images were undistorted with and how far it misplaces
the frame's pixels (`pixel_shift_px_mean`, `pixel_shift_px_max`, full frame: what each pixel shows, seen
through the true lens, projected through the calibration, lands that far from the pixel), and
the orchard-lens's own numbers at the same training time from captures.json (`reference`). Training
gets 300 s each (`--train-seconds`), the panel's 5-minute snapshot time; `--quick` 60 s.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from captures import PHONE_LENS, scene_configs
from common import REPO, machine_info, merge, result_path, run_workflow, write_result, write_workdir

CLAIMED_LENS = [PHONE_LENS[0], PHONE_LENS[1], 0.0, 0.0]  # the tangential terms left out
BUILDS = {
    "as-given": {},
    "poses-refined": {"poses": {"refine": "colmap", "refine_distortion": False}},
    "distortion-refined": {"poses": {"refine": "colmap", "refine_distortion": True}},
}


def misstate_lens(capture: Path, distortion) -> None:
    """Rewrite the generated capture's transforms.json to claim `distortion` (k1, k2, p1, p2); a
    capture that claims it already is left untouched (a re-run rebuilds nothing it built)."""
    path = capture / "transforms.json"
    transforms = json.loads(path.read_text())
    claimed = dict(zip(("k1", "k2", "p1", "p2"), (float(v) for v in distortion)))
    if all(transforms.get(key) == value for key, value in claimed.items()):
        return
    path.write_text(json.dumps({**transforms, **claimed}, indent=1))


def pixel_shift_px(intrinsics, size, true_lens, lens) -> tuple[float, float]:
    """Mean and largest distance (pixels) between each pixel of a frame of `size` (width, height)
    and where `lens` projects the direction that `true_lens` sees through it (OpenCV's model)."""
    import cv2

    from srfpipe import cameras

    u, v = np.meshgrid(np.arange(size[0]) + 0.5, np.arange(size[1]) + 0.5)
    x, y = cameras.undistort_normalized(u, v, intrinsics, true_lens)
    directions = np.stack([x.ravel(), y.ravel(), np.ones(x.size)], axis=-1)
    fx, fy, cx, cy = (float(c) for c in intrinsics)
    projected, _ = cv2.projectPoints(directions, np.zeros(3), np.zeros(3), cameras.intrinsic_matrix(fx, fy, cx, cy),
                                     np.asarray(lens, dtype=np.float64))
    shift = np.linalg.norm(projected.reshape(-1, 2) - np.stack([u.ravel(), v.ravel()], axis=-1), axis=-1)
    return float(shift.mean()), float(shift.max())


def lens_builds(lens: str) -> tuple[list[float], str, str]:
    """The distortion the capture claims, the result's name and the builds' scene prefix, for `--lens`."""
    if lens == "misstated":
        return CLAIMED_LENS, "lens", "lens-"
    return list(PHONE_LENS), "lens_stated_right", "lens-right-"


def build_report(workdir: Path, name: str) -> dict:
    from srfpipe.artifacts import open_artifact, read_provenance

    results = workdir / "results" / name
    metrics = json.loads((results / "eval" / "metrics.json").read_text())
    poses = open_artifact(results / "poses.zarr", stage="poses")
    distortion = np.asarray(poses["distortion"][0], dtype=np.float64)
    intrinsics = np.asarray(poses["intrinsics"][0], dtype=np.float64)
    size = tuple(int(v) for v in poses["image_size"][0])
    mean, largest = pixel_shift_px(intrinsics, size, PHONE_LENS, distortion)
    refinement = read_provenance(results / "poses.zarr").get("refinement") or {}
    srf = read_provenance(results / "srf.zarr")
    report = {key: metrics.get(key) for key in ("psnr", "psnr_object", "ssim", "miou_gt_classes", "train_view_psnr",
                                                 "generalization_gap_db")}
    report.update(steps=srf.get("iterations_done"), distortion=distortion.tolist(),
                  pixel_shift_px_mean=mean, pixel_shift_px_max=largest,
                  reprojection_error_px=refinement.get("reprojection_error_after_px"))
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="60 s of training per build")
    parser.add_argument("--workdir", type=Path, default=REPO / "benchmarks" / "work" / "lens")
    parser.add_argument("--train-seconds", type=float, default=300.0)
    parser.add_argument("--lens", choices=("misstated", "right"), default="misstated",
                        help="the calibration the capture claims: without its tangential terms (lens.json), or "
                             "the lens as it is (lens_stated_right.json)")
    parser.add_argument("--iterations", type=int, default=None,
                        help="train every build for this many steps, time budget off (equal steps on any host)")
    parser.add_argument("--snakemake-args", nargs=argparse.REMAINDER, default=[],
                        help="more Snakemake arguments (last), e.g. --rerun-triggers mtime")
    args = parser.parse_args()
    extra = tuple(args.snakemake_args)
    seconds = 60.0 if args.quick else args.train_seconds

    claimed, result_name, prefix = lens_builds(args.lens)
    budget = {"time_budget": seconds} if args.iterations is None else {"time_budget": 0, "iterations": args.iterations}
    base = scene_configs(["orchard-lens"], quick=False)["orchard-lens"]
    scenes = {}
    for build, overrides in BUILDS.items():
        scene = merge(base, overrides)
        scene.setdefault("train", {}).update(budget)
        scene["train"].pop("snapshot_seconds", None)
        scenes[f"{prefix}{build}"] = scene
    write_workdir(args.workdir, scenes, "eval")
    log = args.workdir / "snakemake.log"
    for name in scenes:
        run_workflow(args.workdir, [f"results/{name}/capture"], log=log, extra=extra)
        misstate_lens(args.workdir / "results" / name / "capture", claimed)
    for name in scenes:
        run_workflow(args.workdir, [f"results/{name}/eval"], log=log, extra=extra)

    builds = {name.removeprefix(prefix): build_report(args.workdir, name) for name in scenes}
    captures = json.loads((REPO / "benchmarks" / "results" / "captures.json").read_text())
    panel = captures.get("panel", {}).get("orchard-lens", {})
    report = {
        "machine": machine_info(),
        "true_lens": PHONE_LENS, "claimed_lens": claimed,
        "train": budget,
        "train_seconds": seconds if args.iterations is None else None,
        "builds": builds,
        "reference": {"orchard_lens_psnr_5min": panel.get("srfpipe_psnr_5min"),
                      "orchard_lens_psnr_10min": panel.get("psnr"),
                      "source": "captures.json panel: the same images with the lens stated right"},
        "psnr_gain_db": builds["distortion-refined"]["psnr"] - builds["as-given"]["psnr"],
        "psnr_gain_poses_only_db": builds["poses-refined"]["psnr"] - builds["as-given"]["psnr"],
    }
    path = write_result(result_path(result_name, args.quick), report)
    print(f"{'build':<20} {'psnr':>7} {'object':>7} {'mIoU':>6} {'train':>7} {'steps':>6} {'pixel shift mean/max':>20}")
    for name, row in builds.items():
        print(f"{name:<20} {row['psnr']:7.2f} {row['psnr_object'] or float('nan'):7.2f} "
              f"{row['miou_gt_classes'] or float('nan'):6.2f} {row['train_view_psnr'] or float('nan'):7.2f} "
              f"{row['steps'] or 0:6d} {row['pixel_shift_px_mean']:9.2f} / {row['pixel_shift_px_max']:.2f}")
    print(f"orchard-lens, lens stated right: {panel.get('srfpipe_psnr_5min')} dB at 5 min; wrote {path}")


if __name__ == "__main__":
    main()

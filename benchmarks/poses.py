"""Benchmark: does COLMAP refinement repair perturbed poses on the orchard?

Builds, through the Snakemake workflow in a scratch work directory, the orchard capture and two
pose artifacts from it, both with the same deliberate perturbation (1 deg rotation about a random
axis, 2 % of the scene size translation, per camera):

* `perturbed/poses.zarr`: imported and perturbed, not refined;
* `refined/poses.zarr`: imported, perturbed, then refined with COLMAP (`poses.refine: colmap`).

Both are compared with the generator's exact poses (the capture's transforms.json) after a
similarity alignment of the camera centres; translation errors are relative to the scene size
(the largest side of the scene bounds). Writes benchmarks/results/poses.json; exits 1 when
refinement does not lower both errors.

    python benchmarks/poses.py            # the default orchard: 80 views of 640x480
    python benchmarks/poses.py --quick    # 48 views of 640x480 (wider baselines: fewer images refined)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from common import machine_info, result_path, rule_seconds, run_workflow, write_result, write_workdir

PERTURBATION = {"perturb_rot_deg": 1.0, "perturb_trans_frac": 0.02, "perturb_seed": 0}


def scenes(orchard: dict) -> dict:
    """Two scenes from one capture: refined with COLMAP, and the same perturbed poses unrefined."""
    refined = {"source": {"format": "orchard"}, "orchard": orchard,
               "poses": {"refine": "colmap", **PERTURBATION}}
    # the same capture (the refined scene's generated folder), imported as plain nerfstudio data
    perturbed = {"source": {"format": "nerfstudio", "path": "results/refined/capture"},
                 "poses": {"refine": "none", **PERTURBATION}}
    return {"refined": refined, "perturbed": perturbed}


def evaluate(workdir: Path) -> dict:
    from srfpipe.artifacts import meta, open_artifact
    from srfpipe.poses.align import pose_errors
    from srfpipe.poses.nerfstudio import read_nerfstudio

    truth = read_nerfstudio(workdir / "results" / "refined" / "capture").camera_to_world
    results = {}
    for scene in ("perturbed", "refined"):
        group = open_artifact(workdir / "results" / scene / "poses.zarr", stage="poses")
        info = meta(group)
        bounds = np.asarray(info["bounds_world"])
        errors = pose_errors(group["camera_to_world"][:], truth, scene_size=float(np.max(bounds[1] - bounds[0])))
        results[scene] = {"errors": errors, "refinement": info["refinement"], "bounds_source": info["bounds_source"]}
    return results


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="48 views instead of the default orchard's 80")
    parser.add_argument("--workdir", type=Path, default=None, help="scratch folder (default: a temporary one)")
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--out", type=Path, help="result file (default: benchmarks/results/poses[_quick].json)")
    args = parser.parse_args(argv)
    import pycolmap

    orchard = {"views": 48, "width": 640, "height": 480} if args.quick else {}
    with tempfile.TemporaryDirectory(prefix="srfpipe-bench-poses-") as tmp:
        workdir = args.workdir or Path(tmp)
        write_workdir(workdir, scenes(orchard), final_artifact="poses")
        wall = run_workflow(workdir, [f"results/{scene}/poses.zarr" for scene in ("refined", "perturbed")],
                            args.cores, extra=("--quiet", "rules"))
        results = evaluate(workdir)
        refined = results["refined"]
        report = {
            "rot_err_deg_before": results["perturbed"]["errors"]["rot_err_deg"],
            "rot_err_deg_after": refined["errors"]["rot_err_deg"],
            "trans_err_before": results["perturbed"]["errors"]["trans_err"],
            "trans_err_after": refined["errors"]["trans_err"],
            "rot_err_deg_max_after": refined["errors"]["rot_err_deg_max"],
            "trans_err_max_after": refined["errors"]["trans_err_max"],
            "reprojection_error_before_px": refined["refinement"]["reprojection_error_before_px"],
            "reprojection_error_after_px": refined["refinement"]["reprojection_error_after_px"],
            "num_points3D": refined["refinement"]["num_points3D"],
            "num_images": refined["refinement"]["num_images"],
            "num_images_refined": refined["refinement"]["num_images_refined"],
            "matcher": refined["refinement"]["matcher"],
            "refine_rule_seconds": rule_seconds(workdir, "refined", "poses"),
            "capture_rule_seconds": rule_seconds(workdir, "refined", "orchard_capture"),
            "snakemake_wall_seconds": wall,
            "quick": args.quick,
            "config": {"orchard": orchard or "schema defaults (80 views of 640x480)", "poses": PERTURBATION,
                       "translation_error": "camera-centre error / largest side of bounds_world, after the "
                                            "similarity that best aligns the cameras (centres and axes, "
                                            "srfpipe.poses.align_poses) to the ground truth"},
            "machine": machine_info(cores=args.cores, pycolmap=pycolmap.__version__),
        }
    lowered = report["rot_err_deg_after"] < report["rot_err_deg_before"] and \
        report["trans_err_after"] < report["trans_err_before"]
    report["refinement_lowers_error"] = lowered
    out = write_result(args.out or result_path("poses", args.quick), report)

    print(f"{'':24}{'before':>12}{'after':>12}")
    print(f"{'rotation error (deg)':24}{report['rot_err_deg_before']:12.4f}{report['rot_err_deg_after']:12.4f}")
    print(f"{'translation error (rel)':24}{report['trans_err_before']:12.5f}{report['trans_err_after']:12.5f}")
    print(f"{'reprojection error (px)':24}{report['reprojection_error_before_px']:12.3f}"
          f"{report['reprojection_error_after_px']:12.3f}")
    print(f"points {report['num_points3D']}, images refined {report['num_images_refined']}/{report['num_images']}, "
          f"refine rule {report['refine_rule_seconds']} s -> {out}")
    return 0 if lowered else 1


if __name__ == "__main__":
    sys.exit(main())

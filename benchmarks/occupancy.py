"""Benchmark: the occupancy cache of the demo orchard against its ground-truth meshes, and its speed.

Builds the demo orchard (config/scenes/orchard.yaml) to occupancy.zarr through the Snakemake
workflow, voxelizes the ground-truth meshes (capture/ground_truth/meshes/{apple,branch,leaf}.ply)
on the cache's own grid (open3d triangle-box voxelization; apples and branches are closed, so
their interiors are filled, leaves are surfaces), and measures:

* iou_<class>: per-class occupancy IoU over the grid; apple_precision / apple_recall;
  branch_recall (thin structures). The ground truth is conservative (a voxel any triangle crosses
  is occupied), so `exact_field_apples` distills the exact apple spheres (apples.json) with the
  same options: the ceiling that distillation alone allows against this ground truth;
* lookups_per_s: batched nearest-voxel occupancy lookups (10 M random points in the grid box);
* trilinear_per_s: trilinear semantic queries (all classes per point);
* cache_vs_network_speedup: lookups_per_s / the trained network's density queries per second.

Writes benchmarks/results/occupancy.json.

    python benchmarks/occupancy.py                    # demo scene, --iterations 300 training steps
    python benchmarks/occupancy.py --quick            # 16 views, 60 steps, 4 cm voxels
    python benchmarks/occupancy.py --srf S --capture C  # reuse a trained srf.zarr and its capture folder
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from common import REPO, machine_info, result_path, rule_seconds, run_workflow, write_result, write_workdir

MESH_CLASSES = {"apple": True, "branch": True, "leaf": False}  # name -> closed (fill the interior)


def scene_config(quick: bool, iterations: int) -> dict:
    scene = yaml.safe_load((REPO / "config" / "scenes" / "orchard.yaml").read_text())
    if quick:
        scene.setdefault("orchard", {})["views"] = 16
        scene.setdefault("occupancy", {})["voxel_size"] = 0.04
    scene.setdefault("train", {})["iterations"] = iterations
    return scene


def voxelize_mesh(path: Path, grid, closed: bool) -> np.ndarray:
    """Voxels (z, y, x) of `grid` that the mesh's triangles cross; with `closed`, plus the inside."""
    import open3d as o3d
    from scipy.ndimage import binary_fill_holes

    mesh = o3d.io.read_triangle_mesh(str(path))
    box = grid.bounds_world
    voxels = o3d.geometry.VoxelGrid.create_from_triangle_mesh_within_bounds(
        mesh, voxel_size=grid.voxel_size, min_bound=box[0], max_bound=box[1])
    out = np.zeros(grid.shape, dtype=bool)
    index = np.array([v.grid_index for v in voxels.get_voxels()], dtype=np.int64).reshape(-1, 3)
    index = index[np.all((index >= 0) & (index < grid.dims_xyz), axis=1)]
    out[index[:, 2], index[:, 1], index[:, 0]] = True
    return binary_fill_holes(out) if closed else out


def class_accuracy(cache, ground_truth: Path, classes: dict = MESH_CLASSES) -> tuple[dict, dict]:
    """iou_/precision_/recall_/voxels_true_/voxels_pred_<class> of the cache's class occupancy against
    ground_truth/meshes/<class>.ply voxelized on the cache's grid, for each of `classes` (name ->
    closed); and the voxelized ground truth of each class (z, y, x). A class the cache lacks predicts
    nothing. benchmarks/tradeoff.py reports these per setting."""
    from srfpipe.artifacts import open_artifact

    predicted = open_artifact(cache.path, stage="distill")["class_occupancy"][...].astype(bool)
    metrics, truths = {}, {}
    for name, closed in classes.items():
        truth = voxelize_mesh(ground_truth / "meshes" / f"{name}.ply", cache.grid, closed)
        pred = predicted[cache.classes.index(name)] if name in cache.classes else np.zeros_like(truth)
        tp = float(np.logical_and(pred, truth).sum())
        union = float(np.logical_or(pred, truth).sum())
        metrics[f"iou_{name}"] = round(tp / union, 4) if union else 1.0
        metrics[f"precision_{name}"] = round(tp / pred.sum(), 4) if pred.sum() else 0.0
        metrics[f"recall_{name}"] = round(tp / truth.sum(), 4) if truth.sum() else 1.0
        metrics[f"voxels_true_{name}"] = int(truth.sum())
        metrics[f"voxels_pred_{name}"] = int(pred.sum())
        truths[name] = truth
    return metrics, truths


def accuracy(cache, ground_truth: Path) -> dict:
    from srfpipe.artifacts import open_artifact

    group = open_artifact(cache.path, stage="distill")
    metrics, truths = class_accuracy(cache, ground_truth)
    metrics["iou_by_alpha_threshold"] = threshold_sweep(group, cache, truths)
    metrics["apple_precision"] = metrics["precision_apple"]
    metrics["apple_recall"] = metrics["recall_apple"]
    metrics["branch_recall"] = metrics["recall_branch"]
    return metrics


def threshold_sweep(group, cache, truths: dict) -> dict:
    """Per-class IoU if the cache had used another alpha threshold (density and probability are
    stored, so occupancy can be re-thresholded without distilling again)."""
    from srfpipe.occupancy.distill import voxel_alpha

    meta_thresholds = cache.attrs["thresholds"]["class_thresholds"]
    alpha = voxel_alpha(group["density"][...], cache.voxel_size)
    probability = group["probability"][...] / 255.0
    sweep = {}
    for threshold in (0.01, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7):
        occupied = alpha >= threshold
        row = {}
        for name, truth in truths.items():
            if name not in cache.classes:
                continue
            pred = occupied & (probability[cache.classes.index(name)] > meta_thresholds[name])
            union = np.logical_or(pred, truth).sum()
            row[name] = round(float(np.logical_and(pred, truth).sum() / union), 4) if union else 1.0
        sweep[str(threshold)] = row
    return sweep


def distillation_ceiling(cache, ground_truth: Path, workdir: Path) -> dict:
    """Apple accuracy when the field is exact: distill the analytic apples (apples.json spheres) with
    the same options and grid, against the same voxelized apple.ply. What distillation alone loses."""
    from srfpipe.occupancy import AnalyticField, distill

    apples = json.loads((ground_truth / "apples.json").read_text())
    field = AnalyticField(list(cache.classes), np.asarray(cache.attrs["field_bounds_world"]))
    for apple in apples:
        field.add_sphere(apple["centre"], apple["radius"], "apple")
    path = distill(field, workdir / "analytic_apples.zarr", cache.attrs["config"], progress=False)
    from srfpipe.artifacts import open_artifact

    pred = open_artifact(path, stage="distill")["class_occupancy"][cache.classes.index("apple")].astype(bool)
    truth = voxelize_mesh(ground_truth / "meshes" / "apple.ply", cache.grid, closed=True)
    tp = float(np.logical_and(pred, truth).sum())
    return {"iou_apple": round(tp / float(np.logical_or(pred, truth).sum()), 4),
            "apple_precision": round(tp / max(float(pred.sum()), 1.0), 4),
            "apple_recall": round(tp / max(float(truth.sum()), 1.0), 4)}


def best_rate(fn, count: int, repeats: int = 3) -> float:
    fn()  # warm up (numba compiles or loads its cache)
    best = np.inf
    for _ in range(repeats):
        started = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - started)
    return count / best


def throughput(cache, srf_path: Path, n_points: int) -> dict:
    from srfpipe.srf.query import SemanticRadianceField

    rng = np.random.default_rng(0)
    box = cache.bounds_world
    points = rng.uniform(box[0], box[1], size=(n_points, 3)).astype(np.float32)
    lookups = best_rate(lambda: cache.occupancy(points), n_points)
    trilinear = best_rate(lambda: cache.semantic(points), n_points)
    field = SemanticRadianceField.load(srf_path, device="cpu")
    sample = points[: 1 << 17].astype(np.float64)
    network_density = best_rate(lambda: field.density(sample), len(sample), repeats=2)
    network_semantic = best_rate(lambda: field.semantic(sample), len(sample), repeats=2)
    return {
        "lookups_per_s": round(lookups),
        "trilinear_per_s": round(trilinear),
        "network_density_per_s": round(network_density),
        "network_semantic_per_s": round(network_semantic),
        "cache_vs_network_speedup": round(lookups / network_density, 1),
        "semantic_cache_vs_network_speedup": round(trilinear / network_semantic, 1),
        "points": n_points,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="16 views, 60 training steps, 4 cm voxels")
    parser.add_argument("--iterations", type=int, default=None,
                        help="training steps (default 300, quick 60; the CPU trains at seconds per step)")
    parser.add_argument("--workdir", type=Path, help="keep the Snakemake work directory here")
    parser.add_argument("--srf", type=Path, help="skip the build: distill this trained srf.zarr ...")
    parser.add_argument("--capture", type=Path, help="... and compare with this capture's ground_truth/")
    parser.add_argument("--voxel-size", type=float, default=None, help="with --srf: voxel size (default: schema)")
    parser.add_argument("--points", type=int, default=10_000_000, help="points per throughput batch")
    parser.add_argument("--out", type=Path, help="result file (default: benchmarks/results/occupancy[_quick].json)")
    args = parser.parse_args(argv)

    from srfpipe.occupancy import OccupancyCache, distill

    iterations = args.iterations or (60 if args.quick else 300)
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="srfpipe-occupancy-bench-"))
    timings = {}
    if args.srf:
        if not args.capture:
            parser.error("--srf needs --capture (the folder holding ground_truth/)")
        from srfpipe.srf.query import SemanticRadianceField

        srf_path, ground_truth = args.srf, args.capture / "ground_truth"
        options = {"voxel_size": args.voxel_size} if args.voxel_size else {}
        started = time.perf_counter()
        distill(SemanticRadianceField.load(srf_path, device="cpu"), workdir / "occupancy.zarr", options,
                inputs=[srf_path])
        timings["distill_s"] = round(time.perf_counter() - started, 1)
        cache_path = workdir / "occupancy.zarr"
        scene = {"srf": str(srf_path), "occupancy": options}
    else:
        scene = scene_config(args.quick, iterations)
        write_workdir(workdir, {"orchard": scene}, final_artifact="occupancy")
        timings["build_s"] = round(run_workflow(workdir, ["results/orchard/occupancy.zarr"]), 1)
        for rule in ("train", "distill"):
            timings[f"{rule}_s"] = rule_seconds(workdir, "orchard", rule)
        root = workdir / "results" / "orchard"
        srf_path, ground_truth, cache_path = root / "srf.zarr", root / "capture" / "ground_truth", root / "occupancy.zarr"

    cache = OccupancyCache.load(cache_path)
    from srfpipe.artifacts import read_provenance

    srf_meta = read_provenance(srf_path)
    result = {
        **accuracy(cache, ground_truth),
        "exact_field_apples": distillation_ceiling(cache, ground_truth, workdir),
        **throughput(cache, srf_path, args.points),
        "grid_shape_zyx": list(cache.grid.shape),
        "voxel_size": cache.voxel_size,
        "occupied_voxels": cache.attrs["counts"]["occupied_voxels"],
        "stored_bytes": sum(p.stat().st_size for p in Path(cache_path).rglob("*") if p.is_file()),
        "training": {"iterations": srf_meta.get("final", {}).get("step"), "psnr": srf_meta.get("final", {}).get("psnr"),
                     "semantic_loss": srf_meta.get("final", {}).get("semantic")},
        **timings,
        "quick": args.quick,
        "config": {"scene": scene, "occupancy": cache.attrs["config"]},
        "machine": machine_info(cores=2),
    }
    write_result(args.out or result_path("occupancy", args.quick), result)
    keys = ["iou_apple", "iou_branch", "iou_leaf", "apple_precision", "apple_recall", "branch_recall",
            "lookups_per_s", "trilinear_per_s", "network_density_per_s", "cache_vs_network_speedup"]
    width = max(map(len, keys))
    for key in keys:
        value = result[key]
        print(f"{key:<{width}}  {value:,.4g}" if value < 1000 else f"{key:<{width}}  {value / 1e6:,.1f} M")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark: the built-in segmenter's masks against ground truth on the demo orchard.

Builds the demo orchard (seed 0, which the shipped model never saw) to labels.zarr through the
Snakemake workflow and measures, per class, the IoU (and precision, recall) of the composited
label image against `ground_truth/labels` of images.zarr (each pixel: the class covering most of
its full-resolution footprint), pooled over all frames. Writes benchmarks/results/masks.json with
iou_apple, iou_branch, iou_leaf.

    python benchmarks/masks.py            # the demo scene: 80 views, 640x480 -> 160x120
    python benchmarks/masks.py --quick    # 16 views
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

from common import REPO, machine_info, result_path, rule_seconds, run_workflow, write_result, write_workdir

CLASSES = {"apple": 1, "branch": 2, "leaf": 3}  # ground-truth label values


def scene_config(views: int) -> dict:
    demo = yaml.safe_load((REPO / "config" / "scenes" / "orchard.yaml").read_text())
    demo.setdefault("orchard", {})["views"] = views
    demo.setdefault("segmentation", {})["prompts"] = list(CLASSES)
    return demo


def measure(workdir: Path) -> dict:
    from srfpipe.artifacts import meta, open_artifact

    root = workdir / "results" / "orchard"
    truth = np.asarray(open_artifact(root / "images.zarr")["ground_truth/labels"][:])
    labels = open_artifact(root / "labels.zarr", stage="composite")
    label = np.asarray(labels["label"][:])
    values = meta(labels)["class_values"]
    metrics = {}
    for name, true_value in CLASSES.items():
        pred = label == values.get(name, -1)
        gt = truth == true_value
        both, union = np.logical_and(pred, gt).sum(), np.logical_or(pred, gt).sum()
        metrics[f"iou_{name}"] = round(float(both / union), 4) if union else 1.0
        metrics[f"precision_{name}"] = round(float(both / max(pred.sum(), 1)), 4)
        metrics[f"recall_{name}"] = round(float(both / max(gt.sum(), 1)), 4)
        metrics[f"gt_fraction_{name}"] = round(float(gt.mean()), 5)
    metrics["frames"] = int(label.shape[0])
    metrics["resolution"] = [int(label.shape[2]), int(label.shape[1])]
    return metrics


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="16 views instead of the demo's 80")
    parser.add_argument("--workdir", type=Path, help="keep the Snakemake work directory here")
    parser.add_argument("--out", type=Path, help="result file (default: benchmarks/results/masks[_quick].json)")
    args = parser.parse_args(argv)

    views = 16 if args.quick else 80
    scene = scene_config(views)
    with tempfile.TemporaryDirectory(prefix="srfpipe-masks-") as tmp:
        workdir = (args.workdir or Path(tmp)).resolve()
        write_workdir(workdir, {"orchard": scene}, final_artifact="labels")
        seconds = run_workflow(workdir, ["results/orchard/labels.zarr"])
        metrics = measure(workdir)
        metrics["segment_seconds"] = round(rule_seconds(workdir, "orchard", "segment_*"), 2)
    model_card = json.loads((REPO / "srfpipe" / "models" / "orchard_segmenter.json").read_text())
    result = {
        **metrics,
        "build_seconds": round(seconds, 1),
        "targets": {"iou_apple": 0.85, "iou_branch": 0.6, "iou_leaf": 0.85},
        "quick": args.quick,
        "scene": scene,
        "model": {"file": model_card["file"], "parameters": model_card["parameters"],
                  "training_seeds": model_card["training"]["seeds"]},
        "machine": machine_info(cores=2),
    }
    print(f"{'class':<8}{'IoU':>8}{'precision':>11}{'recall':>8}{'target':>8}")
    for name in CLASSES:
        print(f"{name:<8}{result['iou_' + name]:>8.3f}{result['precision_' + name]:>11.3f}"
              f"{result['recall_' + name]:>8.3f}{result['targets']['iou_' + name]:>8.2f}")
    print(f"{metrics['frames']} frames at {metrics['resolution'][0]}x{metrics['resolution'][1]}, "
          f"segment jobs {metrics['segment_seconds']:.1f} s, build {seconds:.0f} s")
    write_result(args.out or result_path("masks", args.quick), result)
    return 0


if __name__ == "__main__":
    sys.exit(main())

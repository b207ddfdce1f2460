"""Benchmark: which appearance a new view is rendered with (`train.novel_view_appearances`).

A capture with per-image appearance embeddings (the panel's real ones: fox, bottle, fern, beer)
has no embedding for a view no training image was taken from. Each trained field is scored
here several times, the same field each time, so the differences are the rendering's alone:
with the appearance of the nearest training image (1), and with the weighted mean of what the
appearances of its 2 and 3 nearest training images make of the view (`nearest_training_views`).

    python benchmarks/appearance.py [--scenes beer bottle ...] [--counts 1 2 3] [--quick]

It scores the fields of `benchmarks/work/captures-candidate` (or --workdir), building a capture
there with its panel settings and a 10-minute training (`captures.py`'s scene files) when its
srf.zarr is missing. Writes benchmarks/results/appearance.json (a run of some captures keeps the
others' rows): per capture and count, `psnr`,
`ssim`, `train_view_psnr` (each training view with its own appearance: unchanged by the count),
`generalization_gap_db`, `train_view_psnr_borrowed_appearance`, `appearance_gap_db`,
`psnr_change_db` against the count 1, and `evaluate_seconds` (the whole evaluation: held-out
and training views, the second renders with borrowed appearance, metrics and figures).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from common import REPO, machine_info, result_path, run_workflow, write_result, write_workdir

REAL_CAPTURES = ("fox", "bottle", "fern", "beer")
KEYS = ("psnr", "ssim", "psnr_object", "train_view_psnr", "generalization_gap_db",
        "train_view_psnr_borrowed_appearance", "appearance_gap_db")


def score(results: Path, name: str, counts: list[int]) -> dict:
    """The held-out metrics of `name`'s field rendered with each count of nearest appearances."""
    from srfpipe.evaluate import evaluate_field
    from srfpipe.srf.data import load_posed_images
    from srfpipe.srf.query import SemanticRadianceField

    folder = results / name
    field = SemanticRadianceField.load(folder / "srf.zarr", "cpu")
    data = load_posed_images(folder / "images.zarr", folder / "labels.zarr")
    rows = {}
    for count in counts:
        field.model.field.novel_view_appearances = int(count)
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            metrics = evaluate_field(field, data, Path(tmp) / "eval", {}, folder / "labels.zarr", folder / "srf.zarr")
            seconds = time.perf_counter() - start
        rows[str(count)] = {**{key: metrics.get(key) for key in KEYS}, "evaluate_seconds": seconds}
        print(f"{name:8s} {count}  " + "  ".join(f"{key} {rows[str(count)][key]:.2f}" for key in KEYS
                                                  if rows[str(count)][key] is not None), flush=True)
    for row in rows.values():
        row["psnr_change_db"] = row["psnr"] - rows[str(counts[0])]["psnr"]
    return {"counts": rows, "steps": field.attrs.get("iterations_done"), "trained_with":
            field.model.config.get("novel_view_appearances", 1)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=list(REAL_CAPTURES), choices=REAL_CAPTURES)
    parser.add_argument("--counts", nargs="+", type=int, default=[1, 2, 3])
    parser.add_argument("--workdir", type=Path, default=REPO / "benchmarks" / "work" / "captures-candidate")
    parser.add_argument("--quick", action="store_true", help="60 s of training where a field is built")
    args = parser.parse_args()
    if min(args.counts) < 1:
        parser.error("--counts: each count is at least 1")

    from captures import scene_configs

    results = args.workdir / "results"
    missing = [name for name in args.scenes if not (results / name / "srf.zarr").exists()]
    if missing:
        write_workdir(args.workdir, scene_configs(missing, args.quick), "occupancy")
        run_workflow(args.workdir, [f"results/{name}/srf.zarr" for name in missing],
                     log=args.workdir / "snakemake.log")
    path = result_path("appearance", args.quick)
    report = json.loads(path.read_text()) if path.exists() else {"scenes": {}}  # other captures' rows stay
    machine = machine_info(quick=args.quick)
    report.update(machine=machine, measured_now=[])
    for name in args.scenes:  # written after each capture: an interrupted run keeps what it measured
        report["scenes"][name] = {**score(results, name, sorted(args.counts)), "machine": machine}
        report["measured_now"].append(name)
        write_result(path, report)
    print(json.dumps({name: {c: round(r["psnr_change_db"], 2) for c, r in entry["counts"].items()}
                      for name, entry in report["scenes"].items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

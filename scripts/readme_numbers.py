"""Write the README's headline table from benchmarks/results/*.json, so no number there can go stale.

Every number in the table's `headline` column is read from the JSON file its row links (and, for the
peers row, the panel in captures.json), formatted to the precision shown. Edit a row's wording here,
not in README.md; re-run after a benchmark writes its JSON. tests/test_readme.py fails when the
README's table differs from what this script writes.

Usage: python scripts/readme_numbers.py [--check]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
RESULTS = REPO / "benchmarks" / "results"
HEADER = "| benchmark | what | headline | results |"


def load(name: str) -> dict:
    return json.loads((RESULTS / f"{name}.json").read_text(encoding="utf-8"))


def margins(panel: dict) -> list[float]:
    """srfpipe's 10-minute held-out PSNR minus nerfacto's, per panel capture nerfacto ran on."""
    return [entry["psnr"] - entry["nerfacto_psnr_10min"] for entry in panel.values()
            if entry.get("nerfacto_psnr_10min") is not None]


def headline_rows() -> list[tuple[str, str, str]]:
    """(benchmark, what, headline) per row, the headline's numbers read from the benchmark's JSON."""
    train, captures, peers, tradeoff = load("train"), load("captures"), load("peers"), load("tradeoff")
    occupancy, sim, masks, poses = load("occupancy"), load("sim"), load("masks"), load("poses")
    wild, cluster, reliability, lens = load("wild"), load("cluster"), load("reliability"), load("lens")

    panel = captures["panel"]
    psnrs = [entry["psnr"] for entry in panel.values()]
    ahead = margins(panel)
    ahead_of = f"{sum(m > 0 for m in ahead)} of {len(ahead)}"
    earlier = sum(1 for name in panel if captures["scenes"].get(name, {}).get("measured_in_an_earlier_run"))
    presets = tradeoff["presets"]
    posed = wild["posed_reference"]["orchard"]
    return [
        ("train", "orchard, 10 min of training, 10 held-out views",
         f"PSNR {train['psnr']:.1f} dB, SSIM {train['ssim']:.2f}, mIoU {train['miou']:.2f} "
         f"(targets {train['targets']['psnr']:g} dB, {train['targets']['miou']:.2f})"),
        ("captures", f"{len(panel)} captures, defaults, 10 min",
         f"held-out {min(psnrs):.1f}-{max(psnrs):.1f} dB, ahead of nerfacto on {ahead_of} "
         f"({earlier} from earlier runs); small plant mIoU {panel['plant-small']['miou_classes']:.2f}"),
        ("peers", "against nerfstudio's nerfacto, same images, cores",
         f"orchard: its 5-min PSNR {peers['orchard']['time_to_nerfacto300_ratio']:.1f}x sooner; 10 min: ahead on "
         f"{ahead_of} ({min(ahead):+.1f} to {max(ahead):+.1f} dB)"),
        ("tradeoff", "presets and knobs, orchard and plant",
         f"orchard: `fast` {presets['fast']['psnr']:.1f} dB in {presets['fast']['train_seconds'] / 60:.0f} min, "
         f"`balanced` {presets['balanced']['psnr']:.1f} in {presets['balanced']['train_seconds'] / 60:.0f}, "
         f"`accurate` {presets['accurate']['psnr']:.1f} in {presets['accurate']['train_seconds'] / 60:.0f}"),
        ("occupancy", f"{occupancy['voxel_size'] * 100:.0f} cm cache against true meshes; query speed",
         f"IoU apple {occupancy['iou_apple']:.2f}, branch {occupancy['iou_branch']:.2f}; "
         f"{occupancy['lookups_per_s'] / 1e6:.0f} M lookups/s, {occupancy['cache_vs_network_speedup']:.0f}x the network"),
        ("sim", "apple reaching in the orchard's package",
         f"scripted success {sim['scripted_success_rate']:.2f} (random {sim['random_success_rate']:.2f}); "
         f"{sim['config']['wrist'].split(',')[0]} wrist view {sim['render_hz']:.0f} Hz; contact {sim['contact_ms']:.2f} ms"),
        ("masks", "built-in segmenter against ground truth",
         f"IoU apple {masks['iou_apple']:.2f}, branch {masks['iou_branch']:.2f}, leaf {masks['iou_leaf']:.2f}"),
        ("poses", "COLMAP refinement of perturbed orchard poses",
         f"rotation error {poses['rot_err_deg_before']:.3f} -> {poses['rot_err_deg_after']:.3f} deg, translation "
         f"{poses['trans_err_before'] * 100:.2f} % -> {poses['trans_err_after'] * 100:.2f} %"),
        ("lens", "phone lens misstated (no tangential terms)",
         f"COLMAP refinement, lens held {lens['builds']['poses-refined']['psnr']:.2f} dB, distortion refined "
         f"{lens['builds']['distortion-refined']['psnr']:.2f} (stated right "
         f"{lens['reference']['orchard_lens_psnr_5min']:.2f}), {lens['train_seconds'] / 60:.0f} min each"),
        ("wild", "video, photos, few labels",
         f"video {wild['orchard_video_rot_err_deg']:.2f} deg, {wild['orchard_video_psnr']:.1f} dB, mIoU "
         f"{wild['orchard_video_miou']:.2f} (posed {posed['psnr']:.1f}, {posed['miou']:.2f}); fox photos "
         f"{wild['fox_sfm_rot_err_deg']:.2f} deg, {wild['fox_sfm_psnr']:.1f} dB; 3 labels mIoU {wild['orchard_sparse_miou_3frames']:.2f} "
         f"(plant {wild['plant_sparse_miou_3frames']:.2f})"),
        ("cluster", "two-scene batch on a real SLURM cluster",
         f"{cluster['slurm_jobs_submitted']} jobs: good scene done, broken one FAILED alone; a train key re-runs "
         f"{cluster['rerun_jobs_after_train_change']} jobs"),
        ("reliability", "faults, bad and hostile inputs",
         f"{reliability['faults_survived']}/{reliability['faults_injected']} faults survived; "
         f"{reliability['bad_inputs_clear_error']}/{reliability['bad_inputs_tried']} bad, "
         f"{reliability['hostile_inputs_clear_error']}/{reliability['hostile_inputs_tried']} hostile inputs a clear error"),
    ]


def table() -> list[str]:
    rows = [HEADER, "|---|---|---|---|"]
    for name, what, headline in headline_rows():
        rows.append(f"| {name} | {what} | {headline} | [{name}.json](benchmarks/results/{name}.json) |")
    return rows


def with_table(readme: str) -> str:
    """`readme` with its headline table (the rows under HEADER) replaced by `table()`."""
    lines = readme.splitlines()
    if HEADER not in lines:
        raise ValueError(f"{README}: no headline table (a line {HEADER!r})")
    start = lines.index(HEADER)
    end = start
    while end < len(lines) and lines[end].startswith("|"):
        end += 1
    return "\n".join(lines[:start] + table() + lines[end:]) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if README.md differs instead of writing it")
    args = parser.parse_args(argv)
    current = README.read_text(encoding="utf-8")
    wanted = with_table(current)
    if args.check:
        if current != wanted:
            print("README.md's headline table is stale: run python scripts/readme_numbers.py", file=sys.stderr)
            return 1
        return 0
    README.write_text(wanted, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The pure helpers of benchmarks/tradeoff.py: the Pareto front and the setting names."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import tradeoff  # noqa: E402


def test_tradeoff_pareto_front_keeps_only_settings_nothing_beats():
    points = [("balanced", 600.0, 28.0), ("fast", 300.0, 27.9), ("slow-worse", 900.0, 27.5),
              ("rays-8192", 610.0, 28.3), ("tie-slower", 320.0, 27.9), ("quick", 60.0, 21.0)]
    assert tradeoff.pareto_front(points) == ["quick", "fast", "balanced", "rays-8192"]
    settings = {f"orchard-{n}": {"train_seconds": s, "psnr": q} for n, s, q in points}
    settings["plant-fast"] = {"train_seconds": 200.0, "psnr": 29.0, "miou_gt": 0.7}
    fronts = tradeoff.pareto_fronts(settings)
    assert fronts["orchard"]["psnr"] == ["quick", "fast", "balanced", "rays-8192"]
    assert fronts["plant"] == {"psnr": ["fast"], "miou_gt": ["fast"]}


def test_setting_names_split_at_the_setting_even_when_the_scene_has_hyphens():
    assert tradeoff.scene_and_setting("orchard-rays-1024") == ("orchard", "rays-1024")
    assert tradeoff.scene_and_setting("my-plant-fast") == ("my-plant", "fast")
    # a setting an earlier run measured and SETTINGS no longer lists: split at the first hyphen
    assert tradeoff.scene_and_setting("orchard-retired-knob") == ("orchard", "retired-knob")


def test_cache_knobs_train_nothing_and_keep_their_cache_numbers():
    # the voxel knobs change only the occupancy section: they distill the balanced field again
    assert tradeoff.is_cache_knob("voxels-68") and tradeoff.is_cache_knob("voxels-272")
    assert not any(tradeoff.is_cache_knob(s) for s in ("fast", "balanced", "rays-1024", "downscale-2"))
    assert tradeoff.CACHE_KNOB_FIELD in tradeoff.SETTINGS
    measured = {"orchard-voxels-68": {"field": "orchard-balanced", "distill_ok": True, "occupancy_iou": 0.5},
                "orchard-voxels-272": {},  # its field was not built
                "orchard-rays-8192": {"distill_ok": False},  # training failed
                "orchard-fast": {"psnr": 27.9, "distill_ok": True}}
    assert sorted(tradeoff.built(measured)) == ["orchard-fast", "orchard-voxels-68"]


def test_every_preset_has_an_orchard_entry_and_the_paper_gpu_run_says_why_it_has_no_measurement():
    per_setting = {"orchard-fast": {"psnr": 28.0, "psnr_object": 25.0, "miou_gt": 0.8, "train_seconds": 300.0},
                   "plant-balanced": {"psnr": 29.0, "train_seconds": 600.0}}  # not the orchard: no entry
    summary = tradeoff.preset_summary(per_setting)
    assert summary["fast"]["psnr"] == 28.0 and summary["fast"]["miou"] == 0.8 and "balanced" not in summary
    # the paper's 500k hash-grid iterations at the committed train.json's CPU speed: days, not minutes
    paper = summary["paper"]
    assert paper["measured"] is False and paper["iterations"] == 500000
    assert paper["cpu_hours_estimate"] > 24 and "GPU" in paper["why"]

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

"""The built-in captures' `ground_truth/` folder (orchard, plant), attached to an imported capture."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from srfpipe.poses.bounds import check_bounds
from srfpipe.poses.capture import Capture, load_json


def attach_ground_truth(capture: Capture) -> Capture:
    """Attach `ground_truth/` (orchard) when present: check one label and depth file per frame, read bounds."""
    folder = capture.root / "ground_truth"
    if not folder.is_dir():
        return capture
    names = [Path(p).stem for p in capture.image_paths]
    for kind, suffix in (("labels", ".png"), ("depth", ".npy")):
        sub = folder / kind
        if not sub.is_dir():
            continue
        have = {p.stem for p in sub.glob(f"*{suffix}")}
        missing = [n for n in names if n not in have]
        if missing:
            raise ValueError(
                f"{sub}: mismatched counts: {len(have)} {kind} files for {len(names)} frames "
                f"(no {suffix} file for {', '.join(missing[:3])})"
            )
    bounds = None
    scene_json = folder / "scene.json"
    if scene_json.exists():
        scene = load_json(scene_json)
        if "bounds_world" in scene:
            bounds = check_bounds(scene["bounds_world"], f"{scene_json}: bounds_world")
    return replace(capture, ground_truth=folder.resolve(), ground_truth_bounds=bounds)

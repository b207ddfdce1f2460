"""Faults: rules killed halfway with SIGKILL, a full disk, read-only output folders, two scenes at
once, determinism. Tiny scenes only; benchmarks/reliability.py runs the heavier versions.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from srfpipe.artifacts import open_artifact, read_provenance
from tests.conftest import TINY_ORCHARD, snakemake_env
from tests.faults import compare_artifacts, kill_stage_halfway, leftovers, tmpfs
from tests.test_poses import ring, write_nerfstudio

pytestmark = pytest.mark.faults

# Small enough for CI, long enough that each stage is caught halfway: training logs every step
# and checkpoints every 8 of 48 steps.
FAULT_SCENE = {
    **TINY_ORCHARD,
    "train": {"iterations": 48, "rays_per_batch": 256, "default_cells": 20, "outer_resolution": 12,
              "hidden": 32, "outer_samples": 16, "before_samples": 8, "checkpoint_every": 8, "log_every": 1,
              "occupancy_update_every": 8, "occupancy_warmup": 16, "time_budget": 0},
    "evaluate": {"holdout_every": 4},
    "occupancy": {"voxels_across": 24, "brick": 16},
}


@pytest.mark.workflow
def test_every_stage_killed_halfway_is_redone_by_the_same_command(workflow):
    """downscale, segment, train, distill and package are each SIGKILLed while writing; after
    every kill the same command runs again. The build finishes, nothing partial is taken as
    complete or left behind, and training resumes from its last checkpoint (at most one interval
    lost)."""
    workflow.write_scene("tiny", FAULT_SCENE)
    target = "results/tiny/sim"
    results = workflow.root / "results"
    kills = []
    for stage in ("downscale", "segment", "train", "distill", "package"):
        outcome = kill_stage_halfway(workflow.root, [target], "tiny", stage, min_step=28)
        assert outcome["killed"], f"{stage} was not caught halfway:\n{outcome['output']}"
        assert outcome["returncode"] != 0, "Snakemake must report the killed job"
        kills.append(outcome)
        # nothing of the killed stage is left where the next run would take it as complete
        for artifact in visible_artifacts(results):
            open_artifact(artifact)  # raises for a partial or incomplete one
        killed_output = {"downscale": "images.zarr", "train": "srf.zarr", "distill": "occupancy.zarr",
                         "package": "sim"}.get(stage)
        if killed_output:
            assert not (results / "tiny" / killed_output).exists(), f"{killed_output} exists after a kill"
    workflow.run(target)
    assert leftovers(results) == [], "a killed stage left partial files behind"
    for name, stage in (("images.zarr", "downscale"), ("labels.zarr", "composite"), ("srf.zarr", "train"),
                        ("occupancy.zarr", "distill")):
        open_artifact(results / "tiny" / name, stage=stage)
    assert (results / "tiny" / "sim" / "scene.json").is_file()
    srf = read_provenance(results / "tiny" / "srf.zarr")
    killed_at = next(k["train_step"] for k in kills if k["stage"] == "train")
    assert srf["iterations_done"] == 48
    assert srf["resumed_from_step"] > 0, "training started over instead of resuming"
    assert srf["resumed_from_step"] >= 24 and killed_at - srf["resumed_from_step"] <= 8, (killed_at, srf)
    assert workflow.dry_run_jobs(target) == {}, "the finished build has nothing left to do"


def visible_artifacts(results):
    return [p for p in results.rglob("*.zarr") if not any(part.startswith(".") for part in p.parts)]


def small_poses(tmp_path, width=160, height=120, views=6):
    """poses.zarr of a capture of noise images (incompressible: they fill a small disk fast)."""
    from srfpipe.poses import import_poses

    capture = write_nerfstudio(tmp_path / "capture", ring(views), width=width, height=height,
                               intrinsics=(150.0, 150.0, width / 2, height / 2))
    return import_poses({"format": "nerfstudio"}, capture, {}, tmp_path / "poses.zarr", progress=False)


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "srfpipe.cli", *args], capture_output=True, text=True,
                          env=snakemake_env())


def mounted(path, **kwargs):
    try:
        return tmpfs(path, **kwargs)
    except PermissionError as exc:  # not root, or no CAP_SYS_ADMIN in this container
        pytest.skip(str(exc))


@pytest.mark.parametrize("read_only", [False, True], ids=["disk_full", "read_only"])
def test_full_or_read_only_disk_gives_one_clear_line_and_no_partial_artifact(tmp_path, read_only):
    poses = small_poses(tmp_path)
    disk = tmp_path / "disk"
    with mounted(disk, size="96k", read_only=read_only):
        out = disk / "scene" / "images.zarr" if not read_only else disk / "images.zarr"
        result = run_cli("downscale", "--poses", str(poses), "--options", json.dumps({"downscale": 1}),
                         "--no-progress", "--out", str(out))
        assert result.returncode == 1, result.stderr
        error = [line for line in result.stderr.splitlines() if line.startswith("srfpipe downscale: error:")]
        problem = "Read-only file system" if read_only else "No space left on device"
        assert len(error) == 1 and problem in error[0] and str(disk) in error[0], result.stderr
        assert "Traceback" not in result.stderr
        assert not out.exists() and leftovers(disk) == []
        if not read_only:
            used = sum(p.stat().st_size for p in disk.rglob("*") if p.is_file())
            assert used == 0, f"{used} bytes left on the full disk"


def test_checkpoint_on_a_full_disk_leaves_no_temporary_file(tmp_path):
    import torch

    from srfpipe.srf.hooks import save_checkpoint

    with mounted(tmp_path / "disk", size="64k"):
        folder = tmp_path / "disk" / "srf.ckpt"
        with pytest.raises(OSError, match=r"cannot write the checkpoint.*bytes free on its disk.*step-000000008.pt"):
            save_checkpoint(folder, {"step": 8, "model": {"w": torch.zeros(100_000)}})
        assert list(folder.iterdir()) == []


def test_two_scenes_never_share_a_path(workflow):
    """Every job's files (outputs, logs, benchmarks, checkpoints, metrics) carry its scene's name,
    and no path of one scene's jobs appears in the other's: both may be built at once."""
    workflow.write_scene("north", FAULT_SCENE)
    workflow.write_scene("south", {**FAULT_SCENE, "orchard": {**FAULT_SCENE["orchard"], "seed": 3}})
    result = workflow.run("-n", "-p", "--forceall", "results/north/occupancy.zarr", "results/south/occupancy.zarr")
    jobs = re.split(r"\n(?=\[|rule |localrule )", result.stdout)
    paths = {"north": set(), "south": set()}
    for job in jobs:
        scene = re.search(r"wildcards: .*scene=(\w+)", job)
        if not scene:
            continue
        for token in re.findall(r"(?:results|logs|benchmarks)/[\w./{}-]+", job):
            paths[scene.group(1)].add(token)
    assert paths["north"] and paths["south"]
    for scene, other in (("north", "south"), ("south", "north")):
        for path in paths[scene]:
            assert f"/{scene}/" in path or f"/{scene}." in path, f"{path} of scene {scene} is not scene-specific"
    assert not paths["north"] & paths["south"]
    for kind in ("srf.ckpt", "train_metrics.jsonl", "train.log"):
        assert any(kind in p for p in paths["north"]) and any(kind in p for p in paths["south"]), kind


@pytest.mark.workflow
def test_two_identical_scenes_built_at_once_are_bitwise_equal(workflow):
    """Two scenes with the same config and seed, built concurrently (--cores 2), give the same
    capture, poses, images, masks and labels bit for bit: nothing leaks from one to the other."""
    scene = {key: value for key, value in FAULT_SCENE.items() if key not in ("train", "occupancy")}
    workflow.write_scene("left", scene)
    workflow.write_scene("right", scene)
    workflow.run("--cores", "2", "results/left/labels.zarr", "results/right/labels.zarr")
    results = workflow.root / "results"
    for name in ("poses.zarr", "images.zarr", "masks/apple.zarr", "labels.zarr"):
        arrays = compare_artifacts(results / "left" / name, results / "right" / name)
        assert arrays and all(a["bitwise"] for a in arrays.values()), (name, arrays)
    left_images = sorted((results / "left" / "capture" / "images").iterdir())
    for path in left_images:
        assert path.read_bytes() == (results / "right" / "capture" / "images" / path.name).read_bytes()
    assert np.array_equal(open_artifact(results / "left" / "labels.zarr")["label"][...],
                          open_artifact(results / "right" / "labels.zarr")["label"][...])

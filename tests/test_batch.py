"""Batches of scenes: the batch target (every scene file or a sheet's), --keep-going past a failing
scene, the per-scene summary, and what a config change re-runs (dry runs, --list-changes params)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from srfpipe.artifacts import open_artifact, read_provenance
from srfpipe.batch import read_sheet, summary_lines
from tests.conftest import REPO, TINY_ORCHARD

DEFAULT_PROFILE = str(REPO / "workflow" / "profiles" / "default")

# The tiny orchard through every stage in seconds: two prompts, a few training steps, a coarse cache.
TINY_FULL = {
    **TINY_ORCHARD,
    "segmentation": {"prompts": ["apple", "leaf"]},
    "train": {"iterations": 20, "rays_per_batch": 256, "default_cells": 20, "outer_resolution": 12,
              "hidden": 32, "outer_samples": 16, "checkpoint_every": 0, "time_budget": 0},
    "evaluate": {"holdout_every": 4},
    "occupancy": {"voxels_across": 24},
}


def write_broken_capture(folder: Path) -> Path:
    """A nerfstudio capture whose images were never copied: transforms.json lists three frames."""
    folder.mkdir(parents=True, exist_ok=True)
    frames = [{"file_path": f"images/frame_{i:05d}.png",
               "transform_matrix": [[1, 0, 0, i * 0.1], [0, 1, 0, 0], [0, 0, 1, 2], [0, 0, 0, 1]]}
              for i in range(3)]
    (folder / "transforms.json").write_text(json.dumps(
        {"fl_x": 50.0, "fl_y": 50.0, "cx": 32.0, "cy": 24.0, "w": 64, "h": 48, "frames": frames}))
    return folder


# ------------------------------------------------------------------------------------------ sheets

def test_sheet_lists_scenes_in_order_and_errors_name_file_and_row(tmp_path):
    sheet = tmp_path / "batch.tsv"
    sheet.write_text("scene\tnote\n# comment\nplant\tfar views\n\norchard\tdemo\n")
    assert read_sheet(sheet, known=["orchard", "plant", "fox"]) == ["plant", "orchard"]
    csv_sheet = tmp_path / "batch.csv"
    csv_sheet.write_text("owner,scene\nme,fox\n")
    assert read_sheet(csv_sheet) == ["fox"]

    sheet.write_text("scene\nplant\nfox\n")
    with pytest.raises(ValueError, match=r"batch.tsv: row 3: no scene file for 'fox'"):
        read_sheet(sheet, known=["orchard", "plant"])
    sheet.write_text("scene\nplant\nplant\n")
    with pytest.raises(ValueError, match=r"batch.tsv: row 3: scene 'plant' is listed twice"):
        read_sheet(sheet)
    sheet.write_text("name\nplant\n")
    with pytest.raises(ValueError, match=r"batch.tsv: no 'scene' column"):
        read_sheet(sheet)


def test_sheet_errors_name_the_line_of_the_file_counting_blank_and_comment_lines(tmp_path):
    """The row an error names is the line an editor or a spreadsheet shows, not the count of the
    rows that were kept after blank lines and comments."""
    sheet = tmp_path / "batch.tsv"
    sheet.write_text("scene\n# first batch\nplant\n\norchard\nfox\n")
    with pytest.raises(ValueError, match=r"batch.tsv: row 6: no scene file for 'fox'"):
        read_sheet(sheet, known=["orchard", "plant"])
    sheet.write_text("scene\tnote\n\nplant\tx\n\n\nplant\ty\n")
    with pytest.raises(ValueError, match=r"batch.tsv: row 6: scene 'plant' is listed twice"):
        read_sheet(sheet)
    sheet.write_text(" scene \tnote\nplant\tx\n")  # the header's names are stripped for the rows too
    assert read_sheet(sheet) == ["plant"]


def test_sheet_saved_by_a_spreadsheet_with_a_byte_order_mark_or_not_in_utf8(tmp_path):
    """Excel's "CSV UTF-8" starts with a byte order mark, which is not part of the first column's
    name; a sheet in another encoding is an error naming the sheet, not a bare codec error."""
    sheet = tmp_path / "batch.csv"
    sheet.write_bytes("scene,note\nplant,caf\u00e9\n".encode("utf-8-sig"))
    assert read_sheet(sheet, known=["plant"]) == ["plant"]
    sheet.write_bytes("scene,note\nplant,caf\u00e9\n".encode("latin-1"))
    with pytest.raises(ValueError, match=r"sheet .*batch.csv: not UTF-8 text"):
        read_sheet(sheet)


@pytest.mark.workflow
def test_batch_target_builds_every_scene_file_or_a_sheets(workflow):
    for name in ("a", "b", "c"):
        workflow.write_scene(name, TINY_ORCHARD)
    workflow.write_config({"scenes_dir": "config/scenes", "scenes": ["a"], "results_dir": "results",
                           "final_artifact": "images"})
    assert workflow.dry_run_jobs("batch")["downscale"] == 3, "every scene file, whatever `scenes` says"
    (workflow.root / "sheet.tsv").write_text("scene\tnote\nc\tfirst\nb\n")
    jobs = workflow.run("-n", "batch", "--config", "sheet=sheet.tsv").stdout
    assert "results/b/images.zarr" in jobs and "results/c/images.zarr" in jobs
    assert "results/a/" not in jobs
    (workflow.root / "sheet.tsv").write_text("scene\nc\nd\n")
    result = workflow.run("-n", "batch", "--config", "sheet=sheet.tsv", check=False)
    assert result.returncode != 0 and "sheet.tsv: row 3: no scene file for 'd'" in result.stdout + result.stderr


# ------------------------------------------------------------------- a failing scene in a batch

@pytest.mark.workflow
def test_failing_scene_does_not_stop_the_others_and_the_summary_names_it(workflow):
    capture = write_broken_capture(workflow.root / "captures" / "broken")
    workflow.write_scene("broken", {"source": {"format": "nerfstudio", "path": str(capture)}})
    workflow.write_scene("tiny", TINY_ORCHARD)
    workflow.write_config({"scenes_dir": "config/scenes", "scenes": [], "results_dir": "results",
                           "final_artifact": "labels"})
    # keep-going comes from the profile
    result = workflow.run("batch", "--workflow-profile", DEFAULT_PROFILE, check=False)
    assert result.returncode != 0, "a failed scene fails the run"
    labels = open_artifact(workflow.root / "results/tiny/labels.zarr", stage="composite")
    assert labels["label"].shape == (12, 48, 64)
    assert not (workflow.root / "results/broken/poses.zarr").exists()

    lines = [line.strip() for line in result.stdout.splitlines()]
    tiny = next(line for line in lines if line.startswith("tiny "))
    broken = next(line for line in lines if line.startswith("broken "))
    assert tiny.split()[1:3] == ["done", "labels.zarr"]
    assert broken.split()[1:3] == ["FAILED", "poses.zarr"]
    assert "srfpipe poses: error:" in broken and "[logs/broken/poses.log]" in broken
    assert "scenes: 1 done, 1 failed, 0 incomplete (final artifact labels.zarr)" in lines

    # the same summary from the files, at any time; without the failing scene's log it is incomplete
    (workflow.root / "logs/broken/poses.log").unlink()
    lines = summary_lines(["tiny", "broken"], workflow.root / "results", workflow.root / "logs",
                          ("poses.zarr", "images.zarr", "labels.zarr"))
    assert lines[1].split()[1:3] == ["incomplete", "poses.zarr"]


def test_a_scene_built_to_its_occupancy_cache_without_eval_is_done_and_says_it_was_not_evaluated(tmp_path):
    """The README's first command builds results/orchard/occupancy.zarr, which needs srf.zarr and not
    eval/: `srfpipe summary` then reports the scene done (exit 0) and how to score it, not
    incomplete; an evaluation that failed is reported as the failure, with its log."""
    from srfpipe.batch import DEFAULT_CHAIN, scene_state

    results, logs = tmp_path / "results", tmp_path / "logs"
    for scene in ("built", "scored", "broken"):
        for artifact in DEFAULT_CHAIN:
            if artifact != "eval":  # stand-ins: a folder holding what a stage writes at its top
                (results / scene / artifact).mkdir(parents=True)
                (results / scene / artifact / "zarr.json").write_text("{}")
    (results / "scored" / "eval").mkdir()
    (results / "scored" / "eval" / "metrics.json").write_text(json.dumps({"psnr": 28.4, "miou": 0.8}))
    (logs / "broken").mkdir(parents=True)
    (logs / "broken" / "evaluate.log").write_text("srfpipe evaluate: error: results/broken/srf.zarr: no weights\n")
    lines = summary_lines(["built", "scored", "broken"], results, logs)
    assert lines[0].split()[1:3] == ["done", "occupancy.zarr"]
    assert "not evaluated: snakemake results/built/eval scores it" in lines[0]
    assert lines[1].split()[1:3] == ["done", "occupancy.zarr"] and "PSNR 28.4 dB, mIoU 0.80" in lines[1]
    assert lines[2].split()[1:3] == ["FAILED", "eval"] and "no weights" in lines[2]
    assert lines[3] == "scenes: 2 done, 1 failed, 0 incomplete (final artifact occupancy.zarr)"
    # eval as the final artifact is a step like any other
    assert scene_state("built", results, logs, DEFAULT_CHAIN[:5]).status == "incomplete"
    # a scene stopped before srf.zarr is incomplete at that artifact, whatever eval/ holds
    (results / "built" / "srf.zarr" / "zarr.json").unlink()
    (results / "built" / "srf.zarr").rmdir()
    assert scene_state("built", results, logs).missing == "srf.zarr"


def test_an_empty_folder_or_a_file_where_an_artifact_belongs_is_not_a_finished_stage(tmp_path):
    """Every stage writes its output atomically, so a finished artifact holds what its stage writes;
    an empty folder (made by hand, or by a tool that pre-creates outputs) or a plain file at
    results/{scene}/occupancy.zarr is not a built scene."""
    from srfpipe.batch import DEFAULT_CHAIN, scene_state

    results, logs = tmp_path / "results", tmp_path / "logs"
    for artifact in DEFAULT_CHAIN[:-1]:
        (results / "tree" / artifact).mkdir(parents=True)
        (results / "tree" / artifact / ("metrics.json" if artifact == "eval" else "zarr.json")).write_text("{}")
    (results / "tree" / "occupancy.zarr").mkdir()
    state = scene_state("tree", results, logs)
    assert (state.status, state.missing) == ("incomplete", "occupancy.zarr")
    (results / "tree" / "occupancy.zarr").rmdir()
    (results / "tree" / "occupancy.zarr").write_text("not an artifact")
    assert scene_state("tree", results, logs).missing == "occupancy.zarr"
    (results / "tree" / "occupancy.zarr").unlink()
    (results / "tree" / "occupancy.zarr").mkdir()
    (results / "tree" / "occupancy.zarr" / "zarr.json").write_text("{}")
    assert scene_state("tree", results, logs).status == "done"


# ------------------------------------------------------------ what a config change re-runs

def changed_outputs(workflow, *targets: str) -> list[str]:
    """The outputs whose rule's params differ from the ones they were built with: the "params
    changed" rows of `--detailed-summary`. `--list-changes params` must name them too; in Snakemake
    9.27 it also lists outputs whose params did not change (ParamsChange.__or__ keeps the file set of
    an empty change), so it is checked as a superset."""
    summary = workflow.run("--detailed-summary", *targets).stdout
    rows = [line.split("\t") for line in summary.splitlines() if line.startswith("results/")]
    changed = sorted(row[0] for row in rows if row[-2] == "params changed")
    listed = workflow.run("--list-changes", "params", *targets).stdout
    assert set(changed) <= {line.strip() for line in listed.splitlines()}
    return changed


@pytest.mark.workflow
def test_config_changes_rerun_their_stage_and_what_follows(workflow):
    targets = ("results/tiny/eval", "results/tiny/occupancy.zarr")
    scene = copy.deepcopy(TINY_FULL)
    workflow.write_scene("tiny", scene)
    workflow.run(*targets)
    assert changed_outputs(workflow, *targets) == [] and workflow.dry_run_jobs(*targets) == {}
    upstream = {name: (workflow.root / "results/tiny" / name).stat().st_mtime_ns
                for name in ("poses.zarr", "images.zarr", "masks/apple.zarr", "masks/leaf.zarr", "labels.zarr")}

    # a training key: training, evaluation and the cache; nothing before them
    scene["train"]["iterations"] = 25
    workflow.write_scene("tiny", scene)
    assert changed_outputs(workflow, *targets) == ["results/tiny/srf.zarr"]
    assert workflow.dry_run_jobs(*targets) == {"train": 1, "evaluate": 1, "distill": 1}

    # one prompt's setting: that prompt's masks and everything after them
    scene["train"]["iterations"] = 20
    scene["segmentation"]["thresholds"] = {"leaf": 0.6}
    workflow.write_scene("tiny", scene)
    assert changed_outputs(workflow, *targets) == ["results/tiny/masks/leaf.zarr"]
    jobs = workflow.run("-n", *targets).stdout
    assert "output: results/tiny/masks/leaf.zarr" in jobs
    assert "output: results/tiny/masks/apple.zarr" not in jobs
    assert workflow.dry_run_jobs(*targets) == {"segment": 1, "composite": 1, "train": 1, "evaluate": 1,
                                               "distill": 1}
    # ... and doing it leaves the other prompt's masks, the images and the poses alone
    workflow.run(*targets)
    after = {name: (workflow.root / "results/tiny" / name).stat().st_mtime_ns for name in upstream}
    assert {name for name in upstream if after[name] != upstream[name]} == {"masks/leaf.zarr", "labels.zarr"}
    assert read_provenance(workflow.root / "results/tiny/masks/leaf.zarr")["config"]["threshold"] == 0.6

    # forcing one stage: it and what follows
    assert workflow.dry_run_jobs(*targets, "--forcerun", "train") == {"train": 1, "evaluate": 1, "distill": 1}


def test_slurm_profile_gpu_example_sends_only_train_and_evaluate_to_the_gpu():
    """The profile's commented GPU block, uncommented as its text says, is valid YAML for Snakemake's
    profile keys, names rules that exist, and gives a GPU to train and evaluate only."""
    import re

    import yaml

    profile = REPO / "workflow" / "profiles" / "slurm" / "config.yaml"
    text = profile.read_text()
    block = text[text.index("# set-resources:"):]
    uncommented = "\n".join(line[2:] if line.startswith("# ") else line.lstrip("#") for line in block.splitlines())
    example = yaml.safe_load(uncommented)
    rules = set(re.findall(r"^rule (\w+):", "\n".join(p.read_text() for p in (REPO / "workflow" / "rules").glob("*.smk")),
                           flags=re.M))
    assert set(example["set-resources"]) <= rules and set(example["set-threads"]) <= rules
    gpu = {rule for rule, resources in example["set-resources"].items() if resources.get("gpu")}
    assert gpu == {"train", "evaluate"}
    assert all(resources["slurm_partition"] == "gpu" for resources in example["set-resources"].values())
    assert {**yaml.safe_load(text), **example}["executor"] == "slurm"

"""The Snakemake workflow end to end on a tiny orchard, and what a config change re-runs."""

import numpy as np
import pytest

from srfpipe.artifacts import open_artifact, read_provenance
from tests.conftest import TINY_ORCHARD

pytestmark = pytest.mark.workflow


def test_tiny_orchard_to_images(workflow):
    workflow.write_scene("tiny", TINY_ORCHARD)
    workflow.run("results/tiny/images.zarr")
    images = open_artifact(workflow.root / "results/tiny/images.zarr", stage="downscale")
    assert images["images"].shape == (12, 48, 64, 3)
    assert images["images"].dtype == np.uint8
    pixels = images["images"][0]
    assert pixels.std() > 5, "the render should not be a flat colour"
    poses = read_provenance(workflow.root / "results/tiny/poses.zarr")
    assert poses["complete"] and poses["source_format"] == "orchard"
    for rule in ("orchard_capture", "poses", "downscale"):
        assert (workflow.root / "logs" / "tiny" / f"{rule}.log").exists()
        assert (workflow.root / "benchmarks" / "runs" / "tiny" / f"{rule}.tsv").exists()


def test_changing_downscale_reruns_only_downstream(workflow):
    workflow.write_scene("tiny", TINY_ORCHARD)
    workflow.run("results/tiny/images.zarr")
    assert workflow.dry_run_jobs("results/tiny/images.zarr") == {}, "a finished build has nothing to do"

    changed = {**TINY_ORCHARD, "images": {"downscale": 2}}
    workflow.write_scene("tiny", changed)
    jobs = workflow.dry_run_jobs("results/tiny/images.zarr")
    assert jobs.get("downscale") == 1
    assert "poses" not in jobs and "orchard_capture" not in jobs

    workflow.run("results/tiny/images.zarr")
    images = open_artifact(workflow.root / "results/tiny/images.zarr", stage="downscale")
    assert images["images"].shape == (12, 24, 32, 3)
    assert read_provenance(workflow.root / "results/tiny/images.zarr")["config"]["images"]["downscale"] == 2


def test_bad_scene_file_fails_at_start_naming_file_and_key(workflow):
    workflow.write_scene("tiny", {**TINY_ORCHARD, "images": {"downscale": 0.5}})
    result = workflow.run("-n", "results/tiny/images.zarr", check=False)
    assert result.returncode != 0
    output = result.stdout + result.stderr
    assert "tiny.yaml" in output and "images.downscale" in output


def test_a_bad_workflow_config_fails_at_start_naming_the_file_and_key(workflow):
    """config/config.yaml (or --config) with an unknown key or a bad value: one line naming the file
    and the key, a typo's likely meaning, not Snakemake's dump of the whole schema."""
    workflow.write_scene("tiny", TINY_ORCHARD)
    result = workflow.run("-n", "results/tiny/images.zarr", "--config", "final_artifcat=sim", check=False)
    output = result.stdout + result.stderr
    assert result.returncode != 0
    assert ("config.yaml with --config: (top level): Additional properties are not allowed "
            "('final_artifcat' was unexpected); did you mean 'final_artifcat' -> 'final_artifact'?") in output
    assert "Failed validating" not in output and "'description'" not in output
    result = workflow.run("-n", "results/tiny/images.zarr", "--config", "final_artifact=mesh", check=False)
    assert result.returncode != 0
    assert "config.yaml with --config: final_artifact: 'mesh' is not one of" in result.stdout + result.stderr


def test_lint_finds_no_rule_files_mixing_rules_and_functions(workflow):
    """STYLE: `snakemake --lint` stays clean; the helpers rules share live in common.smk (the one
    lint left is conda/container per rule: the project installs into one environment)."""
    workflow.write_scene("tiny", TINY_ORCHARD)
    output = workflow.run("--lint", check=False)
    text = output.stdout + output.stderr
    assert "Lints for rule" in text, "the lint ran"
    assert "Mixed rules and functions" not in text
    lints = {line.strip() for line in text.splitlines() if line.strip().startswith("* ")}
    assert lints == {"* Specify a conda environment or container for each rule.:"}


def test_reordering_the_prompts_recomposites_the_labels_not_the_masks(workflow):
    """The label image's class values follow segmentation.prompts' order (config/README.md): a new
    order re-runs the composite (the masks' input set alone is unchanged) and not the masks."""
    workflow.write_scene("tiny", {**TINY_ORCHARD, "segmentation": {"prompts": ["apple", "leaf"]}})
    workflow.run("results/tiny/labels.zarr")
    workflow.write_scene("tiny", {**TINY_ORCHARD, "segmentation": {"prompts": ["leaf", "apple"]}})
    assert workflow.dry_run_jobs("results/tiny/labels.zarr") == {"composite": 1}
    workflow.run("results/tiny/labels.zarr")
    assert read_provenance(workflow.root / "results/tiny/labels.zarr")["classes"] == ["leaf", "apple"]

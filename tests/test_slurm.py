"""A batch of two tiny scenes built through a real single-node SLURM cluster with Snakemake's SLURM
executor and workflow/profiles/slurm; one scene fails (its capture's images are missing), the
other must still be built to its simulator package.

Marked `slurm`: run by `bash scripts/ci_slurm.sh` (as root; it installs slurm-wlm and munge and
runs `python -m pytest -q -m slurm tests/test_slurm.py`), skipped in the main test run.
"""

from __future__ import annotations

import hashlib
import json

import pytest

from srfpipe.artifacts import open_artifact
from tests.slurm_cluster import SlurmCluster, missing_requirements, run_batch, write_batch
from tests.test_batch import TINY_FULL, write_broken_capture

pytestmark = pytest.mark.slurm

# (artifact, the stage that wrote it) of a finished tiny scene
ARTIFACTS = [("poses.zarr", "poses"), ("images.zarr", "downscale"), ("masks/apple.zarr", "segment"),
             ("masks/leaf.zarr", "segment"), ("labels.zarr", "composite"), ("srf.zarr", "train"),
             ("occupancy.zarr", "distill")]


@pytest.fixture(scope="module")
def cluster(request, tmp_path_factory):
    if "slurm" not in (request.config.getoption("markexpr") or ""):
        pytest.skip("starts a SLURM cluster: run by `bash scripts/ci_slurm.sh` (pytest -m slurm, as root)")
    reason = missing_requirements()
    if reason:
        pytest.fail(f"cannot start the SLURM cluster: {reason}")
    with SlurmCluster(tmp_path_factory.mktemp("slurm")) as running:
        yield running


def test_batch_through_slurm_one_scene_failing(cluster, tmp_path):
    work = tmp_path / "work"
    capture = write_broken_capture(work / "captures" / "broken")
    write_batch(work, {"tiny": TINY_FULL,
                       "broken": {"source": {"format": "nerfstudio", "path": str(capture)}}})
    run = run_batch(cluster, work, timeout=900, log=tmp_path / "snakemake.log")
    print(run.stdout[-6000:])
    assert run.returncode not in (124, 137), f"the run hit its time limit\n{cluster.logs()}"
    assert run.returncode != 0, "a failed scene fails the run"

    # every job went through the cluster, and the cluster saw every one of them end
    rules = sorted(run.submitted.values())
    assert rules.count("poses") == 3, "tiny's poses once, broken's twice (the profile's retries: 1)"
    for rule in ("orchard_capture", "downscale", "composite", "train", "evaluate", "distill", "package"):
        assert rules.count(rule) == 1, (rule, rules)
    assert rules.count("segment") == 2
    finished = {job["JobId"]: job for job in run.finished}
    assert set(run.submitted) <= set(finished), f"jobs without a completion record\n{cluster.logs()}"
    failed = sorted(run.submitted[job_id] for job_id, job in finished.items()
                    if job_id in run.submitted and job["JobState"] != "COMPLETED")
    assert failed == ["poses", "poses"], failed
    assert len(run.succeeded) == len(run.submitted) - 2

    # the good scene is complete and valid
    results = work / "results"
    for name, stage in ARTIFACTS:
        open_artifact(results / "tiny" / name, stage=stage)
    metrics = json.loads((results / "tiny/eval/metrics.json").read_text())
    assert metrics["psnr"] > 5
    package = results / "tiny" / "sim"
    manifest = json.loads((package / "scene.json").read_text())
    assert "scene.xml" in manifest["files"]
    for name, digest in manifest["files"].items():
        assert hashlib.sha256((package / name).read_bytes()).hexdigest() == digest, name
    # ... and the broken one left nothing behind, its log names the error
    assert not (results / "broken" / "poses.zarr").exists()
    assert "error" in (work / "logs/broken/poses.log").read_text()
    assert run.summary == {"tiny": "done", "broken": "FAILED"}, run.summary

"""Shared fixtures: a Snakemake work directory with a tiny orchard scene, and a runner for it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent

# A tiny orchard: enough views and pixels to exercise every stage in seconds.
TINY_ORCHARD = {
    "source": {"format": "orchard"},
    "orchard": {"seed": 0, "views": 12, "width": 64, "height": 48, "n_apples": 10},
    "images": {"downscale": 1},
}


# Under pytest-xdist (the README's `-n 2`) each worker has one of the machine's two cores: its
# Snakemake runs get one core and torch one thread, so two workers never put four threads on two
# cores (2 threads help only when nothing else shares the cores). A test that needs two jobs at
# once passes its own --cores.
XDIST_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
CORES = "1" if XDIST_WORKER else "2"


def snakemake_env() -> dict:
    """The environment for a Snakemake subprocess: the `srfpipe` script of this interpreter on PATH."""
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    if XDIST_WORKER:
        env["OMP_NUM_THREADS"] = "1"
    return env


@pytest.fixture(scope="session", autouse=True)
def one_torch_thread_per_worker():
    if XDIST_WORKER:
        import torch

        torch.set_num_threads(1)


class Workflow:
    """A Snakemake work directory holding config/config.yaml and config/scenes/*.yaml."""

    def __init__(self, root: Path):
        self.root = root
        (root / "config" / "scenes").mkdir(parents=True, exist_ok=True)
        self.write_config({"scenes_dir": "config/scenes", "scenes": [], "results_dir": "results"})

    def write_config(self, config: dict) -> None:
        (self.root / "config" / "config.yaml").write_text(yaml.safe_dump(config))

    def write_scene(self, name: str, scene: dict) -> Path:
        path = self.root / "config" / "scenes" / f"{name}.yaml"
        path.write_text(yaml.safe_dump(scene))
        return path

    def run(self, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        """Run snakemake on the repo's Snakefile in this work directory; output captured."""
        cores = () if "--cores" in args else ("--cores", CORES)
        cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(self.root), *cores, *args]
        result = subprocess.run(cmd, capture_output=True, text=True, env=snakemake_env(), cwd=self.root)
        if check and result.returncode != 0:
            logs = "\n".join(
                f"--- {p}\n{p.read_text()[-3000:]}" for p in sorted((self.root / "logs").rglob("*.log"))
            ) if (self.root / "logs").exists() else ""
            raise AssertionError(
                f"snakemake {' '.join(args)} failed ({result.returncode}):\n"
                f"{result.stdout[-4000:]}\n{result.stderr[-6000:]}\n{logs}"
            )
        return result

    def dry_run_jobs(self, *targets: str) -> dict[str, int]:
        """Rule name -> job count that a dry run (`-n`) would execute."""
        return job_counts(self.run("-n", *targets).stdout)


def job_counts(dry_run_stdout: str) -> dict[str, int]:
    """Rule name -> job count from the job table that `snakemake -n` prints."""
    jobs: dict[str, int] = {}
    in_table = False
    for line in dry_run_stdout.splitlines():
        parts = line.split()
        if parts[:2] == ["job", "count"]:
            in_table = True
            continue
        if in_table and parts[:1] == ["total"]:
            break  # the job table ends; the rule displays that follow have "jobid: 8" lines
        if in_table and len(parts) == 2 and parts[1].isdigit():
            jobs[parts[0]] = int(parts[1])
    return jobs


@pytest.fixture
def workflow(tmp_path) -> Workflow:
    return Workflow(tmp_path / "work")


@pytest.fixture(scope="session")
def device():
    """The torch device for tests that train or render: CUDA when torch sees a GPU, else the CPU
    (session-wide, so module-scoped fixtures can take it too)."""
    from srfpipe.device import choose_device

    return choose_device("auto")

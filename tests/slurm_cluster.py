"""A real single-node SLURM cluster on this machine, and a batch of scenes built through it with
Snakemake's SLURM executor (snakemake-executor-plugin-slurm and workflow/profiles/slurm).

Used by tests/test_slurm.py (the CI step `bash scripts/ci_slurm.sh`) and benchmarks/cluster.py.
Needs root and Debian's `slurm-wlm` and `munge` packages (scripts/ci_slurm.sh installs them).

There is no systemd here, so the daemons are started by hand, in the foreground as children of this
process: munged as the munge user (after creating /run/munge), then slurmctld and slurmd as root
with a slurm.conf written to a folder of their own (`SLURM_CONF` points the clients there; slurmd
takes it from slurmctld, configless, so that srun inside a job finds it too). The
node line comes from `slurmd -C` with RealMemory a little below the machine's; process tracking
by /proc (proctrack/linuxproc), no task plugin, no accounting database (so job status comes from
`squeue`, with MinJobAge 600 s keeping finished jobs visible to it), and every finished job
written to a job-completion file (jobcomp/filetxt): the cluster's own record of what ran and how
it ended. Ports are free loopback ports picked at start. `stop()` ends exactly the daemons it
started, by PID, and removes their pid files.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from tests.conftest import REPO, job_counts, snakemake_env

DAEMONS = ("munged", "slurmctld", "slurmd", "sbatch", "squeue", "sinfo", "scontrol", "srun")
MUNGE_RUN = Path("/run/munge")
SLURM_RUN = Path("/run/slurm")


def missing_requirements() -> str | None:
    """Why this machine cannot start the cluster (None when it can)."""
    if os.geteuid() != 0:
        return "not root (the cluster's daemons run as root and munge)"
    missing = [name for name in DAEMONS if shutil.which(name) is None]
    if missing:
        return f"not installed: {', '.join(missing)} (apt-get install slurm-wlm munge)"
    return None


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def node_line(memory_fraction: float = 0.95) -> tuple[str, str, int]:
    """(node name, NodeName line, RealMemory) from `slurmd -C`, RealMemory lowered to a fraction
    of the machine's (slurmd drains a node that has less memory than slurm.conf says)."""
    text = subprocess.run(["slurmd", "-C"], capture_output=True, text=True, check=True).stdout
    line = next(line for line in text.splitlines() if line.startswith("NodeName="))
    fields = dict(part.split("=", 1) for part in line.split())
    memory = int(int(fields["RealMemory"]) * memory_fraction)
    fields["RealMemory"] = str(memory)
    name = fields.pop("NodeName")
    parts = " ".join(f"{key}={value}" for key, value in fields.items())
    return name, f"NodeName={name} NodeAddr=127.0.0.1 {parts} State=UNKNOWN", memory


class SlurmCluster:
    """munged + slurmctld + slurmd on this machine, configured in `folder`. A context manager."""

    def __init__(self, folder: Path, min_job_age: int = 600):
        self.folder = Path(folder).resolve()
        self.min_job_age = min_job_age
        self.processes: dict[str, subprocess.Popen] = {}
        self.started_munge_run = False
        self.started_slurm_run = False
        self.node = ""
        self.memory_mb = 0
        self.cpus = 0

    @property
    def conf(self) -> Path:
        return self.folder / "slurm.conf"

    @property
    def jobcomp(self) -> Path:
        return self.folder / "jobcomp.txt"

    def env(self) -> dict:
        """The environment for SLURM clients and Snakemake: SLURM_CONF, and srfpipe on PATH."""
        return dict(snakemake_env(), SLURM_CONF=str(self.conf))

    # ------------------------------------------------------------------------------ config

    def write_conf(self) -> None:
        for sub in ("state", "spool"):
            (self.folder / sub).mkdir(parents=True, exist_ok=True)
        self.node, node, self.memory_mb = node_line()
        self.ctld_port = _free_port()
        self.cpus = int(re.search(r"CPUs=(\d+)", node).group(1))
        self.conf.write_text("\n".join([
            "# written by tests/slurm_cluster.py: a single-node cluster for srfpipe's CI",
            "ClusterName=srfpipe",
            f"SlurmctldHost={self.node}(127.0.0.1)",
            f"SlurmctldPort={self.ctld_port}",
            f"SlurmdPort={_free_port()}",
            "SlurmUser=root",
            "SlurmdUser=root",
            "AuthType=auth/munge",
            "CredType=cred/munge",
            f"StateSaveLocation={self.folder / 'state'}",
            f"SlurmdSpoolDir={self.folder / 'spool'}",
            f"SlurmctldPidFile={self.folder / 'slurmctld.pid'}",
            f"SlurmdPidFile={self.folder / 'slurmd.pid'}",
            f"SlurmctldLogFile={self.folder / 'slurmctld.log'}",
            f"SlurmdLogFile={self.folder / 'slurmd.log'}",
            "SlurmctldDebug=info",
            # slurmd takes its config from slurmctld and caches it in /run/slurm/conf, where
            # clients on the node find it: the jobstep executor drops SLURM_CONF (every SLURM_*
            # variable) before its nested srun
            "SlurmctldParameters=enable_configless",
            "SlurmdDebug=info",
            # no systemd, no cgroups: track job processes through /proc, no task binding
            "ProctrackType=proctrack/linuxproc",
            "TaskPlugin=task/none",
            "JobAcctGatherType=jobacct_gather/none",
            # no accounting database: squeue answers for job status (finished jobs stay
            # MinJobAge seconds), and every finished job is written to the job-completion file
            "AccountingStorageType=accounting_storage/none",
            "JobCompType=jobcomp/filetxt",
            f"JobCompLoc={self.jobcomp}",
            f"MinJobAge={self.min_job_age}",
            "MpiDefault=none",
            "SwitchType=switch/none",
            "SchedulerType=sched/backfill",
            "SelectType=select/cons_tres",
            "SelectTypeParameters=CR_Core_Memory",
            "ReturnToService=2",
            "SlurmdTimeout=300",
            "InactiveLimit=0",
            "KillWait=10",
            node,
            f"PartitionName=ci Nodes={self.node} Default=YES MaxTime=INFINITE State=UP",
            "",
        ]))

    # ------------------------------------------------------------------------------ daemons

    def _munge_works(self) -> bool:
        try:
            token = subprocess.run(["munge", "-n"], capture_output=True, timeout=10)
            if token.returncode != 0:
                return False
            return subprocess.run(["unmunge"], input=token.stdout, capture_output=True,
                                  timeout=10).returncode == 0
        except (OSError, subprocess.TimeoutExpired):
            return False

    def _start_munge(self) -> None:
        if self._munge_works():
            print("slurm cluster: munged already running, used as it is", flush=True)
            return
        import grp
        import pwd

        munge = pwd.getpwnam("munge")
        group = grp.getgrgid(munge.pw_gid).gr_name
        key = Path("/etc/munge/munge.key")
        if not key.exists():
            subprocess.run(["mungekey", "--create"], check=True, user="munge", group=group)
        if not MUNGE_RUN.exists():
            MUNGE_RUN.mkdir(mode=0o755, parents=True)
            self.started_munge_run = True
        os.chown(MUNGE_RUN, munge.pw_uid, munge.pw_gid)
        for folder in (Path("/var/lib/munge"), Path("/var/log/munge")):
            folder.mkdir(parents=True, exist_ok=True)
            os.chown(folder, munge.pw_uid, munge.pw_gid)
        # a socket left by a munged that died would make the new one refuse to start
        self._spawn("munged", ["munged", "--foreground", "--force"], user="munge", group=group)
        self._wait(self._munge_works, 30, "munged answers (munge -n | unmunge)")

    def _spawn(self, name: str, command: list[str], **kwargs) -> None:
        log = open(self.folder / f"{name}.out", "ab")
        self.processes[name] = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                                stdin=subprocess.DEVNULL, env=self.env(),
                                                start_new_session=True, **kwargs)
        log.close()
        print(f"slurm cluster: started {name} (pid {self.processes[name].pid})", flush=True)

    def _wait(self, condition, seconds: float, what: str) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            for name, process in self.processes.items():
                if process.poll() is not None:
                    raise RuntimeError(f"slurm cluster: {name} exited ({process.returncode}) while "
                                       f"waiting until {what}\n{self.logs()}")
            if condition():
                return
            time.sleep(0.5)
        raise RuntimeError(f"slurm cluster: timed out after {seconds} s waiting until {what}\n{self.logs()}")

    def node_state(self) -> str:
        result = subprocess.run(["sinfo", "-h", "-N", "-o", "%t"], capture_output=True, text=True,
                                env=self.env(), timeout=20)
        return result.stdout.strip() if result.returncode == 0 else ""

    def start(self) -> "SlurmCluster":
        reason = missing_requirements()
        if reason:
            raise RuntimeError(f"slurm cluster: cannot start: {reason}")
        started = time.monotonic()
        self.folder.mkdir(parents=True, exist_ok=True)
        self.write_conf()
        try:
            self._start_munge()
            self._spawn("slurmctld", ["slurmctld", "-D", "-i", "-f", str(self.conf)])
            self._wait(lambda: subprocess.run(["scontrol", "ping"], capture_output=True, text=True,
                                              env=self.env()).stdout.find("UP") >= 0,
                       60, "slurmctld answers (scontrol ping)")
            self.started_slurm_run = not SLURM_RUN.exists()
            self._spawn("slurmd", ["slurmd", "-D", "-N", self.node, "--conf-server",
                                   f"127.0.0.1:{self.ctld_port}"])
            self._wait(lambda: self.node_state() == "idle", 90, f"sinfo reports node {self.node} idle")
        except BaseException:
            self.stop()
            raise
        print(f"slurm cluster: node {self.node} idle ({self.cpus} CPUs, {self.memory_mb} MB) "
              f"after {time.monotonic() - started:.1f} s; SLURM_CONF={self.conf}", flush=True)
        return self

    def stop(self) -> None:
        """SIGTERM each daemon started here, newest first, by PID (SIGKILL after 20 s); remove the
        pid files they leave behind."""
        for name in reversed(list(self.processes)):
            process = self.processes.pop(name)
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
                try:
                    process.wait(20)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait(10)
            print(f"slurm cluster: stopped {name} (pid {process.pid})", flush=True)
        for pid_file in (self.folder / "slurmctld.pid", self.folder / "slurmd.pid",
                         MUNGE_RUN / "munged.pid"):
            if pid_file.exists() and not _pid_alive(pid_file):
                pid_file.unlink()
        # slurmd's link to its config cache (configless mode), when it points into this folder
        link = SLURM_RUN / "conf"
        if link.is_symlink() and str(os.readlink(link)).startswith(str(self.folder)):
            link.unlink()
        for folder, created in ((SLURM_RUN, self.started_slurm_run), (MUNGE_RUN, self.started_munge_run)):
            if created and folder.is_dir() and not any(folder.iterdir()):
                folder.rmdir()

    def __enter__(self) -> "SlurmCluster":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def logs(self, lines: int = 30) -> str:
        out = []
        for name in ("slurmctld.log", "slurmd.log", "munged.out", "slurmctld.out", "slurmd.out"):
            path = self.folder / name
            if path.exists():
                tail = path.read_text(errors="replace").splitlines()[-lines:]
                out.append(f"--- {path}\n" + "\n".join(tail))
        return "\n".join(out)

    def finished_jobs(self) -> list[dict]:
        """The job-completion file: one dict per finished job (JobId, JobName, JobState, ExitCode,
        StartTime, EndTime, ...)."""
        if not self.jobcomp.exists():
            return []
        jobs = []
        for line in self.jobcomp.read_text().splitlines():
            fields = dict(re.findall(r"(\w+)=(\S*)", line))
            if "JobId" in fields:
                jobs.append(fields)
        return jobs


def _pid_alive(pid_file: Path) -> bool:
    try:
        os.kill(int(pid_file.read_text().split()[0]), 0)
    except (OSError, ValueError, IndexError):
        return False
    return True


# ------------------------------------------------------------------------------ a batch run

@dataclass
class BatchRun:
    """What a Snakemake run through the SLURM executor did."""

    returncode: int
    seconds: float
    stdout: str
    submitted: dict[str, str] = field(default_factory=dict)   # SLURM job id -> rule
    finished: list[dict] = field(default_factory=list)        # the cluster's job-completion records
    summary: dict[str, str] = field(default_factory=dict)     # scene -> done / FAILED / incomplete

    @property
    def succeeded(self) -> list[dict]:
        return [job for job in self.finished if job["JobId"] in self.submitted
                and job.get("JobState") == "COMPLETED"]


def write_batch(workdir: Path, scenes: dict[str, dict], final_artifact: str = "sim") -> None:
    """A work directory with config/config.yaml and one file per scene in config/scenes/."""
    folder = workdir / "config" / "scenes"
    folder.mkdir(parents=True, exist_ok=True)
    for name, scene in scenes.items():
        (folder / f"{name}.yaml").write_text(yaml.safe_dump(scene, sort_keys=False))
    (workdir / "config" / "config.yaml").write_text(yaml.safe_dump(
        {"scenes_dir": "config/scenes", "scenes": [], "results_dir": "results",
         "final_artifact": final_artifact}, sort_keys=False))


def slurm_command(workdir: Path, *targets: str, timeout: int = 900) -> list[str]:
    """Snakemake with the repo's SLURM profile, bounded by `timeout -s INT` (Snakemake takes
    SIGTERM as "finish the running jobs first"; SIGINT cancels them, SIGKILL a minute later).
    Status by squeue (no accounting database), the first status check 5 s after a submission
    instead of 40, no account (this cluster has none), the SLURM logs kept."""
    return ["timeout", "-s", "INT", "-k", "60", str(timeout),
            sys.executable, "-m", "snakemake", *targets, "-s", str(REPO / "Snakefile"), "-d", str(workdir),
            "--workflow-profile", str(REPO / "workflow" / "profiles" / "slurm"),
            "--slurm-status-command", "squeue", "--slurm-init-seconds-before-status-checks", "5",
            "--slurm-no-account", "--slurm-logdir", str(workdir / "slurm_logs"),
            "--slurm-keep-successful-logs"]


_SUBMITTED = re.compile(r"Job \d+ has been submitted with SLURM jobid (\d+) \(log: .*/rule_(\w+)/")
_SUMMARY = re.compile(r"^\s+(\S+)\s+(done|FAILED|incomplete)\s")


def run_batch(cluster: SlurmCluster, workdir: Path, *targets: str, timeout: int = 900,
              log: Path | None = None) -> BatchRun:
    """Run the `batch` target (or `targets`) in `workdir` through the cluster; the run's output
    is echoed (and written to `log`)."""
    command = slurm_command(workdir, *(targets or ("batch",)), timeout=timeout)
    print("$", " ".join(command), flush=True)
    started = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True, env=cluster.env(), cwd=workdir)
    seconds = time.perf_counter() - started
    output = result.stdout + result.stderr
    if log is not None:
        log.write_text(output)
    run = BatchRun(result.returncode, seconds, output)
    # "Job 3 has been submitted with SLURM jobid 7 (log: .../slurm_logs/rule_poses/broken/7.log)."
    for line in output.splitlines():
        match = _SUBMITTED.search(line)
        if match:
            run.submitted[match.group(1)] = match.group(2)
        match = _SUMMARY.match(line)
        if match:
            run.summary[match.group(1)] = match.group(2)
    # the job-completion file is written when a job ends; give the last one a moment
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        run.finished = cluster.finished_jobs()
        if set(run.submitted) <= {job["JobId"] for job in run.finished}:
            break
        time.sleep(1)
    return run


def dry_run_jobs(workdir: Path, *targets: str) -> dict[str, int]:
    """Rule -> count of the job table of `snakemake -n` (no executor: a dry run submits nothing)."""
    command = [sys.executable, "-m", "snakemake", "-n", *targets, "-s", str(REPO / "Snakefile"),
               "-d", str(workdir), "--cores", "2"]
    result = subprocess.run(command, capture_output=True, text=True, env=snakemake_env(), cwd=workdir,
                            check=True)
    return job_counts(result.stdout)


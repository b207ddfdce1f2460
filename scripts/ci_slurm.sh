#!/usr/bin/env bash
# CI step after the main tests: a real single-node SLURM cluster from Debian's packages, and a batch
# of two tiny scenes built through it with Snakemake's SLURM executor (workflow/profiles/slurm), one
# of them failing (tests/test_slurm.py, marker `slurm`; the cluster: tests/slurm_cluster.py).
# Installs slurm-wlm and munge with apt-get when missing; the daemons are started by hand (no
# systemd) and stopped by their PIDs when the test ends. Needs root and apt-get: skipped, saying
# so, on a machine without them. A few minutes.
set -euo pipefail
cd "$(dirname "$0")/.."

if [ "$(id -u)" -ne 0 ]; then
  echo "SLURM CI step skipped: not root (it installs slurm-wlm and munge and starts their daemons)"
  exit 0
fi
if ! command -v apt-get >/dev/null; then
  echo "SLURM CI step skipped: no apt-get (it installs Debian's slurm-wlm and munge)"
  exit 0
fi

missing=""
for tool in munged slurmctld slurmd sbatch squeue sinfo scontrol srun; do
  command -v "$tool" >/dev/null || missing="$missing $tool"
done
if [ -n "$missing" ]; then
  echo "installing slurm-wlm and munge (missing:$missing)"
  apt-get update -qq
  # policy-rc.d 101: the packages' scripts must not start daemons; the test starts its own
  created_policy=""
  if [ ! -e /usr/sbin/policy-rc.d ]; then
    printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d && chmod +x /usr/sbin/policy-rc.d
    created_policy=1
  fi
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends slurm-wlm munge
  if [ -n "$created_policy" ]; then rm -f /usr/sbin/policy-rc.d; fi
fi

. .venv/bin/activate
started=$(date +%s)
python -m pytest -q -m slurm -p no:cacheprovider tests/test_slurm.py
echo "SLURM CI step: $(( $(date +%s) - started )) s"

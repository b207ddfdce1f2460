#!/usr/bin/env bash
# benchmarks/gpu.py on a lent GPU machine in one call: such a machine has CUDA torch but neither
# Snakemake nor a network, so the inputs and the missing wheels are made here and travel with the
# repository (benchmarks/work/gpu-lease, git-ignored: name it in the call's carry list).
#
#   here (2 CPU cores, project installed):  bash benchmarks/gpu_lease.sh prepare
#   there (repository root):                bash benchmarks/gpu_lease.sh run SECONDS ["ORCHARD_BUDGETS"] ["OTHER_BUDGETS"]
#
# `run` installs the wheels, runs the CUDA tests (tests/test_device.py, test_graphed.py), then gpu.py
# on the orchard (throughput, budgets, the paper preset, a profile of the step), then on the fox and
# the plant in the time left; each stage has its own deadline inside SECONDS, so what was measured
# is copied to $OUT (gpu.json, gpu_partial.json, the pytest tail and the training logs) even when
# the lease runs short. The 15-minute H100 lease of 2026-11-28 ran `run 555 "15 20 60" "15 30"` in 541 s (the plant's
# 30-s budget cut short). Throughput runs last 30 s: in 10 s the start-up (CUDA, warm-up steps, the first captures at
# 128 samples a ray) weighed on the rate (172.8 against 244.4 steps/s by the same clock).
set -uo pipefail
cd "$(dirname "$0")/.."
lease=benchmarks/work/gpu-lease
scenes=(orchard fox plant)

prepare() {
  set -e
  local built=${GPU_BUILD_WORKDIR:-benchmarks/work/gpu}
  python benchmarks/gpu.py --build-only --workdir "$built"
  rm -rf "$lease" && mkdir -p "$lease/work/results"
  cp -r "$built/config" "$lease/work/"
  for scene in "${scenes[@]}"; do
    mkdir -p "$lease/work/results/$scene"
    cp -r "$built/results/$scene/images.zarr" "$built/results/$scene/labels.zarr" "$lease/work/results/$scene/"
  done
  # what the GPU image lacks (its Python is 3.12), at the versions this environment runs
  local wanted=()
  for package in zarr numcodecs donfig google-crc32c jsonschema jsonschema-specifications referencing rpds-py; do
    wanted+=("$package==$(python -c "import importlib.metadata as m; print(m.version('$package'))")")
  done
  python -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$lease/wheels" "${wanted[@]}"
  du -sh "$lease"
}

run() {
  local total=${1:-540} orchard_budgets=${2:-"15 30 60"} other_budgets=${3:-"15 30"}
  local start=$SECONDS out=${OUT:-/tmp/gpu-lease-out}
  left() { echo $((total - (SECONDS - start))); }
  mkdir -p "$out"
  export PYTHONUNBUFFERED=1
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
    "$lease"/wheels/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
  # gpu.py runs `srfpipe`: the package is on PYTHONPATH, not installed
  mkdir -p /tmp/bin && printf '#!/bin/sh\nexec python3 -m srfpipe.cli "$@"\n' >/tmp/bin/srfpipe && chmod +x /tmp/bin/srfpipe
  export PATH=/tmp/bin:$PATH
  python3 -c "import torch; print(torch.__version__, torch.cuda.get_device_name(0))" || exit 1
  collect() {
    cp benchmarks/results/gpu.json benchmarks/results/gpu_partial.json "$out"/ 2>/dev/null
    tar czf "$out/logs.tgz" "$lease/work/logs" 2>/dev/null
  }
  timeout 170 python3 -m pytest -q -p no:cacheprovider tests/test_device.py tests/test_graphed.py \
    tests/test_field.py 2>&1 |
    tail -40 >"$out/pytest.log"
  tail -3 "$out/pytest.log"
  timeout $(($(left) - 20)) python3 benchmarks/gpu.py --no-build --workdir "$lease/work" --scenes orchard \
    --budgets $orchard_budgets --throughput-seconds 30 --agreement-steps 0 2>&1 | grep -v '^\$' | tail -30
  collect
  if [ "$(left)" -gt 80 ]; then
    timeout $(($(left) - 15)) python3 benchmarks/gpu.py --no-build --workdir "$lease/work" --scenes fox plant \
      --budgets $other_budgets --throughput-seconds 0 --agreement-steps 0 --profile-steps 0 2>&1 | grep -v '^\$' | tail -30
  fi
  collect
  echo "$(left) s of $total left"
}

case "${1:-}" in
  prepare) prepare ;;
  run) shift; run "$@" ;;
  *) echo "usage: bash benchmarks/gpu_lease.sh prepare | run SECONDS [\"ORCHARD_BUDGETS\"] [\"OTHER_BUDGETS\"]" >&2; exit 2 ;;
esac

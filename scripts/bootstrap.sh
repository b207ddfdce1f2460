#!/usr/bin/env bash
# Sets up srfpipe on a fresh Debian/Ubuntu machine with Python 3.11, in ./.venv.
# Idempotent: re-running it only installs what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

# open3d's shared library links libusb-1.0 (and OpenMP); MuJoCo's headless renderer (the simulator's
# third-person view) needs EGL with Mesa's software driver. None of them is a pip package.
if ! ldconfig -p 2>/dev/null | grep -q libusb-1.0.so.0 || ! ldconfig -p 2>/dev/null | grep -q libgomp.so.1 \
   || ! ldconfig -p 2>/dev/null | grep -q libEGL_mesa.so.0; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq libusb-1.0-0 libgomp1 libegl1 libegl-mesa0 libgl1-mesa-dri
fi

PYTHON=${PYTHON:-python3.11}
command -v "$PYTHON" >/dev/null || PYTHON=python3
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip
# The CPU wheel first: a bare `torch` requirement would pull a multi-GB CUDA build on a CPU machine.
# On a GPU machine, install the CUDA torch of your choice first instead; the project range accepts it.
python -c "import torch" 2>/dev/null || pip install -q torch==2.13.0
pip install -q -e '.[test,sim,cluster]'
echo "srfpipe is installed in .venv (activate it with: . .venv/bin/activate)"

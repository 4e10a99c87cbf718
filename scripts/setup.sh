#!/usr/bin/env bash
# Set up pipe on a fresh Debian machine (idempotent, a few seconds when already done):
#   - the system library open3d needs (libusb-1.0-0),
#   - a virtual environment in .venv with torch 2.13.0 from the local CPU wheel (never a CUDA build),
#   - pipe itself (editable) with its dependencies, the test tools, the STEP/IGES reader (extra cad),
#     Hydra's SLURM launcher (extra slurm) and Optuna sweeper (extra search).
set -euo pipefail
cd "$(dirname "$0")/.."

if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
  echo "setup: installing libusb-1.0-0 (needed by open3d)"
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libusb-1.0-0 >/dev/null
fi

[ -x .venv/bin/python ] || python3 -m venv .venv
PIP=".venv/bin/pip --quiet --disable-pip-version-check"
stamp=".venv/.pipe-setup-$(cat pyproject.toml constraints.txt | sha256sum | cut -c1-16)"
if [ ! -f "$stamp" ]; then
  echo "setup: installing torch 2.13.0 (CPU) and pipe's dependencies into .venv"
  # torch first, pinned by constraints.txt: a bare torch requirement would pull a CUDA build.
  $PIP install -c constraints.txt torch
  $PIP install -c constraints.txt -e ".[dev,cad,slurm,search]"
  rm -f .venv/.pipe-setup-*
  touch "$stamp"
fi
.venv/bin/python -c "import torch, open3d, pipe; assert not torch.version.cuda, 'a CUDA build of torch was installed'"
echo "setup: ready (.venv: torch $(.venv/bin/python -c 'import torch; print(torch.__version__)'))"

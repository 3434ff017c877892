#!/usr/bin/env bash
# Set up .venv on a fresh machine (idempotent; `make setup` skips it when nothing changed).
# Order matters: torch is pinned to the CPU wheel and installed first, torch-cluster is
# built from source against it (no wheel exists on the registry), then the rest.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}

# open3d needs the system library libusb-1.0
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so'; then
  if [ "$(id -u)" = 0 ]; then
    echo "[setup] installing libusb-1.0-0 (needed by open3d)"
    apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    echo "[setup] open3d needs libusb-1.0: run 'sudo apt-get install libusb-1.0-0' and retry" >&2
    exit 1
  fi
fi

[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
PIP="$VENV/bin/python -m pip"
TORCH=$(grep -E '^torch==' requirements.txt)
$PIP install -q "$TORCH" ninja wheel "setuptools>=66"
if ! "$VENV/bin/python" -c "import torch_cluster" 2>/dev/null; then
  echo "[setup] building torch-cluster from source (several minutes the first time; pip caches the wheel)"
  # torch-cluster is nine small extensions of one or two files each, compiled without ninja:
  # MAX_JOBS has nothing to parallelize inside one. setuptools' build_ext can build whole
  # extensions in parallel (its `parallel` option), set here through an extra distutils config
  # file (DIST_EXTRA_CONFIG, read by setuptools >= 66) for this one build.
  BUILD_CFG=$(mktemp)
  printf '[build_ext]\nparallel = %s\n' "$(nproc)" > "$BUILD_CFG"
  DIST_EXTRA_CONFIG="$BUILD_CFG" MAX_JOBS=$(nproc) $PIP install -q --no-build-isolation torch-cluster==1.6.3
  rm -f "$BUILD_CFG"
fi
$PIP install -q -r requirements.txt
$PIP install -q --no-deps --no-build-isolation -e .
"$VENV/bin/python" -c "import torch, torch_cluster, torch_geometric, open3d, h5py, pytorch_lightning; print('[setup] ok: torch', torch.__version__)"

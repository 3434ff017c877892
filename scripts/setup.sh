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
# The installer: uv (`uv pip install`, a drop-in for pip) when it can be had, since it installs from its
# cache in seconds where pip unpacks every wheel again (the set-up of a fresh clone: docs/setup.md); pip
# otherwise, or with GGNS_SETUP_PIP=1. uv does not read pip's configuration, so the index, extra indexes,
# find-links, constraint and certificate that pip would use (its config files and PIP_* variables,
# `pip config list`) are handed to it, and every index is searched for the best match, as pip does.
UV_ARGS=()
if [ "${GGNS_SETUP_PIP:-0}" != 1 ] && $PIP install -q uv >/dev/null 2>&1 && [ -x "$VENV/bin/uv" ]; then
  UV_ARGS=(--python "$VENV/bin/python" --compile-bytecode --index-strategy unsafe-best-match)
  while IFS= read -r line; do  # lines like  global.extra-index-url='a b'  or  :env:.find-links='/opt/wheels'
    key=${line#*.}; key=${key%%=*}; value=${line#*=\'}; value=${value%\'}
    case $key in
      index-url|extra-index-url|find-links|constraint)
        for item in $value; do UV_ARGS+=("--$key" "$item"); done ;;
      cert) [ -n "${SSL_CERT_FILE:-}" ] || export SSL_CERT_FILE=$value ;;
    esac
  done < <($PIP config list 2>/dev/null)
  echo "[setup] installing with uv"
fi
install() {
  if [ ${#UV_ARGS[@]} -gt 0 ]; then "$VENV/bin/uv" pip install "${UV_ARGS[@]}" "$@"; else $PIP install "$@"; fi
}
TORCH=$(grep -E '^torch==' requirements.txt)
install -q "$TORCH" ninja wheel "setuptools>=66"
# torch-cluster: built from source (no wheel on the registry), by default only the extensions ggns
# calls (scripts/torch_cluster_subset.py; TORCH_CLUSTER_OPS=all builds the whole package). The wheel
# is kept in $WHEELS, so a later set-up on this machine (a fresh clone, CI) installs it in seconds.
TORCH_CLUSTER_OPS=${TORCH_CLUSTER_OPS:-version radius knn}
WHEELS=${GGNS_WHEEL_CACHE:-${XDG_CACHE_HOME:-$HOME/.cache}/ggns/wheels}
if ! "$VENV/bin/python" -c "import torch_cluster" 2>/dev/null; then
  TORCH_TAG=$("$VENV/bin/python" -c "import importlib.metadata as m; print(m.version('torch').replace('+', '_'))")
  CACHED="$WHEELS/torch-$TORCH_TAG/$(echo "$TORCH_CLUSTER_OPS" | tr ' ' '.')"
  if ! ls "$CACHED"/torch_cluster-*.whl >/dev/null 2>&1; then
    echo "[setup] building torch-cluster ($TORCH_CLUSTER_OPS) from source (minutes the first time; the wheel is kept in $CACHED)"
    # Each extension is one or two files compiled without ninja: MAX_JOBS has nothing to parallelize
    # inside one. setuptools' build_ext builds whole extensions in parallel (its `parallel` option),
    # set through an extra distutils config file (DIST_EXTRA_CONFIG, read by setuptools >= 66).
    WORK=$(mktemp -d)
    printf '[build_ext]\nparallel = %s\n' "$(nproc)" > "$WORK/build.cfg"
    $PIP download -q --no-deps --no-binary :all: torch-cluster==1.6.3 -d "$WORK"
    tar -xzf "$WORK"/torch_cluster-1.6.3.tar.gz -C "$WORK"
    if [ "$TORCH_CLUSTER_OPS" != all ]; then
      # shellcheck disable=SC2086
      # one translation unit per core, not one or two per extension: torch's headers are most of each
      # file's 40 s (docs/setup.md)
      "$VENV/bin/python" scripts/torch_cluster_subset.py "$WORK/torch_cluster-1.6.3" $TORCH_CLUSTER_OPS --units "$(nproc)"
    fi
    mkdir -p "$CACHED"
    DIST_EXTRA_CONFIG="$WORK/build.cfg" MAX_JOBS=$(nproc) $PIP wheel -q --no-deps --no-build-isolation \
      "$WORK/torch_cluster-1.6.3" -w "$WORK/wheel"
    mv "$WORK"/wheel/torch_cluster-*.whl "$CACHED"/
    rm -rf "$WORK"
  fi
  install -q --no-deps "$CACHED"/torch_cluster-*.whl
fi
install -q -r requirements.txt
install -q --no-deps --no-build-isolation -e .
# A check of what can fail after pip said yes: the compiled operators against this torch, and open3d's system
# library (importing Lightning and PyG too would add 4 s to every set-up; the first command imports them).
"$VENV/bin/python" -c "
import importlib.metadata
import torch, torch_cluster, open3d, h5py
x = torch.rand(20, 3)
torch_cluster.radius_graph(x, 0.5), torch_cluster.knn(x, x, 2)  # the operators ggns calls
for name in ('torch-geometric', 'pytorch-lightning', 'ggns'):
    importlib.metadata.version(name)  # PackageNotFoundError names a missing one
print('[setup] ok: torch', torch.__version__, '| torch-cluster', torch_cluster.__version__)"

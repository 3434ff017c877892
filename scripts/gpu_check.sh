#!/usr/bin/env bash
# The checks that need a GPU, as one script for a GPU machine that cannot reach a package registry
# (this workplace's device machines: python3 with a CUDA torch, pytorch-lightning, torch-geometric and
# h5py already there, nvcc, no open3d). It uses a kit made beforehand by scripts/gpu_kit.sh on a machine
# with this project's set-up:
#   KIT/whl/*.whl          the pure-Python packages the GPU machine lacks (jsonargparse, omegaconf, ...)
#   KIT/torch_cluster-1.6.3.tar.gz   built here against this machine's torch, with CUDA, our ops only
#   KIT/data/              plate_tiny12 splits for tests/test_cuda.py (no open3d here to raycast them)
#   KIT/plate_small/test.h5 and KIT/ckpt/*.ckpt (optional): the speed/accuracy trade on the GPU
# Writes what it saw under OUT (default /tmp/gpu_check): env.txt, pytest_cuda.txt, tradeoff/,
# bench_models_cuda.csv. Each step runs even when an earlier one failed; the exit status is the
# number of failed steps.
#   bash scripts/gpu_check.sh [KIT] [OUT]
set -uo pipefail
cd "$(dirname "$0")/.."
KIT=$(realpath "${1:-.gpu}")
OUT=${2:-${OUT:-/tmp/gpu_check}}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=/tmp/ggns_site:$PWD/src
failed=0
step() {  # step NAME COMMAND...: run, time and report one step
  local name=$1; shift
  local start=$SECONDS
  echo "[gpu_check $(date +%T)] $name"
  if "$@"; then echo "[gpu_check] $name: ok in $((SECONDS - start)) s"
  else echo "[gpu_check] $name: FAILED (status $?) after $((SECONDS - start)) s"; failed=$((failed + 1)); fi
}

environment() {
  { nvidia-smi -L; nproc; python3 -c "import torch, torch_geometric, pytorch_lightning as pl
print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name(0))
print('torch_geometric', torch_geometric.__version__, 'pytorch_lightning', pl.__version__)"; } 2>&1 | tee "$OUT/env.txt"
}

packages() {
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/ggns_site "$KIT"/whl/*.whl
}

torch_cluster() {  # the extensions ggns calls, compiled for this GPU's architecture only
  local src=/tmp/torch_cluster-1.6.3 arch
  if python3 -c "import torch_cluster" 2>/dev/null; then echo "torch_cluster already built in /tmp/ggns_site"
  else
  arch=$(python3 -c "import torch; print('.'.join(map(str, torch.cuda.get_device_capability(0))))")
  rm -rf "$src" && tar -xzf "$KIT"/torch_cluster-1.6.3.tar.gz -C /tmp &&
    python3 scripts/torch_cluster_subset.py "$src" version radius knn &&
    printf '[build_ext]\nparallel = %s\n' "$(nproc)" > /tmp/build.cfg &&
    (cd "$src" && DIST_EXTRA_CONFIG=/tmp/build.cfg FORCE_CUDA=1 TORCH_CUDA_ARCH_LIST="$arch" MAX_JOBS=$(nproc) \
      python3 -m pip install -q --no-build-isolation --no-deps --no-index --target /tmp/ggns_site .) || return 1
  fi
  python3 -c "import torch, torch_cluster
x = torch.rand(2000, 3, device='cuda')
a, b = torch_cluster.radius_graph(x, 0.1), torch_cluster.radius_graph(x.cpu(), 0.1)
key = lambda e: sorted(zip(*e.tolist()))
assert key(a.cpu()) == key(b), 'radius_graph differs between the GPU and the CPU'
print('torch_cluster', torch_cluster.__version__, 'radius_graph on cuda: the CPU edges', a.shape[1])"
}

cuda_tests() {
  GGNS_TEST_DATA="$KIT/data" python3 -m pytest -p no:cacheprovider -v -rs tests/test_cuda.py 2>&1 | tee "$OUT/pytest_cuda.txt"
}

tradeoff() {  # the checkpoints of KIT/ckpt on this GPU, 9 test trajectories of plate_small
  local args=()
  for path in "$KIT"/ckpt/*.ckpt; do args+=(--checkpoint "$(basename "$path" .ckpt)=$path"); done
  python3 -m ggns bench tradeoff --dataset plate_small --data-dir "$KIT/plate_small" --no-simulator \
    --devices cuda --trajectories 9 "${args[@]}" --output-dir "$OUT/tradeoff"
}

models() {  # training and rollout throughput of the paper-size models (conf/plate/*.yaml) on the GPU
  mkdir -p data/plate_small && cp "$KIT/plate_small/test.h5" data/plate_small/test.h5 &&
    cp "$KIT/plate_small/test.h5" data/plate_small/train.h5 &&  # training windows from the test trajectories
    cp "$KIT/plate_small/test.h5" data/plate_small/val.h5 &&
    python3 -m ggns bench models --dataset plate_small --models ggns,mgn --train-batches 10 --rollout-steps 10 \
      --batch-size 32 --device cuda --output "$OUT/bench_models_cuda.csv"
}

step environment environment
step packages packages
step torch_cluster torch_cluster
step cuda_tests cuda_tests
[ -d "$KIT/ckpt" ] && step tradeoff tradeoff
[ -f "$KIT/plate_small/test.h5" ] && step models models
echo "[gpu_check] $failed step(s) failed; output in $OUT"
exit "$failed"

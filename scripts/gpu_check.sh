#!/usr/bin/env bash
# The checks and speed measurements that need a GPU, as one script for a GPU machine that cannot reach a
# package registry (python3 with a CUDA torch, pytorch-lightning, torch-geometric and h5py already there,
# nvcc, no open3d), within one call of at most 8 minutes. It uses a kit made beforehand by
# scripts/gpu_kit.sh on a machine with this project's set-up:
#   KIT/whl/*.whl          the pure-Python packages the GPU machine lacks (jsonargparse, omegaconf, ...)
#   KIT/torch_cluster-1.6.3.tar.gz   built here against this machine's torch, our ops only
#   KIT/data/              plate_tiny12 splits for tests/test_cuda.py (no open3d here to raycast them)
#   KIT/plate_small/test.h5          the speed measurements' data (also used as train and val split)
#   KIT/baseline/src       the baseline commit's sources (KIT/baseline/COMMIT), for `bench ab`
#   KIT/ckpt/*.ckpt (optional)       checkpoints for `bench precision` (TF32 and bf16 against float32)
# Steps, most important first, each bounded by what is left of DEADLINE seconds (default 450) and
# skipped when under 20 s remain: environment, packages, torch-cluster, tests/test_cuda.py, bench ab
# (this tree against the baseline on the GPU: a training iteration and rollout steps), bench profile,
# bench learning (experiments/speed/learning/plate_gpu.yaml, 1 minute per variant), bench precision. Writes what it
# saw under OUT (default /tmp/gpu_check); the exit status is the number of failed steps.
#   bash scripts/gpu_check.sh [KIT] [OUT]
set -uo pipefail
cd "$(dirname "$0")/.."
KIT=$(realpath "${1:-.gpu}")
OUT=${2:-${OUT:-/tmp/gpu_check}}
DEADLINE=${DEADLINE:-450}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=/tmp/ggns_site:$PWD/src KIT OUT
failed=0
step() {  # step NAME MAX_SECONDS: run the function NAME (in a child bash, under `timeout`), time and report it
  local name=$1 most=$2
  local left=$((DEADLINE - SECONDS)) start=$SECONDS
  if [ "$left" -lt 20 ]; then echo "[gpu_check] $name: SKIPPED ($left s left of $DEADLINE)"; return; fi
  [ "$most" -gt "$left" ] && most=$left
  echo "[gpu_check $(date +%T)] $name (at most $most s)"
  if timeout "$most" bash -c "set -o pipefail; $name"; then echo "[gpu_check] $name: ok in $((SECONDS - start)) s"
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

torch_cluster() {  # the extensions ggns calls, CUDA builds only (FORCE_ONLY_CUDA: the _cuda extensions serve the
  # CPU too; FORCE_CUDA with a parallel build_ext makes the _cpu and _cuda variants race on csrc/version.o)
  local src=/tmp/torch_cluster-1.6.3 arch
  if python3 -c "import torch_cluster" 2>/dev/null; then echo "torch_cluster already built in /tmp/ggns_site"
  else
  arch=$(python3 -c "import torch; print('.'.join(map(str, torch.cuda.get_device_capability(0))))")
  rm -rf "$src" && tar -xzf "$KIT"/torch_cluster-1.6.3.tar.gz -C /tmp &&
    python3 scripts/torch_cluster_subset.py "$src" version radius knn &&
    printf '[build_ext]\nparallel = %s\n' "$(nproc)" > /tmp/build.cfg &&
    (cd "$src" && DIST_EXTRA_CONFIG=/tmp/build.cfg FORCE_ONLY_CUDA=1 TORCH_CUDA_ARCH_LIST="$arch" MAX_JOBS=$(nproc) \
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

plate_small() {  # the speed data: plate_small's test split, also as its train and val split (where none is)
  if [ -f data/plate_small/train.h5 ]; then echo "data/plate_small exists: used as it is"; return; fi
  mkdir -p data/plate_small && for split in train val test; do cp "$KIT/plate_small/test.h5" "data/plate_small/$split.h5"; done
}

ab() {  # this tree against the baseline commit on the GPU, one round (tree order alternates within it)
  python3 -m ggns bench ab --baseline "$KIT/baseline" --device cuda --rounds 1 --output-dir "$OUT/ab" \
    --probe "train ggns 128 5 32" --probe "rollout ggns 128 5 1 every:1 static" \
    --probe "rollout ggns 128 5 32 every:1 static" 2>&1 | tee "$OUT/ab.txt"
}

profile() {
  python3 -m ggns bench profile --device cuda --steps 10 --fit-steps 100 --output-dir "$OUT/profile" 2>&1 |
    tee "$OUT/profile.txt"
}

learning() {
  python3 -m ggns bench learning --config plate_gpu --output-dir "$OUT/learning" 2>&1 | tail -40 | tee "$OUT/learning.txt"
}

precision() {
  local args=()
  for path in "$KIT"/ckpt/*.ckpt; do args+=(--checkpoint "$(basename "$path" .ckpt)=$path"); done
  python3 -m ggns bench precision --device cuda --trajectories 9 "${args[@]}" --output-dir "$OUT/precision" 2>&1 |
    tee "$OUT/precision.txt"
}

export -f environment packages torch_cluster cuda_tests plate_small ab profile learning precision
step environment 30
step packages 60
step torch_cluster 240
step cuda_tests 120
step plate_small 10
step ab 150
step profile 90
step learning 170
ls "$KIT"/ckpt/*.ckpt >/dev/null 2>&1 && step precision 90
echo "[gpu_check] $failed step(s) failed in $SECONDS s; output in $OUT"
exit "$failed"

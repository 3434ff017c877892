#!/usr/bin/env bash
# The checks and speed measurements that need a GPU, as one script for a GPU machine that cannot reach a
# package registry (python3 with a CUDA torch, pytorch-lightning, torch-geometric and h5py already there,
# nvcc, no open3d), within one call of at most 8 minutes (copying files included). It uses a kit made
# beforehand by scripts/gpu_kit.sh on a machine with this project's set-up:
#   KIT/whl/*.whl          the pure-Python packages the GPU machine lacks (jsonargparse, omegaconf, ...)
#   KIT/torch_cluster-1.6.3.tar.gz   built here against this machine's torch, our ops only
#   KIT/artefacts/torch_cluster_site.tar.gz (optional)   that build from an earlier call (its
#                          OUT/artefacts/, put in the kit by `PREVIOUS=... bash scripts/gpu_kit.sh`):
#                          used instead of building when made for the same python, torch, CUDA and GPU
#   KIT/data/              plate_tiny12 splits for tests/test_cuda.py (no open3d here to raycast them)
#   KIT/plate_small/test.h5          the speed measurements' data (also used as train and val split)
#   KIT/baseline/src       the baseline commit's sources (KIT/baseline/COMMIT), for `bench ab`
#   KIT/ckpt/*.ckpt (optional)       checkpoints for `bench precision` (TF32 and bf16 against float32)
#
# The plan: each step, most important first, has a fixed budget (PLAN below); the budgets add up to at most
# DEADLINE (default 450) minus MARGIN (default 20: packing the archive, the call's own start) seconds, and
# are scaled down when a smaller DEADLINE leaves less. A step may run for its budget plus whatever earlier
# steps left unused (a reused torch-cluster build leaves most of its budget to the measurements after it),
# never into a later step's budget: its limit is what is left before DEADLINE - MARGIN less the budgets of
# the steps after it. At its limit a step gets SIGINT (pytest then still writes its JUnit file), 5 s later
# SIGKILL. A step that fails or times out does not stop the others.
#   environment (5)  packages (15)  torch_cluster (170: the build, about 130 s on 16 cores; reusing the
#   artefact takes a few seconds)  plate_small (5)  tests (70: tests/test_cuda.py as JUnit XML; the CPU's
#   tests/test_static_step.py needs open3d for its data)  profile_static (30: bench profile --static)
#   profile (30: bench profile, with a 100-step fit)
#   ab (65: this tree against the baseline on the GPU)  learning (25, plus what is left: plate_gpu, its
#   per-variant minutes cut to the time there is)  precision (15, when the kit has checkpoints)
#
# Writes under OUT (default /tmp/gpu_check): logs/STEP.log (each step's output), env.txt, junit.xml,
# profile_static/, profile/, ab/, learning/, precision/, artefacts/torch_cluster_site.tar.gz (the
# torch-cluster build, for the next call's kit), gpu_check.log (what this script printed), steps.tsv (each
# step's planned, allowed and used seconds and status), and at the end all of OUT in one archive,
# OUT/gpu_check.tar.gz (ARCHIVE= elsewhere). The exit status is the number of failed steps.
#
# --dry-run (or DRY_RUN=1) runs the plan on any machine, each step's command replaced by a stub that prints
# its limit and exits at once (DRY_RUN_FAIL="STEP ...": those stubs fail; DRY_RUN_HANG="STEP ...": those
# sleep until their limit), to check the plan, steps.tsv and the archive without a GPU.
#   bash scripts/gpu_check.sh [--dry-run] [KIT] [OUT]
# shellcheck disable=SC2317  # the steps' functions run through `bash -c NAME`
set -uo pipefail
cd "$(dirname "$0")/.." || exit 1
DRY_RUN=${DRY_RUN:-0}
if [ "${1:-}" = --dry-run ]; then DRY_RUN=1; shift; fi
KIT=$(realpath -m "${1:-.gpu}")
OUT=$(realpath -m "${2:-${OUT:-/tmp/gpu_check}}")
DEADLINE=${DEADLINE:-450}
MARGIN=${MARGIN:-20}
ARCHIVE=$(realpath -m "${ARCHIVE:-$OUT/gpu_check.tar.gz}")
SITE=/tmp/ggns_site                  # the kit's pure-Python packages
CLUSTER_SITE=/tmp/torch_cluster_site # torch-cluster, built or unpacked from the artefact
SKIP=99                              # a step's exit status for "nothing to do" (not a failure)
# step:budget, most important first
PLAN=(environment:5 packages:15 torch_cluster:170 plate_small:5 tests:70 profile_static:30 profile:30 ab:65
      learning:25 precision:15)
mkdir -p "$OUT/logs"
export PYTHONUNBUFFERED=1 PYTHONPATH=$SITE:$CLUSTER_SITE:$PWD/src KIT OUT SITE CLUSTER_SITE SKIP
: > "$OUT/gpu_check.log"

say() { echo "$*" | tee -a "$OUT/gpu_check.log"; }
# the plan's clock: microseconds since the start (bash's SECONDS counts whole seconds of the wall clock, so it
# can read 1 after 0.1 s)
START_US=${EPOCHREALTIME//[!0-9]/}
us() { if [ -n "$START_US" ]; then local now=${EPOCHREALTIME//[!0-9]/}; echo $((now - START_US)); else echo $((SECONDS * 1000000)); fi; }
tenths() { echo "$(($1 / 1000000)).$(($1 / 100000 % 10))"; }  # microseconds as seconds, one decimal

environment() {
  { nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
    echo "cores $(nproc)"
    python3 -c "import sys
from importlib.metadata import version
print('python', sys.version.split()[0], *(f'{p} {version(p)}' for p in ('torch', 'torch_geometric', 'pytorch_lightning', 'h5py')))"
  } 2>&1 | tee "$OUT/env.txt"
}

packages() {
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" "$KIT"/whl/*.whl
}

torch_cluster() {  # the extensions ggns calls, CUDA builds only (FORCE_ONLY_CUDA: the _cuda extensions serve the
  # CPU too), one extension after another (no parallel build_ext: the _cpu and _cuda variants of a parallel
  # FORCE_CUDA build raced on csrc/version.o; ninja still compiles an extension's files in parallel, MAX_JOBS;
  # TC_PARALLEL=N builds N extensions at once).
  # Reused when $CLUSTER_SITE or the kit's artefact was built for this python, torch, CUDA and GPU; saved
  # as OUT/artefacts/torch_cluster_site.tar.gz for the next call's kit.
  local src=/tmp/torch_cluster-1.6.3 given=$KIT/artefacts/torch_cluster_site.tar.gz key arch
  key=$(python3 -c "import sys, torch
print('python %d.%d' % sys.version_info[:2], 'torch', torch.__version__, 'cuda', torch.version.cuda,
      'sm_%d%d' % torch.cuda.get_device_capability(0))") || return 1
  echo "this machine: $key"
  if [ "$(cat "$CLUSTER_SITE/BUILT_FOR" 2>/dev/null)" = "$key" ]; then echo "reusing $CLUSTER_SITE"
  elif [ -f "$given" ]; then
    rm -rf "$CLUSTER_SITE" && mkdir -p "$CLUSTER_SITE" && tar -xzf "$given" -C "$CLUSTER_SITE" || return 1
    if [ "$(cat "$CLUSTER_SITE/BUILT_FOR" 2>/dev/null)" = "$key" ]; then echo "reusing $given"
    else echo "$given was built for $(cat "$CLUSTER_SITE/BUILT_FOR" 2>/dev/null || echo '?'): building"; rm -rf "$CLUSTER_SITE"; fi
  fi
  if [ ! -f "$CLUSTER_SITE/BUILT_FOR" ]; then
    arch=$(python3 -c "import torch; print('.'.join(map(str, torch.cuda.get_device_capability(0))))") || return 1
    printf '[build_ext]\nparallel = %s\n' "${TC_PARALLEL:-1}" > /tmp/torch_cluster_build.cfg
    rm -rf "$src" "$CLUSTER_SITE" && tar -xzf "$KIT"/torch_cluster-1.6.3.tar.gz -C /tmp &&
      python3 scripts/torch_cluster_subset.py "$src" version radius knn &&
      (cd "$src" && DIST_EXTRA_CONFIG=/tmp/torch_cluster_build.cfg FORCE_ONLY_CUDA=1 TORCH_CUDA_ARCH_LIST="$arch" \
        MAX_JOBS=$(nproc) python3 -m pip install -q --no-build-isolation --no-deps --no-index --target "$CLUSTER_SITE" .) ||
      return 1
    echo "$key" > "$CLUSTER_SITE/BUILT_FOR"
  fi
  python3 -c "import torch, torch_cluster
x = torch.rand(2000, 3, device='cuda')
a, b = torch_cluster.radius_graph(x, 0.1), torch_cluster.radius_graph(x.cpu(), 0.1)
key = lambda e: sorted(zip(*e.tolist()))
assert key(a.cpu()) == key(b), 'radius_graph differs between the GPU and the CPU'
print('torch_cluster', torch_cluster.__version__, 'from', torch_cluster.__file__, 'radius_graph on cuda: the CPU edges', a.shape[1])" ||
    return 1
  mkdir -p "$OUT/artefacts" && tar -czf "$OUT/artefacts/torch_cluster_site.tar.gz" -C "$CLUSTER_SITE" . &&
    echo "saved $OUT/artefacts/torch_cluster_site.tar.gz ($(du -h "$OUT/artefacts/torch_cluster_site.tar.gz" | cut -f1))"
}

plate_small() {  # the speed data: plate_small's test split, also as its train and val split (where none is)
  if [ -f data/plate_small/train.h5 ]; then echo "data/plate_small exists: used as it is"; return; fi
  mkdir -p data/plate_small && for split in train val test; do cp "$KIT/plate_small/test.h5" "data/plate_small/$split.h5"; done
}

tests() {  # the GPU tests, as JUnit XML
  GGNS_TEST_DATA="$KIT/data" python3 -m pytest -p no:cacheprovider -v -rs --junitxml="$OUT/junit.xml" tests/test_cuda.py
}

profile_static() {
  python3 -m ggns bench profile --static --device cuda --steps 10 --output-dir "$OUT/profile_static"
}

profile() {
  python3 -m ggns bench profile --device cuda --steps 10 --fit-steps 100 --output-dir "$OUT/profile"
}

ab() {  # this tree against the baseline commit on the GPU, one round (tree order alternates within it); a probe
  # that fails is reported in ab/ab_summary.md and the others still run (the step then fails)
  python3 -m ggns bench ab --baseline "$KIT/baseline" --device cuda --rounds 1 --output-dir "$OUT/ab" \
    --probe "train ggns 128 5 32" --probe "rollout ggns 128 5 1 every:1 static" \
    --probe "rollout ggns 128 5 32 every:1 static"
}

learning() {  # plate_gpu's two variants one after the other, each for (limit - 60 s of start-ups and report) / 2,
  # at most the file's minute; skipped under 20 s each
  local each=$(((STEP_LIMIT - 60) / 2))
  if [ "$each" -lt 20 ]; then echo "$STEP_LIMIT s are too few for two fits of at least 20 s"; return "$SKIP"; fi
  [ "$each" -gt 60 ] && each=60
  echo "each variant for $each s"
  python3 -m ggns bench learning --config plate_gpu --minutes "$(awk "BEGIN { printf \"%.4f\", $each / 60 }")" \
    --output-dir "$OUT/learning" 2>&1 | tail -40
}

precision() {
  local args=() path
  for path in "$KIT"/ckpt/*.ckpt; do [ -f "$path" ] && args+=(--checkpoint "$(basename "$path" .ckpt)=$path"); done
  if [ ${#args[@]} -eq 0 ]; then echo "no checkpoints in $KIT/ckpt"; return "$SKIP"; fi
  python3 -m ggns bench precision --device cuda --trajectories 9 "${args[@]}" --output-dir "$OUT/precision"
}

dry_run_stub() {  # what a step runs in a dry run
  echo "dry run: $1 (at most $STEP_LIMIT s)"
  case " ${DRY_RUN_FAIL:-} " in *" $1 "*) echo "dry run: $1 fails"; return 1 ;; esac
  case " ${DRY_RUN_HANG:-} " in *" $1 "*) echo "dry run: $1 hangs"; sleep 3600 ;; esac
  return 0
}

export -f environment packages torch_cluster plate_small tests profile_static profile ab learning precision dry_run_stub

# the budgets, scaled down to DEADLINE - MARGIN if they add up to more
AVAILABLE=$((DEADLINE - MARGIN))
NAMES=() BUDGETS=() total=0
for entry in "${PLAN[@]}"; do NAMES+=("${entry%%:*}"); BUDGETS+=("${entry##*:}"); total=$((total + ${entry##*:})); done
if [ "$total" -gt "$AVAILABLE" ]; then
  for i in "${!BUDGETS[@]}"; do BUDGETS[i]=$((BUDGETS[i] * (AVAILABLE > 0 ? AVAILABLE : 0) / total)); done
fi
PLANNED=0
for budget in "${BUDGETS[@]}"; do PLANNED=$((PLANNED + budget)); done
plan=""
for i in "${!NAMES[@]}"; do plan+=" ${NAMES[i]} ${BUDGETS[i]},"; done
say "[gpu_check $(date +%T)]$([ "$DRY_RUN" = 1 ] && echo ' DRY RUN') plan (s):${plan%,} = $PLANNED of $AVAILABLE" \
    "(deadline $DEADLINE, margin $MARGIN); kit $KIT, output $OUT"
printf 'step\tplanned_s\tlimit_s\tused_s\tstatus\n' > "$OUT/steps.tsv"

failed=0 skipped=0
finish() {  # the totals row and the archive of OUT (without the archive itself)
  printf 'total\t%s\t%s\t%s\t%s\n' "$PLANNED" "$AVAILABLE" "$(tenths "$(us)")" "$failed failed, $skipped skipped" >> "$OUT/steps.tsv"
  say "[gpu_check $(date +%T)] $failed step(s) failed, $skipped skipped, in $(tenths "$(us)") s of $DEADLINE; output in $OUT"
  column -t -s $'\t' "$OUT/steps.tsv" 2>/dev/null | tee -a "$OUT/gpu_check.log" || cat "$OUT/steps.tsv"
  local part  # written outside OUT (tar refuses a folder that changes as it reads it), then moved in place
  part=$(mktemp "${TMPDIR:-/tmp}/gpu_check.XXXXXX") || return
  mkdir -p "$(dirname "$ARCHIVE")"
  if tar -czf "$part" -C "$OUT" --exclude="./$(basename "$ARCHIVE")" . && mv "$part" "$ARCHIVE"; then
    echo "[gpu_check] all of it in $ARCHIVE ($(du -h "$ARCHIVE" | cut -f1))"
  else echo "[gpu_check] could not write $ARCHIVE"; rm -f "$part"; fi
}
trap 'say "[gpu_check] interrupted"; finish; exit 143' TERM INT

for i in "${!NAMES[@]}"; do
  name=${NAMES[i]} budget=${BUDGETS[i]} later=0
  for ((j = i + 1; j < ${#BUDGETS[@]}; j++)); do later=$((later + BUDGETS[j])); done
  limit=$((AVAILABLE - $(us) / 1000000 - later))  # its budget, plus what earlier steps left unused
  if [ "$limit" -lt 1 ]; then
    say "[gpu_check] $name: SKIPPED (no time left: $(tenths "$(us)") s used, $later s promised to later steps)"
    printf '%s\t%s\t%s\t%s\t%s\n' "$name" "$budget" 0 0 "skipped: no time left" >> "$OUT/steps.tsv"
    skipped=$((skipped + 1)); continue
  fi
  command=$name
  [ "$DRY_RUN" = 1 ] && command="dry_run_stub $name"
  say "[gpu_check $(date +%T)] $name (budget $budget s, at most $limit s)"
  start=$(us)
  STEP_LIMIT=$limit timeout -s INT -k 5 "$limit" bash -c "set -o pipefail; $command" > "$OUT/logs/$name.log" 2>&1
  status=$? used=$(tenths $(($(us) - start)))
  case $status in
    0) result=ok ;;
    "$SKIP") result="skipped: $(tail -n 1 "$OUT/logs/$name.log" | tr '\t' ' ')"; skipped=$((skipped + 1)) ;;
    124 | 137) result="timeout after $limit s"; failed=$((failed + 1)) ;;
    *) result="failed (status $status)"; failed=$((failed + 1)) ;;
  esac
  say "[gpu_check] $name: $result, $used s"
  tail -n 6 "$OUT/logs/$name.log" | sed 's/^/    /' | tee -a "$OUT/gpu_check.log"
  printf '%s\t%s\t%s\t%s\t%s\n' "$name" "$budget" "$limit" "$used" "$result" >> "$OUT/steps.tsv"
done
trap - TERM INT
finish
exit "$failed"

#!/usr/bin/env bash
# Build time of torch-cluster's extensions that ggns calls (version, radius, knn) with and without
# `torch_cluster_subset.py --units $(nproc)` (docs/experiments/test_suite_time.md): the sdist (pip's download) is
# built twice in temporary folders against .venv's torch with `setup.py build_ext` and the parallel setting
# scripts/setup.sh uses (it then packs a wheel, not timed here), each C++ file's compile timed by a wrapper around
# g++; then both builds' radius, radius_graph and knn are compared on the same inputs.
# Usage: bash scripts/bench_torch_cluster_build.sh > raw.txt
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
PY=${PY:-$ROOT/.venv/bin/python}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT
echo "commit $(git rev-parse --short HEAD), $(nproc) cores, $(date -u +%FT%TZ), $("$PY" -c 'import torch; print("torch", torch.__version__)')"
cat > "$WORK/gxx" <<'EOF'
#!/usr/bin/env bash
start=$(date +%s.%N); g++ "$@"; status=$?
source=$(printf '%s\n' "$@" | grep -m1 '\.cpp$' || true)
[ -n "$source" ] && printf '  compiled %s in %.1f s\n' "$source" "$(echo "$(date +%s.%N) - $start" | bc)" >> "$LOG"
exit $status
EOF
chmod +x "$WORK/gxx"
printf '[build_ext]\nparallel = %s\n' "$(nproc)" > "$WORK/build.cfg"
"$PY" -m pip download -q --no-deps --no-binary :all: torch-cluster==1.6.3 -d "$WORK" 2>/dev/null
for variant in "per extension" "units"; do
  dir="$WORK/${variant// /_}"
  mkdir -p "$dir" && tar -xzf "$WORK"/torch_cluster-1.6.3.tar.gz -C "$dir"
  src="$dir/torch_cluster-1.6.3"
  if [ "$variant" = units ]; then extra=(--units "$(nproc)"); else extra=(); fi
  "$PY" scripts/torch_cluster_subset.py "$src" version radius knn "${extra[@]}"
  export LOG="$dir/compiles.txt"; : > "$LOG"
  start=$(date +%s.%N)
  (cd "$src" && DIST_EXTRA_CONFIG="$WORK/build.cfg" MAX_JOBS=$(nproc) CC="$WORK/gxx" CXX="$WORK/gxx" \
    "$PY" setup.py -q build_ext --inplace >"$dir/build.log" 2>&1)
  printf '%s: build_ext %.1f s wall\n' "$variant" "$(echo "$(date +%s.%N) - $start" | bc)"
  cat "$LOG"
done
cat > "$WORK/edges.py" <<'EOF'
import sys
import torch
sys.path.insert(0, sys.argv[1])
import torch_cluster as tc
torch.manual_seed(0)
x, y = torch.rand(3000, 3), torch.rand(500, 3)
bx, by = ((torch.arange(n) >= n // 2).long() for n in (3000, 500))
out = {"radius_graph": tc.radius_graph(x, 0.08, bx, max_num_neighbors=64),
       "radius": tc.radius(x, y, 0.1, bx, by, max_num_neighbors=32), "knn": tc.knn(x, y, 5, bx, by)}
torch.save({k: sorted(zip(*v.tolist())) for k, v in out.items()}, sys.argv[2])
EOF
"$PY" "$WORK/edges.py" "$WORK/per_extension/torch_cluster-1.6.3" "$WORK/a.pt"
"$PY" "$WORK/edges.py" "$WORK/units/torch_cluster-1.6.3" "$WORK/b.pt"
"$PY" -c "
import torch
a, b = torch.load('$WORK/a.pt'), torch.load('$WORK/b.pt')
print('the same edges from both builds:', {k: a[k] == b[k] for k in a}, {k: len(v) for k, v in a.items()})"

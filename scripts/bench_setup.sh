#!/usr/bin/env bash
# Set-up time of a fresh virtual environment, pip against uv (scripts/setup.sh, docs/setup.md): each
# installer makes a new venv in a temporary folder from this machine's warm caches (pip's, uv's and the
# torch-cluster wheel), timed by the shell. Usage: bash scripts/bench_setup.sh [repeats] > raw.txt
set -euo pipefail
cd "$(dirname "$0")/.."
REPEATS=${1:-1}
echo "commit $(git rev-parse --short HEAD), $(nproc) cores, $(date -u +%FT%TZ)"
for i in $(seq "$REPEATS"); do
  for installer in pip uv; do
    venv=$(mktemp -d)/venv
    start=$(date +%s.%N)
    if [ "$installer" = pip ]; then flag=1; else flag=0; fi
    VENV=$venv GGNS_SETUP_PIP=$flag bash scripts/setup.sh >/dev/null 2>&1
    end=$(date +%s.%N)
    printf '%s repeat %d: %.1f s\n' "$installer" "$i" "$(echo "$end - $start" | bc)"
    rm -rf "$(dirname "$venv")"
  done
done

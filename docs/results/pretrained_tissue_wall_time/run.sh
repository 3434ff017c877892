#!/bin/bash
# retrain the tissue's shipped baselines at the GGNS's budget, one process at a time on one core
cd /work/wt_base
source /work/main/.venv/bin/activate
export PYTHONPATH=src OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
set -e
echo "start $(date -u +%FT%T) commit $(git rev-parse HEAD)"
python -m ggns generate --config tissue_cpu --workers 1
echo "data $(date -u +%FT%T)"
for m in mgn mgn_m; do
  python -m ggns pretrained train --name tissue/$m
  echo "trained $m $(date -u +%FT%T)"
done
for m in mgn mgn_m; do
  python -m ggns pretrained package --name tissue/$m
  echo "packaged $m $(date -u +%FT%T)"
done
echo "done $(date -u +%FT%T)"

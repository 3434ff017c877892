#!/usr/bin/env bash
# the tissue's realistic sensor one tick late again (9 test trajectories), with each tissue baseline retrained
# at its GGNS's 9,474 optimizer steps: MGN registered (tissue_realistic_late1_equal_mgn) and MGN(M) registered
# (tissue_realistic_late1_equal_mgn_m); run from the repository's top folder, the code's commit printed first
set -euo pipefail
cd "$(git rev-parse --show-toplevel)"
git rev-parse --short HEAD
for model in mgn mgn_m; do
  python -m ggns bench online-study --task tissue --trajectories 9 --baseline $model --registered $model \
    --sensor realistic --every 1 --latency 1 --data-dir data/tissue_cpu \
    --output-dir docs/results/online_registration/tissue_realistic_late1_equal_$model
done

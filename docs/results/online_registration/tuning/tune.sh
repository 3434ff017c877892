#!/usr/bin/env bash
# the registration's smoothness on 3 tissue validation trajectories, flawless frames every 3rd tick
cd /work/main
for s in 0.1 1 10; do
  .venv/bin/python -m ggns bench online-study --task tissue --trajectories 3 --split val --sensor none --every 3 \
    --latency 0 --baseline mgn --registered mgn --no-grounded --registration smoothness=$s \
    --data-dir /work/wt_fits/data/tissue_cpu --output-dir /work/study/tune_tissue_s$s
done
echo TUNE_DONE

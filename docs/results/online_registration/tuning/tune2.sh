#!/usr/bin/env bash
cd /work/main
for s in 0.01 0.03 0.1; do
  .venv/bin/python -m ggns bench online-study --task tissue --trajectories 3 --split val --sensor none,realistic --every 3 \
    --latency 0 --baseline mgn --registered mgn --no-grounded --registration smoothness=$s \
    --data-dir /work/wt_fits/data/tissue_cpu --output-dir /work/study/tune2_tissue_s$s
done
for s in 0.1 1; do for r in 0 1; do
  .venv/bin/python -m ggns bench online-study --task plate --trajectories 3 --split val --sensor none,realistic --every 3 \
    --latency 0 --baseline mgn --registered mgn --no-grounded --registration smoothness=$s --registration reverse=$r \
    --data-dir /work/wt_fits/data/plate --output-dir /work/study/tune2_plate_s${s}_r$r
done; done
echo TUNE_DONE

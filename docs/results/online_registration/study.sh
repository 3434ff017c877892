#!/usr/bin/env bash
# the registration comparison (code at the commit printed first): tissue's realistic sensor one tick late on 9 test
# trajectories; the grid of rates and latencies on the first 3 of the tissue and of the plate
cd /work/wt_study; export PYTHONPATH=src
git rev-parse --short HEAD
REG="--baseline mgn,mgn_m --registered mgn,mgn_m,static,ggns"
.venv/bin/python -m ggns bench online-study --task tissue --trajectories 9 $REG --sensor realistic,realistic_calibration_mm --every 1 --latency 1 \
  --data-dir /work/wt_fits/data/tissue_cpu --output-dir /work/study/tissue_realistic_late1
.venv/bin/python -m ggns bench online-study --task tissue --trajectories 3 $REG --sensor none,realistic --every 1,3,5 --latency 0,2 \
  --data-dir /work/wt_fits/data/tissue_cpu --output-dir /work/study/tissue
.venv/bin/python -m ggns bench online-study --task plate --trajectories 3 $REG --sensor none,realistic --every 1,3,5 --latency 0,2 \
  --data-dir /work/wt_fits/data/plate --output-dir /work/study/plate
echo STUDY_DONE

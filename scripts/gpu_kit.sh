#!/usr/bin/env bash
# Make the kit scripts/gpu_check.sh needs on a GPU machine without a package registry (run here, after
# scripts/setup.sh): Python 3.12 wheels of the pure-Python packages such a machine lacks, the
# torch-cluster sources, the plate_tiny12 splits of tests/test_cuda.py, plate_small's test split (the
# speed measurements' data), the baseline commit's sources (BASELINE, default e59b184: `bench ab` on the
# GPU compares against it), optionally checkpoints (stripped of optimizer states to travel light), and
# the torch-cluster build of an earlier call (PREVIOUS: that call's gpu_check.tar.gz, its OUT folder or
# the torch_cluster_site.tar.gz itself) as KIT/artefacts/torch_cluster_site.tar.gz, so that the next
# call skips the build (about 130 s; gpu_check.sh builds anyway when it was made for another python,
# torch, CUDA or GPU).
#   [PREVIOUS=.../gpu_check.tar.gz] bash scripts/gpu_kit.sh [KIT] [NAME=CHECKPOINT ...]
set -euo pipefail
cd "$(dirname "$0")/.."
KIT=${1:-.gpu}; shift || true
PY=.venv/bin/python
mkdir -p "$KIT/whl" "$KIT/data" "$KIT/ckpt"
PREVIOUS=${PREVIOUS:-}
if [ -n "$PREVIOUS" ]; then
  mkdir -p "$KIT/artefacts"
  case $PREVIOUS in
    */torch_cluster_site.tar.gz) cp "$PREVIOUS" "$KIT/artefacts/" ;;
    *.tar.gz) tar -xzf "$PREVIOUS" -C "$KIT/artefacts" --strip-components=2 ./artefacts/torch_cluster_site.tar.gz ;;
    *) cp "$PREVIOUS/artefacts/torch_cluster_site.tar.gz" "$KIT/artefacts/" ;;
  esac
  echo "torch-cluster build from $PREVIOUS: $KIT/artefacts/torch_cluster_site.tar.gz"
fi
PLATFORMS=()
for tag in manylinux_2_35 manylinux_2_31 manylinux_2_28 manylinux_2_27 manylinux_2_24 manylinux_2_17 manylinux2014; do
  PLATFORMS+=(--platform "${tag}_x86_64")
done
for package in $(grep -E '^(jsonargparse|omegaconf|trimesh|scikit-fem|shapely)' requirements.txt | sed 's/\[.*\]//') \
               docstring_parser==0.18.0 typeshed_client==2.15.0; do
  $PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp "${PLATFORMS[@]}" \
    -d "$KIT/whl" "$package"
done
[ -f "$KIT/torch_cluster-1.6.3.tar.gz" ] ||
  $PY -m pip download -q --no-deps --no-build-isolation --no-binary :all: torch-cluster==1.6.3 -d "$KIT"
$PY - "$KIT" "$@" <<'EOF'
import sys
from pathlib import Path

import torch

from ggns.checkpoints import read_checkpoint
from ggns.config import CONF_DIR, load_config
from ggns.data.generate import generate

kit = Path(sys.argv[1]).resolve()
data = kit / "data"
if not (data / "test.h5").is_file():  # the conftest fixture cli_data's preset: plate_tiny with T = 12
    (data / "plate_tiny12.yaml").write_text(f"base: {CONF_DIR / 'data' / 'plate_tiny.yaml'}\nscene:\n  num_steps: 12\n"
                                            f"output: {data}\n")
    generate(load_config(data / "plate_tiny12.yaml"), progress=False)
for spec in sys.argv[2:]:
    name, path = spec.split("=", 1)
    checkpoint = read_checkpoint(path)
    kept = {k: v for k, v in checkpoint.items() if k not in ("optimizer_states", "lr_schedulers", "callbacks", "loops")}
    torch.save(kept, kit / "ckpt" / f"{name}.ckpt")
    print(f"{name}: {path}")
EOF
[ -f data/plate_small/test.h5 ] || $PY -m ggns generate --config plate_small --split test
mkdir -p "$KIT/plate_small" && cp data/plate_small/test.h5 "$KIT/plate_small/test.h5"
BASELINE=${BASELINE:-e59b184}
rm -rf "$KIT/baseline" && mkdir -p "$KIT/baseline" && git archive "$BASELINE" src conf | tar -x -C "$KIT/baseline"
echo "$BASELINE" > "$KIT/baseline/COMMIT"
du -sh "$KIT"

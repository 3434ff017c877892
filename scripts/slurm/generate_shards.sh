#!/bin/bash
# A dataset made by a SLURM job array, one shard per task (docs/robustness.md, "Beyond one machine"):
#   sbatch --array=0-99 scripts/slurm/generate_shards.sh cavity 100
# makes <output>/<split>.shard-<i>-of-100.h5 for every split of the preset, each task alone (its
# trajectories' seeds depend only on the preset's seed, the split and the trajectory's index), and
# resumable: a requeued or resubmitted task keeps the trajectories it finished. Then, anywhere:
#   sbatch --dependency=afterok:<array job id> --wrap ".venv/bin/python -m ggns generate --config cavity --merge-shards 100"
# writes <split>.h5, bit for bit what one machine would have made (it copies arrays, simulates nothing).
# Run it without sbatch to make one shard here: SLURM_ARRAY_TASK_ID=3 bash scripts/slurm/generate_shards.sh plate_tiny 4
#SBATCH --job-name=ggns-generate
#SBATCH --ntasks=1
#SBATCH --cpus-per-task=8
#SBATCH --time=12:00:00
#SBATCH --requeue
#SBATCH --output=slurm-%A_%a.out
set -euo pipefail
config=${1:?usage: generate_shards.sh <data preset> <number of shards> [key=value overrides]}
shards=${2:?usage: generate_shards.sh <data preset> <number of shards> [key=value overrides]}
shift 2
task=${SLURM_ARRAY_TASK_ID:?SLURM_ARRAY_TASK_ID is not set: submit with sbatch --array=0-$((shards - 1))}
cd "${SLURM_SUBMIT_DIR:-$(dirname "$0")/../..}"
# one worker process per CPU SLURM gave the task (the preset's own count otherwise)
exec .venv/bin/python -m ggns generate --config "$config" --shard "$task/$shards" \
  ${SLURM_CPUS_PER_TASK:+--workers "$SLURM_CPUS_PER_TASK"} "$@"

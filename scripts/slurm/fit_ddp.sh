#!/bin/bash
# One fit on several nodes with Lightning's DDP (docs/robustness.md, "Beyond one machine"):
#   sbatch --nodes=4 scripts/slurm/fit_ddp.sh conf/cavity/ggns.yaml --data.dataset cavity --data.batch_size 8
# runs one process per GPU (SLURM starts them, Lightning reads the ranks from SLURM's environment).
# Each process trains on its own share of every epoch's windows, the normalizer's statistics are
# merged across all of them, and the logged loss is their mean: N processes with batches of B train
# as one with batches of N x B (tests/test_distributed.py, 2 CPU processes). find_unused_parameters is
# needed: a batch without contact leaves an edge MLP without a gradient (plain ddp is refused).
# On SIGUSR1 (90 s before the time limit) Lightning saves hpc_ckpt_<n>.ckpt in the trainer's
# default_root_dir and requeues the job (`scontrol requeue`); the requeued job keeps its job id, finds
# the checkpoint in the same folder (one per job id, so two jobs from one folder never share one) and
# resumes with the same data order and random draws (tests/test_faults.py plays this on one CPU process
# with SLURM's environment and a stand-in scontrol; not run on a real cluster here).
#SBATCH --job-name=ggns-fit
#SBATCH --nodes=2
#SBATCH --ntasks-per-node=4
#SBATCH --gres=gpu:4
#SBATCH --cpus-per-task=8
#SBATCH --time=24:00:00
#SBATCH --signal=SIGUSR1@90
#SBATCH --output=slurm-%j.out
set -euo pipefail
config=${1:?usage: fit_ddp.sh <model config> [Lightning CLI arguments]}
shift
cd "${SLURM_SUBMIT_DIR:-$(dirname "$0")/../..}"
srun .venv/bin/python -m ggns fit --config "$config" \
  --trainer.accelerator gpu --trainer.devices "${SLURM_NTASKS_PER_NODE:-1}" --trainer.num_nodes "${SLURM_JOB_NUM_NODES:-1}" \
  --trainer.strategy ddp_find_unused_parameters_true --trainer.default_root_dir "lightning_logs/slurm/${SLURM_JOB_ID:-local}" "$@"

"""GGNSID's material estimate along rollouts under point-cloud schedules (the k=5 question):
python experiments/material_estimator/material_trace.py CHECKPOINT [--dataset plate --data-dir DIR --split test --trajectories 27 --schedules 1,5]

Rolls the checkpoint out one step at a time from S_0 under "a point cloud every k steps" for each k and
prints, every 5 steps, the mean |estimate - Poisson's ratio| over the trajectories (GGNSID; nan for a
model without an estimate), the same for the estimate fused from the *true* states at the same
point-cloud steps (teacher forcing: what the estimator reads when the mesh has not drifted), the share
of trajectories whose rollout estimate is off by more than 0.2, and the position MSE at that state
(mean over nodes and coordinates). A diagnostic, not a library command."""
from __future__ import annotations

import argparse

import torch

from ggns.batch import TrajectoryBatch
from ggns.data.module import SimulationDataModule
from ggns.evaluation.evaluate import split_trajectories
from ggns.evaluation.metrics import rollout_mse
from ggns.evaluation.rollout import rollout
from ggns.evaluation.schedules import EveryK, Never
from ggns.pretrained import load_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--dataset", default="plate")
    parser.add_argument("--data-dir", default=None, help="folder of the split files (default: the preset's output)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--trajectories", type=int, default=27)
    parser.add_argument("--schedules", default="1,5", help="comma-separated k")
    parser.add_argument("--oracle", action="store_true",
                        help="also roll GGNSID out with the label as its carried material (k=1 and blind): "
                             "how far its dynamics are from MGN(M)'s once the material is known exactly")
    args = parser.parse_args()
    model = load_model(args.checkpoint, map_location="cpu")
    carries = hasattr(model, "material_estimate")  # GGNSID; any other model: the position error only
    data = SimulationDataModule(args.dataset, data_dir=args.data_dir, generate_missing=False)
    batch = TrajectoryBatch.from_trajectories(data.trajectories(args.split)[:args.trajectories])
    last = batch.num_steps - 1
    print("| k | step | material error | material error, true states | share off by > 0.2 | position MSE |\n"
          "|---|---|---|---|---|---|")

    def errors(state) -> torch.Tensor:
        if not carries or state is None:
            return torch.full_like(batch.material, float("nan"))
        return (model.material_estimate(state) - batch.material).abs()

    with torch.no_grad():
        for k in (int(x) for x in args.schedules.split(",")):
            position, state, true_state = batch.positions[0], None, None
            for t in range(last):
                nxt, state = rollout(model.step, batch, EveryK(k), model.connectivity, model.with_material,
                                     position, t, 1, state)
                _, true_state = rollout(model.step, batch, EveryK(k), model.connectivity, model.with_material,
                                        None, t, 1, true_state)
                position = nxt[1]
                if (t + 1) % 5 == 0:
                    error, true_error = errors(state), errors(true_state)
                    mse = ((position - batch.positions[t + 1]) ** 2).mean().item()
                    print(f"| {k} | {t + 1} | {error.mean().item():.3f} | {true_error.mean().item():.3f} | "
                          f"{(error > 0.2).float().mean().item():.2f} | {mse:.2e} |")
        if args.oracle and carries:
            oracle_rollouts(model, batch)


def oracle_rollouts(model, batch) -> None:
    """Full-rollout MSE (the test metric's) of GGNSID given the label as its fused estimate (a precision of 1e6 in normalized
    units, which no estimate moves), a point cloud every step and none, beside its own estimate."""
    label = model.material_normalizer(batch.material[:, None])[:, 0]
    known = (torch.full_like(label, 1e6), label * 1e6)
    true = split_trajectories(batch.positions, batch)
    print("\n| schedule | rollout MSE, own estimate | rollout MSE, the label as estimate |\n|---|---|---|")
    for name, schedule in (("k=1", EveryK(1)), ("never", Never())):
        own, _ = rollout(model.step, batch, schedule, model.connectivity, model.with_material)
        told, _ = rollout(model.step, batch, schedule, model.connectivity, model.with_material, state=known)
        mse = [torch.tensor([rollout_mse(p, t)[0] for p, t in zip(split_trajectories(pred, batch), true)]).mean().item()
               for pred in (own, told)]
        print(f"| {name} | {mse[0]:.3e} | {mse[1]:.3e} |")


if __name__ == "__main__":
    main()

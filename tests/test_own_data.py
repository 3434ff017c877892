"""GGNS on a user's own data: a trajectory from plain arrays (`data.observations`) and its refusals,
predictions files (`data.predictions`), and `python -m ggns rollout` end to end on plate_tiny with
real checkpoints, real HDF5 files and the refusals of mismatched inputs. Single-threaded."""
from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest
import pytorch_lightning as pl
import torch

from ggns.__main__ import main
from ggns.batch import TrajectoryBatch
from ggns.data.generate import split_path
from ggns.data.module import SimulationDataModule, WindowDataset
from ggns.data.observations import trajectory_from_arrays
from ggns.checkpoints import sha256
from ggns.data.predictions import Predictions, read_predictions, write_predictions
from ggns.data.schema import DatasetError, SplitReader, SplitWriter
from ggns.evaluation.evaluate import split_trajectories
from ggns.geometry import signed_volumes
from ggns.models.simulators import GGNS, MGNM
from ggns.models.loading import load_simulator
from conftest import box_mesh, save_untrained

pytestmark = pytest.mark.usefixtures("single_thread")


def arrays(traj) -> dict:
    """A generated trajectory's arrays as a user would hand them over (fixed nodes as an index list)."""
    return dict(rest_positions=traj.rest_positions, cells=traj.cells, fixed=np.flatnonzero(traj.fixed),
                collider_faces=traj.collider_faces, collider_positions=traj.collider_positions,
                point_clouds=[traj.point_cloud(t) for t in range(traj.num_steps)],
                youngs_modulus=traj.youngs_modulus)


# ---- 1. a trajectory from arrays ----------------------------------------------------------------------------
def test_arrays_of_a_generated_trajectory_give_it_back(trajs):
    traj = trajs["test"][0]
    built = trajectory_from_arrays(**arrays(traj), poissons_ratio=traj.poissons_ratio, true_positions=traj.positions)
    for name in ("rest_positions", "cells", "edges", "positions", "fixed", "collider_faces", "collider_positions",
                 "points", "point_offsets"):
        mine, theirs = getattr(built, name), getattr(traj, name)
        assert mine.dtype == theirs.dtype and np.array_equal(mine, theirs), name
    assert built.has_ground_truth and built.material_known and built.poissons_ratio == traj.poissons_ratio


def test_without_ground_truth_nothing_is_invented(trajs, tmp_path):
    """Unknown future states are the initial state repeated and marked so: the mark survives a split
    file, and metrics, teacher forcing and training refuse such trajectories."""
    traj = trajs["test"][0]
    built = trajectory_from_arrays(**arrays(traj))
    assert not built.has_ground_truth and not built.material_known
    assert np.array_equal(built.positions, np.broadcast_to(traj.rest_positions, traj.positions.shape))
    with SplitWriter(tmp_path / "own.h5", scene="own", split="test", dim=2, generator_config={}) as writer:
        writer.append(built)
    with SplitReader(tmp_path / "own.h5") as split:
        again = split[0]
    assert not again.has_ground_truth and not again.material_known
    batch = TrajectoryBatch.from_trajectories([traj, again])
    model = GGNS(latent=8, blocks=1)
    with pytest.raises(ValueError, match=r"computing metrics needs the true positions, but trajectory\(ies\) \[1\]"):
        model.evaluate(batch)
    with pytest.raises(ValueError, match="no ground truth"):
        WindowDataset([again], 1)
    with pytest.raises(ValueError, match="built without poissons_ratio"):
        MGNM(latent=8, blocks=1).rollout(TrajectoryBatch.from_trajectories([again]), "never")
    assert model.rollout(TrajectoryBatch.from_trajectories([again]), "every:1").shape == traj.positions.shape


def box_case(dim: int) -> dict:
    """A valid box mesh in [-1, 1]^dim, fixed bottom, a collider of 2 vertices above, clouds on the mesh, T = 3."""
    rest, cells = box_mesh(dim, n=4)
    rest = 2 * rest - 1
    negative = signed_volumes(rest, cells) < 0  # scikit-fem's cells come in either orientation
    cells[negative] = cells[negative][:, [1, 0, *range(2, dim + 1)]]
    clouds = [rest[::2] + 0.01, np.zeros((0, dim)), rest[1::3]]
    collider = np.stack([np.full((2, dim), 1.1) + 0.05 * t for t in range(3)])
    faces = np.array([[0, 1]]) if dim == 2 else np.zeros((0, 3), dtype=np.int64)
    return dict(rest_positions=rest, cells=cells, fixed=rest[:, 1] < -0.99, collider_faces=faces,
                collider_positions=collider, point_clouds=clouds, youngs_modulus=5000.0)


def inverted(case):
    cells = case["cells"].copy()
    cells[[2, 5]] = cells[[2, 5]][:, [1, 0, *range(2, cells.shape[1])]]
    return {"cells": cells}


def with_nan(case):
    rest = case["rest_positions"].copy()
    rest[3, 0] = np.nan
    return {"rest_positions": rest}


def with_flat_cell(case):
    cells = case["cells"]
    return {"cells": np.concatenate([cells, cells[:1, [0, 0, *range(1, cells.shape[1] - 1)]]])}


def with_lone_node(case):
    rest = case["rest_positions"]
    return {"rest_positions": np.concatenate([rest, np.zeros((1, rest.shape[1]))])}


def one_step(case):
    return {"point_clouds": case["point_clouds"][:1], "collider_positions": case["collider_positions"][:1]}


BAD_CASES = {  # name: (change of the valid case, expected message part)
    "4 dimensions": (lambda c: {"rest_positions": np.zeros((5, 4))}, "d = 2 or 3"),
    "cells of another dimension": (lambda c: {"cells": c["cells"][:, :-1]}, "must be integer [C,"),
    "NaN in the mesh": (with_nan, "rest_positions contains NaN"),
    "cell index out of range": (lambda c: {"cells": np.where(c["cells"] == 0, 999, c["cells"])}, "index outside"),
    "inverted cells": (inverted, "2 of the"),
    "flat cell": (with_flat_cell, "are flat"),
    "node in no cell": (with_lone_node, "belong to no cell"),
    "fixed index out of range": (lambda c: {"fixed": [0, 10_000]}, "fixed node index outside"),
    "one step": (one_step, "T >= 2"),
    "collider steps differ": (lambda c: {"collider_positions": c["collider_positions"][:2]},
                              "collider_positions has 2 steps but point_clouds has 3"),
    "collider face index": (lambda c: {"collider_faces": np.full((1, c["rest_positions"].shape[1]), 7)},
                            "collider_faces index outside"),
    "cloud of another dimension": (lambda c: {"point_clouds": [p[:, :1] for p in c["point_clouds"]]},
                                   "point_clouds[0] must be"),
    "cloud in millimetres": (lambda c: {"point_clouds": [1000 * p for p in c["point_clouds"]]}, "other units"),
    "cloud in another frame": (lambda c: {"point_clouds": [p + 5.0 for p in c["point_clouds"]]},
                               "farther than 3 mesh edge lengths"),
    "mesh in millimetres": (lambda c: {"rest_positions": 1000 * c["rest_positions"]}, "rest_positions reach 1000"),
    "true positions of other steps": (lambda c: {"true_positions": np.stack([c["rest_positions"]] * 2)},
                                      "true_positions must be [T=3"),
    "true positions not starting at rest": (lambda c: {"true_positions": np.stack([c["rest_positions"] + 0.1] * 3)},
                                            "true_positions[0] differs from rest_positions"),
    "poisson's ratio": (lambda c: {"poissons_ratio": 0.5}, "poissons_ratio must lie in (-1, 0.5)"),
}


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("case", sorted(BAD_CASES))
def test_bad_arrays_are_refused_with_one_clear_message(case, dim):
    valid = box_case(dim)
    trajectory_from_arrays(**valid)  # the unchanged case is accepted
    change, message = BAD_CASES[case]
    with pytest.raises(ValueError) as error:
        trajectory_from_arrays(**{**valid, **change(valid)})
    assert message in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize("dim", [2, 3])
def test_inverted_cells_are_reoriented_only_when_asked(dim):
    valid = box_case(dim)
    with pytest.raises(ValueError, match=r"2 of the \d+ cells are inverted .*first: \[2, 5\]\).*fix_orientation=True"):
        trajectory_from_arrays(**{**valid, **inverted(valid)})
    fixed = trajectory_from_arrays(**{**valid, **inverted(valid)}, fix_orientation=True)
    assert np.array_equal(fixed.edges, trajectory_from_arrays(**valid).edges)
    assert np.array_equal(np.sort(fixed.cells, axis=1), np.sort(valid["cells"], axis=1))


# ---- 2. predictions files -----------------------------------------------------------------------------------
def test_predictions_file_round_trip_and_atomic_refusals(trajs, tiny_data_dir, tmp_path):
    inputs = trajs["test"]
    rng = np.random.default_rng(0)
    written = Predictions(positions=[(t.positions + rng.normal(0, 0.01, t.positions.shape)).astype(np.float32)
                                     for t in inputs],
                          inputs=inputs, model_class="GGNS", schedule="every:2", checkpoint="x.ckpt",
                          checkpoint_sha256="ab" * 32, input_file="/data/test.h5", input_indices=[4, 7], scene="plate")
    path = write_predictions(tmp_path / "p.h5", written)
    back = read_predictions(path)
    assert back.created and back.dim == 2
    assert dataclasses.replace(back, positions=[], inputs=[], created="") == \
        dataclasses.replace(written, positions=[], inputs=[])
    for a, b in zip(back.positions, written.positions):
        assert a.dtype == np.float32 and np.array_equal(a, b)
    for a, b in zip(back.inputs, inputs):
        assert np.array_equal(a.positions, b.positions) and np.array_equal(a.points, b.points) and a.params == b.params
    with pytest.raises(FileExistsError, match="already exists"):
        write_predictions(path, written)
    with pytest.raises(ValueError, match="rollout 1 has shape"):
        write_predictions(tmp_path / "q.h5", dataclasses.replace(written, positions=[written.positions[0],
                                                                                     written.positions[1][:-1]]))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.h5"]  # no partial file left behind
    with pytest.raises(DatasetError, match="not a ggns-predictions file"):
        read_predictions(split_path(tiny_data_dir, "test"))


# ---- 3. python -m ggns rollout --------------------------------------------------------------------------------
def run(args: list[str]) -> None:
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sys, "argv", ["ggns"])
        main(args)


@pytest.fixture(scope="module")
def checkpoints(tiny_data_dir, tmp_path_factory):
    """A GGNS fitted for one step on plate_tiny, and an untrained 3D (tissue) GGNS."""
    out = tmp_path_factory.mktemp("own_data_ckpts")
    torch.manual_seed(0)
    model = GGNS(latent=8, blocks=1)
    data = SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=8, generate_missing=False)
    trainer = pl.Trainer(max_steps=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, limit_val_batches=0)
    trainer.fit(model, datamodule=data)
    trainer.save_checkpoint(out / "ggns.ckpt")
    return {"plate": out / "ggns.ckpt",
            "tissue": save_untrained(GGNS(latent=8, blocks=1, dim=3, connectivity="tissue_reduced_graph"),
                                     out / "tissue.ckpt")}


def test_rollout_command_round_trips_through_the_predictions_file(checkpoints, tiny_data_dir, trajs, tmp_path):
    test_file = split_path(tiny_data_dir, "test")
    out = tmp_path / "preds.h5"
    run(["rollout", "--checkpoint", str(checkpoints["plate"]), "--input", str(test_file), "--trajectories", "1,0",
         "--schedule", "every:2", "--output", str(out)])
    back = read_predictions(out)
    model = load_simulator(checkpoints["plate"], map_location="cpu")
    batch = TrajectoryBatch.from_trajectories([trajs["test"][1], trajs["test"][0]])
    direct = [x[0].numpy() for x in split_trajectories(model.rollout(batch, "every:2"), batch)]
    assert len(back.positions) == 2 and all(np.array_equal(a, b) for a, b in zip(back.positions, direct))
    assert back.input_indices == [1, 0] and back.input_file == str(test_file.resolve()) and back.scene == "plate"
    assert (back.model_class, back.schedule, back.checkpoint) == ("GGNS", "every:2", str(checkpoints["plate"]))
    assert back.checkpoint_sha256 == sha256(checkpoints["plate"])
    assert all(np.array_equal(a.positions, trajs["test"][i].positions) for a, i in zip(back.inputs, (1, 0)))


def test_own_arrays_to_a_rollout_without_ground_truth(checkpoints, trajs, tmp_path):
    """The documented path: arrays -> split file -> `rollout`; with the plate's truly fixed nodes the
    rollout is the one of the generated trajectory, and the stored input says it has no ground truth."""
    traj = trajs["test"][0]
    with SplitWriter(tmp_path / "own.h5", scene="own", split="test", dim=2, generator_config={}) as writer:
        writer.append(trajectory_from_arrays(**arrays(traj)))
    run(["rollout", "--checkpoint", str(checkpoints["plate"]), "--input", str(tmp_path / "own.h5"),
         "--output", str(tmp_path / "preds.h5")])
    back = read_predictions(tmp_path / "preds.h5")
    model = load_simulator(checkpoints["plate"], map_location="cpu")
    direct = model.rollout(TrajectoryBatch.from_trajectories([traj]), "every:1").numpy()
    assert np.array_equal(back.positions[0], direct)
    assert not back.inputs[0].has_ground_truth and back.schedule == "every:1"


@pytest.fixture(scope="module")
def other_files(tiny_data_dir, trajs, tmp_path_factory):
    """A 2D split file of the tissue scene (another task than the plate checkpoint's), a predictions
    file and a text file, as wrong inputs."""
    out = tmp_path_factory.mktemp("other_files")
    with SplitWriter(out / "tissue2d.h5", scene="tissue", split="test", dim=2, generator_config={}) as writer:
        writer.append(trajs["test"][0])
    traj = trajs["test"][0]
    write_predictions(out / "preds.h5", Predictions(positions=[traj.positions.astype(np.float32)], inputs=[traj],
                                                    model_class="GGNS", schedule="never"))
    (out / "notes.h5").write_text("not HDF5")
    return out


REFUSALS = {  # name: (a `checkpoints` key, a missing .ckpt or a pretrained name; input: "test" or a file of
    # other_files; expected message part)
    "3D model on 2D data": ("tissue", "test", "the GGNS model is 3D, the data are 2D"),
    "model of another task": ("plate", "tissue2d.h5", "trained for the plate task, the data are of the tissue scene"),
    "missing checkpoint": ("missing.ckpt", "test", "missing.ckpt"),
    "unknown pretrained name": ("plate/none", "test", "no pretrained simulator 'plate/none'"),
    "missing input": ("plate", "missing.h5", "missing.h5: dataset file not found"),
    "predictions file as input": ("plate", "preds.h5",
                                  "not a ggns-trajectories file (format attribute is 'ggns-predictions')"),
    "not HDF5": ("plate", "notes.h5", "not a readable HDF5 file"),
    "trajectory index": ("plate", "test", "--trajectories [5]"),
    "schedule": ("plate", "test", "unknown point-cloud schedule 'often'"),
}


@pytest.mark.parametrize("case", sorted(REFUSALS))
def test_rollout_refuses_bad_input_with_one_line(case, checkpoints, other_files, tiny_data_dir, tmp_path, capsys):
    checkpoint, data, message = REFUSALS[case]
    checkpoint = str(checkpoints[checkpoint] if checkpoint in checkpoints else
                     tmp_path / checkpoint if checkpoint.endswith(".ckpt") else checkpoint)
    data = split_path(tiny_data_dir, "test") if data == "test" else other_files / data
    extra = {"trajectory index": ["--trajectories", "0,5"], "schedule": ["--schedule", "often"]}.get(case, [])
    with pytest.raises(SystemExit) as exit_info:
        run(["rollout", "--checkpoint", checkpoint, "--input", str(data), "--output", str(tmp_path / "p.h5"), *extra])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and message in err and err.startswith("error: ") and err.count("\n") == 1
    assert not (tmp_path / "p.h5").exists()


def test_rollout_never_overwrites_silently(checkpoints, tiny_data_dir, tmp_path, capsys):
    out = tmp_path / "p.h5"
    out.write_bytes(b"keep")
    args = ["rollout", "--checkpoint", str(checkpoints["plate"]), "--input", str(split_path(tiny_data_dir, "test")),
            "--output", str(out), "--trajectories", "0"]
    with pytest.raises(SystemExit):
        run(args)
    assert "p.h5: already exists (--overwrite replaces it)" in capsys.readouterr().err and out.read_bytes() == b"keep"
    run([*args, "--overwrite"])
    assert len(read_predictions(out).positions) == 1

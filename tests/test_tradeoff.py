"""The speed/accuracy trade benchmark (ggns.bench.tradeoff) on the plate_tiny preset and a tiny tissue preset."""
from __future__ import annotations

import csv
import math

import pytest
import pytorch_lightning as pl
import torch

from ggns.config import load_config
from ggns.data.module import SimulationDataModule

from ggns.bench.tradeoff import (COLUMNS, model_points, pareto_mask, pareto_plot,
                                       reference_substeps_for, simulator_points, tradeoff_csv)
from ggns.models.simulators import GGNS, MGN
from ggns.models.loading import load_simulator


@pytest.fixture(scope="module")
def sim_rows():
    return simulator_points(load_config("plate_tiny"), trajectories=1, coarsen=(1, 2, 5))


@pytest.fixture(scope="module")
def checkpoints(tiny_data_dir, tmp_path_factory):
    """Tiny MGN and GGNS checkpoints: one training step each (normalizers fitted, saved with the weights)."""
    root = tmp_path_factory.mktemp("ckpt")
    paths = {}
    for name, cls in (("mgn", MGN), ("ggns", GGNS)):
        torch.manual_seed(0)
        model = cls(latent=8, blocks=1, statistics_batches=1)
        data = SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=4, generate_missing=False)
        trainer = pl.Trainer(max_epochs=1, limit_train_batches=1, limit_val_batches=0, logger=False,
                             enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                             default_root_dir=root, accelerator="cpu")
        trainer.fit(model, data)
        paths[name] = root / f"{name}.ckpt"
        trainer.save_checkpoint(paths[name])
    return paths


def test_reference_substeps():
    assert reference_substeps_for(1, (1, 2, 5)) == 10
    assert reference_substeps_for(10, (1, 2, 5)) == 10
    assert reference_substeps_for(4, (1, 3)) == 12


def test_simulator_points(sim_rows):
    assert [r["setting"] for r in sim_rows] == ["substeps=10 (coarsen 1x)", "substeps=5 (coarsen 2x)",
                                                 "substeps=2 (coarsen 5x)"]
    assert sim_rows[0]["rollout_mse"] == 0.0  # the reference itself
    for row in sim_rows[1:]:
        assert math.isfinite(row["rollout_mse"]) and row["rollout_mse"] > 0
    assert sim_rows[2]["rollout_mse"] > sim_rows[1]["rollout_mse"]  # coarser steps, larger error
    for row in sim_rows:
        assert row["ms_per_trajectory_step"] > 0 and row["nodes"] == 81 and row["steps"] == 7


def test_simulator_mesh_resolution_and_errors():
    rows = simulator_points(load_config("plate_tiny", ["scene.num_steps=3"]), trajectories=1, coarsen=(2, 4),
                            grid_nodes=5)
    assert [r["nodes"] for r in rows] == [25, 25] and all(r["rollout_mse"] > 0 for r in rows)  # reference 4 substeps, untimed
    with pytest.raises(ValueError, match="divisible"):
        simulator_points(load_config("plate_tiny"), trajectories=1, coarsen=(1, 3), reference_substeps=4)


def test_checkpoint_class_is_detected(checkpoints, tmp_path):
    assert type(load_simulator(checkpoints["mgn"])) is MGN
    assert type(load_simulator(checkpoints["ggns"])) is GGNS
    # a checkpoint without the stored class (older files): the class whose parameters load strictly
    for name, cls in (("mgn", MGN), ("ggns", GGNS)):
        ckpt = torch.load(checkpoints[name], weights_only=False)
        assert ckpt.pop("simulator_class") == cls.__name__
        torch.save(ckpt, tmp_path / f"{name}.ckpt")
        assert type(load_simulator(tmp_path / f"{name}.ckpt")) is cls
    torch.save({"state_dict": {}}, tmp_path / "other.ckpt")
    with pytest.raises(ValueError, match="not a Lightning checkpoint"):
        load_simulator(tmp_path / "other.ckpt")


def test_model_points(checkpoints, tiny_data_dir):
    rows = model_points(checkpoints, "plate_tiny", ("every:1", "never"), trajectories=2, batch=3, repeats=1,
                        devices=["cpu"], data_dir=str(tiny_data_dir))
    assert [(r["name"], r["setting"]) for r in rows] == [("mgn", "never"), ("ggns", "every:1"), ("ggns", "never")]
    sizes = {r["name"]: (r["model_class"], r["latent"], r["blocks"], r["parameters"]) for r in rows}
    for name, path in checkpoints.items():  # model size, an axis of the trade-off
        model = load_simulator(path)
        assert sizes[name] == (type(model).__name__, model.hparams.latent, model.hparams.blocks,
                               sum(p.numel() for p in model.parameters()))
    for row in rows:
        assert row["ms_per_step_1"] > 0 and row["ms_per_step_batched"] > 0
        assert row["ms_per_trajectory_step"] == pytest.approx(row["ms_per_step_batched"] / 3)
        assert math.isfinite(row["rollout_mse"]) and row["rollout_mse"] > 0
        assert row["trajectories"] == 2 and row["steps"] == 7 and row["device"] == "cpu"


def test_pareto_csv_and_plot(sim_rows, tmp_path):
    rows = sim_rows + [
        {"kind": "model", "name": "m", "setting": "never", "device": "cpu", "ms_per_trajectory_step": 1e-3, "rollout_mse": 1.0},
        {"kind": "model", "name": "m", "setting": "slow", "device": "cpu", "ms_per_trajectory_step": 1e6, "rollout_mse": 2.0},
    ]
    front = pareto_mask(rows)
    assert front[0] and front[-2] and not front[-1]  # zero-error reference and fastest model; the dominated one not
    path = tradeoff_csv(rows, tmp_path / "t.csv")
    with open(path) as f:
        read = list(csv.DictReader(f))
    assert tuple(read[0]) == COLUMNS and len(read) == len(rows)
    assert [r["pareto"] for r in read] == [str(x) for x in front]
    png = pareto_plot(rows, tmp_path / "t.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_tradeoff_at_two_mesh_resolutions(checkpoints, tiny_data_dir, tmp_path):
    """The simulator and the models at the preset's resolution and at a finer one, whose test
    trajectories (with point clouds) are generated once beside the dataset."""
    from ggns.config import load_config
    from ggns.bench.tradeoff import tradeoff

    preset = int(load_config("plate_tiny")["scene"]["grid_nodes"])
    finer = preset + 2
    rows = tradeoff("plate_tiny", checkpoints, trajectories=1, coarsen=(1, 2), output_dir=tmp_path / "out",
                    schedules=("every:1", "never"), batch=2, repeats=1, grid_nodes=[preset, finer],
                    data_dir=str(tiny_data_dir))
    nodes = {(r["kind"], r["name"], r["setting"], r["nodes"]) for r in rows}
    for n in (preset, finer):
        assert ("model", "ggns", "every:1", n * n) in nodes and ("model", "mgn", "never", n * n) in nodes
        assert sum(1 for r in rows if r["kind"] == "simulator" and r["nodes"] == n * n) == 2
    finer_rows = [r for r in rows if r["kind"] == "model" and r["nodes"] == finer * finer]
    assert all(f"_grid{finer}" in r["reference"] and "trained at" in r["reference"] for r in finer_rows)
    assert all(math.isfinite(r["rollout_mse"]) and r["ms_per_step_1"] > 0 for r in rows)
    assert (tmp_path / "out" / "tradeoff.csv").is_file() and (tmp_path / "out" / "tradeoff.png").is_file()


# ---- the 3D tissue scene: mesh resolution levels and Newton tolerances --------------------------------

def test_tissue_resolution_levels():
    from ggns.scenes import plate, tissue

    scene = load_config("tissue_tiny")["scene"]
    assert tissue.resolution(scene) == 10 and tissue.with_resolution(scene, 10) == scene  # the preset maps to itself
    assert tissue.with_resolution(scene, 7)["block"]["nodes"] == [7, 6, 3]
    assert tissue.with_resolution(scene, 13)["block"]["nodes"] == [13, 12, 5]
    assert tissue.with_resolution(scene, 3)["block"]["nodes"][2] == 2  # at least 2 node layers along z
    assert scene["block"]["nodes"] == [10, 9, 4]  # a copy: the preset is untouched
    coarse = tissue.with_resolution(scene, 7)
    rest = tissue.tissue_mesh(coarse)[0]
    assert len(tissue.grasped_patch(coarse, rest, int(tissue.grasp_candidates(coarse, rest)[0]))) > 1  # never a point load
    plate_scene = load_config("plate_tiny")["scene"]
    assert plate.with_resolution(plate_scene, 5)["grid_nodes"] == 5 and plate.resolution(plate_scene) == 9


def test_a_scene_without_resolution_levels_is_named(monkeypatch):
    from ggns.bench.tradeoff import resolution_module
    from ggns.scenes import tissue

    monkeypatch.delattr(tissue, "with_resolution")
    with pytest.raises(ValueError, match="scene 'tissue' has no mesh resolution levels.*with_resolution"):
        resolution_module("tissue")


def test_tissue_tradeoff_at_two_resolutions(tmp_path):
    """The 3D trade on a tiny tissue preset (T = 6): simulator rows at the preset's resolution and a
    coarser one (time steps and a Newton tolerance), a shipped tissue model's rows at both (the
    coarser level's test trajectories, with point clouds, generated beside the data), and the CSV."""
    from ggns.bench.tradeoff import tradeoff
    from ggns.config import CONF_DIR
    from ggns.data.generate import generate

    preset = tmp_path / "tissue_tiny6.yaml"
    preset.write_text(f"base: {CONF_DIR / 'data' / 'tissue_tiny.yaml'}\nscene:\n  num_steps: 6\n"
                      f"splits: {{train: 1, val: 1, test: 1}}\noutput: {tmp_path / 'data'}\n")
    generate(load_config(preset), ["test"], progress=False)  # the models' test split at the preset's level
    rows = tradeoff(str(preset), {"mgn": "tissue/mgn"}, trajectories=1, coarsen=(1, 2), output_dir=tmp_path / "out",
                    schedules=("never",), batch=2, repeats=1, resolution=[10, 5], newton_tolerances=(1e-4,),
                    threads=1)  # 2 threads on a busy 2-core machine: index_add_ 100x slower
    with open(tmp_path / "out" / "tradeoff.csv") as f:
        read = list(csv.DictReader(f))
    assert tuple(read[0]) == COLUMNS and len(read) == len(rows)
    sim = [r for r in read if r["kind"] == "simulator"]
    assert {(r["resolution"], r["nodes"]) for r in sim} == {("10", "360"), ("5", "50")}
    for level in ("10", "5"):
        mine = [r for r in sim if r["resolution"] == level]
        assert [(r["axis"], r["substeps"]) for r in mine] == [("time step", "2"), ("time step", "1"),
                                                              ("newton tolerance", "1")]
        assert float(mine[0]["rollout_mse"]) == 0.0 and float(mine[1]["rollout_mse"]) > 0
        assert mine[2]["setting"] == "newton_tolerance=0.0001 (substeps=1)" and float(mine[2]["newton_tolerance"]) == 1e-4
        assert 0 <= float(mine[2]["mse_vs_preset_tolerance"]) < float(mine[1]["rollout_mse"])
        assert float(mine[2]["newton_iterations"]) <= float(mine[1]["newton_iterations"])
    models = [r for r in read if r["kind"] == "model"]
    assert [(r["name"], r["setting"], r["resolution"], r["nodes"], r["device"]) for r in models] == [
        ("mgn", "never", "10", "360", "cpu (1 thread)"), ("mgn", "never", "5", "50", "cpu (1 thread)")]
    assert all(math.isfinite(float(r["rollout_mse"])) and float(r["ms_per_step_1"]) > 0 for r in models)
    assert "_grid5" in models[1]["reference"] and "trained at resolution 10" in models[1]["reference"]
    assert (tmp_path / "out" / "tradeoff.png").is_file()


def test_devices_choose_where_the_models_roll_out(checkpoints, tiny_data_dir, tmp_path):
    """`--devices cpu` gives CPU rows only; `--devices cuda` without a GPU is refused before any work,
    naming CUDA (tests/test_cuda.py covers the GPU itself)."""
    from ggns.cli.bench import bench_tradeoff

    rows = bench_tradeoff("plate_tiny", {"ggns": str(checkpoints["ggns"])}, trajectories=1, schedules=["never"],
                          rollout_trajectories=2, repeats=1, output_dir=str(tmp_path / "out"),
                          data_dir=str(tiny_data_dir), simulator=False, devices=["cpu"])
    assert len(rows) == 1 and rows[0]["device"].startswith("cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            bench_tradeoff("plate_tiny", {"ggns": str(checkpoints["ggns"])}, output_dir=str(tmp_path / "gpu"),
                           data_dir=str(tiny_data_dir), simulator=False, devices=["cuda"])
        assert not (tmp_path / "gpu").exists()

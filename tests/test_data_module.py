"""The SimulationDataModule (ggns.data.module) on plate_tiny: training windows, loaders, and the
errors for missing files and mismatched models. Runs single-threaded (conftest `single_thread`)."""
from __future__ import annotations

import types

import pytest
import torch

from ggns.batch import TrajectoryBatch
from ggns.data.module import SimulationDataModule, WindowDataset
from ggns.models.simulators import GGNS, GGNSLSTM
from conftest import SMALL, T, make, quiet_trainer

pytestmark = pytest.mark.usefixtures("single_thread")


# ---- 9. bad input ------------------------------------------------------------------------------------------
def test_bad_input_errors(tiny_data_dir, tmp_path):
    with pytest.raises(ValueError, match="point edges"):
        GGNS(connectivity="plate_mgn", point_probability=0.5)
    GGNS(connectivity="plate_mgn", point_probability=0.0, **SMALL)  # fine without points

    missing = tmp_path / "nowhere"
    data = SimulationDataModule("plate_tiny", data_dir=str(missing), generate_missing=False)
    data.prepare_data()
    assert not missing.exists()
    with pytest.raises(FileNotFoundError) as error:
        data.train_dataloader()
    message = str(error.value)
    assert str(missing / "train.h5") in message and "python -m ggns generate --config plate_tiny" in message
    assert f"--output {missing}" in message

    model = make(GGNS, dim=3, latent=8, blocks=1)
    data = SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=4, generate_missing=False)
    with pytest.raises(ValueError, match=r"dim=3 .* is 2D"):
        quiet_trainer(tmp_path).fit(model, data)


# ---- 10. datamodule windows ------------------------------------------------------------------------------
@pytest.mark.parametrize("window", [1, 3, 7])
def test_window_dataset_slices_trajectories(window, trajs):
    source = trajs["train"]
    ds = WindowDataset(source, window)
    assert len(ds) == len(source) * (T - window)
    for i in range(len(ds)):
        traj, start = divmod(i, T - window)
        sample, original = ds[i], source[traj]
        assert sample.num_steps == window + 1
        assert torch.equal(torch.as_tensor(sample.positions), torch.as_tensor(original.positions[start:start + window + 1]))
        assert torch.equal(torch.as_tensor(sample.collider_positions),
                           torch.as_tensor(original.collider_positions[start:start + window + 1]))
        for s in range(window + 1):
            assert torch.equal(torch.as_tensor(sample.point_cloud(s)), torch.as_tensor(original.point_cloud(start + s)))
    with pytest.raises(ValueError, match="fewer than window"):
        WindowDataset(source, T)


def test_datamodule_loaders(tiny_data_dir, trajs):
    data = SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=4, train_window=3,
                                eval_batch_size=2, max_eval_trajectories=1, generate_missing=False)
    batches = list(data.train_dataloader())
    assert all(isinstance(b, TrajectoryBatch) and b.num_steps == 4 for b in batches)
    assert sum(b.num_graphs for b in batches) == 3 * (T - 3) and batches[0].num_graphs == 4
    assert sum(b.num_graphs for b in data.val_dataloader()) == 1 * (T - 3)  # val cut to 1 trajectory
    (test,) = list(data.test_dataloader())
    assert test.num_graphs == 1 and test.num_steps == T
    assert torch.equal(test.positions, torch.as_tensor(trajs["test"][0].positions, dtype=torch.float32))
    assert data.dim == 2
    # train_window None: the attached model's window (the LSTM's), else 1
    auto = SimulationDataModule("plate_tiny", data_dir=str(tiny_data_dir), batch_size=64, generate_missing=False)
    assert next(iter(auto.train_dataloader())).num_steps == 2
    auto.trainer = types.SimpleNamespace(lightning_module=make(GGNSLSTM, window=4))
    (batch,) = list(auto.train_dataloader())
    assert batch.num_steps == 5 and batch.num_graphs == 3 * (T - 4)



"""Splits read in pieces (`ggns.data.stream`, the data module's `memory_budget`), on real HDF5
files of the plate_tiny scene (8 training trajectories of 8 states, made once per module, as a whole
split file and as 3 shard files): the streamed windows are the in-memory ones, their order is
reproducible and resumable, each process reads only its share, the cache stays within its budget,
and broken or foreign files are refused by name. Runs single-threaded (conftest `single_thread`)."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import pytorch_lightning as pl
import torch

from ggns.config import CONF_DIR, load_config
from ggns.data.generate import generate
from ggns.data.module import SimulationDataModule, WindowDataset
from ggns.data.schema import DatasetError
from ggns.data.stream import METADATA_CACHE, BlockSampler, StreamedSplit, StreamingWindowDataset, parse_bytes
from conftest import T, make, quiet_trainer

pytestmark = pytest.mark.usefixtures("single_thread")
COUNT = 8  # training trajectories
WINDOWS = COUNT * (T - 1)  # windows of one transition


def _preset(directory: Path, output: Path, seed: int = 0) -> Path:
    path = directory / f"{output.name}_seed{seed}.yaml"
    path.write_text(f"base: {CONF_DIR / 'data' / 'plate_tiny.yaml'}\noutput: {output}\nseed: {seed}\n"
                    f"splits: {{train: {COUNT}, val: 2, test: 2}}\n")
    return path


@pytest.fixture(scope="module")
def stream_data(tmp_path_factory) -> dict:
    """{"whole": preset of a directory with train/val/test.h5, "shards": preset of a directory whose train
    split is 3 shard files (val and test whole)}."""
    root = tmp_path_factory.mktemp("stream")
    whole, sharded = root / "whole", root / "sharded"
    threads = torch.get_num_threads()
    try:
        generate(load_config(_preset(root, whole)), progress=False)
        for i in range(3):
            generate(load_config(_preset(root, sharded)), ["train"], progress=False, shard=(i, 3))
    finally:
        torch.set_num_threads(threads)
    for split in ("val", "test"):
        shutil.copy(whole / f"{split}.h5", sharded / f"{split}.h5")
    return {"whole": _preset(root, whole), "shards": _preset(root, sharded), "root": root}


def _module(preset: Path, budget=1, **kwargs) -> SimulationDataModule:
    """A data module that streams every split (a budget of 1 byte) unless budget is None."""
    return SimulationDataModule(str(preset), batch_size=8, train_window=1, generate_missing=False,
                                memory_budget=budget, seed=3, **kwargs)


def _windows(batches) -> list[bytes]:
    """Each window of each batch as the bytes of its positions [2, N, d]."""
    return [b.positions[:, b.mesh_batch == g].numpy().tobytes() for b in batches for g in range(b.num_graphs)]


def test_parse_bytes():
    assert parse_bytes("4MB") == 4_000_000 and parse_bytes("2 GiB") == 2 * 2**30 and parse_bytes(512) == 512
    assert parse_bytes("1.5kb") == 1500
    for bad in ("lots", "-1MB", 0, "4 MBs"):
        with pytest.raises(ValueError, match="memory size"):
            parse_bytes(bad)


@pytest.mark.parametrize("layout", ["whole", "shards"])
def test_streamed_windows_are_the_in_memory_ones(stream_data, layout):
    """Window i is the in-memory window i; an epoch of the block order holds every window once; loaders with
    2 workers give the in-memory epoch's windows (as a multiset) in the same order for the same seed twice."""
    streamed, memory = _module(stream_data[layout]), _module(stream_data[layout], budget=None)
    assert streamed.streams("train") and not memory.streams("train")
    split = streamed.trajectories("train")
    assert isinstance(split, StreamedSplit) and isinstance(memory.trajectories("train"), list)
    windows = StreamingWindowDataset(split, 1, cache_bytes=0)
    in_memory = WindowDataset(memory.trajectories("train"), 1)
    assert len(windows) == len(in_memory) == WINDOWS
    for i in range(len(windows)):
        assert (windows[i].positions == in_memory[i].positions).all() and windows[i].seed == in_memory[i].seed
    epoch = list(BlockSampler(windows, seed=3, block_bytes=3 * windows.nbytes[0]))
    assert sorted(epoch) == list(range(WINDOWS))

    expected = sorted(_windows(memory.train_dataloader()))
    runs = [_windows(_module(stream_data[layout], num_workers=2).train_dataloader()) for _ in range(2)]
    assert sorted(runs[0]) == expected
    assert runs[0] == runs[1]
    other_seed = _module(stream_data[layout], num_workers=2)
    other_seed.seed = 4
    assert _windows(other_seed.train_dataloader()) != runs[0]


def test_a_resumed_block_order_continues_where_the_uninterrupted_one_would_be(stream_data):
    windows = StreamingWindowDataset(_module(stream_data["whole"]).trajectories("train"), 1, cache_bytes=0)
    block = 3 * windows.nbytes[0]
    for world in (1, 2):
        for rank in range(world):
            whole = BlockSampler(windows, seed=3, block_bytes=block, num_replicas=world, rank=rank)
            epochs = []
            for epoch in range(3):
                whole.set_epoch(epoch)
                epochs.append(list(whole))
            assert epochs[0] != epochs[1] and len(epochs[0]) == len(epochs[1]) == WINDOWS // world
            batches = -(-len(whole) // 5)  # batches of 5
            for done in (0, 3, batches, batches + 2, 2 * batches + 1):
                resumed = BlockSampler(windows, seed=3, block_bytes=block, num_replicas=world, rank=rank)
                resumed.resume(done, batch_size=5, batches_per_epoch=batches)
                epoch, within = divmod(done, batches)
                assert list(resumed) == epochs[epoch][within * 5:], (world, rank, done)
                assert list(resumed) == epochs[epoch]  # only the first iteration after a resume is cut


def test_the_cache_stays_within_its_budget(stream_data):
    """A budget of 1.5 trajectories: one trajectory resident at a time, each read once per epoch (blocks of
    one trajectory); a budget of 3 of trajectory 0's size (point clouds differ in size): at most 3 resident,
    still one read each per epoch."""
    data = _module(stream_data["whole"])
    size = StreamingWindowDataset(data.trajectories("train"), 1, 0).nbytes[0]
    for budget, most in ((int(1.5 * size), {1}), (3 * size, {2, 3})):
        data = _module(stream_data["whole"], budget=budget)
        assert data.streams("train")
        loader = data.train_dataloader()
        dataset = loader.dataset
        for epoch in range(2):
            loader.sampler.set_epoch(epoch)
            assert sum(b.num_graphs for b in loader) == WINDOWS
            assert dataset.cache.reads == COUNT * (epoch + 1)
        assert dataset.cache.peak_count in most and dataset.cache.peak_bytes <= budget and len(dataset.cache) <= max(most)


def test_a_streamed_split_keeps_one_file_open_with_a_capped_metadata_cache(stream_data):
    """What a process keeps of the files does not grow with the split's length: opening the 3 shards reads
    their metadata and closes them; reads across the shards leave one file open at a time, whose HDF5
    metadata cache is capped at METADATA_CACHE (HDF5's own default allows 32 MiB)."""
    split = _module(stream_data["shards"]).trajectories("train")
    assert len(split.readers) == 3 and not any(r.is_open for r in split.readers)
    for i in range(COUNT):
        split[i]
        assert [r.is_open for r in split.readers] == [k == i % 3 for k in range(3)]
        config = split.readers[i % 3]._h5().id.get_mdc_config()
        assert config.max_size == METADATA_CACHE < 2**25
    assert split.info(5) == split.readers[2].info(1)  # trajectory 5 is shard 2's second
    assert split[3:6].info(2) == split.info(5) and len(split[3:6]) == 3


def test_two_ranks_read_only_their_share(stream_data):
    """world 2: each rank reads 4 of the 8 trajectories per epoch, never the other's, and both have the same
    number of windows; together they hold every window of the epoch once."""
    shares, indices = [], []
    for rank in range(2):
        data = _module(stream_data["shards"])
        windows = StreamingWindowDataset(data.trajectories("train"), 1, cache_bytes=2 * 10**6)
        sampler = BlockSampler(windows, seed=3, block_bytes=2 * windows.nbytes[0], num_replicas=2, rank=rank)
        mine = list(sampler)
        for i in mine:
            windows[i]
        shares.append({windows.locate(i)[0] for i in mine})
        indices.append(mine)
        assert windows.cache.reads == data.trajectories("train").reads == COUNT // 2 == len(shares[-1])
    assert not shares[0] & shares[1] and shares[0] | shares[1] == set(range(COUNT))
    assert len(indices[0]) == len(indices[1]) and sorted(indices[0] + indices[1]) == list(range(WINDOWS))


def test_dim_eval_batch_and_test_rollouts_read_only_what_they_use(stream_data):
    streamed, memory = _module(stream_data["whole"]), _module(stream_data["whole"], budget=None)
    assert streamed.dim == 2 and streamed.trajectories("train").reads == 0
    batch = streamed.eval_batch("val", 2, rank=1, world=2)
    assert streamed.trajectories("val").reads == 1 and batch.num_graphs == 1
    assert torch.equal(batch.positions, memory.eval_batch("val", 2, rank=1, world=2).positions)
    streamed.eval_batch_size = 1
    tests = list(streamed.test_dataloader())
    assert [b.num_steps for b in tests] == [T, T]
    for got, expected in zip(tests, memory.test_dataloader()):
        assert torch.equal(got.positions, expected.positions[:, expected.mesh_batch == 0])
    # val windows: in index order, one trajectory kept, each read once
    val = streamed.val_dataloader()
    assert sum(b.num_graphs for b in val) == 2 * (T - 1) and val.dataset.cache.reads == 2


def test_broken_missing_or_foreign_files_are_refused_by_name(stream_data, tmp_path):
    # a preset of another scene: refused by the streaming reader as by the in-memory one
    other = tmp_path / "other.yaml"
    other.write_text(f"base: {stream_data['whole']}\nscene:\n  num_steps: 9\n")
    with pytest.raises(DatasetError, match="train.h5: generated with another configuration.*scene.num_steps"):
        _module(other).trajectories("train")
    # another seed: shards whose trajectories are not the preset's
    sharded = Path(load_config(stream_data["shards"])["output"])
    copy = tmp_path / "copy"
    shutil.copytree(sharded, copy)
    reseeded = _preset(tmp_path, copy, seed=1)
    with pytest.raises(DatasetError, match="train.shard-0-of-3.h5: trajectory 0 has seed"):
        _module(reseeded).trajectories("train")
    # a truncated shard, then a missing one
    shard = copy / "train.shard-1-of-3.h5"
    shard.write_bytes(shard.read_bytes()[:2000])
    preset = _preset(tmp_path, copy)
    with pytest.raises(DatasetError, match=r"train.shard-1-of-3.h5: not a readable HDF5 file \(truncated"):
        _module(preset).trajectories("train")
    shard.unlink()
    with pytest.raises(DatasetError, match=r"shards \[1\] of 3 are missing \(train.shard-1-of-3.h5"):
        _module(preset).train_dataloader()
    with pytest.raises(ValueError, match="memory size"):
        _module(preset, budget="a lot")


class _Crash(pl.Callback):
    """Raises at the start of training step `step`, as a killed process stops (what it saved stays)."""

    def __init__(self, step: int):
        self.step = step

    def on_train_batch_start(self, trainer, *_):
        if trainer.global_step == self.step:
            raise RuntimeError("crash")


def _streamed_fit(preset: Path, root: Path, budget: int, crash: int | None = None, resume: Path | None = None):
    """2 epochs of 7 batches of a tiny GGNS through the streaming reader, last.ckpt every 3 steps; returns
    the model."""
    from pytorch_lightning.callbacks import ModelCheckpoint

    from ggns.callbacks import RandomState
    from ggns.models.simulators import GGNS

    pl.seed_everything(0, verbose=False)
    model = make(GGNS, latent=8, blocks=1, statistics_batches=2)
    callbacks = [ModelCheckpoint(dirpath=root, filename="last", every_n_train_steps=3, enable_version_counter=False),
                 RandomState()]  # the noise draws resume too
    trainer = quiet_trainer(root, max_epochs=2, limit_train_batches=1.0, enable_checkpointing=True,
                            callbacks=callbacks + ([_Crash(crash)] if crash is not None else []))
    trainer.fit(model, _module(preset, budget=budget), ckpt_path=resume)
    assert trainer.global_step == 2 * WINDOWS // 8
    return model


def test_a_streamed_fit_stopped_mid_epoch_resumes_to_the_uninterrupted_weights(stream_data, tmp_path):
    """Blocks of 2 trajectories; stopped at step 11 (epoch 1), resumed from the step-9 checkpoint: the resumed
    fit trains on the windows (and the noise draws) the uninterrupted one did, so the weights are equal."""
    preset = stream_data["whole"]
    budget = 2 * max(StreamingWindowDataset(_module(preset).trajectories("train"), 1, 0).nbytes)
    whole = _streamed_fit(preset, tmp_path / "whole", budget)
    with pytest.raises(RuntimeError, match="crash"):
        _streamed_fit(preset, tmp_path / "run", budget, crash=11)
    last = tmp_path / "run" / "last.ckpt"
    assert torch.load(last, weights_only=True)["global_step"] == 9
    resumed = _streamed_fit(preset, tmp_path / "run", budget, resume=last)
    for name, value in whole.state_dict().items():
        torch.testing.assert_close(resumed.state_dict()[name], value, rtol=1e-6, atol=1e-9, msg=name)

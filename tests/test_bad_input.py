"""The bad-input matrix (docs/robustness.md): every entry point that reads a dataset, given
each kind of bad split file, ends with one line `error: ...` that names the problem and exit status 2
(no traceback), and the files already written stay as they were; valid but unusual data (an empty
point cloud at a step, a point cloud far from the mesh) roll out without error. Real HDF5 files made
by the real generator (plate_tiny), damaged with h5py."""
from __future__ import annotations

import dataclasses
import shutil
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from ggns.__main__ import main
from ggns.batch import TrajectoryBatch
from ggns.config import CONF_DIR
from ggns.data.generate import split_path
from ggns.data.schema import DatasetError, read_trajectories
from ggns.models.simulators import GGNS

from conftest import TINY12, save_untrained

SPLITS = ("train", "val", "test")


def run(args: list[str]) -> None:
    """`python -m ggns ARGS` in this process."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sys, "argv", ["ggns"])
        main(args)


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _edit(path: Path, change) -> None:
    with h5py.File(path, "r+") as f:
        change(f, f["trajectories"]["000000"])


def _nan(f, g):
    positions = g["mesh/positions"][()]
    positions[3, 0, 0] = np.nan
    g["mesh/positions"][...] = positions


def _edge_beyond_nodes(f, g):
    edges = g["mesh/edges"][()]
    edges[-1, 1] = 10_000
    g["mesh/edges"][...] = edges


# bad split file -> (how it is made from a valid one, the words the error must contain, or alternatives)
BAD_FILES = {
    "missing file": (lambda p: p.unlink(), ("not found", "split file missing")),
    "truncated HDF5": (_truncate, "not a readable HDF5 file (truncated or corrupt)"),
    "not HDF5": (lambda p: p.write_text("mesh,positions\n0,1\n"), "not a readable HDF5 file"),
    "wrong schema version": (lambda p: _edit(p, lambda f, g: f.attrs.__setitem__("schema_version", 99)),
                             "schema version 99"),
    "writer interrupted": (lambda p: _edit(p, lambda f, g: f.attrs.__setitem__("complete", False)),
                           "incomplete file"),
    "NaN positions": (lambda p: _edit(p, _nan), "contains NaN or inf"),
    "material out of range": (lambda p: _edit(p, lambda f, g: g.attrs.__setitem__("poissons_ratio", 0.7)),
                              "Poisson's ratio must satisfy -1 < nu < 0.5"),
    "topology (edge beyond the nodes)": (lambda p: _edit(p, _edge_beyond_nodes), "indices must lie in"),
}


@pytest.fixture(scope="module")
def checkpoint(cli_data, tmp_path_factory) -> Path:
    """A GGNS (latent 8, 1 block) fitted for one step on plate_tiny12 through the CLI: its last.ckpt."""
    logs = tmp_path_factory.mktemp("bad_input_fit")
    run(["fit", "--config", str(CONF_DIR / "plate" / "ggns.yaml"), "--data.dataset", str(cli_data / TINY12),
         "--data.data_dir", str(cli_data), "--data.generate_missing", "false", "--data.batch_size", "8",
         "--model.init_args.latent", "8", "--model.init_args.blocks", "1", "--trainer.max_steps", "1",
         "--trainer.limit_val_batches", "0", "--trainer.logger.init_args.save_dir", str(logs),
         "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false"])
    (last,) = logs.rglob("last.ckpt")
    return last


def _bad_copy(cli_data: Path, where: Path, bad: str) -> Path:
    """plate_tiny12's splits copied into `where`, each damaged as `bad` says, and a preset file naming them."""
    where.mkdir()
    for split in SPLITS:
        path = split_path(where, split)
        shutil.copy(split_path(cli_data, split), path)
        BAD_FILES[bad][0](path)
    preset = where / "preset.yaml"
    preset.write_text(f"base: {cli_data / TINY12}\noutput: {where}\n")
    return preset


def _entry_points(checkpoint: Path, data: Path, preset: Path, out: Path) -> dict[str, list[str]]:
    model = ["--model.init_args.latent", "8", "--model.init_args.blocks", "1"]
    lightning = ["--config", str(CONF_DIR / "plate" / "ggns.yaml"), "--data.dataset", str(preset), *model,
                 "--trainer.logger", "false", "--trainer.enable_progress_bar", "false"]
    return {
        "fit": ["fit", *lightning, "--trainer.max_steps", "1", "--trainer.default_root_dir", str(out)],
        "test": ["test", *lightning, "--ckpt_path", str(checkpoint)],
        "predict": ["predict", *lightning, "--ckpt_path", str(checkpoint)],
        "rollout": ["rollout", "--checkpoint", str(checkpoint), "--input", str(split_path(data, "test")),
                    "--output", str(out / "predictions.h5")],
        "export": ["export", "--checkpoint", str(checkpoint), "--dataset", str(preset), "--output", str(out / "export")],
        "diagnose": ["diagnose", "--checkpoint", str(checkpoint), "--dataset", str(preset), "--split", "test",
                     "--trajectories", "1"],
        "geometry": ["geometry", "--dataset", str(preset), "--split", "test", "--trajectories", "1"],
        "bench tradeoff": ["bench", "tradeoff", "--dataset", str(preset), "--no-simulator", "--checkpoint",
                           f"ggns={checkpoint}", "--trajectories", "1", "--rollout-trajectories", "1", "--repeats", "1",
                           "--output-dir", str(out / "tradeoff")],
    }


ENTRY_POINTS = ("fit", "test", "predict", "rollout", "export", "diagnose", "geometry", "bench tradeoff")
# these generate a preset's missing split files by design (the data module's generate_missing): a
# missing file is not an error for them
GENERATE_MISSING = {"fit", "test", "predict", "bench tradeoff"}
MATRIX = [(bad, entry) for bad in sorted(BAD_FILES) for entry in ENTRY_POINTS
          if not (bad == "missing file" and entry in GENERATE_MISSING)]


@pytest.mark.parametrize("bad, entry", MATRIX)
def test_every_entry_point_refuses_every_bad_file_with_one_line(bad, entry, checkpoint, cli_data, tmp_path, capsys):
    data = tmp_path / "data"
    preset = _bad_copy(cli_data, data, bad)
    out = tmp_path / "out"
    out.mkdir()
    (out / "kept.txt").write_text("written before")
    before = {p: p.read_bytes() for p in data.iterdir()}
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        run(_entry_points(checkpoint, data, preset, out)[entry])
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1] if err.strip() else ""
    assert exit_info.value.code == 2, err[-2000:]
    expected = BAD_FILES[bad][1]
    assert last.startswith("error: ") and any(words in last for words in (
        (expected,) if isinstance(expected, str) else expected)), err[-2000:]
    assert "Traceback" not in err
    assert {p: p.read_bytes() for p in data.iterdir()} == before  # the inputs are untouched
    assert sorted(p.name for p in out.iterdir()) == ["kept.txt"] and (out / "kept.txt").read_text() == "written before"


@pytest.mark.parametrize("bad", sorted(BAD_FILES))
def test_the_python_reader_raises_one_error_naming_the_problem(bad, cli_data, tmp_path):
    _bad_copy(cli_data, tmp_path / "data", bad)
    expected = FileNotFoundError if bad == "missing file" else DatasetError
    words = BAD_FILES[bad][1]
    with pytest.raises(expected) as error:
        read_trajectories(split_path(tmp_path / "data", "test"))
    assert any(w in str(error.value) for w in ((words,) if isinstance(words, str) else words))


def test_a_3d_checkpoint_on_2d_data_and_a_config_typo_are_refused(tiny_data_dir, tmp_path, capsys):
    tissue = save_untrained(GGNS(latent=8, blocks=1, dim=3, connectivity="tissue_reduced_graph"),
                            tmp_path / "tissue.ckpt")
    with pytest.raises(SystemExit) as exit_info:
        run(["export", "--checkpoint", str(tissue), "--dataset", "plate_tiny", "--data-dir", str(tiny_data_dir),
              "--output", str(tmp_path / "export")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "the GGNS model is 3D, the data are 2D" in err and "Traceback" not in err
    with pytest.raises(SystemExit) as exit_info:
        run(["fit", "--config", str(CONF_DIR / "plate" / "ggns.yaml"), "--model.init_args.latnet", "8"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "latnet" in err and "Traceback" not in err
    assert not (tmp_path / "export").exists()


def _with_step_points(traj, t: int, points: np.ndarray):
    """`traj` with the point cloud of step t replaced by `points`."""
    clouds = [traj.point_cloud(s) for s in range(traj.num_steps)]
    clouds[t] = points.astype(traj.points.dtype)
    offsets = np.concatenate([[0], np.cumsum([len(c) for c in clouds])]).astype(traj.point_offsets.dtype)
    return dataclasses.replace(traj, points=np.concatenate(clouds), point_offsets=offsets)


def test_an_empty_or_far_away_point_cloud_rolls_out_as_no_points_at_that_step(checkpoint, trajs):
    from ggns.pretrained import load_model

    model = load_model(str(checkpoint), map_location="cpu")
    traj = trajs["test"][0]
    empty = _with_step_points(traj, 2, np.zeros((0, traj.dim)))
    far = _with_step_points(traj, 2, traj.point_cloud(2) + 100.0)
    out = {name: model.rollout(TrajectoryBatch.from_trajectories([t]), "every:1")
           for name, t in (("empty", empty), ("far", far), ("as recorded", traj))}
    assert all(torch.isfinite(x).all() for x in out.values())
    # points with no mesh node within the radius send no message: the same prediction as no points
    torch.testing.assert_close(out["far"], out["empty"], rtol=0, atol=1e-6)
    assert not torch.allclose(out["empty"][3], out["as recorded"][3])  # step 2's points did matter


# sweep and bench learning run fit (and test) as subprocesses: the subprocess's own error line reaches
# the user as the command's one line, with the log that has the rest (each entry with one kind of bad file:
# the fit refuses every kind with its line, test_every_entry_point_refuses_every_bad_file_with_one_line)
@pytest.mark.parametrize("bad, entry", [("NaN positions", "sweep"), ("truncated HDF5", "bench learning")])
def test_sweep_and_bench_learning_pass_on_their_fits_error_line(bad, entry, cli_data, tmp_path, capsys):
    import yaml

    data = tmp_path / "data"
    preset = _bad_copy(cli_data, data, bad)
    before = {p: p.read_bytes() for p in data.iterdir()}
    overrides = {"data": {"dataset": str(preset), "generate_missing": False},
                 "model": {"init_args": {"latent": 8, "blocks": 1}},
                 "trainer": {"max_steps": 1, "enable_progress_bar": False}}
    config = str(CONF_DIR / "plate" / "mgn.yaml")
    if entry == "sweep":
        spec = {"output": str(tmp_path / "out"), "seeds": [0], "parallel": 1, "overrides": overrides,
                "models": {"mgn": {"config": config}}}
    else:
        spec = {"output": str(tmp_path / "out"), "minutes": 1, "val_every": 1, "seed": 0, "parallel": 1,
                "run": {"config": config, "overrides": overrides}, "variants": {"mgn": {}}}
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(spec))
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        run([*entry.split(), "--config", str(path)])
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert exit_info.value.code == 2 and "Traceback" not in err, err[-2000:]
    assert last.startswith("error: fit of ") and BAD_FILES[bad][1] in last and "; see " in last, last
    assert {p: p.read_bytes() for p in data.iterdir()} == before

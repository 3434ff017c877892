"""Importing the paper authors' pickles (ggns.data.reference, `python -m ggns import-reference`):
synthetic files in their layout (2D plate keys, 3D tissue / cavity keys) round-trip into split
files, a pickle that would run code is refused before it runs, bad input gets one clear error, and
imported data trains through the Lightning CLI."""
from __future__ import annotations

import json
import os
import pickle
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from ggns.__main__ import main
from ggns.config import CONF_DIR, load_config
from ggns.data.module import SimulationDataModule
from ggns.data.reference import ReferenceFormatError, UnsafePickleError, import_reference, load_pickle
from ggns.data.schema import SplitReader
from ggns.evaluation.observability import error_shares
from ggns.geometry import box_tet_mesh, boundary_facets, cell_edges, signed_volumes

T = 12  # states per trajectory: more than 10, so that validation's m+10 metric is defined


def plate_record(seed: int, nu: float = 0.49, steps: int = T) -> dict:
    """One trajectory in the authors' plate layout: a 4 x 4 node plate in [-0.8, 0.8] x [-1, 0.6]
    with its bottom row still, a filled circle (centre + 8 ring nodes) moving down, 0-5 points per step."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(-0.8, 0.8, 4), np.linspace(-1.0, 0.6, 4))
    rest = np.stack([x.ravel(), y.ravel()], axis=1)
    quads = [(j * 4 + i, j * 4 + i + 1, (j + 1) * 4 + i + 1, (j + 1) * 4 + i) for j in range(3) for i in range(3)]
    # half of them clockwise: the importer orients them
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, d, c))], dtype=np.int32)
    edges = cell_edges(triangles)
    edges = np.concatenate([edges, edges[:, ::-1]])  # directed, as the authors' code makes them
    sag = (rest[:, 1] + 1.0)[:, None] * np.array([0.02, -0.05])
    nodes = [rest + t / steps * sag * (1 + 0.1 * seed) for t in range(steps)]
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    circle = np.concatenate([[[0.0, 0.0]], 0.2 * np.stack([np.cos(angles), np.sin(angles)], axis=1)]) + [0.1, 0.85]
    ring = [(0, 1 + k, 1 + (k + 1) % 8) for k in range(8)]
    collider = [circle - [0.0, 0.02 * t] for t in range(steps)]
    clouds = [nodes[t][rng.choice(16, size=rng.integers(0, 6), replace=False)] + 0.01 for t in range(steps)]
    return {"nodes_grid": nodes, "edge_index_grid": edges, "nodes_collider": collider,
            "pcd_points": [c.astype(np.float32) for c in clouds], "pcd_colors": [np.ones((len(c), 3)) for c in clouds],
            "poisson_ratio": np.float64(nu), "triangles_grid": triangles, "triangles_collider": np.array(ring)}


def tissue_record(seed: int, nu: float = 0.0, gripper_triangles: bool = False) -> dict:
    """One trajectory in the authors' 3D layout: a 2 x 2 x 1 block of 18 nodes, bottom layer still,
    pulled up by a 1-node gripper (as the tissue) or a 4-node one with triangles (as the cavity)."""
    rest, tets = box_tet_mesh([-0.5, -0.5, -0.5], [0.5, 0.5, 0.0], [2, 2, 1])
    lift = (rest[:, 2] + 0.5)[:, None] * np.array([0.0, 0.01, 0.1])
    nodes = np.stack([rest + t / T * lift * (1 + 0.1 * seed) for t in range(T)])  # [T, N, 3] array, not a list
    edges = cell_edges(tets).T  # [2, E]
    record = {"tissue_mesh_positions": nodes, "tissue_mesh_edges": edges,
              "gripper_position": [np.array([0.0, 0.0, 0.1 + 0.01 * t]) for t in range(T)],  # [3] per step: one node
              "tissue_pcd_points": [n[n[:, 2] > -0.1] for n in nodes], "poisson_ratio": nu,
              "tissue_mesh_triangles": boundary_facets(tets)}
    if gripper_triangles:
        square = np.array([[-0.1, -0.1, 0.1], [0.1, -0.1, 0.1], [0.1, 0.1, 0.1], [-0.1, 0.1, 0.1]])
        record["gripper_position"] = [square + [0, 0, 0.01 * t] for t in range(T)]
        record["gripper_triangles"] = np.array([[0, 1, 2], [0, 2, 3]])
    return record


def write(path: Path, records) -> Path:
    with open(path, "wb") as f:
        pickle.dump(records, f)
    return path


def preset(name: str, **importer) -> dict:
    config = load_config(name)
    config["importer"].update(importer)
    return config


# ---- round trips -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("protocol", [2, 4, 5])
def test_plate_round_trip(tmp_path, protocol):
    records = [plate_record(0, nu=-0.9), plate_record(1, nu=0.49)]
    records[1]["edge_index_grid"] = records[1]["edge_index_grid"].T  # [2, E] is read too
    records[1]["nodes_collider"] = [np.c_[c, np.zeros(len(c))] for c in records[1]["nodes_collider"]]  # z = 0 dropped
    source = tmp_path / "deformable_plate_dataset_train.pkl"
    source.write_bytes(pickle.dumps(records, protocol=protocol))
    summary = import_reference(source, load_config("reference_plate"), "train", tmp_path / "out")
    assert summary["path"] == tmp_path / "out" / "train.h5" and summary["trajectories"] == 2
    assert summary["sizes"]["fixed"] == (4, 4) and summary["sizes"]["steps"] == (T, T)

    with SplitReader(summary["path"]) as split:
        assert (split.scene, split.split, split.dim, len(split)) == ("reference_plate", "train", 2, 2)
        source_info = split.generator_config["source"]
        assert source_info["file"] == source.name and len(source_info["sha256"]) == 64
        assert split.generator_config["importer"]["youngs_modulus"] == 5000.0
        for i, (traj, record) in enumerate(zip(split, records)):
            assert traj.seed == i and traj.youngs_modulus == 5000.0 and traj.poissons_ratio == record["poisson_ratio"]
            np.testing.assert_array_equal(traj.positions, np.stack(record["nodes_grid"]))
            np.testing.assert_array_equal(traj.rest_positions, record["nodes_grid"][0])
            np.testing.assert_array_equal(traj.collider_positions[:, :, :2],
                                          np.stack([c[:, :2] for c in record["nodes_collider"]]))
            assert traj.collider_positions.shape == (T, 9, 2)
            for t in range(T):
                np.testing.assert_array_equal(traj.point_cloud(t), record["pcd_points"][t])
            np.testing.assert_array_equal(traj.edges, cell_edges(record["triangles_grid"]))
            assert (signed_volumes(traj.rest_positions, traj.cells) > 0).all()
            assert {frozenset(c) for c in traj.cells} == {frozenset(c) for c in record["triangles_grid"]}
            np.testing.assert_array_equal(traj.fixed, traj.rest_positions[:, 1] == -1.0)  # the still bottom row
            # the collider outline: the ring's 8 segments in loop order, counter-clockwise
            faces = traj.collider_faces
            assert len(faces) == 8 and (faces[1:, 0] == faces[:-1, 1]).all() and faces[-1, 1] == faces[0, 0]
            loop = traj.collider_positions[0][faces[:, 0]]
            assert np.sum(loop[:, 0] * np.roll(loop[:, 1], -1) - np.roll(loop[:, 0], -1) * loop[:, 1]) > 0


def test_tissue_and_cavity_round_trip(tmp_path):
    source = write(tmp_path / "tissue_manipulation_dataset_test.pkl",
                   [tissue_record(0, nu=0.0), tissue_record(1, nu=-0.9)])
    path = import_reference(source, load_config("reference_tissue"), "test", tmp_path / "tissue")["path"]
    with SplitReader(path) as split:
        assert (split.scene, split.dim) == ("reference_tissue", 3)
        first, second = split[0], split[1]
    assert (first.youngs_modulus, second.youngs_modulus) == (80000.0, 10000.0)  # E by nu (the preset's table)
    assert first.cells.shape == (0, 4)  # the files hold no tetrahedra
    rest, tets = box_tet_mesh([-0.5, -0.5, -0.5], [0.5, 0.5, 0.0], [2, 2, 1])
    np.testing.assert_array_equal(first.edges, cell_edges(tets))
    np.testing.assert_array_equal(first.positions[0], rest)
    np.testing.assert_array_equal(first.fixed, rest[:, 2] == -0.5)
    with pytest.raises(ValueError, match="the surface is found from the tetrahedra and this mesh has none"):
        error_shares(first.positions, first.positions, rest, first.cells, first.fixed)  # `python -m ggns diagnose`
    assert first.collider_positions.shape == (T, 1, 3) and first.collider_faces.shape == (0, 3)
    assert first.point_cloud(3).shape == (9, 3)

    # the cavity: E is not known, so the import asks for it; the gripper's triangles become the collider faces
    source = write(tmp_path / "cavity_grasping_dataset_train.pkl", [tissue_record(0, gripper_triangles=True)])
    with pytest.raises(ReferenceFormatError, match="no Young's modulus for nu = 0.*--youngs-modulus"):
        import_reference(source, load_config("reference_cavity"), "train", tmp_path / "cavity")
    assert not (tmp_path / "cavity" / "train.h5").exists()
    bottom = list(range(0, 18, 2))  # box_tet_mesh's nodes (i, j, k = 0)
    path = import_reference(source, preset("reference_cavity", youngs_modulus=20000.0, fixed=bottom), "train",
                            tmp_path / "cavity")["path"]
    with SplitReader(path) as split:
        traj = split[0]
    assert traj.youngs_modulus == 20000.0
    np.testing.assert_array_equal(traj.fixed, rest[:, 2] == -0.5)
    np.testing.assert_array_equal(traj.collider_faces, [[0, 1, 2], [0, 2, 3]])


def test_the_command_names_the_split_from_the_file(tmp_path, capsys):
    source = write(tmp_path / "deformable_plate_dataset_eval.pkl", [plate_record(0)])
    main(["import-reference", "--input", str(source), "--output", str(tmp_path / "out"), "--steps", "8"])
    out = capsys.readouterr().out
    assert f"{tmp_path / 'out' / 'val.h5'}: 1 trajectories; steps 8, nodes 16, fixed 4" in out
    with SplitReader(tmp_path / "out" / "val.h5") as split:
        assert split.split == "val" and split[0].num_steps == 8 and split.generator_config["importer"]["steps"] == 8
    for argv, message in ((["--output", str(tmp_path / "out")], "val.h5: already exists (--overwrite replaces it)"),
                          (["--config", "plate_tiny"], "--config plate_tiny: not a preset of imported data")):
        with pytest.raises(SystemExit):
            main(["import-reference", "--input", str(source), *argv])
        assert message in capsys.readouterr().err


# ---- files are data, never code ----------------------------------------------------------------------------
class RunsCode:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


class WritesFile:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return exec, (f"open({str(self.marker)!r}, 'w').write('ran')",)


@pytest.mark.parametrize("payload, refused", [(RunsCode, "posix.system"), (WritesFile, "builtins.exec")])
def test_a_pickle_that_runs_code_is_refused(tmp_path, payload, refused):
    marker = tmp_path / "ran"
    record = plate_record(0)
    record["poisson_ratio"] = payload(marker)
    source = write(tmp_path / "evil_train.pkl", [record])
    with pytest.raises(UnsafePickleError, match=f"refused to load {refused}"):
        load_pickle(source)
    with pytest.raises(UnsafePickleError, match=refused):
        import_reference(source, load_config("reference_plate"), "train", tmp_path / "out")
    assert not marker.exists() and not (tmp_path / "out").exists()


# ---- bad input: one clear error, nothing written or damaged ------------------------------------------------
def mutate(records: list, change: str) -> list:
    r = records[0]
    if change == "missing key":
        del r["triangles_grid"]
    elif change == "wrong dimension":
        r["nodes_grid"] = [np.c_[x, np.ones(len(x))] for x in r["nodes_grid"]]
    elif change == "ragged":
        r["nodes_grid"][5] = r["nodes_grid"][5][:-1]
    elif change == "non-finite":
        r["pcd_points"][2] = np.full((2, 2), np.nan, dtype=np.float32)
    elif change == "not normalized":
        r["nodes_grid"] = [100.0 * x for x in r["nodes_grid"]]
    elif change == "step counts":
        r["pcd_points"] = r["pcd_points"][:-1]
    return records  # "moving fixed node": the importer option below


@pytest.mark.parametrize("change, message", [
    ("missing key", r"lacks key\(s\) \['triangles_grid'\] of the 2D layout; keys present: \['edge_index_grid'"),
    ("wrong dimension", r"key 'nodes_grid', step 0: expected \[n, 2\]"),
    ("ragged", "key 'nodes_grid': ragged across steps: step 0 has 16 nodes, step 5 has 15"),
    ("non-finite", "key 'pcd_points', step 2: contains NaN or inf"),
    ("not normalized", r"key 'nodes_grid': the mesh at step 0 leaves \[-1, 1\]\^2 \(max \|coordinate\| 100\)"),
    ("step counts", "key 'pcd_points' has 11 steps, 'nodes_grid' has 12"),
    ("moving fixed node", "fixed node 15 moves by"),
])
def test_bad_trajectories_are_named(tmp_path, change, message):
    old = tmp_path / "out" / "train.h5"
    import_reference(write(tmp_path / "good.pkl", [plate_record(0)]), load_config("reference_plate"), "train",
                     tmp_path / "out")
    before = old.read_bytes()
    source = write(tmp_path / "bad.pkl", [plate_record(0), *mutate([plate_record(1)], change)])
    config = preset("reference_plate", fixed="0-3,15" if change == "moving fixed node" else None)
    with pytest.raises(ReferenceFormatError, match=rf"bad.pkl: trajectory \d: {message}"):
        import_reference(source, config, "train", tmp_path / "out", overwrite=True)
    assert old.read_bytes() == before and sorted(p.name for p in old.parent.iterdir()) == ["train.h5"]


@pytest.mark.parametrize("content, message", [
    ({"nodes_grid": []}, "expected a non-empty list with one dict per trajectory, got dict"),
    ([], r"got list \(empty\)"),
    (["not a dict"], "trajectory 0: expected a dict of arrays, got str"),
    ([tissue_record(0)], r"lacks key\(s\) .* of the 2D layout; the file holds the other dimension's keys"),
])
def test_bad_files_are_named(tmp_path, content, message):
    with pytest.raises(ReferenceFormatError, match=message):
        import_reference(write(tmp_path / "x.pkl", content), load_config("reference_plate"), "train", tmp_path)
    (tmp_path / "x.pkl").write_bytes(b"not a pickle")
    with pytest.raises(ReferenceFormatError, match="not a readable pickle"):
        load_pickle(tmp_path / "x.pkl")


# ---- training on imported data -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def imported_plate(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("reference_plate")
    for split, seeds in (("train", [0, 1, 2]), ("val", [3]), ("test", [4])):
        source = write(out / f"deformable_plate_dataset_{split}.pkl", [plate_record(s) for s in seeds])
        import_reference(source, load_config("reference_plate"), split, out)
    return out


def test_the_data_module_reads_imported_splits(imported_plate, tmp_path):
    data = SimulationDataModule("reference_plate", data_dir=str(imported_plate))
    assert data.imported and data.dim == 2 and len(data.trajectories("train")) == 3
    empty = SimulationDataModule("reference_plate", data_dir=str(tmp_path / "none"))
    empty.prepare_data()  # imported data are never generated
    with pytest.raises(FileNotFoundError, match="import it with `python -m ggns import-reference "
                                                "--config reference_plate --split train"):
        empty.trajectories("train")


def cli(logs: Path, task: str, data_dir: Path, command: str, *extra: str) -> Path:
    """`python -m ggns <command>` with conf/<task>/ggns.yaml on the imported `reference_<task>` data, tiny
    model; returns the run's log directory."""
    main([command, "--config", str(CONF_DIR / task / "ggns.yaml"), "--data.dataset", f"reference_{task}",
          "--data.data_dir", str(data_dir), "--data.batch_size", "8",
          "--trainer.logger.init_args.save_dir", str(logs), "--trainer.logger.init_args.version", command,
          "--model.init_args.latent", "8", "--model.init_args.blocks", "1", "--trainer.enable_progress_bar",
          "false", "--trainer.enable_model_summary", "false", "--trainer.log_every_n_steps", "1", *extra])
    return next(logs.glob(f"*/{command}"))


FIT_ONE_EPOCH = ("--trainer.max_epochs", "1", "--trainer.limit_train_batches", "2", "--trainer.check_val_every_n_epoch",
                 "1", "--trainer.limit_val_batches", "1")


@pytest.mark.usefixtures("single_thread")
def test_imported_plate_trains_and_tests_through_the_cli(imported_plate, tmp_path, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["ggns"])
    run = cli(tmp_path, "plate", imported_plate, "fit", *FIT_ONE_EPOCH)
    (best,) = (run / "checkpoints").glob("best-k1-step=2.ckpt")  # validation rolled out the imported val split
    run = cli(tmp_path, "plate", imported_plate, "test", "--ckpt_path", str(best))
    metrics = json.loads((run / "test_metrics.json").read_text())
    assert 0 < metrics["rollout_iou_k1"]["mean"] <= 1  # the 2D IoU from the imported triangles


@pytest.mark.usefixtures("single_thread")
def test_imported_tissue_trains_and_names_what_needs_cells(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["ggns"])
    for split, seeds in (("train", [0, 1, 2]), ("val", [3]), ("test", [4])):
        source = write(tmp_path / f"tissue_manipulation_dataset_{split}.pkl", [tissue_record(s) for s in seeds])
        import_reference(source, load_config("reference_tissue"), split, tmp_path / "data")
    with pytest.warns(UserWarning, match="RolloutPictures: val trajectory 0 has no cells"):
        run = cli(tmp_path / "logs", "tissue", tmp_path / "data", "fit", *FIT_ONE_EPOCH)
    with pytest.raises(SystemExit) as exit_info:
        cli(tmp_path / "logs", "tissue", tmp_path / "data", "test", "--ckpt_path",
            str(run / "checkpoints" / "last.ckpt"))
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and re.search("error: .*volume IoU needs tetrahedra .* --evaluation.iou false", err)

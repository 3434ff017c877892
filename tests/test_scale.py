"""The paper-scale plate and the scale check (`ggns.graphs.scale`, `python -m ggns geometry`):
the measured quantities against hand computations on real generated files, the preset's
geometry, and the refusal of split files generated for another scene."""

import numpy as np
import pytest

from ggns.config import load_config, resolve_preset
from ggns.data.generate import split_path
from ggns.data.module import SimulationDataModule
from ggns.data.schema import DatasetError, config_differences, read_trajectories
from ggns.batch import TrajectoryBatch
from ggns.graphs.connectivity import load_connectivity
from ggns.graphs.scale import check, graph_hops, measure, report
from ggns.graphs.state import state_graph
from ggns.scenes.plate import plate_mesh

PLATE = load_config("plate")["scene"]


@pytest.mark.parametrize("shape", range(9))
def test_plate_fills_the_task_space_with_uniform_diagonals(shape):
    rest, cells, fixed = plate_mesh(PLATE, shape)
    assert rest.min() >= -1 and rest.max() <= 1
    assert np.all(rest[fixed, 1] == -1.0) and fixed.sum() == 9  # the fixed bottom edge lies at y = -1
    n = PLATE["grid_nodes"]
    j, i = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
    a = (j * n + i).ravel()
    b, d = a + 1, a + n
    pairs = {frozenset(p) for c in cells for p in ((c[0], c[1]), (c[1], c[2]), (c[0], c[2]))}
    assert all(frozenset((x, y)) in pairs for x, y in zip(b, d))  # bottom-right to top-left in every quad
    assert not any(frozenset((x, x + n + 1)) in pairs for x in a)  # never the other diagonal
    edge = np.linalg.norm(rest[[e for e in b]] - rest[[e for e in a]], axis=1)
    assert edge.min() >= 0.15  # the smallest mesh edge target (docs/plate_scale.md)


def test_measure_matches_hand_counts(tiny_data_dir):
    trajs = read_trajectories(split_path(tiny_data_dir, "train"))
    full, mgn = load_connectivity("plate_full_graph"), load_connectivity("plate_mgn")
    values = measure(trajs, full, mgn, noise_std=0.01, stride=3)
    steps = range(0, trajs[0].num_steps - 1, 3)
    counts = [len(t.point_cloud(s)) for t in trajs for s in steps]
    assert values["points_per_step"] == np.median(counts)
    assert (values["points_per_step_min"], values["points_per_step_max"]) == (min(counts), max(counts))
    edges, pp = [], 0
    for t in trajs:
        batch = TrajectoryBatch.from_trajectories([t])
        for s in steps:
            g = state_graph(batch, s, batch.positions[s], True, full)
            edges.append(sum(g[et].edge_index.size(1) for et in g.edge_types))
            pp += g["point", "near", "point"].edge_index.size(1)
    assert values["edges_per_graph"] == pytest.approx(np.mean(edges))
    assert values["point_neighbours"] == pytest.approx(pp / sum(counts))
    lengths = np.concatenate([np.linalg.norm(t.rest_positions[t.edges[:, 0]] - t.rest_positions[t.edges[:, 1]], axis=1)
                              for t in trajs])
    assert values["smallest_mesh_edge"] == pytest.approx(lengths.min())
    motion = np.concatenate([np.diff(t.positions, axis=0)[:, ~t.fixed].ravel() for t in trajs])
    assert values["free_motion_rms"] == pytest.approx(np.sqrt(np.mean(motion**2)))
    assert values["noise_over_motion"] == pytest.approx(0.01 / values["free_motion_rms"])


def test_check_and_report_flag_values_out_of_range():
    values = {"points_per_step": 450.0, "point_neighbours": 4.0}
    targets = {"points_per_step": [500, 700], "point_neighbours": [3, 6]}
    assert check(values, targets) == {"points_per_step": False, "point_neighbours": True}
    table = report(values, targets, "t")
    assert "| points_per_step | 450 | 500 to 700 | OUT OF RANGE |" in table
    assert "| point_neighbours | 4 | 3 to 6 | ok |" in table
    with pytest.raises(ValueError, match="unknown quantities"):
        check(values, {"typo": [0, 1]})


def test_geometry_command_prints_the_table(tiny_data_dir, tmp_path, capsys):
    preset = tmp_path / "tiny.yaml"
    preset.write_text(f"base: {load_config.__globals__['CONF_DIR'] / 'data' / 'plate_tiny.yaml'}\noutput: {tiny_data_dir}\n")
    from ggns.__main__ import main

    capsys.readouterr()
    main(["geometry", "--dataset", str(preset), "--trajectories", "2", "--stride", "4"])
    out = capsys.readouterr().out
    assert "| edges_per_graph |" in out and "| free_motion_rms |" in out and "targets" in out


def test_split_of_another_scene_is_refused(tiny_data_dir, tmp_path):
    path = split_path(tiny_data_dir, "val")
    config = load_config("plate_tiny")
    assert read_trajectories(path, expected_config=config)  # the same preset reads
    changed = load_config("plate_tiny", ["scene.plane=strain", "sensor.voxel_size=0.04"])
    assert config_differences(config, changed) == ["scene.plane", "sensor.voxel_size"]
    with pytest.raises(DatasetError, match="scene.plane.*file: 'stress', preset: 'strain'"):
        read_trajectories(path, expected_config=changed)
    earlier = tmp_path / "earlier.yaml"  # the earlier scene's preset pointed at today's files
    earlier.write_text(f"base: {resolve_preset('plate_earlier', 'data')}\n"  # experiments/earlier_dataset/data/
                       f"scene: {{num_steps: 8}}\noutput: {tiny_data_dir}\n")
    data = SimulationDataModule(str(earlier), generate_missing=False)
    with pytest.raises(DatasetError, match="another configuration.*scene.bottom_width"):
        data.trajectories("val")


def test_graph_hops_on_a_path_and_a_split_graph():
    path = np.array([[0, 1, 2], [1, 2, 3]])  # 0-1-2-3, one direction only: hops count both ways
    assert graph_hops(4, path).max() == 3
    assert graph_hops(4, path, np.array([False, False, False, True])).tolist() == [3, 2, 1, 0]
    assert graph_hops(4, path, np.array([1])).tolist() == [1, 0, 1, 2]
    assert np.isinf(graph_hops(5, path, np.array([0]))[4])  # node 4 has no edge
    assert np.isinf(graph_hops(4, path, np.zeros(4, dtype=bool))).all()  # no source


def test_hops_of_the_plate_grid_match_its_rows(tiny_data_dir):
    """Plate grids of n x n nodes with one diagonal per quad (bottom-right to top-left): opposite corners
    lie 2(n-1) mesh hops apart, the top row n-1 hops above the fixed bottom row; world edges shorten both."""
    trajs = read_trajectories(split_path(tiny_data_dir, "train"))[:2]
    n = load_config("plate_tiny")["scene"]["grid_nodes"]
    values = measure(trajs, load_connectivity("plate_full_graph"), load_connectivity("plate_mgn"), 0.01, stride=4)
    assert values["mesh_hops_diameter"] == 2 * (n - 1)
    assert values["fixed_hops_max"] == n - 1
    assert values["mesh_hops_diameter_world"] <= values["mesh_hops_diameter"]
    assert values["fixed_hops_max_world"] <= values["fixed_hops_max"]
    assert 0 < values["collider_hops_max"] <= 2 * (n - 1) or np.isnan(values["collider_hops_max"])

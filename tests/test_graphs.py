"""Graph construction: radius edges equal brute force, symmetric cross types, world edges,
the neighbour cap, absent types, edge features and the connectivity presets."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from ggns.config import CONF_DIR, load_config, preset_files
from ggns.geometry import cell_edges
from ggns.batch import directed_mesh_edges
from ggns.graphs.build import build_graph
from ggns.graphs.connectivity import Connectivity, load_connectivity
from ggns.graphs.types import EDGE_TYPES, MESH_EDGE, NODE_TYPES, WORLD_EDGE
from ggns.scenes.plate import plate_mesh

CONN = Connectivity(
    point_point=0.15, mesh_point=0.12, collider_point=0.1, collider_mesh=0.2, collider_collider=0.13, world=0.27, max_num_neighbors=128
)
SIZES = {"mesh": (20, 35, 27), "collider": (8, 0, 12), "point": (60, 45, 0)}  # per graph; empty graphs on purpose


def random_scene(dim: int, seed: int = 0) -> dict:
    """build_graph keyword inputs for B = 3 overlapping graphs. Coordinates are multiples of
    1/256 so that squared distances are exact and translations by 1/4 change no bit."""
    g = torch.Generator().manual_seed(seed)
    inputs, offset, edges, half = {}, 0, [], 128 if dim == 2 else 64  # 3D: a smaller cube, as dense
    for name, sizes in SIZES.items():
        inputs[name] = torch.randint(-half, half, (sum(sizes), dim), generator=g).float() / 256
        inputs[f"{name}_batch"] = torch.repeat_interleave(torch.arange(3), torch.tensor(sizes))
    for size in SIZES["mesh"]:  # mesh edges: each node to its 3 nearest nodes in its graph
        pos = inputs["mesh"][offset : offset + size]
        near = torch.cdist(pos, pos).topk(4, largest=False).indices[:, 1:]
        pairs = torch.stack([torch.arange(size).repeat_interleave(3), near.reshape(-1)], 1).sort(dim=1).values
        edges.append(pairs.unique(dim=0) + offset)
        offset += size
    return dict(
        mesh_pos=inputs["mesh"],
        mesh_rest=torch.randint(-128, 128, inputs["mesh"].shape, generator=g).float() / 256,
        mesh_edges=directed_mesh_edges(torch.cat(edges)),
        fixed=torch.rand(offset, generator=g) < 0.2,
        mesh_batch=inputs["mesh_batch"],
        collider_pos=inputs["collider"],
        collider_next=inputs["collider"] + torch.randint(-4, 5, inputs["collider"].shape, generator=g) / 256,
        collider_batch=inputs["collider_batch"],
        points=inputs["point"],
        point_batch=inputs["point_batch"],
        connectivity=CONN,
        num_graphs=3,
    )


def positions(scene: dict) -> dict:
    return {"mesh": scene["mesh_pos"], "collider": scene["collider_pos"], "point": scene["points"]}


def batches(scene: dict) -> dict:
    return {"mesh": scene["mesh_batch"], "collider": scene["collider_batch"], "point": scene["point_batch"]}


def pair_set(edge_index: torch.Tensor) -> set:
    return set(map(tuple, edge_index.T.tolist()))


def within(pos_a, batch_a, pos_b, batch_b, r: float, same: bool) -> torch.Tensor:
    """[|a|, |b|] bool: pairs of one graph with |a_i - b_j| < r (and i != j for one node type)."""
    sq = torch.cdist(pos_a.double(), pos_b.double()).square()
    assert ((sq - r**2).abs() > 1e-6).all(), "test setup: a distance is too close to the radius"
    mask = (sq < r**2) & (batch_a[:, None] == batch_b[None, :])
    if same:
        mask.fill_diagonal_(False)
    return mask


@pytest.mark.parametrize("dim", [2, 3])
def test_radius_edges_equal_brute_force(dim):
    scene = random_scene(dim)
    data = build_graph(**scene)
    pos, batch = positions(scene), batches(scene)
    mesh_pairs = pair_set(scene["mesh_edges"])
    assert set(data.edge_types) == set(EDGE_TYPES)
    for edge_type, r in CONN.radii().items():
        src, _, dst = edge_type
        expected = pair_set(within(pos[src], batch[src], pos[dst], batch[dst], r, src == dst).nonzero().T)
        if edge_type == WORLD_EDGE:
            assert expected & mesh_pairs, "test setup: some mesh edges should lie within the world radius"
            expected -= mesh_pairs
        found = data[edge_type].edge_index
        assert found.size(1) == len(pair_set(found)), f"{edge_type}: duplicate edges"
        assert pair_set(found) == expected, edge_type
        reverse = data[dst, edge_type[1], src].edge_index
        assert torch.equal(found.flip(0), reverse) or src == dst, f"{edge_type}: not the flipped reverse type"
    for edge_type in data.edge_types:  # no edge crosses graphs
        src, _, dst = edge_type
        index = data[edge_type].edge_index
        assert torch.equal(batch[src][index[0]], batch[dst][index[1]]), edge_type
    assert pair_set(data[MESH_EDGE].edge_index) == mesh_pairs


@pytest.mark.parametrize("dim", [2, 3])
def test_features_columns_and_translation_invariance(dim):
    scene = random_scene(dim, seed=1)
    data = build_graph(**scene)
    pos = positions(scene)
    for edge_type in data.edge_types:
        src, _, dst = edge_type
        index, attr = data[edge_type].edge_index, data[edge_type].edge_attr
        rel = pos[src][index[0]] - pos[dst][index[1]]
        columns = [rel, rel.norm(dim=1, keepdim=True)]
        if edge_type == MESH_EDGE:
            rest = scene["mesh_rest"][index[0]] - scene["mesh_rest"][index[1]]
            columns += [rest, rest.norm(dim=1, keepdim=True)]
        assert torch.equal(attr, torch.cat(columns, 1)), edge_type
        assert attr.shape[1] == (2 if edge_type == MESH_EDGE else 1) * (dim + 1)
    shift = torch.full((dim,), 0.25)
    moved = dict(scene, mesh_pos=scene["mesh_pos"] + shift, collider_pos=scene["collider_pos"] + shift,
                 collider_next=scene["collider_next"] + shift, points=scene["points"] + shift)
    other = build_graph(**moved)
    assert other.edge_types == data.edge_types
    for edge_type in data.edge_types:
        assert torch.equal(other[edge_type].edge_index, data[edge_type].edge_index), edge_type
        assert torch.equal(other[edge_type].edge_attr, data[edge_type].edge_attr), edge_type
    for node_type in data.node_types:
        assert torch.equal(other[node_type].x, data[node_type].x), node_type


def test_node_features_and_material():
    scene = random_scene(2, seed=2)
    material = torch.tensor([-0.9, 0.0, 0.49])
    data = build_graph(**scene, material=material)
    assert data.num_graphs == 3 and data.node_types == list(NODE_TYPES)
    assert torch.equal(data["mesh"].x, torch.stack([scene["fixed"].float(), material[scene["mesh_batch"]]], 1))
    assert torch.equal(data["collider"].x, scene["collider_next"] - scene["collider_pos"])
    assert data["point"].x.shape == (sum(SIZES["point"]), 0)
    assert build_graph(**scene)["mesh"].x.shape == (sum(SIZES["mesh"]), 1)
    for node_type in data.node_types:
        assert torch.equal(data[node_type].batch, batches(scene)[node_type])


def test_neighbour_cap_is_exact_and_raises():
    scene = random_scene(2, seed=3)
    pos, batch = positions(scene), batches(scene)
    most = 0  # largest neighbour count of one node in any radius query (world: mesh edges included)
    for (src, _, dst), r in CONN.radii().items():
        mask = within(pos[src], batch[src], pos[dst], batch[dst], r, src == dst)
        most = max(most, int(mask.sum(0).max()), int(mask.sum(1).max()))
    assert most > 1
    tight, data = build_graph(**dict(scene, connectivity=dataclasses.replace(CONN, max_num_neighbors=most))), build_graph(**scene)
    assert all(torch.equal(tight[et].edge_index, data[et].edge_index) for et in data.edge_types)
    with pytest.raises(ValueError, match=r"edge type .* more than max_num_neighbors=.*set a larger max_num_neighbors"):
        build_graph(**dict(scene, connectivity=dataclasses.replace(CONN, max_num_neighbors=most - 1)))


def test_absent_types():
    scene = random_scene(3, seed=4)
    no_points = build_graph(**dict(scene, points=None, point_batch=None))
    empty_points = build_graph(**dict(scene, points=scene["points"][:0], point_batch=scene["point_batch"][:0]))
    for data in (no_points, empty_points):
        assert "point" not in data.node_types
        assert all("point" not in (et[0], et[2]) for et in data.edge_types)
        assert len(data.edge_types) == 5
    no_collider = build_graph(**dict(scene, collider_pos=None, collider_next=None, collider_batch=None))
    assert no_collider.node_types == ["mesh", "point"] and len(no_collider.edge_types) == 5
    zero = build_graph(**dict(scene, connectivity=dataclasses.replace(CONN, collider_collider=0.0, world=0.0, mesh_point=0.0)))
    assert set(zero.edge_types) == set(EDGE_TYPES) - {WORLD_EDGE, ("collider", "near", "collider"),
                                                      ("point", "near", "mesh"), ("mesh", "near", "point")}
    far = build_graph(**dict(scene, points=scene["points"] + 10.0))  # points present, but no point edge to others
    assert "point" in far.node_types and ("point", "near", "mesh") not in far.edge_types


def test_rejects_bad_inputs():
    scene = random_scene(2, seed=5)
    with pytest.raises(ValueError, match="point batch sorted"):
        build_graph(**dict(scene, point_batch=scene["point_batch"].flip(0)))
    with pytest.raises(ValueError, match="inside one graph"):
        build_graph(**dict(scene, mesh_edges=torch.tensor([[0, 40], [40, 0]])))
    with pytest.raises(ValueError, match="mesh_rest"):
        build_graph(**dict(scene, mesh_rest=scene["mesh_rest"][:-1]))


def test_plate_mesh_graph():
    rest, cells, fixed = plate_mesh(load_config("plate")["scene"], 4)
    rest = torch.as_tensor(rest, dtype=torch.float32)
    edges = directed_mesh_edges(torch.from_numpy(cell_edges(cells)))
    data = build_graph(
        rest, rest, edges, torch.from_numpy(fixed), torch.zeros(len(rest), dtype=torch.long),
        None, None, None, None, None, load_connectivity("plate_mgn"), num_graphs=1,
    )
    assert data[MESH_EDGE].edge_index.shape == (2, 416)
    assert pair_set(data[MESH_EDGE].edge_index) == pair_set(data[MESH_EDGE].edge_index.flip(0))
    assert data[WORLD_EDGE].edge_index.size(1) > 0 and data.edge_types == [MESH_EDGE, WORLD_EDGE]


def test_connectivity_presets_and_validation():
    names = sorted(p.stem for p in preset_files("graphs"))  # shipped and the experiments' (plate_equal_radii)
    assert {"plate_full_graph", "plate_equal_radii", "plate_reduced_graph", "plate_mgn"} <= set(names)
    for name in names:
        conn = load_connectivity(name)
        assert set(conn.radii()) == set(EDGE_TYPES) - {MESH_EDGE}
    full = load_connectivity("plate_full_graph")
    assert (full.point_point, full.mesh_point, full.collider_point, full.collider_mesh, full.collider_collider, full.world) == (
        0.1, 0.08, 0.08, 0.3, 0.08, 0.0)
    assert load_connectivity("plate_mgn", ["world=0.5"]).world == 0.5
    fields = dataclasses.asdict(full)
    for key, bad in [("world", -0.1), ("point_point", float("nan")), ("mesh_point", float("inf")), ("max_num_neighbors", 0),
                     ("max_num_neighbors", 2.5), ("collider_mesh", "0.3")]:
        with pytest.raises(ValueError, match=key):
            Connectivity.from_dict(dict(fields, **{key: bad}))
    with pytest.raises(ValueError, match="unknown keys"):
        Connectivity.from_dict(dict(fields, radius=1.0))
    with pytest.raises(ValueError, match="missing keys"):
        Connectivity.from_dict({k: v for k, v in fields.items() if k != "world"})

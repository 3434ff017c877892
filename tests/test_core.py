"""Encode-Process-Decode core and Normalizer on small hand-built 2D graphs."""
from __future__ import annotations

import pytest
import torch
from torch_geometric.data import Batch, HeteroData

from ggns.graphs.types import EDGE_TYPES, MESH_EDGE, NODE_TYPES, WORLD_EDGE
from ggns.models import EncodeProcessDecode, Normalizer, NormalizerDict, graph_features
from ggns.models.core import inverse_counts, mean_aggregate

D = 2
NODE_DIMS = {"mesh": 1, "collider": D, "point": 0}
EDGE_DIMS = {t: 2 * (D + 1) if t == MESH_EDGE else D + 1 for t in EDGE_TYPES}
SIZES = {"mesh": 7, "collider": 3, "point": 5}


def make_graph(seed: int, node_types=("mesh", "collider", "point"), edge_types=EDGE_TYPES,
               sizes=SIZES, edges_per_type: int = 9) -> HeteroData:
    """Random 2D graph in the builder's format: features [fixed flag], [velocity], []; edge_attr
    [world rel pos, distance] (+ [mesh rel pos, distance] on mesh edges)."""
    g = torch.Generator().manual_seed(seed)
    data = HeteroData()
    pos = {}
    for t in node_types:
        pos[t] = torch.rand(sizes[t], D, generator=g)
        data[t].pos = pos[t]
        data[t].x = torch.randn(sizes[t], NODE_DIMS[t], generator=g)
    for src, rel, dst in edge_types:
        if src not in node_types or dst not in node_types:
            continue
        index = torch.stack([torch.randint(sizes[src], (edges_per_type,), generator=g),
                             torch.randint(sizes[dst], (edges_per_type,), generator=g)])
        world = pos[src][index[0]] - pos[dst][index[1]]
        attr = [world, world.norm(dim=1, keepdim=True)]
        if (src, rel, dst) == MESH_EDGE:
            mesh = torch.randn(edges_per_type, D, generator=g)
            attr += [mesh, mesh.norm(dim=1, keepdim=True)]
        data[src, rel, dst].edge_index = index
        data[src, rel, dst].edge_attr = torch.cat(attr, dim=1)
    return data


def make_batch(**kwargs) -> HeteroData:
    return Batch.from_data_list([make_graph(0, **kwargs), make_graph(1, **kwargs)])


def make_model(edge_partition: bool, latent: int = 16, blocks: int = 2,
               type_encoding: str = "per_type") -> EncodeProcessDecode:
    torch.manual_seed(0)
    return EncodeProcessDecode(NODE_DIMS, EDGE_DIMS, out_dim=D, latent=latent, blocks=blocks,
                               edge_partition=edge_partition, type_encoding=type_encoding)


VARIANTS = {
    "all types": {},
    "no point cloud": {"node_types": ("mesh", "collider")},
    "some edge types absent": {"edge_types": (MESH_EDGE, ("collider", "near", "mesh"), ("point", "near", "mesh"))},
    "mesh only, mesh edges": {"node_types": ("mesh",), "edge_types": (MESH_EDGE,)},
    "mesh only, no edges": {"node_types": ("mesh",), "edge_types": ()},
}


@pytest.mark.parametrize("edge_partition", [False, True], ids=["GGNS", "MGN"])
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("type_encoding", ["per_type", "one_hot"])
def test_output_shape(type_encoding, edge_partition, variant):
    data = make_batch(**VARIANTS[variant])
    out = make_model(edge_partition, type_encoding=type_encoding)(data)
    assert out.shape == (2 * SIZES["mesh"], D)
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("edge_partition", [False, True], ids=["GGNS", "MGN"])
@pytest.mark.parametrize("type_encoding", ["per_type", "one_hot"])
def test_permutation_equivariance(type_encoding, edge_partition):
    """Relabeling the mesh nodes relabels the output rows the same way."""
    data = make_batch()
    model = make_model(edge_partition, type_encoding=type_encoding).eval()
    n = data["mesh"].num_nodes
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(3))
    new_index = torch.empty_like(perm)
    new_index[perm] = torch.arange(n)  # old node perm[i] becomes node i
    permuted = data.clone()
    for key in ("x", "pos", "batch"):
        permuted["mesh"][key] = data["mesh"][key][perm]
    for t in permuted.edge_types:
        for row, node_type in ((0, t[0]), (1, t[2])):
            if node_type == "mesh":
                permuted[t].edge_index[row] = new_index[data[t].edge_index[row]]
    with torch.no_grad():
        torch.testing.assert_close(model(permuted), model(data)[perm])


@pytest.mark.parametrize("edge_partition", [False, True], ids=["GGNS", "MGN"])
def test_isolated_mesh_node(edge_partition):
    """A mesh node without edges gets zero aggregates: finite output that no other node changes."""
    data = make_graph(0)
    isolated = SIZES["mesh"] - 1
    for t in data.edge_types:
        keep = torch.ones(data[t].edge_index.shape[1], dtype=torch.bool)
        for row, node_type in ((0, t[0]), (1, t[2])):
            if node_type == "mesh":
                keep &= data[t].edge_index[row] != isolated
        data[t].edge_index, data[t].edge_attr = data[t].edge_index[:, keep], data[t].edge_attr[keep]
    model = make_model(edge_partition).eval()
    with torch.no_grad():
        out = model(data)
        data["collider"].x = data["collider"].x + 1.0
        data["mesh"].x[:isolated] += 1.0
        changed = model(data)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(changed[isolated], out[isolated])


@pytest.mark.parametrize("edge_partition", [False, True], ids=["GGNS", "MGN"])
def test_deterministic_in_eval_mode(edge_partition):
    data = make_batch()
    model = make_model(edge_partition).eval()
    with torch.no_grad():
        assert torch.equal(model(data), model(data))


@pytest.mark.parametrize("edge_partition", [False, True], ids=["GGNS", "MGN"])
@pytest.mark.parametrize("type_encoding", ["per_type", "one_hot"])
def test_gradient_reaches_every_parameter(type_encoding, edge_partition):
    model = make_model(edge_partition, type_encoding=type_encoding)
    model(make_batch()).square().sum().backward()
    for name, p in model.named_parameters():
        assert p.grad is not None, name
        assert p.numel() == 0 or p.grad.abs().sum() > 0, name  # the point encoder's weight is [L, 0]


def test_parameter_count():
    """Paper sizes (latent 128, 5 blocks, 1-layer MLPs), 2D, every node and edge type:
    node encoders 256 + 384 + 128 (point: bias only), edge encoders 896 + 9 * 512,
    blocks 5 * (f_E 384->128: 49,280 + f_V 256->128: 32,896), decoder 16,512 + 258
    -> GGNS 433,922. One-hot encoders instead: nodes (3 + 2)->128 (768), edges (10 + 6)->128
    (2,176) -> 430,594 (the paper's homogeneous GGNS: ~430k).
    MGN: blocks 1-4 have 10 edge MLPs (492,800), f_V mesh 640->128 (82,048), collider and
    point 512->128 (65,664 each); the last block only the 4 edge MLPs into mesh and f_V mesh
    (279,168) -> 3,126,914."""
    def count(edge_partition, type_encoding="per_type"):
        model = EncodeProcessDecode(NODE_DIMS, EDGE_DIMS, out_dim=D, edge_partition=edge_partition,
                                    type_encoding=type_encoding)
        return sum(p.numel() for p in model.parameters())

    assert count(False) == 433_922
    assert count(False, "one_hot") == 430_594
    assert count(True) == 3_126_914


def test_mgn_slots_and_ggns_pooled_mean():
    """MGN: one aggregate slot per incoming edge type; GGNS: one mean over all incoming edges."""
    block = make_model(True, latent=4, blocks=1).processor[0]
    assert block.node_mlp["mesh"][0].in_features == 4 * (1 + 4)  # mesh_edge, world, collider->, point->
    messages, receivers = torch.tensor([[1.0], [3.0], [8.0]]), torch.tensor([0, 2, 0])
    pooled = mean_aggregate(messages, receivers, inverse_counts(receivers, 3, messages))
    assert pooled.flatten().tolist() == [4.5, 0.0, 3.0]


def test_unknown_type_refused():
    model = EncodeProcessDecode({"mesh": 1}, {MESH_EDGE: 6}, out_dim=D, latent=8, blocks=1)
    with pytest.raises(KeyError, match="world"):
        model(make_graph(0, node_types=("mesh",), edge_types=(MESH_EDGE, WORLD_EDGE)))
    with pytest.raises(ValueError):
        EncodeProcessDecode({"collider": 2}, {}, out_dim=D)


def test_bad_type_encoding_refused():
    with pytest.raises(ValueError, match="per_type.*one_hot"):
        make_model(False, type_encoding="onehot")


def test_one_hot_encoder_input_layout():
    """Each type's row: [one-hot of its position among the model's types, normalized features,
    zeros up to the widest input]; all types share one Linear."""
    model = make_model(False, type_encoding="one_hot")
    for seed in range(3):
        model.input_normalizer.update(graph_features(make_graph(seed)))
    assert isinstance(model.node_encoder.linear, torch.nn.Linear)
    assert model.node_encoder.linear.in_features == 3 + 2 and model.edge_encoder.linear.in_features == 10 + 6
    data = make_graph(5)
    features = model.input_normalizer(graph_features(data))
    with torch.no_grad():
        encoded = model.encode(data)
    for encoder, types, width, latents in ((model.node_encoder, data.node_types, 2, encoded[0]),
                                           (model.edge_encoder, data.edge_types, 6, encoded[1])):
        inputs = encoder.inputs({t: features[t] for t in types})
        slots = NODE_TYPES if encoder is model.node_encoder else EDGE_TYPES
        for t in types:
            n, f = len(features[t]), features[t].shape[1]
            expected = torch.cat([torch.eye(len(slots))[slots.index(t)].expand(n, -1), features[t],
                                  torch.zeros(n, width - f)], dim=1)
            assert torch.equal(inputs[t], expected), t
            torch.testing.assert_close(latents[t], encoder.linear(expected).detach())
    assert model.input_normalizer["mesh"].std.ne(1).all()  # the features were really rescaled


def test_one_hot_slot_is_fixed_by_the_model_not_the_graph():
    """A graph lacking some types encodes the types it has exactly as a full graph does."""
    model = make_model(False, type_encoding="one_hot").eval()
    full = make_graph(0)
    partial = full.node_type_subgraph(["mesh", "point"])  # no collider, no edges touching it
    assert "collider" not in partial.node_types and WORLD_EDGE in partial.edge_types
    with torch.no_grad():
        (x_full, e_full), (x_part, e_part) = model.encode(full), model.encode(partial)
    assert set(x_part) == {"mesh", "point"}
    for t in x_part:
        assert torch.equal(x_part[t], x_full[t]), t
    for t in e_part:
        assert torch.equal(e_part[t], e_full[t]), t
    point_input = model.node_encoder.inputs({"point": partial["point"].x})["point"]
    assert point_input[:, :3].argmax(1).eq(NODE_TYPES.index("point")).all()  # not slot 1 of (mesh, point)


def test_one_hot_distinguishes_types_with_equal_features():
    """Same features, different type -> different encoding; swapping the data of two edge types
    changes the output (with a shared encoder and pooled mean, only the one-hot tells them apart)."""
    edge_dims = {MESH_EDGE: 3, WORLD_EDGE: 3}
    torch.manual_seed(0)
    model = EncodeProcessDecode({"mesh": 1}, edge_dims, out_dim=D, latent=16, blocks=2,
                                type_encoding="one_hot").eval()
    data = make_graph(0, node_types=("mesh",), edge_types=(MESH_EDGE, WORLD_EDGE))
    data[MESH_EDGE].edge_attr = data[MESH_EDGE].edge_attr[:, 3:]  # both [rel pos, distance]
    swapped = data.clone()
    for a, b in ((MESH_EDGE, WORLD_EDGE), (WORLD_EDGE, MESH_EDGE)):
        swapped[a].edge_index, swapped[a].edge_attr = data[b].edge_index, data[b].edge_attr
    attr = data[WORLD_EDGE].edge_attr
    with torch.no_grad():
        encoded = model.edge_encoder({MESH_EDGE: attr, WORLD_EDGE: attr})
        assert not torch.allclose(encoded[MESH_EDGE], encoded[WORLD_EDGE])
        assert not torch.allclose(model(swapped), model(data))


def test_input_statistics_travel_with_the_state_dict():
    model = make_model(False).eval()
    for seed in range(3):
        model.input_normalizer.update(graph_features(make_graph(seed)))
    model.input_normalizer.freeze()
    restored = make_model(False).eval()
    restored.load_state_dict(model.state_dict())
    data = make_batch()
    with torch.no_grad():
        assert torch.equal(restored(data), model(data))
    assert restored.input_normalizer["mesh"].frozen


# ---- Normalizer

def test_normalizer_matches_statistics_of_the_concatenation():
    g = torch.Generator().manual_seed(0)
    chunks = [torch.randn(m, 3, generator=g) * torch.tensor([1.0, 10.0, 1e-3]) + 1e3 for m in (1, 5, 40, 7)]
    norm = Normalizer(3)
    for chunk in chunks:
        norm.update(chunk)
    full = torch.cat(chunks).double()
    torch.testing.assert_close(norm.acc_mean, full.mean(0))
    torch.testing.assert_close(norm.std.double(), full.std(0, correction=0), rtol=1e-6, atol=0)
    assert int(norm.count) == len(full)


def test_normalizer_floor_inverse_and_identity_before_update():
    x = torch.stack([torch.randn(20), torch.full((20,), 3.0)], dim=1)  # second column constant
    norm = Normalizer(2, std_floor=1e-8)
    assert torch.equal(norm(x), x)  # no statistics yet: identity
    norm.update(x)
    assert norm.std[1] == 1e-8 and (norm(x)[:, 1] == 0).all()
    torch.testing.assert_close(norm.inverse(norm(x)), x)
    # a constant feature is no input: another value of it (a collider that stops) still maps to 0,
    # where dividing by the floor gave 3e8; the varying column is standardized as before
    other = x.clone()
    other[:, 1] = 0.0
    assert (norm(other)[:, 1] == 0).all() and torch.equal(norm(other)[:, 0], norm(x)[:, 0])
    assert norm.varies().tolist() == [True, False]


def test_normalizer_mask_of_constant_features_follows_every_change_of_the_statistics():
    """forward keeps varies() between calls: loading, merging and casting must drop it."""
    varying, constant = torch.randn(6, 2), torch.ones(6, 2)
    x = torch.full((1, 2), 2.0)
    stale = Normalizer(2)
    stale.update(constant)
    assert (stale(x) == 0).all()  # both constant: the mask [0, 0] is now kept
    source = Normalizer(2)
    source.update(varying)
    stale.load_state_dict(source.state_dict())
    assert torch.equal(stale(x), source(x)) and (stale(x) != 0).all()
    merged = Normalizer(2)
    merged.update(constant)
    assert (merged(x) == 0).all()
    merged.merge(torch.tensor([6, 6]), torch.stack([varying.double().mean(0), torch.ones(2, dtype=torch.float64)]),
                 torch.stack([(varying.double() - varying.double().mean(0)).square().sum(0), torch.zeros(2).double()]))
    assert (merged(x) != 0).all()
    assert source.double()(x.double()).dtype == torch.float64


def test_normalizer_state_dict_round_trip_and_freeze():
    chunks = torch.randn(10, 2), torch.randn(5, 2)
    norm = Normalizer(2)
    norm.update(chunks[0])
    copy = Normalizer(2)
    copy.load_state_dict(norm.state_dict())
    x = torch.randn(4, 2)
    assert torch.equal(copy(x), norm(x))
    copy.update(chunks[1])  # accumulation continues exactly from the restored state
    torch.testing.assert_close(copy.acc_mean, torch.cat(chunks).double().mean(0))
    copy.freeze()
    with pytest.raises(RuntimeError, match="frozen"):
        copy.update(chunks[1])
    restored = Normalizer(2)
    restored.load_state_dict(copy.state_dict())
    assert restored.frozen and int(restored.count) == 15


def test_normalizer_refuses_bad_input():
    norm = Normalizer(2)
    with pytest.raises(ValueError, match="NaN"):
        norm.update(torch.tensor([[0.0, float("nan")]]))
    with pytest.raises(ValueError, match="shape"):
        norm.update(torch.zeros(3, 4))
    assert int(norm.count) == 0


def test_normalizer_zero_width():
    norm = Normalizer(0)
    norm.update(torch.zeros(6, 0))
    assert norm(torch.zeros(6, 0)).shape == (6, 0)
    assert norm.inverse(torch.zeros(2, 0)).shape == (2, 0)


def test_normalizer_dict_keys_edge_types():
    norms = NormalizerDict({"mesh": 1, ("collider", "near", "mesh"): 3})
    norms.update({("collider", "near", "mesh"): torch.randn(8, 3) * 5})
    out = norms({("collider", "near", "mesh"): torch.randn(2, 3), "mesh": torch.ones(2, 1)})
    assert out["mesh"].shape == (2, 1) and out["collider", "near", "mesh"].shape == (2, 3)
    assert "normalizers.collider__near__mesh.mean" in norms.state_dict()
    with pytest.raises(KeyError):
        norms({"point": torch.zeros(1, 0)})


def test_module_dicts_take_type_tuples_and_keep_the_checkpoint_names():
    """The per-type module dicts are keyed by node / edge types (PyG-style) but store parameters under
    the names checkpoints written before them have (`edge_mlp.collider__near__mesh.0.weight`)."""
    dims = {"mesh": 3, "collider": 2}
    edges = {MESH_EDGE: 4, ("collider", "near", "mesh"): 4}
    model = EncodeProcessDecode(dims, edges, 2, latent=8, blocks=2, edge_partition=True)
    block = model.processor[0]
    assert set(block.edge_mlp.keys()) == set(edges) and set(model.edge_encoder.keys()) == set(edges)
    assert block.edge_mlp["collider", "near", "mesh"] is block.edge_mlp[("collider", "near", "mesh")]
    names = set(model.state_dict())
    assert {"processor.0.edge_mlp.collider__near__mesh.0.weight", "edge_encoder.collider__near__mesh.weight",
            "processor.0.node_mlp.mesh.0.weight", "node_encoder.collider.weight"} <= names


def test_neighbour_counts_are_exact_past_what_bfloat16_holds():
    """A node receiving 300 edges under bfloat16 (autocast's dtype on the CPU and the GPU): 1/300 to bfloat16's
    precision, not 1/256 (bfloat16 counts integers exactly only up to 256)."""
    receivers = torch.cat([torch.zeros(300, dtype=torch.long), torch.ones(3, dtype=torch.long)])
    like = torch.zeros(1, dtype=torch.bfloat16)
    inverse = inverse_counts(receivers, 3, like)
    assert inverse.dtype == torch.bfloat16 and inverse.shape == (3, 1)
    assert abs(float(inverse[0]) * 300 - 1) < 1 / 128  # bfloat16's relative precision
    assert abs(float(inverse[0]) * 256 - 1) > 0.1  # what a count in bfloat16 gave
    assert float(inverse[1]) == pytest.approx(1 / 3, rel=1 / 128) and float(inverse[2]) == 1.0
    with torch.autocast("cpu", dtype=torch.bfloat16):
        messages = torch.ones(303, 4)
        pooled = mean_aggregate(messages.to(torch.bfloat16), receivers, inverse_counts(receivers, 3, messages.to(torch.bfloat16)))
    assert torch.allclose(pooled.float()[:2], torch.ones(2, 4), rtol=1 / 64)

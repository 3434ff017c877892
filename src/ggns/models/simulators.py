"""The learned simulators as LightningModules sharing one base, one core and one rollout engine: the
paper's four (GGNS, GGNS+LSTM, MGN, MGN(M)), the authors' plate MGN, and two beyond the paper.

    GGNS      the paper's model: one-hot node/edge types into shared encoders, one homogeneous
              processor, trained by imputation (a sample has its point cloud with prob. p)
    GGNSLSTM  GGNS with an LSTM cell on the mesh latents between processor and decoder, trained
              on windows of `window` steps with backpropagation through time
    MGN       MeshGraphNets: per-type encoders, one edge MLP per edge type, world edges, no points
    MGNM      MGN(M): MGN with the Poisson's ratio as a mesh node feature
    MGNShared the authors' plate MGN: GGNS's shared processor on mesh and collider edges, no world edges
    GGNSM     GGNS(M), an ablation: GGNS told the Poisson's ratio (as MGN(M) is)
    GGNSID    beyond the paper: GGNS(M)'s dynamics fed the material that a second, small network reads
              from the point clouds seen so far (trained on the labels; rollouts never read them)

The shared base, `GraphSimulator` (its training, rollout step and checkpoint hooks), is in
`graph_simulator.py`; reading checkpoints (`load_simulator`) and converting older ones is in `loading.py`.
"""
from __future__ import annotations

import torch
from torch import Tensor
from torch_geometric.data import HeteroData

from ..batch import TrajectoryBatch
from ..graphs.state import state_graph
from .core import EncodeProcessDecode, graph_features
from .graph_simulator import GraphSimulator, LstmState
from .normalization import Normalizer
from .training_noise import TrainingNoise

class GGNS(GraphSimulator):
    """Grounding Graph Network Simulator (one-hot types, shared processor, imputation training)."""

    def __init__(self, connectivity: str | dict = "plate_full_graph", point_probability: float = 0.5, **kwargs):
        super().__init__(connectivity=connectivity, point_probability=point_probability, **kwargs)


class GGNSM(GGNS):
    """GGNS(M): GGNS given the material (Poisson's ratio as a mesh node feature). Not a model of the
    paper: an ablation that bounds what inferring the material from point clouds is worth (GGNS
    must infer it; GGNS(M) is told it, as MGN(M) is)."""

    with_material = True


class GGNSID(GGNS):
    """GGNS that identifies the material from its point clouds (not a model of the paper).

    A second, small graph network (`estimator`, on GGNS's graph with the point cloud and without any
    material) reads each state that has a point cloud and says which Poisson's ratio it shows, as a
    Gaussian per trajectory (mean and log-variance, the mean over the mesh nodes of two outputs). Over a
    rollout the estimates of the states with point clouds are fused by their precision with a prior
    (the training labels' mean and std): the estimate moves only when points are seen, is kept through
    blind steps, sharpens with each cloud, and weighs states that show the material (in contact) above
    those that do not, as the network learns to say. The dynamics network is GGNS(M)'s, the material a
    mesh node feature: in training the label (teacher forcing), in rollouts the fused estimate. The
    estimator trains on the label with the Gaussian negative log-likelihood (times
    `material_loss_weight`), on the samples that have their point clouds. Rollouts never read the
    label: their graphs are built without it, so data without materials roll out.

    Against GGNS+LSTM: the LSTM carries a per-node state updated at every step, blind ones included,
    by whatever the network learns to keep; here one number per trajectory (with its uncertainty) is
    carried, changed only by observations, and trained against the quantity it stands for. Like MGN(M)
    and GGNS(M), and unlike GGNS and GGNS+LSTM, it needs the material labels in training.
    """

    material_input = True

    def __init__(self, connectivity: str | dict = "plate_full_graph", point_probability: float = 0.5,
                 estimator_latent: int = 32, estimator_blocks: int = 3, material_loss_weight: float = 1.0,
                 estimator_noise: TrainingNoise = TrainingNoise(std=0.0), **kwargs):
        super().__init__(connectivity=connectivity, point_probability=point_probability, **kwargs)
        self.estimator_noise = TrainingNoise.of(estimator_noise)
        self.save_hyperparameters()
        if not self.uses_points:
            raise ValueError(f"GGNSID estimates the material from point clouds, and connectivity {connectivity!r} "
                             f"has no point edges")
        if estimator_latent < 1 or estimator_blocks < 1 or material_loss_weight < 0:
            raise ValueError(f"need estimator_latent >= 1, estimator_blocks >= 1 and material_loss_weight >= 0; got "
                             f"{estimator_latent}, {estimator_blocks}, {material_loss_weight}")
        h = self.hparams
        self.estimator = EncodeProcessDecode(*self.input_dims(self.connectivity, h.dim, True), out_dim=2,
                                             latent=estimator_latent, blocks=estimator_blocks,
                                             mlp_layers=h.mlp_layers, **self.processor_layout(),
                                             std_floor=h.std_floor)
        self.material_normalizer = Normalizer(1, h.std_floor)

    @staticmethod
    def _set_material(graph: HeteroData, values: Tensor | None) -> HeteroData:
        """The mesh features as the graph builder made them (the fixed flag) plus a material column:
        `values` [B] per trajectory, or zeros (None; a constant, so no input after normalization)."""
        mesh = graph["mesh"]
        base = mesh.x[:, :1]
        column = base.new_zeros(base.size(0), 1) if values is None else values.to(base.dtype)[mesh.batch, None]
        mesh.x = torch.cat([base, column], dim=1)
        return graph

    def estimate(self, graph: HeteroData) -> tuple[Tensor, Tensor, Tensor]:
        """(mean [B], log-variance [B], has_points [B]) of each trajectory's normalized Poisson's ratio as
        the estimator reads it from `graph` (any material column in it is replaced by zeros first; the
        graph's own features are restored)."""
        mesh, num_graphs = graph["mesh"], graph.num_graphs
        saved = mesh.x
        out = self.estimator(self._set_material(graph, None))  # [N_mesh, 2]
        mesh.x = saved
        count = torch.bincount(mesh.batch, minlength=num_graphs).clamp(min=1).to(out.dtype)
        pooled = out.new_zeros(num_graphs, 2).index_add_(0, mesh.batch, out) / count[:, None]
        has = torch.zeros(num_graphs, dtype=torch.bool, device=out.device)
        if "point" in graph.node_types:
            has[graph["point"].batch] = True
        return pooled[:, 0], pooled[:, 1].clamp(-8.0, 4.0), has

    def training_graphs(self, batch: TrajectoryBatch, train: bool = True) -> list[tuple[HeteroData, Tensor]]:
        """GGNS's samples with the label as the material column (teacher forcing)."""
        batch.require_material("GGNSID's training")
        return [(self._set_material(graph, batch.material), target)
                for graph, target in super().training_graphs(batch, train)]

    def auxiliary_loss(self, graph: HeteroData, batch: TrajectoryBatch, t: int = 0,
                       train: bool = False) -> Tensor | None:
        """The estimator's Gaussian negative log-likelihood of the label, on the samples with points (in
        training read from `estimator_graph`)."""
        if "point" not in graph.node_types or self.hparams.material_loss_weight == 0:
            return None
        mean, log_var, has = self.estimate(self.estimator_graph(graph, batch, t) if train else graph)
        label = self.material_normalizer(batch.material.to(mean.dtype)[:, None])[:, 0]
        nll = 0.5 * (log_var + (label - mean).square() * torch.exp(-log_var))
        return self.hparams.material_loss_weight * (nll * has).sum() / has.sum()  # has.sum() >= 1: points are there

    def estimator_graph(self, graph: HeteroData, batch: TrajectoryBatch, t: int) -> HeteroData:
        """What the estimator trains on for sample `graph` (transition t of `batch`): the sample itself, or,
        with an `estimator_noise` (a `TrainingNoise`, e.g. a smooth field: `{std: 0, field_std: 0.03,
        field_mixture: true}`), its free mesh nodes moved by that noise, with the same point clouds,
        rebuilt (the point-mesh edges follow the moved mesh)."""
        noise = self.estimator_noise
        if noise.std == 0 and noise.field_std_at(self.global_step) == 0:
            return graph
        has = torch.zeros(batch.num_graphs, dtype=torch.bool, device=batch.device)
        has[graph["point"].batch] = True
        pos = noise.perturb(graph["mesh"].pos, ~batch.fixed[:, None], batch.rest, batch.mesh_batch, batch.num_graphs,
                            self.global_step, with_points=has)
        return state_graph(batch, t, pos, has, self.connectivity, self.with_material)

    def update_statistics(self, graph: HeteroData, batch: TrajectoryBatch) -> None:
        saved = graph["mesh"].x
        self.estimator.input_normalizer.update(graph_features(self._set_material(graph, None)))
        graph["mesh"].x = saved
        self.material_normalizer.update(batch.material.to(self.material_normalizer.acc_mean.dtype)[:, None])

    def step(self, graph: HeteroData, state: LstmState = None) -> tuple[Tensor, LstmState]:
        """The rollout step: fuse this state's estimate (if it has points) into the carried (precision,
        precision-weighted mean) per trajectory, starting from the prior N(0, 1) in normalized units, and
        predict with the fused estimate as the material."""
        if state is None:
            ones = graph["mesh"].pos.new_ones(graph.num_graphs)
            state = (ones, torch.zeros_like(ones))
        precision, weighted = state
        if "point" in graph.node_types:
            mean, log_var, has = self.estimate(graph)
            weight = torch.exp(-log_var) * has
            precision, weighted = precision + weight, weighted + weight * mean
        material = self.material_normalizer.inverse((weighted / precision)[:, None])[:, 0]
        out, _ = self.predict_normalized(self._set_material(graph, material), None)
        return self.target_normalizer.inverse(out), (precision, weighted)

    def material_estimate(self, state: LstmState) -> Tensor:
        """The fused Poisson's ratio [B] that a rollout's final `state` holds."""
        precision, weighted = state
        return self.material_normalizer.inverse((weighted / precision)[:, None])[:, 0]


class GGNSLSTM(GraphSimulator):
    """GGNS with an LSTM on the mesh latents, trained on windows of `window` steps (paper: 5).

    `backprop_steps` (default: all, the paper's): truncated backpropagation, only the window's last
    `backprop_steps` transitions carry the loss and gradients; the earlier ones run without gradients
    and only warm the LSTM state up (a step without backward costs about a third of one with it)."""

    recurrent = True

    def __init__(self, connectivity: str | dict = "plate_full_graph", point_probability: float = 0.5, window: int = 5,
                 backprop_steps: int | None = None, **kwargs):
        super().__init__(connectivity=connectivity, point_probability=point_probability, window=window, **kwargs)
        self.save_hyperparameters("backprop_steps")
        if backprop_steps is not None and not 1 <= backprop_steps <= window:
            raise ValueError(f"backprop_steps must lie in [1, window={window}], got {backprop_steps}")
        self.backprop_steps = backprop_steps


class MGN(GraphSimulator):
    """MeshGraphNets baseline: per-type encoders and edge MLPs (its default processor), world edges, no
    point clouds."""

    default_processor = "per_type"

    def __init__(self, connectivity: str | dict = "plate_mgn", point_probability: float = 0.0,
                 **kwargs):
        super().__init__(connectivity=connectivity, point_probability=point_probability, **kwargs)


class MGNM(MGN):
    """MGN(M): MGN given the material (Poisson's ratio as a mesh node feature)."""

    with_material = True


class MGNShared(GraphSimulator):
    """The authors' own plate MGN baseline: GGNS's architecture (one-hot node and edge types into
    shared encoders, one shared processor) on mesh and collider edges only, no world edges, no
    point clouds. A second MGN row for a like-for-like comparison with the paper's numbers."""

    def __init__(self, connectivity: str | dict = "plate_mgn_shared", point_probability: float = 0.0,
                 **kwargs):
        super().__init__(connectivity=connectivity, point_probability=point_probability, **kwargs)


MODELS = {"ggns": GGNS, "ggns_lstm": GGNSLSTM, "mgn": MGN, "mgn_m": MGNM, "mgn_shared": MGNShared, "ggns_m": GGNSM,
          "ggns_id": GGNSID}


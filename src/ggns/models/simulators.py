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

A class fixes what the model reads and carries (point clouds, the material, an LSTM state, class
attributes); it is built from parts: the connectivity (which edges), the processor layout
(`PROCESSORS`: "shared", GGNS's one-hot types into shared encoders and one processor, or "per_type",
MGN's per-type encoders and edge MLPs; each class defaults to the paper's), the training noise
(`TrainingNoise`) and the learning-rate schedule (`LRSchedule`). The model predicts the displacement
x_{t+1} - x_t of every mesh node from the graph of state t (`TrajectoryBatch.graph`); fixed nodes take
their known positions and are left out of the loss. Training adds noise to the free input positions
and corrects the target, so the model learns to return to the true next state. Input features and targets are standardized with
statistics from one pass over the training data at the start of `fit` (`statistics_batches`
limits it), which are saved with the checkpoint. Under DDP every process makes the pass over its own
share of the windows and the statistics are merged across processes (exact, `Normalizer.merge`), so
all ranks normalize alike and as one process over the same windows would.

What a run does around the model is in callbacks: `RandomState` keeps the random generators' states
in a fit's checkpoints so that a resumed fit repeats the uninterrupted one, `evaluation.callbacks.
TestReport` writes the test metrics beside the logs (`ggns.cli` adds both to every run).

Checkpoints hold the hyperparameters as plain values (components as dicts); those written before
the components existed (flat `noise_std`, `lr_decay_rate`, `type_partition`, ...) are converted when
read (`upgrade_hparams`).
"""
from __future__ import annotations

import dataclasses
import inspect
import warnings
from pathlib import Path
from typing import Any, Literal

import pytorch_lightning as pl
from pytorch_lightning.strategies import DDPStrategy
import torch
from torch import Tensor, nn
from torch_geometric.data import HeteroData

from ..evaluation.capture import StaticStep
from .static_training import StaticTrainStep
from ..evaluation.evaluate import MetricTable, evaluate_batch
from ..reports import metrics_markdown
from ..evaluation.rollout import rollout
from ..evaluation.schedules import EveryK, Schedule, effective_schedule, parse_schedule
from ..batch import TrajectoryBatch
from ..checkpoints import CHECKPOINT_FORMAT, FORMAT_KEY, CheckpointError, check_format, read_checkpoint
from ..checks import DeferredCheck
from ..graphs.build import NeighbourCheck
from ..graphs.connectivity import Connectivity, load_connectivity
from ..graphs.state import state_graph
from ..graphs.types import MESH_EDGE
from ..phases import host_side, phase
from .core import EncodeProcessDecode, graph_features, inverse_counts
from .lr_schedule import LRSchedule
from .normalization import DEFAULT_STD_FLOOR, Normalizer, merge_across
from .training_noise import TrainingNoise, smooth_field

LstmState = tuple[Tensor, Tensor] | None

# the processor layouts: name -> (one edge MLP per edge type, node type encoding)
PROCESSORS = {"shared": (False, "one_hot"), "per_type": (True, "per_type")}

# init arguments of the simulators before the parts: old flat name -> the part's field
_FLAT_NOISE = {"noise_std": "std", "noise_field_std": "field_std", "noise_field_wavelength": "field_wavelength",
               "noise_field_mixture": "field_mixture", "noise_field_points_only": "field_points_only",
               "noise_field_decay_steps": "field_decay_steps"}
_FLAT_LR = {"lr": "lr", "lr_final": "final", "lr_decay_rate": "decay_rate", "lr_decay_steps": "decay_steps",
            "lr_warmup_steps": "warmup_steps"}
RENAMED_ARGS = {**{k: f"noise.{v}" for k, v in _FLAT_NOISE.items()},
                **{k: f"lr_schedule.{v}" for k, v in _FLAT_LR.items()},
                "type_partition": "processor (\"per_type\" for true, \"shared\" for false)"}


def upgrade_hparams(hparams: dict) -> dict:
    """A simulator's hyperparameters as this version's init arguments: the flat training-noise,
    lr-schedule and `type_partition` arguments of checkpoints written before the components
    (`TrainingNoise`, `LRSchedule`, `processor`) moved into them; anything else is kept as it is."""
    out = {k: v for k, v in hparams.items() if k not in _FLAT_NOISE and k not in _FLAT_LR and k != "type_partition"}
    noise = {field: hparams[old] for old, field in _FLAT_NOISE.items() if old in hparams}
    schedule = {field: hparams[old] for old, field in _FLAT_LR.items() if old in hparams}
    if noise:
        out["noise"] = {**dict(out.get("noise") or {}), **noise}
    if schedule:
        out["lr_schedule"] = {**dict(out.get("lr_schedule") or {}), **schedule}
    if hparams.get("type_partition") is not None:
        out["processor"] = "per_type" if hparams["type_partition"] else "shared"
    return out


def refuse_distributed(trainer, stage: str) -> None:
    """Refuse a run that cannot work with `trainer`'s processes, before it starts them when called early
    (the CLI) or on every rank (the model's setup): a fit under DDP without find_unused_parameters (a batch
    without contact or without a point cloud leaves the edge MLPs of that edge type without a gradient,
    and plain DDP then waits for it forever; it hung on the plate), and test or predict in more than one
    process (Lightning's distributed sampler would give each process part of the split, padded with
    repeats, and the metrics or predictions written would be one process's part). Raises ValueError."""
    strategy = trainer.strategy
    if stage == "fit" and isinstance(strategy, DDPStrategy) and \
            not getattr(strategy, "_ddp_kwargs", {}).get("find_unused_parameters", False):
        raise ValueError("DDP needs find_unused_parameters: a batch without contact or point clouds leaves the "
                         "edge MLPs of that edge type unused, and plain DDP waits for their gradients forever; "
                         "use --trainer.strategy ddp_find_unused_parameters_true")
    if stage in ("test", "predict") and trainer.world_size > 1:
        raise ValueError(f"{stage} runs in one process (it writes metrics and predictions of the whole split); "
                         f"use --trainer.devices 1 (this run has {trainer.world_size} processes)")


class GraphSimulator(pl.LightningModule):
    """Shared base (module docstring).

    Args:
        connectivity: graph preset (conf/graphs/<name>.yaml) or YAML path.
        dim: spatial dimension of the scene (2 or 3).
        latent: width of every latent vector of the core (paper: 128).
        blocks: message-passing blocks of the processor (paper: 5).
        mlp_layers: hidden layers of every MLP (paper: 1).
        processor: the processor layout, "shared" or "per_type" (`PROCESSORS`); None: the class's
            default (the paper's: GGNS "shared", MGN "per_type"). The paper's "MGN (1H)" ablation is MGN
            with "shared".
        point_probability: chance that a training sample (a window for the LSTM) gets its point clouds.
        noise: the training noise (`TrainingNoise`, or a mapping of its fields; paper: std 0.01).
        lr_schedule: Adam's learning rate per optimizer step (`LRSchedule`, or a mapping of its fields;
            paper: a constant 5e-4).
        window: transitions per training sample (backpropagation through time for the LSTM).
        eval_schedules: point-cloud schedules of the test rollouts ("every:K", "first:M", "never").
        test_m_plus_10: also compute the m+10-step error in `test`.
        test_iou: also compute the IoU in `test` (2D: areas; 3D: volumes, every 10th state).
        statistics_batches: training batches in the normalization pass (None: the whole split).
        std_floor: lower bound of every normalization std (see `normalization.DEFAULT_STD_FLOOR`).
    """

    default_processor = "shared"  # the processor layout of the class in the paper (`PROCESSORS`)
    recurrent = False  # LSTM between processor and decoder
    backprop_steps: int | None = None  # truncated backpropagation (GGNSLSTM)
    with_material = False  # Poisson's ratio as a mesh node feature, from the data (MGN(M))
    material_input = False  # a material column that the model fills itself (GGNSID), not the graph

    def __init__(self, connectivity: str = "plate_full_graph", dim: int = 2, latent: int = 128, blocks: int = 5,
                 mlp_layers: int = 1, processor: Literal["shared", "per_type"] | None = None, point_probability: float = 0.5,
                 noise: TrainingNoise = TrainingNoise(), lr_schedule: LRSchedule = LRSchedule(), window: int = 1,
                 eval_schedules: tuple[str, ...] = ("every:1", "every:2", "every:5", "every:10", "never"),
                 test_m_plus_10: bool = True, test_iou: bool = True, statistics_batches: int | None = None,
                 std_floor: float = DEFAULT_STD_FLOOR):
        super().__init__()
        self.noise, self.lr_schedule = TrainingNoise.of(noise), LRSchedule.of(lr_schedule)
        self.save_hyperparameters()
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim}")
        if not 0.0 <= point_probability <= 1.0:
            raise ValueError(f"point_probability must lie in [0, 1], got {point_probability}")
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        if processor is not None and processor not in PROCESSORS:
            raise ValueError(f"processor must be one of {sorted(PROCESSORS)} (or None: the class's "
                             f"{self.default_processor!r}), got {processor!r}")
        self.processor = processor or self.default_processor
        self.connectivity: Connectivity = load_connectivity(connectivity)
        if self.noise.field_points_only and not self.connectivity.uses_points:
            raise ValueError(f"noise.field_points_only needs point clouds, and connectivity {connectivity!r} has no "
                             f"point edges")
        if point_probability > 0 and not self.connectivity.uses_points:
            raise ValueError(f"point_probability={point_probability} but connectivity {connectivity!r} has no point "
                             f"edges; set point_probability=0 or use a connectivity with point radii")
        if point_probability == 0 and self.connectivity.uses_points:
            raise ValueError(f"point_probability=0 but connectivity {connectivity!r} has point edges: the model would "
                             f"never see a point cloud in training, yet evaluation feeds them; use p > 0 or a "
                             f"connectivity without point radii")
        self.schedules: list[Schedule] = [parse_schedule(s) for s in eval_schedules]
        self.window = window
        self.core = EncodeProcessDecode(*self.input_dims(self.connectivity, dim, self.with_material or self.material_input),
                                        out_dim=dim,
                                        latent=latent, blocks=blocks, mlp_layers=mlp_layers,
                                        **self.processor_layout(),
                                        std_floor=std_floor)
        self.target_normalizer = Normalizer(dim, std_floor)
        self.lstm = nn.LSTMCell(latent, latent) if self.recurrent else None
        self._test_table: MetricTable | None = None
        self.static_rollouts, self._static_step = False, None  # `rollout_step`
        self.static_training, self._static_train = False, None  # `training_step`
        # the most edges of each type per graph in a batch of the statistics pass (`fit_normalizers`): where the
        # static training step's edge capacities start (not saved: a resumed fit measures its first batch)
        self.statistics_edges: dict = {}
        # the hot path's checks, read at logging intervals (`raise_if_checks_failed`), not in every step
        self.loss_check = DeferredCheck()
        self.neighbour_check = NeighbourCheck(self.connectivity, what="training")

    @staticmethod
    def input_dims(connectivity: Connectivity, dim: int, with_material: bool) -> tuple[dict, dict]:
        """Input width per node and edge type a model with this connectivity sees (see `graphs.build`)."""
        node_dims = {"mesh": 2 if with_material else 1, "collider": dim}
        if connectivity.uses_points:
            node_dims["point"] = 0
        edge_dims = {MESH_EDGE: 2 * (dim + 1)}
        for edge_type, r in connectivity.radii().items():
            if r > 0 and edge_type[0] in node_dims and edge_type[2] in node_dims:
                edge_dims[edge_type] = dim + 1
        return node_dims, edge_dims

    def save_hyperparameters(self, *args, ignore=None, frame=None, logger: bool = True) -> None:
        """Lightning's, with the components kept as dicts of their fields: checkpoints hold plain values
        (`ggns.checkpoints`), and a subclass that saves its own arguments keeps them so too."""
        super().save_hyperparameters(*args, ignore=ignore, frame=frame or inspect.currentframe().f_back,
                                     logger=logger)
        for key in ("noise", "lr_schedule"):
            if key in self.hparams:
                self.hparams[key] = dataclasses.asdict(getattr(self, key))

    def processor_layout(self) -> dict:
        """`EncodeProcessDecode`'s layout arguments for this model's `processor`."""
        edge_partition, type_encoding = PROCESSORS[self.processor]
        return {"edge_partition": edge_partition, "type_encoding": type_encoding}

    @property
    def edge_partition(self) -> bool:
        """One edge MLP per edge type (the "per_type" processor)."""
        return PROCESSORS[self.processor][0]

    @property
    def uses_points(self) -> bool:
        return self.connectivity.uses_points

    # ---- prediction -------------------------------------------------------------------------
    def predict_normalized(self, graph: HeteroData, state: LstmState = None) -> tuple[Tensor, LstmState]:
        """Graph -> (normalized displacement [N_mesh, d], new LSTM state or None)."""
        latents = self.core.encode_process(graph)
        if self.lstm is not None:
            if state is None:
                state = (latents.new_zeros(latents.shape), latents.new_zeros(latents.shape))
            state = self.lstm(latents, state)
            latents = state[0]
        return self.core.decode(latents), state

    def step(self, graph: HeteroData, state: LstmState = None) -> tuple[Tensor, LstmState]:
        """The rollout step function: graph of state t -> (displacement [N_mesh, d] in task units, state)."""
        out, state = self.predict_normalized(graph, state)
        return self.target_normalizer.inverse(out), state

    def forward(self, graph: HeteroData) -> Tensor:
        """Displacement of every mesh node [N_mesh, d] for a single step (no recurrent state)."""
        return self.step(graph)[0]

    def rollout_step(self):
        """The step function `evaluate`, `rollout` and `predict` roll out with: `step`, or with `static_rollouts`
        set (a runtime setting, e.g. by the `StaticRollouts` callback) a `StaticStep`: the whole step (graph,
        model, integration, checks) on static shapes, captured as a CUDA graph on a GPU (`evaluation.capture`;
        kept between calls, so validations reuse it; dropped when the weights are loaded anew or moved or
        cast, `_apply`, `_load_from_state_dict`)."""
        if not self.static_rollouts:
            return self.step
        device = next(self.parameters()).device
        if self._static_step is None or self._static_step.device != device:
            self._static_step = StaticStep(self)
        return self._static_step

    def _apply(self, fn, *args, **kwargs):
        self._static_step = self._static_train = None  # a recorded step reads the old tensors' memory
        return super()._apply(fn, *args, **kwargs)

    def _load_from_state_dict(self, *args, **kwargs) -> None:
        # the normalizers' cached masks are made anew: a recording would read freed ones
        self._static_step = self._static_train = None
        super()._load_from_state_dict(*args, **kwargs)

    def static_train_step(self) -> StaticTrainStep:
        """The static training step (`models.static_training`), kept between steps (dropped like `rollout_step`'s)."""
        device = next(self.parameters()).device
        if self._static_train is None or self._static_train.device != device:
            self._static_train = StaticTrainStep(self)
        return self._static_train

    # ---- training -------------------------------------------------------------------------
    def training_graphs(self, batch: TrajectoryBatch, train: bool = True) -> list[tuple[HeteroData, Tensor]]:
        """(graph, target displacement [sumN, d]) for each transition of a window batch. train: noise
        and per-window imputation draws; otherwise no noise and point clouds whenever the model uses them.
        The imputation draws come from the host's generator, so which windows see their points is known
        without reading the device (`graphs.state.select_points`)."""
        if train and self.uses_points:
            use_points = host_side(torch.rand(batch.num_graphs) < self.hparams.point_probability)
        else:
            use_points = self.uses_points
        free = ~batch.fixed[:, None]
        samples = []
        self.neighbour_check.step = self.global_step
        for t in range(batch.num_steps - 1):
            pos = batch.positions[t]
            if train:
                pos = self.noise.perturb(pos, free, batch.rest, batch.mesh_batch, batch.num_graphs, self.global_step,
                                         use_points)
            graph = state_graph(batch, t, pos, use_points, self.connectivity, self.with_material, self.neighbour_check)
            samples.append((graph, batch.positions[t + 1] - pos))
        return samples

    def window_loss(self, batch: TrajectoryBatch, train: bool = True,
                    by_points: bool = False) -> Tensor | tuple[Tensor, dict[str, Tensor]]:
        """Mean over the window's transitions of the normalized-target MSE on free mesh nodes. by_points:
        also {"points": ..., "no_points": ...}, the mean per-sample loss (one window's free nodes at one
        transition) of the graphs with / without a point cloud, a group absent from the batch left out.
        A non-finite loss is recorded in `loss_check` (read by `raise_if_checks_failed`), not raised here."""
        free = batch.free_index
        if len(free) == 0:
            raise ValueError("batch has no free mesh nodes: nothing to train on")
        state, losses, samples, with_points, present = None, [], [], [], set()
        if by_points:  # the graph of each free node, and 1 / free nodes per graph
            owner = batch.mesh_batch.index_select(0, free)
            inv_free = inverse_counts(owner, batch.num_graphs, batch.positions)[:, 0]
        burn_in = batch.num_steps - 1 - self.backprop_steps if self.backprop_steps else 0
        for t, (graph, target) in enumerate(self.training_graphs(batch, train)):
            if t < burn_in:  # truncated backpropagation: these steps only carry the recurrent state forward
                with torch.no_grad():
                    _, state = self.predict_normalized(graph, state)
                continue
            out, state = self.predict_normalized(graph, state)
            with phase("loss"):
                squared = (out.index_select(0, free) - self.target_normalizer(target.index_select(0, free))).square()
                extra = self.auxiliary_loss(graph, batch, t, train)
                loss = squared.mean() if extra is None else squared.mean() + extra
            with phase("checks"):
                self._record_loss(loss, squared, free, batch, t)
            losses.append(loss)
            if by_points:
                error = squared.mean(dim=1)
                per_graph = error.new_zeros(batch.num_graphs)
                samples.append(per_graph.index_add_(0, owner, error) * inv_free)
                has = torch.zeros(batch.num_graphs, dtype=torch.bool, device=error.device)
                if "point" in graph.node_types:
                    has[graph["point"].batch] = True
                with_points.append(has)
                present |= set(graph.points_seen)
        loss = torch.stack(losses).mean() if len(losses) > 1 else losses[0]
        if not by_points:
            return loss
        samples, with_points = torch.cat(samples), torch.cat(with_points).to(samples[0].dtype)
        groups = {name: (samples * mask).sum() / mask.sum() for name, mask, seen in
                  (("points", with_points, True), ("no_points", 1 - with_points, False)) if seen in present}
        return loss, groups

    def _record_loss(self, loss: Tensor, squared: Tensor, free: Tensor, batch: TrajectoryBatch, t: int) -> None:
        """Record in `loss_check` whether transition t's loss is non-finite, with its value, the trajectory
        of the batch and the mesh node (within it) of the first free node whose squared error is not finite."""
        bad = ~torch.isfinite(squared).all(dim=1)
        first = free.index_select(0, bad.to(torch.uint8).argmax().view(1))  # [1]: no read of a device scalar
        trajectory = batch.mesh_batch.index_select(0, first)[0]
        node = first[0] - (batch.mesh_batch < trajectory).sum()
        self.loss_check.record(~torch.isfinite(loss.detach()), self.global_step, loss.detach(), trajectory, node,
                               torch.full((), t, device=loss.device))

    def raise_if_checks_failed(self) -> None:
        """Read the deferred checks of the steps so far (one sync): a non-finite training loss raises
        FloatingPointError naming the global step, the trajectory of the batch and the node; a node over the
        neighbour cap raises the graph builder's ValueError naming the step."""
        if self._static_train is not None:
            self._static_train.read_capacities()
        self.neighbour_check.raise_if_failed()
        failure = self.loss_check.failure()
        if failure is not None:
            self.loss_check.reset()
            value, trajectory, node, t = failure.detail
            raise FloatingPointError(f"non-finite training loss {value} at global step {failure.step} (transition {t} "
                                     f"of the window; the first non-finite error: mesh node {node} of trajectory "
                                     f"{trajectory} of the batch)")

    def auxiliary_loss(self, graph: HeteroData, batch: TrajectoryBatch, t: int = 0,
                       train: bool = False) -> Tensor | None:
        """A loss added to a transition's (normalized) MSE, for models with a second head (GGNSID). graph:
        the sample of transition t of `batch`; train: a training sample (noise allowed)."""
        return None

    def update_statistics(self, graph: HeteroData, batch: TrajectoryBatch) -> None:
        """More normalization statistics from a training graph, for models with more normalizers."""

    def training_step(self, batch: TrajectoryBatch, batch_idx: int) -> Tensor:
        if self.static_training:
            return self._static_training_step(batch)
        loss, groups = self.window_loss(batch, train=True, by_points=True)
        sync = self._world_size() > 1  # under DDP the logged loss is the mean over the ranks' batches
        # not on the progress bar: Lightning reads progress-bar values back from the device after every batch
        self.log("train/loss", loss, batch_size=batch.num_graphs, sync_dist=sync)
        for name, value in groups.items():  # a group absent from one rank's batch: that rank's value alone
            self.log(f"train/loss_{name}", value.detach(), batch_size=batch.num_graphs)
        return loss

    def _static_training_step(self, batch: TrajectoryBatch) -> Tensor:
        """One optimizer step by the static training step (manual optimization: the `StaticTraining` callback);
        Lightning's step count advances through its optimizer wrapper's hooks, and the lr schedule steps after."""
        optimizer = self.optimizers()
        step = self.static_train_step()
        optimizer._on_before_step()
        loss = step.step(batch, optimizer.optimizer).clone()  # the step's buffer: the next step overwrites it
        optimizer._on_after_step()
        scheduler = self.lr_schedulers()
        if scheduler is not None:
            scheduler.step()
        self.log("train/loss", loss, batch_size=batch.num_graphs)  # one process (`StaticTraining` refuses DDP)
        use = step.last_use
        groups = step.buffers.groups.clone()
        for name, value, present in (("points", groups[0], use is not None and bool(use.any())),
                                     ("no_points", groups[1], use is None or not bool(use.all()))):
            if present:
                self.log(f"train/loss_{name}", value, batch_size=batch.num_graphs)
        return loss

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        """The deferred checks are read when Lightning logs (every `log_every_n_steps`), where it reads the
        device anyway."""
        every = self.trainer.log_every_n_steps if self._trainer is not None else 1
        if self.global_step % max(every, 1) == 0:
            self.raise_if_checks_failed()

    def on_train_epoch_end(self) -> None:
        self.raise_if_checks_failed()

    def on_validation_epoch_end(self) -> None:
        self.raise_if_checks_failed()

    def on_train_end(self) -> None:
        self.raise_if_checks_failed()

    def validation_step(self, batch: TrajectoryBatch, batch_idx: int) -> None:
        # under DDP each rank validates its share of the windows: the logged loss is the ranks' mean, so that
        # every rank's checkpoint callbacks see the same value
        self.log("val/loss", self.window_loss(batch, train=False), batch_size=batch.num_graphs, prog_bar=True,
                 sync_dist=self._world_size() > 1)

    def configure_optimizers(self):
        """Adam with the `lr_schedule` stepped after every optimizer step; its lr is logged as `train/lr`
        (by the LearningRateMonitor that `ggns.cli` adds to every CLI fit with a logger)."""
        return self.lr_schedule.optimizers(self.parameters())

    @torch.no_grad()
    def fit_normalizers(self, batches) -> int:
        """Statistics of inputs and targets over `batches` (training-time sampling), then freeze.
        Returns the number of samples seen."""
        count = 0
        for i, batch in enumerate(batches):
            if self.hparams.statistics_batches is not None and i >= self.hparams.statistics_batches:
                break
            batch = batch.to(self.device)
            free = ~batch.fixed
            for graph, target in self.training_graphs(batch, train=True):
                self.core.input_normalizer.update(graph_features(graph))
                self.target_normalizer.update(target[free])
                self.update_statistics(graph, batch)
                count += batch.num_graphs
                for edge_type in graph.edge_types:  # where the static training step's capacities start
                    per_graph = graph[edge_type].edge_index.size(1) / batch.num_graphs
                    self.statistics_edges[edge_type] = max(self.statistics_edges.get(edge_type, 0.0), per_graph)
        if count == 0:
            raise ValueError("no training samples for the normalization statistics")
        if self._world_size() > 1:  # each rank saw its own windows: merge, so that every rank normalizes alike
            merge_across([m for m in self.modules() if isinstance(m, Normalizer)], self.all_gather)
        for normalizer in self.modules():
            if isinstance(normalizer, Normalizer):
                normalizer.freeze()
        return count

    def setup(self, stage: str) -> None:
        """Refuse what `refuse_distributed` names (the CLI refuses it before any process starts; this is
        for a Trainer built in Python)."""
        if self._trainer is not None:
            refuse_distributed(self.trainer, getattr(stage, "value", stage))  # Lightning passes a TrainerFn

    def on_fit_start(self) -> None:
        if self.target_normalizer.frozen:  # resumed or fine-tuned: statistics come from the checkpoint
            return
        datamodule = self.trainer.datamodule
        if datamodule is None:
            raise RuntimeError("fit needs a datamodule (SimulationDataModule) for the normalization pass")
        dim = datamodule.dim
        if dim != self.hparams.dim:
            raise ValueError(f"model dim={self.hparams.dim} but the dataset {datamodule.data_dir} is {dim}D")
        self.fit_normalizers(datamodule.train_dataloader())

    # ---- evaluation -------------------------------------------------------------------------
    def evaluate(self, batch: TrajectoryBatch, schedules: list[Schedule | str] | None = None,
                 **kwargs: Any) -> dict[str, Tensor]:
        """Per-trajectory paper metrics of this model on `batch` (`evaluation.evaluate_batch`).

        Args:
            batch: B trajectories of T states each (`TrajectoryBatch.from_trajectories`).
            schedules: point-cloud schedules of the full rollouts ("every:K", "first:M", "never" or
                `Schedule` objects); default: the model's `eval_schedules`.
            **kwargs: `evaluate_batch`'s options (`m_plus_10`, `iou`, ...).

        Returns:
            metric name (`one_step_mse`, `rollout_mse_k1`, `rollout_iou_k1`, ..., `rollout_mse_never`,
            `m10_mse` when computed) -> a [B] tensor, one value per trajectory (MSE in squared
            task-space units).
        """
        schedules = self.schedules if schedules is None else [parse_schedule(s) for s in schedules]
        one_step = effective_schedule(EveryK(1), self.uses_points)
        with torch.no_grad():
            return evaluate_batch(self.rollout_step(), batch, self.connectivity, schedules,
                                  with_material=self.with_material,
                                  one_step_schedule=one_step, **kwargs)

    def rollout(self, batch: TrajectoryBatch, schedule: Schedule | str) -> Tensor:
        """A rollout of every trajectory of `batch` from its first state S_0.

        Args:
            batch: B trajectories of T states each, N_b mesh nodes in trajectory b.
            schedule: when the model sees the point cloud: "every:K", "first:M", "never" or a `Schedule`.

        Returns:
            the predicted mesh positions, [T, sum_b N_b, d] (d = 2 or 3), trajectories concatenated
            along the node axis as in `batch.mesh_batch`; step 0 is S_0.
        """
        schedule = parse_schedule(schedule)
        with torch.no_grad():
            return rollout(self.rollout_step(), batch, schedule, self.connectivity, self.with_material)[0]

    def on_test_epoch_start(self) -> None:
        self._test_table = MetricTable()

    def test_step(self, batch: TrajectoryBatch, batch_idx: int) -> None:
        self._test_table.add(self.evaluate(batch, m_plus_10=self.hparams.test_m_plus_10, iou=self.hparams.test_iou))

    def on_test_epoch_end(self) -> None:
        """`test_results`: metric name -> {"mean", "std", ...} over the test trajectories (each mean logged
        as `test/<name>`); the `TestReport` callback writes them beside the logs."""
        summary = self._test_table.summary()
        for name, s in summary.items():
            self.log(f"test/{name}", s["mean"])
        print("\n" + metrics_markdown(summary, f"{type(self).__name__} test metrics"))
        self.test_results = summary

    def predict_step(self, batch: TrajectoryBatch, batch_idx: int) -> dict[str, Any]:
        """Rollouts of the first eval schedule: {"schedule", "positions" [T, sumN, d], "node_offsets"}."""
        return {"schedule": str(self.schedules[0]), "positions": self.rollout(batch, self.schedules[0]).cpu(),
                "node_offsets": batch.node_offsets}

    # ---- checkpoints -------------------------------------------------------------------------
    def _world_size(self) -> int:
        return self._trainer.world_size if self._trainer is not None else 1

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        self.raise_if_checks_failed()  # a step since the last read that went non-finite is never saved
        checkpoint["connectivity"] = dataclasses.asdict(self.connectivity)
        checkpoint["simulator_class"] = type(self).__name__
        checkpoint[FORMAT_KEY] = CHECKPOINT_FORMAT

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        check_format(checkpoint, "the checkpoint")
        saved = checkpoint.get("connectivity")
        if saved is not None:  # written before the search was a setting: this model's search
            saved = {"search": self.connectivity.search, **saved}
        if saved is not None and saved != dataclasses.asdict(self.connectivity):
            warnings.warn(f"connectivity preset {self.hparams.connectivity!r} changed since the checkpoint was "
                          f"written; using the checkpoint's radii {saved}", stacklevel=2)
            self.connectivity = Connectivity.from_dict(saved)
            self.neighbour_check = NeighbourCheck(self.connectivity, what="training")


class GGNS(GraphSimulator):
    """Grounding Graph Network Simulator (one-hot types, shared processor, imputation training)."""

    def __init__(self, connectivity: str = "plate_full_graph", point_probability: float = 0.5, **kwargs):
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

    def __init__(self, connectivity: str = "plate_full_graph", point_probability: float = 0.5,
                 estimator_latent: int = 32, estimator_blocks: int = 3, material_loss_weight: float = 1.0,
                 estimator_noise_std: float = 0.0, **kwargs):
        super().__init__(connectivity=connectivity, point_probability=point_probability, **kwargs)
        self.save_hyperparameters()
        if not self.uses_points:
            raise ValueError(f"GGNSID estimates the material from point clouds, and connectivity {connectivity!r} "
                             f"has no point edges")
        if estimator_latent < 1 or estimator_blocks < 1 or material_loss_weight < 0 or estimator_noise_std < 0:
            raise ValueError(f"need estimator_latent >= 1, estimator_blocks >= 1, material_loss_weight >= 0 and "
                             f"estimator_noise_std >= 0; got {estimator_latent}, {estimator_blocks}, "
                             f"{material_loss_weight}, {estimator_noise_std}")
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
        with `estimator_noise_std`, its mesh moved by a smooth field on the free nodes, with the same point
        clouds, rebuilt (the point-mesh edges follow the moved mesh)."""
        std = self.hparams.estimator_noise_std
        if std == 0:
            return graph
        has = torch.zeros(batch.num_graphs, dtype=torch.bool, device=batch.device)
        has[graph["point"].batch] = True
        field = smooth_field(batch.rest, batch.mesh_batch, batch.num_graphs, std, self.noise.field_wavelength,
                             mixture=True)
        pos = graph["mesh"].pos + field * ~batch.fixed[:, None]
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

    def __init__(self, connectivity: str = "plate_full_graph", point_probability: float = 0.5, window: int = 5,
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

    def __init__(self, connectivity: str = "plate_mgn", point_probability: float = 0.0,
                 eval_schedules: tuple[str, ...] = ("never",), **kwargs):
        super().__init__(connectivity=connectivity, point_probability=point_probability,
                         eval_schedules=eval_schedules, **kwargs)


class MGNM(MGN):
    """MGN(M): MGN given the material (Poisson's ratio as a mesh node feature)."""

    with_material = True


class MGNShared(GraphSimulator):
    """The authors' own plate MGN baseline: GGNS's architecture (one-hot node and edge types into
    shared encoders, one shared processor) on mesh and collider edges only, no world edges, no
    point clouds. A second MGN row for a like-for-like comparison with the paper's numbers."""

    def __init__(self, connectivity: str = "plate_mgn_shared", point_probability: float = 0.0,
                 eval_schedules: tuple[str, ...] = ("never",), **kwargs):
        super().__init__(connectivity=connectivity, point_probability=point_probability,
                         eval_schedules=eval_schedules, **kwargs)


MODELS = {"ggns": GGNS, "ggns_lstm": GGNSLSTM, "mgn": MGN, "mgn_m": MGNM, "mgn_shared": MGNShared, "ggns_m": GGNSM,
          "ggns_id": GGNSID}


def load_simulator(path: str | Path, map_location=None) -> GraphSimulator:
    """Any of the simulators from a Lightning checkpoint written by this library, in eval mode, read
    as data only (`ggns.checkpoints`: a file that would run code is refused with CheckpointError, and
    so is one of another checkpoint format). The class is stored in the checkpoint
    ("simulator_class"); for checkpoints without it the class whose parameters load strictly is used
    (their parameter sets differ). Hyperparameters of checkpoints written before the components are
    converted (`upgrade_hparams`)."""
    checkpoint = read_checkpoint(path, map_location="cpu")
    check_format(checkpoint, path)
    if "hyper_parameters" not in checkpoint or "state_dict" not in checkpoint:
        raise CheckpointError(f"{path}: not a Lightning checkpoint of a ggns simulator")
    classes = {cls.__name__: cls for cls in MODELS.values()}
    name = checkpoint.get("simulator_class")
    if name is not None:
        if name not in classes:
            raise CheckpointError(f"{path}: unknown simulator_class {name!r} (known: {sorted(classes)})")
        return from_checkpoint(classes[name], checkpoint, map_location)
    errors = []
    for cls in classes.values():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return from_checkpoint(cls, checkpoint, map_location)
        except (RuntimeError, KeyError, TypeError, ValueError) as error:
            errors.append(f"{cls.__name__}: {str(error).splitlines()[0][:120]}")
    raise CheckpointError(f"{path}: no simulator class loads this checkpoint ({'; '.join(errors)})")


def from_checkpoint(cls: type[GraphSimulator], checkpoint: dict, map_location=None) -> GraphSimulator:
    """A `cls` built from a checkpoint dict's (upgraded) hyperparameters with its weights loaded strictly,
    in eval mode."""
    hparams = {k: v for k, v in upgrade_hparams(checkpoint["hyper_parameters"]).items() if not k.startswith("_")}
    model = cls(**hparams)
    model.on_load_checkpoint(checkpoint)
    model.load_state_dict(checkpoint["state_dict"], strict=True)
    return (model.to(map_location) if map_location is not None else model).eval()

"""`GraphSimulator`: the LightningModule every simulator of `simulators.py` is.

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
in a fit's checkpoints so that a resumed fit repeats the uninterrupted one; the rollout evaluations
(`ggns.callbacks`: validation metrics, test metrics and their report, predictions) roll out
through the model's step and know the schedules; the model knows no schedule, metric table or report.

Checkpoints hold the hyperparameters as plain values (components as dicts); `loading.py` reads them and
converts those of older versions (`upgrade_hparams`).
"""
from __future__ import annotations

import dataclasses
import inspect
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import pytorch_lightning as pl
from pytorch_lightning.strategies import DDPStrategy
import torch
from torch import Tensor, nn
from torch_geometric.data import HeteroData

from ..evaluation.capture import StaticStep
from .static_training import StaticTrainStep
from ..evaluation.evaluate import evaluate_model
from ..evaluation.rollout import rollout
from ..evaluation.schedules import Schedule, parse_schedule
from ..batch import TrajectoryBatch
from ..checkpoints import CHECKPOINT_FORMAT, FORMAT_KEY, check_format
from ..checks import DeferredCheck
from ..graphs.build import NeighbourCheck
from ..graphs.connectivity import Connectivity, load_connectivity
from ..graphs.state import state_graph
from ..graphs.types import MESH_EDGE
from ..phases import host_side, phase
from .core import EncodeProcessDecode, graph_features, inverse_counts
from .lr_schedule import LRSchedule
from .normalization import DEFAULT_STD_FLOOR, Normalizer, merge_across
from .training_noise import TrainingNoise

LstmState = tuple[Tensor, Tensor] | None

# the processor layouts: name -> (one edge MLP per edge type, node type encoding)
PROCESSORS = {"shared": (False, "one_hot"), "per_type": (True, "per_type")}

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
        connectivity: graph preset (conf/graphs/<name>.yaml), a YAML path, or the preset's values (a mapping of
            `Connectivity`'s fields); the hyperparameters keep the values, so a checkpoint is self-contained.
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
        statistics_batches: training batches in the normalization pass (None: the whole split).
        std_floor: lower bound of every normalization std (see `normalization.DEFAULT_STD_FLOOR`).
    """

    default_processor = "shared"  # the processor layout of the class in the paper (`PROCESSORS`)
    recurrent = False  # LSTM between processor and decoder
    backprop_steps: int | None = None  # truncated backpropagation (GGNSLSTM)
    with_material = False  # Poisson's ratio as a mesh node feature, from the data (MGN(M))
    material_input = False  # a material column that the model fills itself (GGNSID), not the graph
    scene: str | None = None  # the scene of the training data, once loaded from a checkpoint that says

    def __init__(self, connectivity: str | dict = "plate_full_graph", dim: int = 2, latent: int = 128, blocks: int = 5,
                 mlp_layers: int = 1, processor: Literal["shared", "per_type"] | None = None, point_probability: float = 0.5,
                 noise: TrainingNoise = TrainingNoise(), lr_schedule: LRSchedule = LRSchedule(), window: int = 1,
                 statistics_batches: int | None = None,
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
        # a preset's name or path is resolved here, where it enters, and the hyperparameters keep its values: a
        # checkpoint loads where the preset file is not
        self.connectivity: Connectivity = (Connectivity.from_dict(dict(connectivity)) if isinstance(connectivity, Mapping)
                                           else load_connectivity(connectivity))
        self.hparams["connectivity"] = dataclasses.asdict(self.connectivity)
        connectivity = connectivity if isinstance(connectivity, str) else "given"
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
        self.window = window
        self.core = EncodeProcessDecode(*self.input_dims(self.connectivity, dim, self.with_material or self.material_input),
                                        out_dim=dim,
                                        latent=latent, blocks=blocks, mlp_layers=mlp_layers,
                                        **self.processor_layout(),
                                        std_floor=std_floor)
        self.target_normalizer = Normalizer(dim, std_floor)
        self.lstm = nn.LSTMCell(latent, latent) if self.recurrent else None
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
        """Lightning's, with the components kept as dicts of their fields (the connectivity's radii, not its preset's
        name): checkpoints hold plain values (`ggns.checkpoints`), and a subclass that saves its own arguments keeps
        them so too."""
        super().save_hyperparameters(*args, ignore=ignore, frame=frame or inspect.currentframe().f_back,
                                     logger=logger)
        for key in list(self.hparams):  # `noise`, `lr_schedule`, GGNSID's `estimator_noise`, `connectivity` once built
            if isinstance(getattr(self, key, None), (TrainingNoise, LRSchedule, Connectivity)):
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

    # ---- rollouts --------------------------------------------------------------------------
    def evaluate(self, batch: TrajectoryBatch, schedules: list[Schedule | str] | None = None,
                 **kwargs: Any) -> dict[str, Tensor]:
        """Per-trajectory paper metrics of this model on `batch` under each of `schedules` (default: the
        paper's five as this model runs them), `evaluation.evaluate.evaluate_model`'s, which the evaluation
        callbacks call (its arguments and return value), e.g. `model.evaluate(batch, ["every:1", "never"])`."""
        return evaluate_model(self, batch, schedules, **kwargs)

    def rollout(self, batch: TrajectoryBatch, schedule: Schedule | str) -> Tensor:
        """A rollout of every trajectory of `batch` from its first state S_0.

        Args:
            batch: B trajectories of T states each, N_b mesh nodes in trajectory b.
            schedule: when the model sees the point cloud: a `Schedule` (or "every:K", "first:M", "never").

        Returns:
            the predicted mesh positions, [T, sum_b N_b, d] (d = 2 or 3), trajectories concatenated
            along the node axis as in `batch.mesh_batch`; step 0 is S_0.
        """
        with torch.no_grad():
            return rollout(self.rollout_step(), batch, parse_schedule(schedule), self.connectivity,
                           self.with_material)[0]

    def test_step(self, batch: TrajectoryBatch, batch_idx: int) -> None:
        """Nothing of its own: `test`'s rollouts and metrics are the `TestEvaluation` callback's (the CLI
        adds it; a Trainer built in Python needs it among its callbacks, else this raises)."""
        self._require_callback("TestEvaluation", "test")

    def predict_step(self, batch: TrajectoryBatch, batch_idx: int) -> dict[str, int]:
        """`predict`'s rollouts are the `RolloutWriter` callback's (its `schedule`); this returns only how
        many trajectories the batch holds."""
        self._require_callback("RolloutWriter", "predict")
        return {"trajectories": batch.num_graphs}

    def _require_callback(self, name: str, stage: str) -> None:
        if not any(any(kind.__name__ == name for kind in type(c).__mro__) for c in self.trainer.callbacks):
            raise RuntimeError(f"{stage} needs the ggns.callbacks.{name} callback among the Trainer's "
                               f"callbacks (python -m ggns {stage} adds it); the model only rolls out")

    # ---- checkpoints -------------------------------------------------------------------------
    def _world_size(self) -> int:
        return self._trainer.world_size if self._trainer is not None else 1

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        self.raise_if_checks_failed()  # a step since the last read that went non-finite is never saved
        checkpoint["connectivity"] = dataclasses.asdict(self.connectivity)
        checkpoint["simulator_class"] = type(self).__name__
        datamodule = getattr(self._trainer, "datamodule", None) if self._trainer is not None else None
        scene = ((getattr(datamodule, "config", None) or {}).get("scene") or {}).get("name")
        if scene is not None:  # the training data's scene: what `evaluation.predict.check_model_fits` compares
            checkpoint["scene"] = str(scene)
        checkpoint[FORMAT_KEY] = CHECKPOINT_FORMAT

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        check_format(checkpoint, "the checkpoint")
        named = (checkpoint.get("hyper_parameters") or {}).get("connectivity")
        # the training data's scene (older checkpoints: the one their connectivity preset is named after)
        self.scene = checkpoint.get("scene") or (Path(named).stem.split("_")[0] if isinstance(named, str) else None)
        saved = checkpoint.get("connectivity")
        if saved is not None:  # written before the search was a setting: this model's search
            saved = {"search": self.connectivity.search, **saved}
        if saved is not None and saved != dataclasses.asdict(self.connectivity):
            warnings.warn(f"connectivity {dataclasses.asdict(self.connectivity)} differs from the checkpoint's; using "
                          f"the checkpoint's radii {saved}", stacklevel=2)
            self.connectivity = Connectivity.from_dict(saved)
            self.neighbour_check = NeighbourCheck(self.connectivity, what="training")

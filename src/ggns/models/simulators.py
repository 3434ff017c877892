"""The four learned simulators as LightningModules sharing one base, one core and one rollout engine.

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

A class fixes the model family (class attributes); its init args tune it. The model predicts
the displacement x_{t+1} - x_t of every mesh node from the graph of state t (`TrajectoryBatch.
graph`); fixed nodes take their known positions and are left out of the loss. Training adds
Gaussian noise (`noise_std`) to the free input positions and corrects the target, so the model
learns to return to the true next state. Input features and targets are standardized with
statistics from one pass over the training data at the start of `fit` (`statistics_batches`
limits it), which are saved with the checkpoint. Under DDP every process makes the pass over its own
share of the windows and the statistics are merged across processes (exact, `Normalizer.merge`), so
all ranks normalize alike and as one process over the same windows would.

A fit's checkpoint also holds the state of torch's random generator of every process (`RNG_KEY`:
the training noise and the imputation draws come from it); a fit resumed from it (`fit --ckpt_path`)
sets it back before its first batch, so that, with the data order `SimulationDataModule` resumes, the
resumed fit repeats what the uninterrupted one would have done (tests/test_faults.py).
"""
from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import Any

import pytorch_lightning as pl
from pytorch_lightning.strategies import DDPStrategy
import torch
from torch import Tensor, nn
from torch_geometric.data import HeteroData

from ..evaluation.capture import StaticStep
from ..evaluation.evaluate import MetricTable, evaluate_batch, metrics_markdown
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
from ..reports import write_json, write_text
from .core import EncodeProcessDecode, graph_features, inverse_counts
from .lr_schedule import scheduled_lr, validate_schedule
from .normalization import DEFAULT_STD_FLOOR, Normalizer, merge_across
from .training_noise import smooth_field

RNG_KEY = "ggns_rng_states"

LstmState = tuple[Tensor, Tensor] | None


def linear_decay(value: float, steps: int, step: int) -> float:
    """`value` falling linearly to 0 over `steps` (0: constant), at `step`."""
    return value * max(0.0, 1.0 - step / steps) if steps else value


class GraphSimulator(pl.LightningModule):
    """Shared base (module docstring). Args:
        connectivity: graph preset (conf/graphs/<name>.yaml) or YAML path.
        dim: spatial dimension of the scene (2 or 3).
        latent, blocks, mlp_layers: core size (paper: 128, 5, 1).
        point_probability: chance that a training sample (a window for the LSTM) gets its point clouds.
        noise_std: std of the training noise on free input mesh positions (task-space units).
        noise_field_std, noise_field_wavelength, noise_field_mixture: std, wavelength and per-graph scale
            mixture of a smooth random displacement field added on top (`training_noise.smooth_field`;
            std 0, the default, is the paper's noise alone).
        noise_field_points_only: the field only on training samples that get their point clouds (a blind
            step cannot see a smooth offset, so there it only adds unlearnable noise to the target).
        noise_field_decay_steps: the field's std falls linearly to 0 over this many optimizer steps
            (0, the default: constant).
        lr: Adam learning rate (paper: 5e-4).
        lr_final, lr_decay_rate, lr_decay_steps, lr_warmup_steps: schedule per optimizer step (`lr_schedule`):
            lr_final + (lr - lr_final) * lr_decay_rate ** (step / lr_decay_steps), times a linear warm-up over
            lr_warmup_steps; lr_decay_rate = 1 and no warm-up (the defaults) keep the paper's constant lr.
        window: transitions per training sample (backpropagation through time for the LSTM).
        eval_schedules: point-cloud schedules of the test rollouts ("every:K", "first:M", "never").
        test_m_plus_10, test_iou: also compute the m+10-step error and the IoU (2D: areas; 3D: volumes, every 10th state) in `test`.
        statistics_batches: training batches in the normalization pass (None: the whole split).
        std_floor: lower bound of every normalization std (see `normalization.DEFAULT_STD_FLOOR`).
        type_partition: True: MGN's per-type encoders and one edge MLP per edge type; False: GGNS's
            one-hot types into shared encoders and one shared processor; None: the class's own (the
            paper's: GGNS False, MGN True). The paper's "MGN (1H)" ablation is MGN with False.
    """

    edge_partition = False  # one edge MLP per edge type (MGN) or one shared processor (GGNS)
    type_encoding = "one_hot"  # "one_hot" (GGNS) or "per_type" encoders (MGN)
    recurrent = False  # LSTM between processor and decoder
    backprop_steps: int | None = None  # truncated backpropagation (GGNSLSTM)
    with_material = False  # Poisson's ratio as a mesh node feature, from the data (MGN(M))
    material_input = False  # a material column that the model fills itself (GGNSID), not the graph

    def __init__(self, connectivity: str = "plate_full_graph", dim: int = 2, latent: int = 128, blocks: int = 5,
                 mlp_layers: int = 1, point_probability: float = 0.5, noise_std: float = 0.01, lr: float = 5e-4,
                 window: int = 1, eval_schedules: tuple[str, ...] = ("every:1", "every:2", "every:5", "every:10", "never"),
                 test_m_plus_10: bool = True, test_iou: bool = True, statistics_batches: int | None = None,
                 std_floor: float = DEFAULT_STD_FLOOR, lr_final: float = 0.0, lr_decay_rate: float = 1.0,
                 lr_decay_steps: int = 1, lr_warmup_steps: int = 0, noise_field_std: float = 0.0,
                 noise_field_wavelength: float = 4.0, noise_field_mixture: bool = False,
                 type_partition: bool | None = None, noise_field_points_only: bool = False,
                 noise_field_decay_steps: int = 0):
        super().__init__()
        self.save_hyperparameters()
        validate_schedule(lr, lr_final, lr_decay_rate, lr_decay_steps, lr_warmup_steps)
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim}")
        if not 0.0 <= point_probability <= 1.0:
            raise ValueError(f"point_probability must lie in [0, 1], got {point_probability}")
        if noise_std < 0 or noise_field_std < 0 or noise_field_wavelength <= 0 or window < 1:
            raise ValueError(f"need noise_std >= 0, noise_field_std >= 0, noise_field_wavelength > 0 and window >= 1; "
                             f"got {noise_std}, {noise_field_std}, {noise_field_wavelength}, {window}")
        if noise_field_decay_steps < 0:
            raise ValueError(f"noise_field_decay_steps must be >= 0, got {noise_field_decay_steps}")
        self.connectivity: Connectivity = load_connectivity(connectivity)
        if noise_field_points_only and not self.connectivity.uses_points:
            raise ValueError(f"noise_field_points_only needs point clouds, and connectivity {connectivity!r} has no "
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
        if type_partition is not None:  # the paper's "MGN (1H)" ablation and its converse, per instance
            self.edge_partition = type_partition
            self.type_encoding = "per_type" if type_partition else "one_hot"
        self.core = EncodeProcessDecode(*self.input_dims(self.connectivity, dim, self.with_material or self.material_input),
                                        out_dim=dim,
                                        latent=latent, blocks=blocks, mlp_layers=mlp_layers,
                                        edge_partition=self.edge_partition, type_encoding=self.type_encoding,
                                        std_floor=std_floor)
        self.target_normalizer = Normalizer(dim, std_floor)
        self.lstm = nn.LSTMCell(latent, latent) if self.recurrent else None
        self._test_table: MetricTable | None = None
        self.static_rollouts, self._static_step = False, None  # `rollout_step`
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
        set (a runtime setting, e.g. by the `StaticRollouts` callback) a `StaticStep` on static-shape graphs,
        captured as a CUDA graph on a GPU (`evaluation.capture`; kept between calls, so validations reuse it)."""
        if not self.static_rollouts:
            return self.step
        device = next(self.parameters()).device
        if self._static_step is None or self._static_step.buffers.device != device:
            self._static_step = StaticStep(self)
        return self._static_step

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
            if train and self.hparams.noise_std > 0:
                pos = pos + torch.randn_like(pos) * self.hparams.noise_std * free
            field_std = self.noise_field_std_now() if train else 0.0
            if field_std > 0:
                field = smooth_field(batch.rest, batch.mesh_batch, batch.num_graphs, field_std,
                                     self.hparams.noise_field_wavelength,
                                     mixture=self.hparams.noise_field_mixture)
                if self.hparams.noise_field_points_only:
                    field = field * use_points.to(pos.device, non_blocking=True)[batch.mesh_batch, None]
                pos = pos + field * free
            graph = state_graph(batch, t, pos, use_points, self.connectivity, self.with_material, self.neighbour_check)
            samples.append((graph, batch.positions[t + 1] - pos))
        return samples

    def noise_field_std_now(self) -> float:
        """The smooth field's std at this optimizer step (`noise_field_decay_steps`)."""
        return linear_decay(self.hparams.noise_field_std, self.hparams.noise_field_decay_steps, self.global_step)

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
        loss, groups = self.window_loss(batch, train=True, by_points=True)
        sync = self._world_size() > 1  # under DDP the logged loss is the mean over the ranks' batches
        # not on the progress bar: Lightning reads progress-bar values back from the device after every batch
        self.log("train/loss", loss, batch_size=batch.num_graphs, sync_dist=sync)
        for name, value in groups.items():  # a group absent from one rank's batch: that rank's value alone
            self.log(f"train/loss_{name}", value.detach(), batch_size=batch.num_graphs)
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
        h = self.hparams
        optimizer = torch.optim.Adam(self.parameters(), lr=h.lr, fused=True)  # one kernel for all parameters
        schedule = dict(lr=h.lr, lr_final=h.lr_final, decay_rate=h.lr_decay_rate, decay_steps=h.lr_decay_steps,
                        warmup_steps=h.lr_warmup_steps)
        scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: scheduled_lr(step, **schedule) / h.lr)
        return {"optimizer": optimizer,
                "lr_scheduler": {"scheduler": scheduler, "interval": "step", "frequency": 1, "name": "train/lr"}}

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
        if count == 0:
            raise ValueError("no training samples for the normalization statistics")
        if self._world_size() > 1:  # each rank saw its own windows: merge, so that every rank normalizes alike
            merge_across([m for m in self.modules() if isinstance(m, Normalizer)], self.all_gather)
        for normalizer in self.modules():
            if isinstance(normalizer, Normalizer):
                normalizer.freeze()
        return count

    def setup(self, stage: str) -> None:
        """Refuse DDP that would hang: a batch without contact (or without a point cloud) leaves the edge
        MLPs of that edge type without a gradient, and DDP without find_unused_parameters then waits
        forever for it (seen on the plate). Refuse test and predict in more than one process."""
        strategy = self.trainer.strategy if self._trainer is not None else None
        if stage == "fit" and isinstance(strategy, DDPStrategy) and \
                not getattr(strategy, "_ddp_kwargs", {}).get("find_unused_parameters", False):
            raise ValueError("DDP needs find_unused_parameters: a batch without contact or point clouds leaves the "
                             "edge MLPs of that edge type unused, and plain DDP waits for their gradients forever; "
                             "use --trainer.strategy ddp_find_unused_parameters_true")
        stage = getattr(stage, "value", stage)  # Lightning passes a TrainerFn (a str enum)
        if stage in ("test", "predict") and self._world_size() > 1:
            # Lightning's distributed sampler would give each process part of the split (padded with repeats),
            # and the metrics or predictions written would be one process's part: refused, not half-written
            raise ValueError(f"{stage} runs in one process (it writes metrics and predictions of the whole split); "
                             f"use --trainer.devices 1 (this run has {self._world_size()} processes)")

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
        schedules = self.schedules if schedules is None else [parse_schedule(s) if isinstance(s, str) else s
                                                              for s in schedules]
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
        schedule = parse_schedule(schedule) if isinstance(schedule, str) else schedule
        with torch.no_grad():
            return rollout(self.rollout_step(), batch, schedule, self.connectivity, self.with_material)[0]

    def on_test_epoch_start(self) -> None:
        self._test_table = MetricTable()

    def test_step(self, batch: TrajectoryBatch, batch_idx: int) -> None:
        self._test_table.add(self.evaluate(batch, m_plus_10=self.hparams.test_m_plus_10, iou=self.hparams.test_iou))

    def on_test_epoch_end(self) -> None:
        summary = self._test_table.summary()
        for name, s in summary.items():
            self.log(f"test/{name}", s["mean"])
        table = metrics_markdown(summary, f"{type(self).__name__} test metrics")
        print("\n" + table)
        log_dir = self.trainer.log_dir
        if log_dir is not None and self.trainer.is_global_zero:
            write_text(Path(log_dir) / "test_metrics.md", table)
            write_json(Path(log_dir) / "test_metrics.json", summary)
        self.test_results = summary

    def predict_step(self, batch: TrajectoryBatch, batch_idx: int) -> dict[str, Any]:
        """Rollouts of the first eval schedule: {"schedule", "positions" [T, sumN, d], "node_offsets"}."""
        return {"schedule": str(self.schedules[0]), "positions": self.rollout(batch, self.schedules[0]).cpu(),
                "node_offsets": batch.node_offsets}

    # ---- checkpoints -------------------------------------------------------------------------
    def _world_size(self) -> int:
        return self._trainer.world_size if self._trainer is not None else 1

    def _rng_states(self) -> dict[str, Tensor]:
        """{generator: state of every rank [world size, n] uint8}: torch's CPU generator, and the CUDA one
        of this device when on a GPU (gathered from every rank under DDP: all ranks save together)."""
        states = {"cpu": torch.get_rng_state()}
        if self.device.type == "cuda":
            states["cuda"] = torch.cuda.get_rng_state(self.device)
        if self._world_size() > 1:
            return {k: self.all_gather(v.to(self.device)).cpu() for k, v in states.items()}
        return {k: v[None] for k, v in states.items()}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        self.raise_if_checks_failed()  # a step since the last read that went non-finite is never saved
        checkpoint["connectivity"] = dataclasses.asdict(self.connectivity)
        checkpoint["simulator_class"] = type(self).__name__
        checkpoint[FORMAT_KEY] = CHECKPOINT_FORMAT
        if self._trainer is not None and self.trainer.state.fn == "fit":  # a fit's checkpoint: resumable
            checkpoint[RNG_KEY] = self._rng_states()

    def on_train_start(self) -> None:
        """A resumed fit takes back its generators' states (saved by `on_save_checkpoint`) just before its
        first batch: nothing between loading and here (validation, loaders) draws from them."""
        states, self._saved_rng = getattr(self, "_saved_rng", None), None
        if states is None or self.trainer.ckpt_path is None:
            return
        rank, world = self.global_rank, self._world_size()
        if any(v.shape[0] != world for v in states.values()):
            warnings.warn(f"the checkpoint was written by a fit of {next(iter(states.values())).shape[0]} processes, "
                          f"this one has {world}: its random generators start afresh and the resumed fit "
                          "differs from an uninterrupted one", stacklevel=2)
            return
        torch.set_rng_state(states["cpu"][rank].clone())
        if "cuda" in states and self.device.type == "cuda":
            torch.cuda.set_rng_state(states["cuda"][rank].clone(), self.device)

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        check_format(checkpoint, "the checkpoint")
        self._saved_rng = checkpoint.get(RNG_KEY)  # taken back by on_train_start when the fit resumes
        saved = checkpoint.get("connectivity")
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
    """GGNS that identifies the material from its point clouds (issue 24; not a model of the paper).

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
                                             mlp_layers=h.mlp_layers, edge_partition=self.edge_partition,
                                             type_encoding=self.type_encoding, std_floor=h.std_floor)
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
        field = smooth_field(batch.rest, batch.mesh_batch, batch.num_graphs, std,
                             self.hparams.noise_field_wavelength, mixture=True)
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
    """MeshGraphNets baseline: per-type encoders and edge MLPs, world edges, no point clouds."""

    edge_partition = True
    type_encoding = "per_type"

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
    (their parameter sets differ)."""
    checkpoint = read_checkpoint(path, map_location="cpu")
    check_format(checkpoint, path)
    classes = {cls.__name__: cls for cls in MODELS.values()}
    name = checkpoint.get("simulator_class")
    if name is not None:
        if name not in classes:
            raise CheckpointError(f"{path}: unknown simulator_class {name!r} (known: {sorted(classes)})")
        return classes[name].load_from_checkpoint(path, map_location=map_location, weights_only=True).eval()
    if "hyper_parameters" not in checkpoint or "state_dict" not in checkpoint:
        raise CheckpointError(f"{path}: not a Lightning checkpoint of a ggns simulator")
    errors = []
    for cls in classes.values():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                return cls.load_from_checkpoint(path, map_location=map_location, strict=True, weights_only=True).eval()
        except (RuntimeError, KeyError, TypeError, ValueError) as error:
            errors.append(f"{cls.__name__}: {str(error).splitlines()[0][:120]}")
    raise CheckpointError(f"{path}: no simulator class loads this checkpoint ({'; '.join(errors)})")

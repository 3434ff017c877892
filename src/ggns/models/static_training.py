"""The whole training step with static shapes and no host read (`StaticTrainStep`), captured as one CUDA
graph on a GPU: forward (training noise, the graphs of the window's transitions, the model, the loss),
backward and the fused Adam step.

A window batch's node counts change from batch to batch, and its graphs' edge counts from step to step.
Here a batch is copied into buffers whose shapes come from a few capacity buckets (`bucket`: at most
1/8 of padding), so that batches of similar size share one recording:
- mesh rows padded with nodes of graph B (no graph): fixed, without edges, weight 0 in the loss;
- mesh edges padded with masked edges, collider vertices and point clouds padded with rows of graph B;
- per radius edge type an edge capacity (`graphs.static`), grown when a batch needs more.
The training noise is drawn on the device (the default generator, which a CUDA-graph capture
registers); the imputation draws (which windows see their point clouds) on the host, as in the eager
step, and copied in. The loss is the eager step's (`GraphSimulator.window_loss`: the mean over the
window's transitions of the normalized MSE on the free nodes) as a weighted sum.

What the step cannot check without a read stays on the device: a non-finite loss (the model's
`loss_check`), a node over `max_num_neighbors` (its `neighbour_check`), and an edge capacity that was
too small. A step whose graphs dropped edges past a capacity is not applied: the fused Adam skips it
(its `found_inf`, as for a gradient scaler's overflow), the capacities grow when the checks are read,
and the skipped steps are counted (`skipped`) and reported by a warning.

On the CPU the same tensor program runs eagerly (tests/test_static_step.py: the losses and weights of
50 steps equal the eager step's, the forward and backward compile with `fullgraph=True`, no host read).
Models whose loss reads more than the graph (GGNSID's second head) are refused.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from ..batch import TrajectoryBatch
from ..evaluation.capture import normalizer_masks, recording_key, same_objects
from ..graphs.static import StaticLayout, batch_layout, fill_clouds, measure_pairs, static_graph
from ..phases import host_side, phase
from .training_noise import smooth_field


def bucket(n: int, minimum: int = 8) -> int:
    """A capacity for n rows from a few buckets: n rounded up to a multiple of 2^(floor(log2 n) - 3), so
    at most 1/8 of it is padding (8 buckets per octave)."""
    if n <= minimum:
        return minimum
    grain = 2 ** max(0, int(math.floor(math.log2(n))) - 3)
    return int(math.ceil(n / grain)) * grain


@dataclass
class WindowBuffers:
    """The device buffers of a static training step (shapes from its layout)."""

    positions: Tensor  # [T, N, d]
    rest: Tensor  # [N, d]
    edges: Tensor  # [2, Em]
    edge_mask: Tensor  # [Em] bool
    fixed: Tensor  # [N] bool (padding rows fixed)
    weight: Tensor  # [N] 1 for a free node of a graph, else 0
    mesh_batch: Tensor  # [N] (padding rows B)
    inv_free: Tensor  # [B] 1 / free nodes per graph
    collider: Tensor | None  # [T, K, d]
    collider_batch: Tensor | None  # [K]
    points: Tensor | None  # [T, P, d]
    point_batch: Tensor | None  # [T, P]
    use: Tensor | None  # [B] bool: the window sees its point clouds
    material: Tensor | None  # [B]
    field_std: Tensor  # 0-d: the smooth field's std at this step
    capacity: Tensor  # [types] long
    found_inf: Tensor  # 0-d float: 1 when this step dropped edges (the optimizer skips it)
    skipped: Tensor  # 0-d long: the steps skipped since the last read
    loss: Tensor  # 0-d: the last step's loss (detached)
    groups: Tensor  # [2]: the mean per-sample loss of the samples with / without points
    bad: Tensor  # [3] long: (trajectory, node, transition) of the first non-finite error
    needed: Tensor  # [types] long: the most pairs each queried edge type needed since the last read
    most: Tensor  # [types, 3] long: the neighbour check's table of the last step


def capturable_optimizer(optimizer, device: torch.device) -> None:
    """Ready a fused Adam for a recorded step on `device`: capturable, and every group's lr a tensor on the
    device, which the lr schedule then updates in place (a float would be recorded as a constant; a
    resumed optimizer's tensor comes back on the CPU and is moved)."""
    for group in optimizer.param_groups:
        if not group.get("fused"):
            raise ValueError("a captured training step needs a fused Adam (its found_inf skips a step that "
                             "dropped edges); the simulators' configure_optimizers gives one")
        group["capturable"] = True  # Adam.step refuses a capture otherwise; the fused kernel does not read it
        lr = group["lr"]
        if not (isinstance(lr, Tensor) and lr.device == device):
            group["lr"] = torch.tensor(float(lr), dtype=torch.float32, device=device)


class StaticTrainStep:
    """The static training step of `model` (module docstring). capture: record forward, backward and the
    optimizer step as one CUDA graph (default: on a GPU, in float32 without autocast)."""

    SLOTS = 16  # recordings kept (batch shapes), the least recently used dropped beyond

    def __init__(self, model, capture: bool | None = None, margin: float = 1.5):
        if model.material_input:
            raise ValueError(f"{type(model).__name__}: a static training step needs a loss that reads only the "
                             f"graph (not GGNSID)")
        self.model, self.margin = model, margin
        self.device = next(model.parameters()).device
        self.capture = self.device.type == "cuda" if capture is None else capture
        if self.capture and self.device.type != "cuda":
            raise ValueError(f"capture needs the model on a CUDA device, it is on {self.device}")
        self.layout: StaticLayout | None = None  # the current batch's; its edge capacities are everyone's
        self.steps: int | None = None  # T of the windows
        self.buffers: WindowBuffers | None = None
        self.recordings, self.skipped, self._slot = 0, 0, None
        # shape key -> [layout, buffers, recording, its key, the normalizer masks it read]
        self._slots: dict = {}
        self._shared: dict | None = None  # the counters every slot's buffers share (`_allocate`)
        self.last_use: Tensor | None = None  # the host's imputation draws of the last prepared batch

    # ---- the tensor program -------------------------------------------------------------------------
    def loss_function(self, b: WindowBuffers, train: bool = True) -> Tensor:
        """The window's loss on the buffers (module docstring); writes the loss, groups and checks into them."""
        model, layout, B = self.model, self.layout, self.layout.num_graphs
        free = b.weight[:, None]
        owner = b.mesh_batch.clamp(max=B - 1)
        burn_in = self.steps - 1 - model.backprop_steps if model.backprop_steps else 0
        state, losses, samples, most, needed = None, [], [], [], []
        first_bad = torch.full((3,), -1, dtype=torch.long, device=b.positions.device)
        for t in range(self.steps - 1):
            pos = b.positions[t]
            if train:
                if model.noise.std > 0:
                    pos = pos + torch.randn_like(pos) * model.noise.std * free
                if model.noise.field_std > 0:
                    field = smooth_field(b.rest, owner, B, 1.0, model.noise.field_wavelength,
                                         mixture=model.noise.field_mixture) * b.field_std
                    if model.noise.field_points_only:
                        field = field * b.use[owner, None] if b.use is not None else field * 0
                    pos = pos + field * free
            graph, checks = static_graph(
                layout, model.connectivity, pos, b.rest, b.edges, b.fixed, b.mesh_batch,
                b.collider[t] if b.collider is not None else None,
                b.collider[t + 1] if b.collider is not None else None, b.collider_batch,
                b.points[t] if b.points is not None else None, b.point_batch[t] if b.points is not None else None,
                b.use, b.material, mesh_edge_mask=b.edge_mask)
            needed.append(checks.needed)
            most.append(checks.most)
            if t < burn_in:
                with torch.no_grad():
                    _, state = model.predict_normalized(graph, state)
                continue
            out, state = model.predict_normalized(graph, state)
            with phase("loss"):
                loss_t, sample, first_bad = self._transition_loss(
                    b, out, model.target_normalizer(b.positions[t + 1] - pos), t, first_bad)
            losses.append(loss_t)
            samples.append(sample)
        loss = torch.stack(losses).mean() if len(losses) > 1 else losses[0]
        per_sample = torch.stack(samples)  # [transitions, B]
        seen = (b.use.to(per_sample.dtype) if b.use is not None else per_sample.new_zeros(B))[None].expand_as(per_sample)
        groups = torch.stack([(per_sample * seen).sum() / seen.sum().clamp(min=1),
                              (per_sample * (1 - seen)).sum() / (1 - seen).sum().clamp(min=1)])
        with torch.no_grad():
            b.loss.copy_(loss.detach())
            b.groups.copy_(groups.detach())
            b.bad.copy_(first_bad)
            if needed:
                step_needed = torch.stack(needed).amax(0)
                b.needed.copy_(torch.maximum(b.needed, step_needed))
                b.found_inf.copy_((step_needed > b.capacity).any().to(b.found_inf.dtype))
                table = torch.stack(most)  # [transitions, types, 3]: the transition with the largest count
                worst = table[:, :, 0].argmax(0)
                b.most.copy_(table.gather(0, worst[None, :, None].expand(1, -1, 3))[0])
        return loss

    def _transition_loss(self, b: WindowBuffers, out: Tensor, target: Tensor, t: int,
                         first_bad: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Transition t's loss (the normalized MSE on the free nodes), its per-graph mean error [B], and the
        (trajectory, node, transition) of the first non-finite error so far, updated."""
        B, d = self.layout.num_graphs, out.size(1)
        squared = torch.where(b.weight[:, None] > 0, (out - target).square(), 0.0)
        loss = squared.sum() / (b.weight.sum() * d)
        error = squared.sum(1) / d
        sample = torch.zeros(B + 1, dtype=error.dtype, device=error.device).index_add_(
            0, b.mesh_batch, error)[:B] * b.inv_free
        bad = ~torch.isfinite(squared).all(dim=1) & (b.weight > 0)
        node = bad.to(torch.uint8).argmax().view(1)
        graph_of = b.mesh_batch.index_select(0, node)
        row = torch.cat([graph_of, node - (b.mesh_batch < graph_of).sum().view(1),
                         torch.full((1,), t, dtype=torch.long, device=node.device)])
        return loss, sample, torch.where((first_bad[0] < 0) & bad.any(), row, first_bad)

    def train_function(self, b: WindowBuffers, optimizer, apply: bool = True) -> None:
        """Forward, backward and the optimizer step (skipped when edges were dropped: `found_inf`; always
        skipped when not `apply`, the warm-up of a recording)."""
        loss = self.loss_function(b, train=True)
        with phase("backward"):
            loss.backward()
        with phase("optimizer"):
            if apply:
                b.skipped.add_(b.found_inf.long())
            else:
                b.found_inf.fill_(1.0)
            fused = optimizer.defaults.get("fused")
            if fused:  # the fused Adam skips a step whose found_inf is 1 (read on the device)
                optimizer.found_inf = b.found_inf
            try:
                optimizer.step()
            finally:
                if fused:
                    del optimizer.found_inf

    # ---- preparation ----------------------------------------------------------------------------------
    def _shape_key(self, layout: StaticLayout, batch: TrajectoryBatch) -> tuple:
        return (layout.num_graphs, tuple(layout.nodes.items()), tuple(layout.spans.items()), tuple(layout.edges),
                batch.num_steps, bucket(batch.edges.size(1)))

    def _allocate(self, batch: TrajectoryBatch, layout: StaticLayout) -> WindowBuffers:
        T, _, d = batch.positions.shape
        N, B, types = layout.nodes["mesh"], layout.num_graphs, len(layout.edges)
        dtype, device = batch.positions.dtype, self.device
        zeros = (lambda *shape, kind=dtype: torch.zeros(*shape, dtype=kind, device=device))
        K, P = layout.nodes.get("collider"), layout.nodes.get("point")
        return WindowBuffers(
            positions=zeros(T, N, d), rest=zeros(N, d), edges=zeros(2, bucket(batch.edges.size(1)), kind=torch.long),
            edge_mask=zeros(bucket(batch.edges.size(1)), kind=torch.bool), fixed=zeros(N, kind=torch.bool),
            weight=zeros(N), mesh_batch=zeros(N, kind=torch.long), inv_free=zeros(B),
            collider=zeros(T, K, d) if K else None, collider_batch=zeros(K, kind=torch.long) if K else None,
            points=zeros(T, P, d) if P else None, point_batch=zeros(T, P, kind=torch.long) if P else None,
            use=zeros(B, kind=torch.bool) if P else None, material=zeros(B) if self.model.with_material else None,
            field_std=zeros(()), found_inf=zeros((), kind=torch.float32), loss=zeros(()), groups=zeros(2),
            bad=zeros(3, kind=torch.long), most=zeros(types, 3, kind=torch.long), **self._counters(layout))

    def _counters(self, layout: StaticLayout) -> dict:
        """The capacity, needed and skipped tensors, one set for every slot (each recording writes the same
        memory, so one read covers them all)."""
        names = tuple(layout.edges)
        if self._shared is None or self._shared["names"] != names:
            device = self.device
            self._shared = {"names": names,
                            "capacity": layout.capacity_tensor(device),
                            "needed": torch.zeros(len(names), dtype=torch.long, device=device),
                            "skipped": torch.zeros((), dtype=torch.long, device=device)}
        return {k: v for k, v in self._shared.items() if k != "names"}

    def prepare(self, batch: TrajectoryBatch, train: bool = True) -> WindowBuffers:
        """Copy `batch` into the buffers of its shape (a slot per bucketed shape, `SLOTS` kept, each with its
        recording; edge capacities measured on the first batch and grown when one needs more,
        `read_capacities`), with this step's imputation draws and field std."""
        model, B = self.model, batch.num_graphs
        layout = batch_layout(batch, model.connectivity, model.uses_points,
                              self.layout.edges if self.layout is not None else None, size=bucket)
        if any(c == 0 for c in layout.edges.values()):  # the first batch: capacities from its states and the
            # statistics pass's graphs (more batches than one; `GraphSimulator.statistics_edges`)
            needed = measure_pairs(batch, model.connectivity, layout)
            for edge_type in needed:
                seen = model.statistics_edges.get(edge_type, 0.0) * B
                needed[edge_type] = max(needed[edge_type], int(math.ceil(seen)))
            layout = layout.grown(needed, self.margin)
        key = self._shape_key(layout, batch)
        if key in self._slots:
            self._slots[key] = self._slots.pop(key)  # the most recently used last: the least recently used goes first
        else:
            if len(self._slots) >= self.SLOTS:
                self._slots.pop(next(iter(self._slots)))
            with torch.inference_mode(False):
                self._slots[key] = [layout, self._allocate(batch, layout), None, None, None]
        slot = self._slots[key]
        slot[0] = layout  # the current capacities (a slot's recording is dropped when they grow)
        self.layout, self.steps, self.buffers, self._slot = layout, batch.num_steps, slot[1], slot
        b = self.buffers
        N, n = b.rest.size(0), batch.rest.size(0)
        for buffer, value, pad in ((b.rest, batch.rest, 0), (b.fixed, batch.fixed, True),
                                   (b.mesh_batch, batch.mesh_batch, B)):
            buffer[:n].copy_(value)
            buffer[n:].fill_(pad)
        b.positions[:, :n].copy_(batch.positions)
        b.positions[:, n:].zero_()
        free = (~batch.fixed).to(b.weight.dtype)
        b.weight[:n].copy_(free)
        b.weight[n:].zero_()
        b.inv_free.copy_(torch.zeros(B, dtype=free.dtype, device=free.device).index_add_(
            0, batch.mesh_batch, free).clamp(min=1).reciprocal())
        e = batch.edges.size(1)
        b.edges[:, :e].copy_(batch.edges)
        b.edges[:, e:].zero_()
        b.edge_mask[:e].fill_(True)
        b.edge_mask[e:].fill_(False)
        if b.collider is not None:
            k = batch.collider.size(1)
            b.collider[:, :k].copy_(batch.collider)
            b.collider[:, k:].zero_()
            b.collider_batch[:k].copy_(batch.collider_batch)
            b.collider_batch[k:].fill_(B)
        if b.points is not None:
            fill_clouds(batch, b.points, b.point_batch)
            if train:  # the eager step's draws, from the host's generator in the same order
                use = host_side(torch.rand(B) < model.hparams.point_probability)
            else:
                use = torch.ones(B, dtype=torch.bool)
            b.use.copy_(use.pin_memory() if b.use.is_cuda else use, non_blocking=True)
            self.last_use = use
        if b.material is not None:
            batch.require_material("this model")
            b.material.copy_(batch.material)
        b.field_std.fill_(model.noise.field_std_at(model.global_step) if train else 0.0)
        return b

    # ---- the step -------------------------------------------------------------------------------------
    def loss(self, batch: TrajectoryBatch, train: bool = True) -> Tensor:
        """The window's loss on the static layout (no optimizer step), with the checks recorded."""
        b = self.prepare(batch, train)
        loss = self.loss_function(b, train)
        self.record_checks()
        return loss

    def step(self, batch: TrajectoryBatch, optimizer) -> Tensor:
        """One optimizer step on `batch` (module docstring): its loss, detached (a buffer on a GPU)."""
        b = self.prepare(batch, train=True)
        if not self.capture:
            optimizer.zero_grad(set_to_none=True)
            self.train_function(b, optimizer)
        else:
            slot, key = self._slot, (recording_key(self.model, self.device), id(optimizer))
            if slot[2] is None or slot[3] != key or not same_objects(slot[4], normalizer_masks(self.model)):
                slot[2], slot[3] = self._record(optimizer), key
                slot[4] = normalizer_masks(self.model)  # after the warm-up made them
            slot[2].replay()
        self.record_checks()
        return b.loss

    def _record(self, optimizer) -> torch.cuda.CUDAGraph:
        """Warm up on a side stream (optimizer state and lazy initializations outside the capture; the
        warm-up's updates skipped through `found_inf`, the random state restored), then record forward,
        backward and the optimizer step (PyTorch's whole-network capture), autocast's cache off."""
        b = self.buffers
        capturable_optimizer(optimizer, self.device)
        cast = torch.autocast("cuda", enabled=torch.is_autocast_enabled("cuda"),
                              dtype=torch.get_autocast_dtype("cuda"), cache_enabled=False)
        with torch.cuda.device(self.device):
            rng = torch.cuda.get_rng_state(self.device)
            side = torch.cuda.Stream(self.device)
            side.wait_stream(torch.cuda.current_stream(self.device))
            with torch.cuda.stream(side), cast:
                for _ in range(3):
                    optimizer.zero_grad(set_to_none=True)
                    self.train_function(b, optimizer, apply=False)
            torch.cuda.current_stream(self.device).wait_stream(side)
            torch.cuda.set_rng_state(rng, self.device)
            graph = torch.cuda.CUDAGraph()
            optimizer.zero_grad(set_to_none=True)
            with torch.cuda.graph(graph, capture_error_mode="thread_local"), cast:
                self.train_function(b, optimizer)
        self.recordings += 1
        return graph

    def set_capacities(self, edges: dict) -> None:
        """Set the edge capacities {queried edge type: pairs} (every recording made anew); they still grow when
        a step needs more (for tests and experiments)."""
        self._grow_to(replace(self.layout, edges=dict(edges)))

    def _grow_to(self, layout: StaticLayout) -> None:
        """New edge capacities for every slot (every recording has the old ones in its shapes)."""
        self.layout = layout
        self._shared["capacity"].copy_(layout.capacity_tensor())
        for slot in self._slots.values():
            slot[0], slot[2] = layout, None

    def __deepcopy__(self, memo):
        return None  # a copied model records its own step (a CUDA graph cannot be copied)

    def record_checks(self) -> None:
        """This step's checks into the model's deferred checks (tensor operations, no read)."""
        model, b = self.model, self.buffers
        model.loss_check.record(~torch.isfinite(b.loss), model.global_step, b.loss, b.bad[0], b.bad[1], b.bad[2])
        if len(self.layout.edges):
            model.neighbour_check.step = model.global_step
            model.neighbour_check.record(dict(zip(self.layout.edges, b.most)))

    def read_capacities(self) -> None:
        """Read how many pairs the steps since the last read needed and how many steps were skipped (one read):
        grow the capacities that were too small (recorded anew) and warn of the skipped steps."""
        b = self.buffers
        if b is None or not len(self.layout.edges):
            return
        with phase("check reads"):
            values = torch.cat([b.needed, b.skipped.view(1)]).tolist()
        needed, skipped = dict(zip(self.layout.edges, values[:-1])), values[-1]
        b.needed.zero_()
        b.skipped.zero_()
        self.skipped += skipped
        if any(needed[t] > c for t, c in self.layout.edges.items()):
            self._grow_to(self.layout.grown(needed, self.margin))
        if skipped:
            warnings.warn(f"static training: {skipped} step(s) since the last read needed more edges than the buffers "
                          f"held and were skipped; edge capacities now {self.layout.edges}", stacklevel=2)

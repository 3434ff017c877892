"""The whole rollout step with static shapes and no host read, captured as one CUDA graph on a GPU
(`StaticStep`).

An eager rollout step builds its graph with radius queries whose edge counts are data (each a read of
the device), then launches every operator of the model from Python. A `StaticStep` instead runs the
whole step on buffers of fixed capacity (`graphs.static`): the state graph (every radius query by the
static search, the features), the model and its normalization, the integration (fixed nodes set to
their known positions) and the rollout's checks (non-finite or escaped nodes, the neighbour cap, an
edge capacity that was too small), recorded into device tensors. The batch's trajectories are copied
once into the step's own buffers, the step number is a device scalar, and the predicted positions are
written into an output buffer, so one step is `t.fill_(step)` and a replay: no host read, no allocation.
On a GPU the step is recorded as a CUDA graph (`torch.cuda.CUDAGraph`, thread-local capture mode,
autocast's weight cache off during the capture) and replayed; `compile=True` compiles it with
`torch.compile(fullgraph=True, dynamic=False)` instead of (CPU) or before (GPU) the capture. On the CPU
without either it runs eagerly: the same tensor program, which tests/test_static_step.py compares with
the eager rollouts, compiles with `fullgraph=True` and counts no host read in.

The checks are read every `check_every` steps (`rollout.check_interval`) and at the end, with one read
of a few numbers. An edge capacity that was too small (the static search found more pairs than the
buffers hold) is not an error: the capacities grow to what was needed, the step is recorded anew, and
the steps since the last read are computed again from the state saved there. A node over
`max_num_neighbors` raises the neighbour check's ValueError, a diverged rollout the rollout's
RolloutError, naming the first step, as the eager rollout does. `recordings` counts the recordings
(captures, compilations, or eager preparations of a new layout).

GGNSID (whose step fuses a material estimate between graphs) is refused; GGNS+LSTM's state lives in
the step's buffers.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from ..batch import TrajectoryBatch
from ..phases import phase
from ..graphs.build import NeighbourCheck
from ..graphs.static import StaticLayout, batch_layout, fill_clouds, measure_pairs, static_graph
from .rollout import ESCAPE_FACTOR, check_interval, raise_divergence
from .schedules import Schedule


RECOMPILE_LIMIT = 256  # compiled layouts of `StaticStep.step_function` in one process (`compile=True`)
SLOTS = 8  # batch shapes whose buffers and recording a `StaticStep` keeps (the least recently used dropped beyond)


def recording_key(model, device: torch.device) -> tuple:
    """What a recorded step depends on besides its shapes: the weights' dtype, autocast and the float32 matmul
    precision (a change of any is recorded anew)."""
    dtype = next(model.parameters()).dtype
    autocast = torch.is_autocast_enabled(device.type) and torch.get_autocast_dtype(device.type)
    return dtype, autocast, torch.get_float32_matmul_precision()


def normalizer_masks(model) -> list:
    """The normalizers' cached masks (`Normalizer.cached_mask`), which a recording reads by address: a
    statistics update or a reload of a part of the model makes them anew, and the recording must follow."""
    return [m.cached_mask for m in model.modules() if hasattr(m, "cached_mask")]


def same_objects(a: list, b: list) -> bool:
    return len(a) == len(b) and all(x is y for x, y in zip(a, b))


@dataclass
class StepBuffers:
    """The device buffers of a static step (every shape fixed by its `StaticLayout` and the batch's
    steps T): the batch's trajectories, the step's state and its check records."""

    positions: Tensor  # [T, N, d] true positions (the fixed nodes' source; teacher forcing)
    rest: Tensor  # [N, d]
    edges: Tensor  # [2, Em]
    fixed: Tensor  # [N] bool
    mesh_batch: Tensor  # [N]
    collider: Tensor | None  # [T, K, d]
    collider_batch: Tensor | None  # [K]
    points: Tensor | None  # [T, P, d], padding rows zero
    point_batch: Tensor | None  # [T, P], padding rows B
    use: Tensor | None  # [T, B] bool: the schedule's point clouds per step and graph
    material: Tensor | None  # [B]
    t: Tensor  # 0-d long: the step to take (state t -> t + 1)
    pos: Tensor  # [N, d] the current state (non-finite rows held at their last finite value)
    out: Tensor  # [T, N, d] the raw predictions: out[t + 1] is the prediction of state t + 1
    origin: Tensor  # [N, d] the start state (the escape check)
    extent: Tensor  # 0-d: the start state's bounding-box diagonal
    escape: Tensor  # 0-d bool: check escaped nodes (rollouts) or not (teacher forcing)
    hidden: tuple[Tensor, Tensor] | None  # an LSTM's (h, c) [N, L]
    diverged_at: Tensor  # 0-d long: the first step with a non-finite or escaped node, -1 if none
    cap_at: Tensor  # 0-d long: the first step where a node had more than max_num_neighbors, -1 if none
    cap_table: Tensor  # [types, 3] long: `NeighbourCheck`'s table at cap_at
    overflow_at: Tensor  # 0-d long: the first step where an edge capacity was too small, -1 if none
    needed: Tensor  # [types] long: the most pairs each queried edge type needed since the last read
    capacity: Tensor  # [types] long: the layout's edge capacities


class StaticStep:
    """The whole rollout step of `model` on static shapes (module docstring). capture: record a CUDA graph
    (default: when the model is on a GPU); compile: `torch.compile(fullgraph=True, dynamic=False)` the step
    (`compile_options`: more keyword arguments of torch.compile, e.g. a backend)."""

    whole_step = True  # the rollout engine hands it whole rollouts (`evaluation.rollout.rollout`)

    def __init__(self, model, capture: bool | None = None, compile: bool = False, margin: float = 1.25,
                 compile_options: dict | None = None):
        if model.material_input:
            raise ValueError(f"{type(model).__name__}: a static step needs a step that reads only the graph and its "
                             f"own state (not GGNSID)")
        device = next(model.parameters()).device
        self.capture = device.type == "cuda" if capture is None else capture
        if self.capture and device.type != "cuda":
            raise ValueError(f"capture needs the model on a CUDA device, it is on {device}")
        self.model, self.device, self.margin = model, device, margin
        self.compile, self.compile_options = compile, dict(compile_options or {})
        if self.compile and self.capture and self.compile_options.get("mode") in ("reduce-overhead",
                                                                                   "max-autotune"):
            raise ValueError(f"compile mode {self.compile_options['mode']!r} records CUDA graphs of its own, which "
                             f"cannot nest in the step's recording; use the default mode")
        self.recordings = 0
        self.layout: StaticLayout | None = None  # the current batch's; its edge capacities only grow
        self.buffers: StepBuffers | None = None
        self._batch: TrajectoryBatch | None = None
        # batch shape -> [layout, buffers, recording (a CUDA graph, a compiled function or "eager"), its key,
        # the normalizer masks it read]
        self._slots: dict = {}
        self._slot: list | None = None

    # ---- the step itself: tensor operations on the buffers, in place ------------------------------------
    def step_function(self, b: StepBuffers) -> None:
        """One step t -> t + 1 on the buffers (state, output and checks updated in place)."""
        model, layout, connectivity = self.model, self.layout, self.model.connectivity
        t = b.t.view(1)
        at = (lambda series: series.index_select(0, t)[0])
        has_collider, uses_points = b.collider is not None, b.points is not None
        graph, checks = static_graph(
            layout, connectivity, b.pos, b.rest, b.edges, b.fixed, b.mesh_batch,
            at(b.collider) if has_collider else None, b.collider.index_select(0, t + 1)[0] if has_collider else None,
            b.collider_batch, at(b.points) if uses_points else None, at(b.point_batch) if uses_points else None,
            at(b.use) if uses_points else None, b.material)
        if b.hidden is not None:
            displacement, hidden = model.step(graph, b.hidden)
            b.hidden[0].copy_(hidden[0])
            b.hidden[1].copy_(hidden[1])
        else:
            displacement, _ = model.step(graph)
        with phase("checks"):  # the integration and the rollout's checks
            self._integrate(b, t, displacement, checks)

    def _integrate(self, b: StepBuffers, t: Tensor, displacement: Tensor, checks) -> None:
        """Fixed nodes to their known positions, the prediction into the output, the checks recorded."""
        connectivity, layout = self.model.connectivity, self.layout
        truth = b.positions.index_select(0, t + 1)[0]
        raw = torch.where(b.fixed[:, None], truth, b.pos + displacement)
        finite = torch.isfinite(raw).all(dim=1)
        escaped = ((raw - b.origin).norm(dim=1) > ESCAPE_FACTOR * b.extent).any() & b.escape
        failed = ~finite.all() | escaped
        b.out.index_copy_(0, t + 1, raw[None])
        b.pos.copy_(torch.where(finite[:, None], raw, b.pos))
        first = (lambda at_, now: torch.where((at_ < 0) & now, b.t, at_))
        b.diverged_at.copy_(first(b.diverged_at, failed))
        if checks.needed.numel():
            over_cap = (checks.most[:, 0] > connectivity.max_num_neighbors).any()
            b.cap_table.copy_(torch.where((b.cap_at < 0) & over_cap, checks.most, b.cap_table))
            b.cap_at.copy_(first(b.cap_at, over_cap))
            b.overflow_at.copy_(first(b.overflow_at, (checks.needed > b.capacity).any()))
            b.needed.copy_(torch.maximum(b.needed, checks.needed))
        b.t.add_(1)

    # ---- preparation ----------------------------------------------------------------------------------
    def _prepare(self, batch: TrajectoryBatch) -> None:
        """The buffers for `batch`'s shape (a slot per shape, `SLOTS` kept, each with its recording), its
        trajectories copied in; the layout from its host offsets, with edge capacities measured on its true
        states (one read, per batch) and never shrunk."""
        model = self.model
        layout = batch_layout(batch, model.connectivity, model.uses_points,
                              self.layout.edges if self.layout is not None else None)
        layout = layout.grown(measure_pairs(batch, model.connectivity, layout), self.margin)
        key = (layout.num_graphs, tuple(layout.nodes.items()), tuple(layout.spans.items()), tuple(layout.edges),
               tuple(batch.positions.shape), batch.edges.size(1), self.model.recurrent)
        if key in self._slots:
            self._slots[key] = self._slots.pop(key)  # the most recently used last: the least recently used goes first
        else:
            if len(self._slots) >= SLOTS:
                self._slots.pop(next(iter(self._slots)))
            with torch.inference_mode(False):  # buffers that a later rollout outside inference mode may update
                self._slots[key] = [layout, self._allocate(batch, layout), None, None, None]
        self._slot, self.buffers = self._slots[key], self._slots[key][1]
        self._use_layout(layout)
        self._fill(batch)
        self._batch = batch

    def _use_layout(self, layout: StaticLayout) -> None:
        """Make `layout` the current slot's (its recording dropped when the edge capacities changed)."""
        if self._slot[0].edges != layout.edges:
            self._slot[2] = None
        self._slot[0] = self.layout = layout
        self.buffers.capacity.copy_(layout.capacity_tensor())

    def set_capacities(self, edges: dict) -> None:
        """Set the edge capacities {queried edge type: pairs} of the current batch (recorded anew); they still
        grow when a step needs more (for tests and experiments)."""
        self._use_layout(replace(self.layout, edges=dict(edges)))

    def _allocate(self, batch: TrajectoryBatch, layout: StaticLayout) -> StepBuffers:
        T, N, d = batch.positions.shape
        dtype, device = batch.positions.dtype, self.device
        zeros = (lambda *shape, kind=dtype: torch.zeros(*shape, dtype=kind, device=device))
        scalar = (lambda value: torch.full((), value, dtype=torch.long, device=device))
        types = len(layout.edges)
        collider = "collider" in layout.nodes
        points = "point" in layout.nodes
        latent = self.model.hparams.latent
        return StepBuffers(
            positions=zeros(T, N, d), rest=zeros(N, d), edges=zeros(2, batch.edges.size(1), kind=torch.long),
            fixed=zeros(N, kind=torch.bool), mesh_batch=zeros(N, kind=torch.long),
            collider=zeros(T, layout.nodes["collider"], d) if collider else None,
            collider_batch=zeros(layout.nodes["collider"], kind=torch.long) if collider else None,
            points=zeros(T, layout.nodes["point"], d) if points else None,
            point_batch=zeros(T, layout.nodes["point"], kind=torch.long) if points else None,
            use=zeros(T, layout.num_graphs, kind=torch.bool) if points else None,
            material=zeros(layout.num_graphs) if self.model.with_material else None,
            t=scalar(0), pos=zeros(N, d), out=zeros(T, N, d), origin=zeros(N, d), extent=zeros(()),
            escape=torch.ones((), dtype=torch.bool, device=device),
            hidden=(zeros(N, latent), zeros(N, latent)) if self.model.recurrent else None,
            diverged_at=scalar(-1), cap_at=scalar(-1), cap_table=zeros(types, 3, kind=torch.long),
            overflow_at=scalar(-1), needed=zeros(types, kind=torch.long),
            capacity=layout.capacity_tensor(device))

    def _fill(self, batch: TrajectoryBatch) -> None:
        """Copy `batch` into the buffers (device copies; the point clouds padded with rows of graph B)."""
        b = self.buffers
        b.positions.copy_(batch.positions)
        b.rest.copy_(batch.rest)
        b.edges.copy_(batch.edges)
        b.fixed.copy_(batch.fixed)
        b.mesh_batch.copy_(batch.mesh_batch)
        if b.collider is not None:
            b.collider.copy_(batch.collider)
            b.collider_batch.copy_(batch.collider_batch)
        if b.points is not None:
            fill_clouds(batch, b.points, b.point_batch)
        if b.material is not None:
            batch.require_material("this model")
            b.material.copy_(batch.material)

    # ---- recording --------------------------------------------------------------------------------------
    def _run(self) -> None:
        """One step: eager, compiled or a replay, recording first where needed (another dtype, autocast or
        matmul precision; in a capture, normalizer masks made anew)."""
        slot, key = self._slot, recording_key(self.model, self.device)
        if slot[2] is None or slot[3] != key or (self.capture and not same_objects(slot[4],
                                                                                    normalizer_masks(self.model))):
            slot[2], slot[3] = self._record(), key
            slot[4] = normalizer_masks(self.model)
        if self.capture:
            slot[2].replay()
        elif self.compile:
            # every layout is a program of its own: more than dynamo's default 8 compilations of this function
            with torch._dynamo.config.patch(recompile_limit=RECOMPILE_LIMIT):
                slot[2](self.buffers)
        else:
            self.step_function(self.buffers)

    def _record(self):
        """The recording of the current slot: a CUDA graph (warmed up on a side stream, the state restored
        after), a compiled function, or "eager"."""
        b = self.buffers
        self.recordings += 1
        if not self.capture:
            return (torch.compile(self.step_function, fullgraph=True, dynamic=False, **self.compile_options)
                    if self.compile else "eager")
        saved = self._save()
        function = (torch.compile(self.step_function, fullgraph=True, dynamic=False, **self.compile_options)
                    if self.compile else self.step_function)
        autocast = torch.is_autocast_enabled("cuda")
        # autocast's cache of low-precision weight copies is freed when autocast exits: a capture must not
        # read it (later replays would read freed memory), so the capture runs with the cache off
        cast = torch.autocast("cuda", enabled=autocast, dtype=torch.get_autocast_dtype("cuda"), cache_enabled=False)
        with torch.cuda.device(self.device):
            side = torch.cuda.Stream(self.device)
            side.wait_stream(torch.cuda.current_stream(self.device))
            with torch.no_grad(), cast, torch.cuda.stream(side), \
                    torch._dynamo.config.patch(recompile_limit=RECOMPILE_LIMIT):
                for _ in range(2):  # lazy initializations (and a compilation) happen outside the capture
                    function(b)
                    self._restore(saved)
            torch.cuda.current_stream(self.device).wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.no_grad(), cast, torch.cuda.graph(graph, capture_error_mode="thread_local"):
                function(b)
        self._restore(saved)
        return graph

    def __deepcopy__(self, memo):
        return None  # a copied model records its own step (a CUDA graph cannot be copied)

    def _save(self) -> dict:
        """A copy of the step's state (position, hidden state, step, check records)."""
        b = self.buffers
        names = ("pos", "t", "diverged_at", "cap_at", "cap_table", "overflow_at", "needed")
        with torch.inference_mode(False):
            saved = {name: getattr(b, name).clone() for name in names}
            if b.hidden is not None:
                saved["hidden"] = tuple(h.clone() for h in b.hidden)
        return saved

    def _restore(self, saved: dict) -> None:
        b = self.buffers
        for name, value in saved.items():
            if name == "hidden":
                b.hidden[0].copy_(value[0])
                b.hidden[1].copy_(value[1])
            else:
                getattr(b, name).copy_(value)

    # ---- rollouts ---------------------------------------------------------------------------------------
    def rollout(self, batch: TrajectoryBatch, schedule: Schedule, start_positions: Tensor | None = None,
                start: int = 0, steps: int | None = None, state: Any = None, check_every: int | None = None,
                teacher_forcing: bool = False) -> tuple[Tensor, Any]:
        """`evaluation.rollout.rollout` on the static step: predictions [steps + 1, N, d] of states start ..
        start + steps, and the final state (an LSTM's (h, c), or None). teacher_forcing: every step starts
        from the true state (`one_step_predictions`; no escape check)."""
        last = batch.num_steps - 1
        steps = last - start if steps is None else steps
        if start < 0 or steps < 0 or start + steps > last:
            raise ValueError(f"rollout start={start}, steps={steps} leaves the states 0..{last}")
        if self._batch is not batch or self.buffers is None:
            self._prepare(batch)
        b = self.buffers
        pos = batch.positions[start] if start_positions is None else start_positions.to(batch.positions)
        b.pos.copy_(pos)
        b.origin.copy_(pos)
        b.extent.copy_((pos.amax(0) - pos.amin(0)).norm())
        b.escape.fill_(not teacher_forcing)
        b.out[start].copy_(pos)
        if b.hidden is not None:
            for buffer, value in zip(b.hidden, state if state is not None else (None, None)):
                buffer.copy_(value) if value is not None else buffer.zero_()
        if b.use is not None:
            counts = [batch.point_range(t) for t in range(batch.num_steps)]
            use = [[schedule.uses_points(t) and o[g + 1] > o[g] for g in range(batch.num_graphs)] for t, o in
                   enumerate(counts)]
            use = torch.tensor(use, dtype=torch.bool)
            b.use.copy_(use.pin_memory() if b.use.is_cuda else use, non_blocking=True)
        every = check_interval(self.device, check_every)
        t = start
        while t < start + steps:
            saved, first = self._save_and_reset(t), t
            with torch.no_grad():
                while t < min(first + every, start + steps):
                    if teacher_forcing:
                        b.pos.copy_(b.positions[t])
                    self._run()
                    t += 1
            if self._read(batch, first, t):  # a capacity grew: these steps again, from the saved state
                self._restore(saved)
                t = first
        final = tuple(h.clone() for h in b.hidden) if b.hidden is not None else None
        return b.out[start:start + steps + 1].clone(), final

    def _save_and_reset(self, t: int) -> dict:
        b = self.buffers
        b.t.fill_(t)
        for name in ("diverged_at", "cap_at", "overflow_at"):
            getattr(b, name).fill_(-1)
        b.needed.zero_()
        return self._save()

    def _read(self, batch: TrajectoryBatch, first: int, end: int) -> bool:
        """Read the checks of steps first .. end - 1 (one read): raise the first failure; True when an edge
        capacity was too small (the layout has grown: the steps must be taken again)."""
        b = self.buffers
        with phase("check reads"):
            values = torch.cat([torch.stack([b.diverged_at, b.cap_at, b.overflow_at]), b.needed]).tolist()
        (diverged, capped, overflow), needed = values[:3], dict(zip(self.layout.edges, values[3:]))
        failures = [s for s in (diverged, capped) if s >= 0]
        if overflow >= 0 and not (failures and min(failures) < overflow):
            # the steps from the overflow on ran on graphs missing edges: grow, take them again
            self._use_layout(self.layout.grown(needed, self.margin))
            return True
        if diverged >= 0:  # as the eager rollout: a divergence first, then the neighbour cap
            raise_divergence(b.out[diverged + 1], b.origin, float(b.extent), batch, diverged)
        if capped >= 0:
            check = NeighbourCheck(self.model.connectivity, what="rollout")
            check.step = capped
            check.record(dict(zip(self.layout.edges, b.cap_table)))
            check.raise_if_failed()
        return False

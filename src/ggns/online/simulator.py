"""`OnlineSimulator`: a trained simulator stepped one tick at a time by its caller (a robot's control loop),
fed the collider's new pose every tick and an observation (a point cloud or depth images) when one arrives.

Ticks and states: tick t holds state t (the mesh as predicted for it). `step(collider=pose of t + 1,
observation=what was seen of state t)` predicts state t + 1 exactly as prediction step t of the offline
engine (`evaluation.rollout.rollout`) does, through the same graph builder and step function
(`online.engine`): fed a recorded trajectory's collider positions and, where a schedule says so, its
point clouds, it returns the offline rollout's states. An observation stamped with an earlier tick s (a
sensor's latency) corrects the state kept for s, and the simulator predicts forward from there to now
with the inputs it had (`history` ticks are kept for that); observations of one tick are joined, whether
they come in one call or in several.

With a `Registration` (online.registration) the observations correct the state of their tick by
registering the mesh to the cloud before the model predicts on (a blind model corrected, or a grounded one
corrected as well); late observations go the same way (the kept tick is corrected, then predicted forward).

Every input is checked before anything changes: bad input raises one ValueError naming the problem and
leaves the state as it was; so does a step whose prediction is not finite or left the scene
(`errors.OnlineDivergence`, naming the object).
"""
from __future__ import annotations

import hashlib
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..batch import TrajectoryBatch
from ..errors import OnlineDivergence
from ..evaluation.rollout import ESCAPE_FACTOR
from ..sensors.camera import RIGID_TOLERANCE, DepthImage, check_rigid
from ..trajectory import Trajectory
from .depth import DepthProcessing
from .engine import advance, points_flags, tick_batch
from .objects import Observation, float_array, grasped_nodes, rigid_motion
from .registration import ObjectGeometry, Registration, register

STATE_FORMAT = 2  # the layout of `OnlineSimulator.state_dict` (2: with the model's identity)


@dataclass
class _Seen:
    """What was observed of one object at one tick, as given (joined with what comes later for that tick)."""

    images: list = field(default_factory=list)  # DepthImage
    points: list = field(default_factory=list)  # np.ndarray [P, d]

    def joined(self, other: _Seen | None) -> _Seen:
        return self if other is None else _Seen(other.images + self.images, other.points + self.points)


@dataclass
class _Tick:
    """What a past tick kept for a correction: state t (mesh positions [sumN, d], model state before step t),
    the collider vertices at t [sumK, d], the point clouds step t used (per object, None: none) and what was
    observed at t (per object, None: nothing), so that a later observation of t joins it."""

    tick: int
    positions: Tensor
    model_state: Any
    collider: Tensor | None
    points: list[Tensor | None]
    seen: list[_Seen | None]


class OnlineSimulator:
    """A trained simulator (GGNS, GGNS+LSTM, GGNSID, MGN, MGN(M), ...) stepped tick by tick (module docstring).

    Args:
        model: the simulator, e.g. `ggns.pretrained.load("plate/ggns")` or `load_simulator(path)`; its
            rollout step function is used (a static one's eager twin, `model.step`).
        objects: one object or several, as `Trajectory`s (`online_object`, or a recorded trajectory: its
            rest positions, cells, fixed mask, collider faces and material, its state 0 as tick 0 and its
            collider at state 0 as the template poses move), a sequence (named 0, 1, ...) or a mapping
            name -> object. All have the model's dimension; they step together in one batch.
        depth: how depth images (and point clouds denser than the training data's) become the cloud the model
            sees (`DepthProcessing`); None: `DepthProcessing.for_model` (a shipped simulator's training sensor)
            when it is first needed.
        history: past ticks kept for late observations (an observation of tick t - d, d <= history).
        registration: correct each observed tick's state by registering the mesh to its cloud (`Registration`);
            None: the clouds only reach the model (a GGNS's grounding).
        rigid_tolerance: how far a collider pose's rotation may be from orthonormal (`check_rigid`).
        warm: import and exercise the depth path and make one prediction now (`warm_up`), so the first frame
            of a control loop costs what the others do.
    """

    def __init__(self, model: Any, objects: Trajectory | Sequence[Trajectory] | Mapping[Hashable, Trajectory],
                 depth: DepthProcessing | None = None, history: int = 8, registration: Registration | None = None,
                 rigid_tolerance: float = RIGID_TOLERANCE, warm: bool = True):
        if isinstance(objects, Trajectory):
            objects = [objects]
        named = dict(objects) if isinstance(objects, Mapping) else dict(enumerate(objects))
        if not named or not all(isinstance(o, Trajectory) for o in named.values()):
            raise ValueError("objects must be one Trajectory, a non-empty sequence of them or a mapping name -> "
                             "Trajectory (ggns.online.online_object builds one from arrays)")
        if isinstance(history, bool) or not isinstance(history, int) or history < 0:
            raise ValueError(f"history must be an integer >= 0, got {history!r}")
        if registration is not None and not isinstance(registration, Registration):
            raise ValueError(f"registration must be a ggns.online.Registration or None, got {type(registration).__name__}")
        dim = int(model.hparams.dim)
        other = [f"{name!r} ({o.dim}D)" for name, o in named.items() if o.dim != dim]
        if other:
            raise ValueError(f"the model simulates {dim}D objects; not object(s) {', '.join(other)}")
        self.model, self.dim, self.history = model, dim, history
        self.registration, self.rigid_tolerance = registration, float(rigid_tolerance)
        self.names: list[Hashable] = list(named)
        self._index = {name: b for b, name in enumerate(self.names)}
        self.depth = depth
        # the rollout step function; a static one (`static_rollouts`) steps whole rollouts: its eager twin here
        self._step_fn = model.step if getattr(model, "static_rollouts", False) else model.rollout_step()
        parameter = next(model.parameters())
        self.device, self.dtype = parameter.device, parameter.dtype
        self.identity = model_identity(model)
        objects = list(named.values())
        two_states = [dataclasses_replace_two_states(o, dim) for o in objects]
        static = TrajectoryBatch.from_trajectories(two_states, dtype=self.dtype)  # checked here, on the host
        if model.with_material:
            static.require_material(f"{type(model).__name__}")
        self._static = static.to(self.device)
        self._cells = [np.asarray(o.cells) for o in objects]
        self._faces = [np.asarray(o.collider_faces) for o in objects]
        self._templates = [np.asarray(o.collider_positions[0], dtype=np.float64) for o in objects]
        self._fixed_index = [np.flatnonzero(o.fixed) for o in objects]
        self._grasped = [grasped_nodes(o) for o in objects]
        self._grasped_start = [np.asarray(o.positions[0][g], dtype=np.float64) for o, g in zip(objects, self._grasped)]
        self._nodes = self._static.node_offsets
        self._vertices = self._static.collider_range
        self._origin = self._static.positions[0].clone()
        self._extent = float((self._origin.amax(0) - self._origin.amin(0)).norm())
        self._geometry = None if registration is None else [
            ObjectGeometry(c, dim, np.asarray(o.fixed, dtype=bool), self.device) for c, o in zip(self._cells, objects)]
        self._tick, self._positions, self._model_state = 0, self._origin.clone(), None
        self._collider = None if self._static.collider is None else self._static.collider[0].clone()
        self._pose = [np.eye(dim + 1) for _ in objects]  # each collider's rigid motion from its template, now
        self._past: list[_Tick] = []
        if warm:
            self.warm_up()

    def warm_up(self) -> None:
        """Pay the first call's costs now, not at the first frame: import Open3D and run the depth path on a tiny
        cloud (when the model's depth processing is known or given), and make one prediction from the current
        state (discarded: the state is unchanged)."""
        depth = self._depth_or_none()
        if depth is not None:
            from ..sensors.camera import open3d_module

            try:
                open3d_module()
            except ImportError:
                pass  # no depth images then; point clouds still work (thinned without Open3D: see thin)
            else:
                grid = np.stack(np.meshgrid(*[np.arange(3.0)] * 3), -1).reshape(-1, 3) * depth.voxel_size
                depth._downsample(grid, self.dim, 0)
        batch = tick_batch(self._static, self._positions, self._positions, self._collider, self._collider,
                           [None] * len(self.names))
        advance(self._step_fn, batch, self._positions, False, self.model.connectivity, self.model.with_material,
                self._model_state)

    # ---- the state ---------------------------------------------------------------------------------------
    @property
    def tick(self) -> int:
        """The current tick t: the positions are the (predicted) state t."""
        return self._tick

    def positions(self) -> dict[Hashable, Tensor]:
        """The mesh of every object at the current tick, name -> [N_b, d] (copies)."""
        return {name: self._positions[self._nodes[b]:self._nodes[b + 1]].clone() for b, name in enumerate(self.names)}

    def collider_positions(self) -> dict[Hashable, Tensor]:
        """The collider vertices of every object at the current tick, name -> [K_b, d] (copies; K_b = 0 without one)."""
        return {name: self._collider_of(self._collider, b).clone() for b, name in enumerate(self.names)}

    def material_estimate(self) -> dict[Hashable, float] | None:
        """The Poisson's ratio each object's point clouds have shown so far, for a model that estimates it
        (GGNSID: the fused estimate its state carries, the prior before any cloud); None for the others."""
        estimate = getattr(self.model, "material_estimate", None)
        if estimate is None:
            return None
        state = self._model_state
        if state is None:  # no step yet: the prior, the state a first step starts from
            ones = self._origin.new_ones(len(self.names))
            state = (ones, torch.zeros_like(ones))
        return dict(zip(self.names, estimate(state).tolist()))

    def state_dict(self) -> dict[str, Any]:
        """Everything a restored simulator continues from (copies): the model's identity (its class and the
        sha256 of its weights: a state is refused by a simulator of another model), the tick, the mesh
        positions [sumN, d], the collider vertices [sumK, d] (or None), the model state (an LSTM's (h, c),
        GGNSID's fused estimate; None before the first step) and the kept past ticks. Plain tensors, lists,
        strings and ints: `torch.save` writes it. (What was observed is not kept: an observation of a tick
        restored from a state replaces its cloud instead of joining it.)"""
        return {"format": STATE_FORMAT, "model": dict(self.identity), "names": list(self.names), "tick": self._tick,
                "positions": self._positions.clone(), "collider": _clone(self._collider),
                "poses": [torch.as_tensor(p) for p in self._pose],
                "model_state": _clone(self._model_state),
                "history": [{"tick": p.tick, "positions": p.positions.clone(), "model_state": _clone(p.model_state),
                             "collider": _clone(p.collider), "points": [_clone(c) for c in p.points]}
                            for p in self._past]}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Continue from a `state_dict` of a simulator of the same model and objects (ValueError naming what does
        not fit; the state is unchanged then)."""
        if not isinstance(state, Mapping) or state.get("format") != STATE_FORMAT:
            raise ValueError(f"not an OnlineSimulator state of format {STATE_FORMAT}")
        if state.get("model") != self.identity:
            made = state.get("model") or {}
            raise ValueError(f"the state was made by a {made.get('class')} (weights sha256 "
                             f"{str(made.get('weights_sha256'))[:12]}...), this simulator runs a {self.identity['class']} "
                             f"({self.identity['weights_sha256'][:12]}...): another model's state is not this one's")
        if list(state.get("names", [])) != self.names:
            raise ValueError(f"the state is of objects {state.get('names')}, this simulator's are {self.names}")
        tick = state.get("tick")
        if isinstance(tick, bool) or not isinstance(tick, int) or tick < 0:
            raise ValueError(f"the state's tick must be an integer >= 0, got {tick!r}")
        past = state.get("history", [])
        if len(past) > self.history or [p["tick"] for p in past] != list(range(tick - len(past), tick)):
            raise ValueError(f"the state's past ticks {[p['tick'] for p in past]} are not the up to {self.history} "
                             f"ticks before its tick {tick}")
        positions = self._checked_tensor(state.get("positions"), self._origin.shape, "positions")
        self._check_model_state(state.get("model_state"), "model state")
        for p in past:
            self._check_model_state(p["model_state"], f"model state of tick {p['tick']}")
        collider = self._checked_collider(state.get("collider"))
        poses = state.get("poses")
        if not isinstance(poses, (list, tuple)) or len(poses) != len(self.names) or not all(
                isinstance(q, Tensor) and tuple(q.shape) == (self.dim + 1, self.dim + 1) and torch.isfinite(q).all()
                for q in poses):
            raise ValueError(f"the state's collider poses must be {len(self.names)} finite [{self.dim + 1}, "
                             f"{self.dim + 1}] tensors")
        kept = [_Tick(p["tick"],
                      self._checked_tensor(p["positions"], self._origin.shape, f"positions of tick {p['tick']}"),
                      _to(p["model_state"], self.device), self._checked_collider(p["collider"]),
                      [None if c is None else self._checked_tensor(c, (None, self.dim), f"points of tick {p['tick']}")
                       for c in p["points"]], [None] * len(self.names))
                for p in past]
        if any(len(p.points) != len(self.names) for p in kept):
            raise ValueError(f"the state's past ticks need one point cloud entry per object ({len(self.names)})")
        self._tick, self._positions, self._collider = tick, positions, collider
        self._pose = [q.double().cpu().numpy() for q in poses]
        self._model_state, self._past = _to(state.get("model_state"), self.device), kept

    # ---- a tick ----------------------------------------------------------------------------------------------
    def step(self, collider: Any = None, observation: Any = None, fixed: Any = None) -> dict[Hashable, Tensor]:
        """Advance every object by one tick: state t -> t + 1.

        Args:
            collider: the collider's pose at t + 1: its vertices [K, d], or a rigid transform [d+1, d+1] of its
                template (the object's collider at tick 0); for several objects a mapping name -> pose. None (or
                an object left out): the collider stays where it is. The nodes it grasps (`online_object`'s
                `grasped`; a recorded trajectory's fixed nodes that move) move with it as a rigid body.
            observation: what was seen of state t (or of an earlier tick, `Observation.tick`): an `Observation`,
                a point cloud [P, d], a `DepthImage`, a list of depth images, or a list of `Observation`s (of one
                tick or several, in any order); for several objects a mapping name -> any of these, or depth
                images (unmasked, cropped around each object) for all of them. None: nothing was seen (the model
                predicts without a point cloud). What is seen of one tick is joined, within a call and across calls.
            fixed: the fixed nodes' positions at t + 1, [F_b, d] in node order (a mapping for several
                objects); None: they stay where they are, but for the grasped ones, which follow the collider.

        Returns:
            the mesh of every object at t + 1, name -> [N_b, d].

        Raises:
            ValueError: bad input (shapes, non-finite values, a transform that is not rigid, an unknown
                object, an observation of a future tick or of one older than the kept history); nothing
                changed.
            OnlineDivergence: the prediction is not finite or left the scene (a `RolloutError` naming the
                object); nothing changed.
        """
        collider_next, poses = self._parse_colliders(collider)
        fixed_next = self._parse_fixed(fixed, poses)
        seen = self._parse_observations(observation)  # {(object, tick): _Seen}
        clouds = self._clouds(seen)  # {(object, tick): cloud [P, d]}
        past = list(self._past)
        positions, model_state = self._positions, self._model_state
        late = [tick for _, tick in clouds if tick < self._tick]
        if late:  # correct the kept tick and predict forward to now with the inputs each tick had
            first = min(late) - past[0].tick
            kept = past[:first]
            positions, model_state = past[first].positions, past[first].model_state
            for i in range(first, len(past)):
                then = past[i]
                points = [clouds.get((b, then.tick), then.points[b]) for b in range(len(self.names))]
                observed = [then.seen[b] if (b, then.tick) not in seen else seen[(b, then.tick)].joined(then.seen[b])
                            for b in range(len(self.names))]
                following = past[i + 1] if i + 1 < len(past) else None
                nxt, next_state = self._advance(
                    positions, following.positions if following else self._positions, then.collider,
                    following.collider if following else self._collider, points, model_state, then.tick)
                kept.append(_Tick(then.tick, positions, model_state, then.collider, points, observed))
                positions, model_state = nxt, next_state
            past = kept
        points = [clouds.get((b, self._tick)) for b in range(len(self.names))]
        observed = [seen.get((b, self._tick)) for b in range(len(self.names))]
        nxt, next_state = self._advance(positions, fixed_next, self._collider, collider_next, points, model_state,
                                        self._tick)
        past.append(_Tick(self._tick, positions, model_state, self._collider, points, observed))
        # nothing failed: commit
        self._past = past[max(0, len(past) - self.history):] if self.history else []
        self._positions, self._model_state, self._collider = nxt, next_state, collider_next
        self._pose = poses
        self._tick += 1
        return self.positions()

    def _advance(self, positions: Tensor, fixed_next: Tensor, collider: Tensor | None, collider_next: Tensor | None,
                 points: list[Tensor | None], model_state: Any, tick: int) -> tuple[Tensor, Any]:
        """One prediction (`engine.advance`) from `positions`, registered first to the tick's clouds when the
        simulator registers, checked for divergence (OnlineDivergence naming the object and tick)."""
        if self.registration is not None and any(c is not None for c in points):
            positions = self._registered(positions, points)
            if not self.registration.feed_model:
                points = [None] * len(points)
        batch = tick_batch(self._static, positions, fixed_next, collider, collider_next, points)
        try:
            nxt, model_state = advance(self._step_fn, batch, positions, points_flags(points), self.model.connectivity,
                                       self.model.with_material, model_state)
        except ValueError as error:
            if "max_num_neighbors" not in str(error):
                raise
            sizes = {self.names[b]: len(c) for b, c in enumerate(points) if c is not None}
            raise ValueError(f"tick {tick}: a point cloud is denser than the model's graph allows (points per object: "
                             f"{sizes}): give OnlineSimulator a DepthProcessing whose voxel_size is the training "
                             f"sensor's, so clouds are down-sampled to its density ({error})") from None
        self._check_divergence(nxt, tick)
        return nxt, model_state

    def _registered(self, positions: Tensor, points: list[Tensor | None]) -> Tensor:
        """`positions` [sumN, d] with each observed object's mesh registered to its cloud."""
        out = positions.clone()
        for b, cloud in enumerate(points):
            if cloud is not None:
                rows = slice(self._nodes[b], self._nodes[b + 1])
                out[rows] = register(self.registration, self._geometry[b], positions[rows], cloud)
        return out

    def _check_divergence(self, prediction: Tensor, tick: int) -> None:
        """OnlineDivergence when the prediction of tick + 1 [sumN, d] is not finite or has a node farther than
        ESCAPE_FACTOR x the objects' extent from its start, naming the first such object and node."""
        finite = torch.isfinite(prediction).all(dim=1)
        far = (prediction - self._origin).norm(dim=1) > ESCAPE_FACTOR * self._extent
        bad = ~finite | far
        if not bool(bad.any()):
            return
        first = int(torch.nonzero(bad)[0])
        b = int(np.searchsorted(np.asarray(self._nodes), first, side="right")) - 1
        name, node = self.names[b], first - self._nodes[b]
        what = "is not finite" if not bool(finite[first]) else \
            f"is {float((prediction[first] - self._origin[first]).norm()):.4g} from its start, more than " \
            f"{ESCAPE_FACTOR:g} x the objects' extent ({self._extent:.4g})"
        raise OnlineDivergence(f"object {name!r} diverged predicting tick {tick + 1} from tick {tick}: its mesh node "
                               f"{node} {what}; {int(bad.sum())} node(s) so; the simulator's state is unchanged",
                               step=tick, object=name)

    # ---- input checks (nothing is changed here) ------------------------------------------------------------------
    def _per_object(self, value: Any, what: str, shared: bool = False) -> dict[int, Any]:
        """{object index: value} of a mapping name -> value, or of a bare value: the one object's, or (shared)
        every object's. ValueError for unknown names, or a bare value with several objects."""
        if value is None:
            return {}
        if isinstance(value, Mapping):
            unknown = [name for name in value if name not in self._index]
            if unknown:
                raise ValueError(f"{what} for unknown object(s) {unknown}; the objects are {self.names}")
            return {self._index[name]: v for name, v in value.items() if v is not None}
        if len(self.names) == 1:
            return {0: value}
        if shared:
            return dict.fromkeys(range(len(self.names)), value)
        raise ValueError(f"{len(self.names)} objects step together: give the {what} as a mapping name -> value "
                         f"(the objects are {self.names})")

    def _parse_colliders(self, collider: Any) -> tuple[Tensor | None, list[np.ndarray]]:
        """(the collider vertices [sumK, d] at t + 1 from the poses given, others kept; each collider's rigid
        motion from its template at t + 1)."""
        poses = self._per_object(collider, "collider pose")
        motions = list(self._pose)
        if self._collider is None:
            if poses:
                raise ValueError("collider pose given, but the object(s) have no collider")
            return None, motions
        parts = [self._collider_of(self._collider, b) for b in range(len(self.names))]
        for b, pose in poses.items():
            name, template = self.names[b], self._templates[b]
            if len(template) == 0:
                raise ValueError(f"collider pose given for object {name!r}, which has no collider")
            pose = float_array(pose, f"collider pose of object {name!r}", finite=False)
            if pose.shape == template.shape:
                if not np.isfinite(pose).all():
                    raise ValueError(f"collider positions of object {name!r} are not finite")
                vertices = pose
                motions[b] = rigid_motion(template, pose) if len(self._grasped[b]) else motions[b]
            elif pose.shape == (self.dim + 1, self.dim + 1):
                transform = check_rigid(pose, self.dim, f"collider pose of object {name!r}", self.rigid_tolerance)
                vertices = template @ transform[:self.dim, :self.dim].T + transform[:self.dim, self.dim]
                motions[b] = transform
            else:
                raise ValueError(f"collider pose of object {name!r} must be its vertices {list(template.shape)} or a "
                                 f"rigid transform [{self.dim + 1}, {self.dim + 1}], got shape {list(pose.shape)}")
            parts[b] = torch.as_tensor(vertices).to(self.device, self.dtype)
        return torch.cat(parts), motions

    def _parse_fixed(self, fixed: Any, motions: list[np.ndarray]) -> Tensor:
        """[sumN, d] whose fixed rows are the fixed nodes at t + 1: as given, else the grasped ones moved with their
        collider (`motions`) and the others where they are."""
        given = self._per_object(fixed, "fixed node positions")
        out = self._positions.clone()
        for b, grasped in enumerate(self._grasped):
            if b not in given and len(grasped) and motions[b] is not self._pose[b]:
                moved = self._grasped_start[b] @ motions[b][:self.dim, :self.dim].T + motions[b][:self.dim, self.dim]
                out[self._nodes[b] + torch.as_tensor(grasped, device=self.device)] = \
                    torch.as_tensor(moved).to(self.device, self.dtype)
        for b, value in given.items():
            index = self._fixed_index[b]
            value = float_array(value, f"fixed node positions of object {self.names[b]!r}")
            if value.shape != (len(index), self.dim):
                raise ValueError(f"fixed node positions of object {self.names[b]!r} must be [{len(index)}, {self.dim}] "
                                 f"(its fixed nodes in node order), got {list(value.shape)}")
            out[self._nodes[b] + torch.as_tensor(index, device=self.device)] = \
                torch.as_tensor(value).to(self.device, self.dtype)
        return out

    def _parse_observations(self, observation: Any) -> dict[tuple[int, int], _Seen]:
        """{(object index, tick): what was seen}: every observation checked, those of one object and tick joined."""
        shared = _is_images(observation) or (isinstance(observation, Observation) and observation.points is None) or (
            _is_observations(observation) and all(o.points is None for o in observation))
        given = self._per_object(observation, "observation", shared=shared)
        if shared and len(self.names) > 1 and any(image.mask is not None for image in _images_of(observation)):
            raise ValueError(f"depth images with a mask show one object: give them as a mapping name -> images (the "
                             f"objects are {self.names}); images without a mask are cropped around each object")
        seen: dict[tuple[int, int], _Seen] = {}
        for b, value in given.items():
            name = self.names[b]
            if _is_observations(value):
                observed = list(value)
            elif isinstance(value, Observation):
                observed = [value]
            elif _is_images(value):
                observed = [Observation(images=value)]
            elif isinstance(value, Sequence) and not isinstance(value, (str, bytes)) and value and not _is_numeric(value):
                kinds = sorted({type(v).__name__ for v in value})
                raise ValueError(f"observation of object {name!r}: a list must hold Observations or DepthImages "
                                 f"(of one kind), or be a point cloud [P, {self.dim}]; got a list of {', '.join(kinds)}")
            else:
                observed = [Observation(points=value)]
            for one in observed:
                tick = self._tick if one.tick is None else int(one.tick)
                if tick > self._tick:
                    raise ValueError(f"observation of object {name!r} is stamped tick {tick}, in the future (the "
                                     f"current tick is {self._tick})")
                if tick < self._tick - len(self._past):
                    raise ValueError(f"observation of object {name!r} is stamped tick {tick}, older than the kept "
                                     f"history (ticks {self._tick - len(self._past)}..{self._tick}; "
                                     f"history={self.history})")
                if one.points is not None and (one.points.ndim != 2 or one.points.shape[1] != self.dim):
                    raise ValueError(f"observation points of object {name!r} must be [P, {self.dim}], got "
                                     f"{list(one.points.shape)}")
                entry = seen.setdefault((b, tick), _Seen())
                entry.images.extend(one.images)
                if one.points is not None:
                    entry.points.append(one.points)
        return seen

    def _clouds(self, seen: dict[tuple[int, int], _Seen]) -> dict[tuple[int, int], Tensor]:
        """The point cloud of each (object, tick) seen, joined with what was seen of that tick before."""
        clouds = {}
        for (b, tick), now in seen.items():
            before = self._past[tick - self._tick].seen[b] if tick < self._tick else None
            both = now.joined(before)
            parts = []
            if both.images:
                parts.append(self._depth_cloud(b, both.images, tick))
            if both.points:
                points = np.concatenate(both.points).astype(np.float32)
                depth = self._depth_or_none()
                parts.append(points if depth is None else depth.thin(points, self.dim, tick))
            cloud = np.concatenate(parts) if len(parts) > 1 else parts[0]
            clouds[(b, tick)] = torch.as_tensor(cloud).to(self.device, self.dtype)
        return clouds

    def _depth_or_none(self) -> DepthProcessing | None:
        """The depth processing given or that of the model's training sensor; None when neither is known."""
        if self.depth is None:
            try:
                self.depth = DepthProcessing.for_model(self.model)
            except ValueError:
                return None
        return self.depth

    def _depth_cloud(self, b: int, images: Sequence[DepthImage], tick: int) -> np.ndarray:
        """Object b's point cloud from depth images of `tick`, cropped around its state kept for that tick."""
        if self._depth_or_none() is None:
            DepthProcessing.for_model(self.model)  # raises the ValueError that says what to give
        then = self._past[tick - self._tick] if tick < self._tick else None
        positions = (then.positions if then else self._positions)[self._nodes[b]:self._nodes[b + 1]]
        collider = self._collider_of(then.collider if then else self._collider, b)
        collider = (collider.cpu().double().numpy(), self._faces[b]) if len(collider) else None
        return self.depth.cloud(images, self.dim, positions.cpu().double().numpy(), self._cells[b], collider, tick)

    def _collider_of(self, collider: Tensor | None, b: int) -> Tensor:
        if collider is None:
            return self._origin.new_zeros(0, self.dim)
        return collider[self._vertices[b]:self._vertices[b + 1]]

    def _checked_tensor(self, value: Any, shape: tuple, what: str) -> Tensor:
        if not isinstance(value, Tensor) or value.dim() != len(shape) or any(
                s is not None and s != v for s, v in zip(shape, value.shape)) or not torch.isfinite(value).all():
            raise ValueError(f"the state's {what} must be a finite tensor of shape {list(shape)}")
        return value.to(self.device, self.dtype).clone()

    def _check_model_state(self, value: Any, what: str) -> None:
        """A model state is None or (nested) tuples of finite tensors with a row per mesh node (an LSTM's) or per
        object (GGNSID's); ValueError otherwise."""
        if value is None:
            return
        tensors = [value] if isinstance(value, Tensor) else list(value) if isinstance(value, (tuple, list)) else None
        rows = (len(self._origin), len(self.names))
        if tensors is None or not all(isinstance(t, Tensor) and t.dim() >= 1 and t.size(0) in rows
                                      and torch.isfinite(t).all() for t in tensors):
            raise ValueError(f"the state's {what} must be None or tensors with a row per mesh node ({rows[0]}) or "
                             f"per object ({rows[1]}), finite")

    def _checked_collider(self, value: Any) -> Tensor | None:
        if self._collider is None:
            if value is not None:
                raise ValueError("the state has collider positions, but these objects have no collider")
            return None
        return self._checked_tensor(value, tuple(self._collider.shape), "collider positions")



def model_identity(model: Any) -> dict[str, str]:
    """A model's class and the sha256 of its weights and buffers (names, shapes, values): what a saved online state
    belongs to."""
    digest = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        digest.update(name.encode())
        digest.update(str(tuple(tensor.shape)).encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return {"class": type(model).__name__, "weights_sha256": digest.hexdigest()}


def dataclasses_replace_two_states(trajectory: Trajectory, dim: int) -> Trajectory:
    """The static parts of an object as a trajectory of two states, both its state 0, without point clouds."""
    import dataclasses

    o = trajectory
    return dataclasses.replace(
        o, positions=np.stack([o.positions[0]] * 2), collider_positions=np.stack([o.collider_positions[0]] * 2),
        points=np.zeros((0, dim), dtype=np.float32), point_offsets=np.zeros(3, dtype=np.int64), diagnostics={})


def _is_images(value: Any) -> bool:
    return isinstance(value, DepthImage) or (isinstance(value, Sequence) and len(value) > 0
                                             and all(isinstance(v, DepthImage) for v in value))


def _is_observations(value: Any) -> bool:
    return isinstance(value, Sequence) and len(value) > 0 and all(isinstance(v, Observation) for v in value)


def _is_numeric(value: Sequence) -> bool:
    """Whether a list is an array of numbers (a point cloud given as nested lists)."""
    try:
        np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return True


def _images_of(observation: Any) -> tuple[DepthImage, ...]:
    """The depth images of a bare observation (a DepthImage, a list of them, an `Observation` or a list of them)."""
    if isinstance(observation, DepthImage):
        return (observation,)
    if isinstance(observation, Observation):
        return tuple(observation.images)
    if _is_observations(observation):
        return tuple(image for o in observation for image in o.images)
    return tuple(observation)


def _clone(value: Any) -> Any:
    """A copy of a tensor, or of the tensors in a (nested) tuple or list; None stays None."""
    if isinstance(value, Tensor):
        return value.clone()
    if isinstance(value, (tuple, list)):
        return type(value)(_clone(v) for v in value)
    return value


def _to(value: Any, device: torch.device) -> Any:
    """`_clone` onto `device`."""
    if isinstance(value, Tensor):
        return value.to(device).clone()
    if isinstance(value, (tuple, list)):
        return type(value)(_to(v, device) for v in value)
    return value

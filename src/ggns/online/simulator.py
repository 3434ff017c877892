"""`OnlineSimulator`: a trained simulator stepped one tick at a time by its caller (a robot's control loop),
fed the collider's new pose every tick and an observation (a point cloud or depth images) when one arrives.

Ticks and states: tick t holds state t (the mesh as predicted for it). `step(collider=pose of t + 1,
observation=what was seen of state t)` predicts state t + 1 exactly as prediction step t of the offline
engine (`evaluation.rollout.rollout`) does, through the same graph builder and step function
(`online.engine`): fed a recorded trajectory's collider positions and, where a schedule says so, its
point clouds, it returns the offline rollout's states. An observation stamped with an earlier tick s (a
sensor's latency) corrects the state kept for s, and the simulator predicts forward from there to now
with the inputs it had (`history` ticks are kept for that).

Every input is checked before anything changes: bad input raises one ValueError naming the problem and
leaves the state as it was; so does a step whose prediction is not finite (a `RolloutError`).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from numpy.typing import ArrayLike
from torch import Tensor

from ..batch import TrajectoryBatch
from ..data.observations import trajectory_from_arrays
from ..evaluation.rollout import raise_divergence
from ..sensors.camera import DepthImage, check_rigid
from ..trajectory import Trajectory
from .depth import DepthProcessing
from .engine import advance, points_flags, tick_batch

STATE_FORMAT = 1  # the layout of `OnlineSimulator.state_dict`


@dataclass(frozen=True, eq=False)
class Observation:
    """What was seen of one object at one tick: a point cloud, or depth images.

    Attributes:
        points: [P, d] points on the object's surface in the task space (used as they are, like a dataset's
            point cloud: crop and down-sample them as the training data's sensor did), or None.
        images: depth images of the tick (`sensors.camera.DepthImage`: depth, intrinsics, camera-to-world
            pose, optional mask), turned into the cloud by the simulator's `DepthProcessing`; or ().
        tick: the tick whose state it shows; None: the tick being stepped (the current one). An earlier tick
            (a sensor's latency) corrects that tick's state and predicts forward again.
    """

    points: Any = None
    images: Sequence[DepthImage] = ()
    tick: int | None = None

    def __post_init__(self) -> None:
        images = (self.images,) if isinstance(self.images, DepthImage) else tuple(self.images)
        if not all(isinstance(image, DepthImage) for image in images):
            raise ValueError("observation images must be DepthImage objects (ggns.sensors.camera.DepthImage)")
        object.__setattr__(self, "images", images)
        if (self.points is None) == (not images):
            raise ValueError("an observation holds either a point cloud (points) or depth images (images), "
                             "not both and not neither")
        if self.points is not None:
            object.__setattr__(self, "points", _float_array(self.points, "observation points"))
        if self.tick is not None and (isinstance(self.tick, bool) or not isinstance(self.tick, (int, np.integer))
                                      or self.tick < 0):
            raise ValueError(f"observation tick must be an integer >= 0 or None, got {self.tick!r}")


@dataclass
class _Tick:
    """What a past tick kept for a correction: state t (mesh positions [sumN, d], model state before step t),
    the collider vertices at t [sumK, d] and the point clouds step t used (per object, None: none)."""

    tick: int
    positions: Tensor
    model_state: Any
    collider: Tensor | None
    points: list[Tensor | None]


def online_object(rest_positions: ArrayLike, cells: ArrayLike, fixed: ArrayLike,
                  collider_vertices: ArrayLike | None = None, collider_faces: ArrayLike | None = None,
                  poissons_ratio: float | None = None, initial_positions: ArrayLike | None = None,
                  youngs_modulus: float = 1.0, fix_orientation: bool = False) -> Trajectory:
    """An object for `OnlineSimulator` from plain arrays, checked as `data.observations.trajectory_from_arrays`
    checks a user's trajectory (ValueError naming the problem): a `Trajectory` of two states, both the initial one.

    Args:
        rest_positions: [N, d] mesh nodes at rest (task space), cells [C, d+1], fixed: bool mask [N] or indices.
        collider_vertices: [K, d] the collider's surface vertices at tick 0, the template its poses move
            (None: no collider); collider_faces [F, d] its segments (2D) or triangles (3D).
        poissons_ratio: for the models told the material (MGN(M), GGNS(M)); None: unknown.
        initial_positions: [N, d] the mesh at tick 0 (None: at rest).
        youngs_modulus: stored only (no model reads it).
    """
    rest = _float_array(rest_positions, "rest_positions")
    dim = rest.shape[1] if rest.ndim == 2 else 2
    if collider_vertices is None:
        vertices, faces = np.zeros((0, dim)), np.zeros((0, dim), dtype=np.int64)
    else:
        vertices, faces = _float_array(collider_vertices, "collider_vertices"), collider_faces
    trajectory = trajectory_from_arrays(rest, cells, fixed, faces, np.stack([vertices, vertices]), [None, None],
                                        youngs_modulus, poissons_ratio, fix_orientation=fix_orientation)
    if initial_positions is not None:
        initial = _float_array(initial_positions, "initial_positions")
        if initial.shape != rest.shape:
            raise ValueError(f"initial_positions must be [N={len(rest)}, {dim}] like rest_positions, got "
                             f"{list(initial.shape)}")
        trajectory = dataclasses.replace(trajectory, positions=np.stack([initial, initial]))
    return trajectory


class OnlineSimulator:
    """A trained simulator (GGNS, GGNS+LSTM, GGNSID, MGN, MGN(M), ...) stepped tick by tick (module docstring).

    Args:
        model: the simulator, e.g. `ggns.pretrained.load("plate/ggns")` or `load_simulator(path)`; its
            rollout step function is used (a static one's eager twin, `model.step`).
        objects: one object or several, as `Trajectory`s (`online_object`, or a recorded trajectory: its
            rest positions, cells, fixed mask, collider faces and material, its state 0 as tick 0 and its
            collider at state 0 as the template poses move), a sequence (named 0, 1, ...) or a mapping
            name -> object. All have the model's dimension; they step together in one batch.
        depth: how depth images become point clouds (`DepthProcessing`); None: `DepthProcessing.for_model`
            when the first depth image arrives (a shipped simulator's training sensor).
        history: past ticks kept for late observations (an observation of tick t - d, d <= history).
    """

    def __init__(self, model: Any, objects: Trajectory | Sequence[Trajectory] | Mapping[Hashable, Trajectory],
                 depth: DepthProcessing | None = None, history: int = 8):
        if isinstance(objects, Trajectory):
            objects = [objects]
        named = dict(objects) if isinstance(objects, Mapping) else dict(enumerate(objects))
        if not named or not all(isinstance(o, Trajectory) for o in named.values()):
            raise ValueError("objects must be one Trajectory, a non-empty sequence of them or a mapping name -> "
                             "Trajectory (ggns.online.online_object builds one from arrays)")
        if isinstance(history, bool) or not isinstance(history, int) or history < 0:
            raise ValueError(f"history must be an integer >= 0, got {history!r}")
        dim = int(model.hparams.dim)
        other = [f"{name!r} ({o.dim}D)" for name, o in named.items() if o.dim != dim]
        if other:
            raise ValueError(f"the model simulates {dim}D objects; not object(s) {', '.join(other)}")
        self.model, self.dim, self.history = model, dim, history
        self.names: list[Hashable] = list(named)
        self._index = {name: b for b, name in enumerate(self.names)}
        self.depth = depth
        # the rollout step function; a static one (`static_rollouts`) steps whole rollouts: its eager twin here
        self._step_fn = model.step if getattr(model, "static_rollouts", False) else model.rollout_step()
        parameter = next(model.parameters())
        self.device, self.dtype = parameter.device, parameter.dtype
        objects = list(named.values())
        two_states = [dataclasses.replace(
            o, positions=np.stack([o.positions[0]] * 2), collider_positions=np.stack([o.collider_positions[0]] * 2),
            points=np.zeros((0, dim), dtype=np.float32), point_offsets=np.zeros(3, dtype=np.int64), diagnostics={})
            for o in objects]
        static = TrajectoryBatch.from_trajectories(two_states, dtype=self.dtype)  # checked here, on the host
        if model.with_material:
            static.require_material(f"{type(model).__name__}")
        self._static = static.to(self.device)
        self._cells = [np.asarray(o.cells) for o in objects]
        self._faces = [np.asarray(o.collider_faces) for o in objects]
        self._templates = [np.asarray(o.collider_positions[0], dtype=np.float64) for o in objects]
        self._fixed_index = [np.flatnonzero(o.fixed) for o in objects]
        self._nodes = self._static.node_offsets
        self._vertices = self._static.collider_range
        self._origin = self._static.positions[0].clone()
        self._extent = float((self._origin.amax(0) - self._origin.amin(0)).norm())
        self._tick, self._positions, self._model_state = 0, self._origin.clone(), None
        self._collider = None if self._static.collider is None else self._static.collider[0].clone()
        self._past: list[_Tick] = []

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
        """Everything a restored simulator continues from (copies): the tick, the mesh positions [sumN, d],
        the collider vertices [sumK, d] (or None), the model state (an LSTM's (h, c), GGNSID's fused
        estimate; None before the first step) and the kept past ticks. Plain tensors, lists and ints:
        `torch.save` writes it."""
        return {"format": STATE_FORMAT, "names": list(self.names), "tick": self._tick,
                "positions": self._positions.clone(), "collider": _clone(self._collider),
                "model_state": _clone(self._model_state),
                "history": [{"tick": p.tick, "positions": p.positions.clone(), "model_state": _clone(p.model_state),
                             "collider": _clone(p.collider), "points": [_clone(c) for c in p.points]}
                            for p in self._past]}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Continue from a `state_dict` of a simulator of the same objects (ValueError naming what does not fit;
        the state is unchanged then)."""
        if not isinstance(state, Mapping) or state.get("format") != STATE_FORMAT:
            raise ValueError(f"not an OnlineSimulator state of format {STATE_FORMAT}")
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
        kept = [_Tick(p["tick"],
                      self._checked_tensor(p["positions"], self._origin.shape, f"positions of tick {p['tick']}"),
                      _to(p["model_state"], self.device), self._checked_collider(p["collider"]),
                      [None if c is None else self._checked_tensor(c, (None, self.dim), f"points of tick {p['tick']}")
                       for c in p["points"]])
                for p in past]
        if any(len(p.points) != len(self.names) for p in kept):
            raise ValueError(f"the state's past ticks need one point cloud entry per object ({len(self.names)})")
        self._tick, self._positions, self._collider = tick, positions, collider
        self._model_state, self._past = _to(state.get("model_state"), self.device), kept

    # ---- a tick ----------------------------------------------------------------------------------------------
    def step(self, collider: Any = None, observation: Any = None, fixed: Any = None) -> dict[Hashable, Tensor]:
        """Advance every object by one tick: state t -> t + 1.

        Args:
            collider: the collider's pose at t + 1: its vertices [K, d], or a rigid transform [d+1, d+1] of its
                template (the object's collider at tick 0); for several objects a mapping name -> pose. None (or
                an object left out): the collider stays where it is.
            observation: what was seen of state t (or of an earlier tick, `Observation.tick`): an `Observation`,
                a point cloud [P, d], a `DepthImage` or a list of them; for several objects a mapping
                name -> observation, or depth images (unmasked, cropped around each object) for all of them.
                None: nothing was seen (the model predicts without a point cloud).
            fixed: the fixed nodes' positions at t + 1, [F_b, d] in node order (a mapping for several
                objects); None: they stay where they are.

        Returns:
            the mesh of every object at t + 1, name -> [N_b, d].

        Raises:
            ValueError: bad input (shapes, non-finite values, a transform that is not rigid, an unknown
                object, an observation of a future tick or of one older than the kept history); nothing
                changed.
            RolloutError: the prediction is not finite or left the scene; nothing changed.
        """
        collider_next = self._parse_colliders(collider)
        fixed_next = self._parse_fixed(fixed)
        clouds = self._parse_observations(observation)  # {object: (tick, cloud)}
        past = list(self._past)
        positions, model_state = self._positions, self._model_state
        late = [tick for tick, _ in clouds.values() if tick < self._tick]
        if late:  # correct the kept tick and predict forward to now with the inputs each tick had
            first = min(late) - past[0].tick
            kept = past[:first]
            positions, model_state = past[first].positions, past[first].model_state
            for i in range(first, len(past)):
                then = past[i]
                points = [clouds[b][1] if b in clouds and clouds[b][0] == then.tick else then.points[b]
                          for b in range(len(self.names))]
                following = past[i + 1] if i + 1 < len(past) else None
                nxt, next_state = self._advance(
                    positions, following.positions if following else self._positions, then.collider,
                    following.collider if following else self._collider, points, model_state, then.tick)
                kept.append(_Tick(then.tick, positions, model_state, then.collider, points))
                positions, model_state = nxt, next_state
            past = kept
        points = [clouds[b][1] if b in clouds and clouds[b][0] == self._tick else None for b in range(len(self.names))]
        nxt, next_state = self._advance(positions, fixed_next, self._collider, collider_next, points, model_state,
                                        self._tick)
        past.append(_Tick(self._tick, positions, model_state, self._collider, points))
        # nothing failed: commit
        self._past = past[max(0, len(past) - self.history):] if self.history else []
        self._positions, self._model_state, self._collider = nxt, next_state, collider_next
        self._tick += 1
        return self.positions()

    def _advance(self, positions: Tensor, fixed_next: Tensor, collider: Tensor | None, collider_next: Tensor | None,
                 points: list[Tensor | None], model_state: Any, tick: int) -> tuple[Tensor, Any]:
        """One prediction (`engine.advance`) checked for divergence (RolloutError naming the tick)."""
        batch = tick_batch(self._static, positions, fixed_next, collider, collider_next, points)
        nxt, model_state = advance(self._step_fn, batch, positions, points_flags(points), self.model.connectivity,
                                   self.model.with_material, model_state)
        raise_divergence(nxt, self._origin, self._extent, self._static, tick)
        return nxt, model_state

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

    def _parse_colliders(self, collider: Any) -> Tensor | None:
        """The collider vertices [sumK, d] at t + 1 from the poses given (others kept)."""
        poses = self._per_object(collider, "collider pose")
        if self._collider is None:
            if poses:
                raise ValueError("collider pose given, but the object(s) have no collider")
            return None
        parts = [self._collider_of(self._collider, b) for b in range(len(self.names))]
        for b, pose in poses.items():
            name, template = self.names[b], self._templates[b]
            if len(template) == 0:
                raise ValueError(f"collider pose given for object {name!r}, which has no collider")
            pose = _float_array(pose, f"collider pose of object {name!r}", finite=False)
            if pose.shape == template.shape:
                if not np.isfinite(pose).all():
                    raise ValueError(f"collider positions of object {name!r} are not finite")
                vertices = pose
            elif pose.shape == (self.dim + 1, self.dim + 1):
                transform = check_rigid(pose, self.dim, f"collider pose of object {name!r}")
                vertices = template @ transform[:self.dim, :self.dim].T + transform[:self.dim, self.dim]
            else:
                raise ValueError(f"collider pose of object {name!r} must be its vertices {list(template.shape)} or a "
                                 f"rigid transform [{self.dim + 1}, {self.dim + 1}], got shape {list(pose.shape)}")
            parts[b] = torch.as_tensor(vertices).to(self.device, self.dtype)
        return torch.cat(parts)

    def _parse_fixed(self, fixed: Any) -> Tensor:
        """[sumN, d] whose fixed rows are the fixed nodes at t + 1 (the current positions where not given)."""
        given = self._per_object(fixed, "fixed node positions")
        if not given:
            return self._positions
        out = self._positions.clone()
        for b, value in given.items():
            index = self._fixed_index[b]
            value = _float_array(value, f"fixed node positions of object {self.names[b]!r}")
            if value.shape != (len(index), self.dim):
                raise ValueError(f"fixed node positions of object {self.names[b]!r} must be [{len(index)}, {self.dim}] "
                                 f"(its fixed nodes in node order), got {list(value.shape)}")
            out[self._nodes[b] + torch.as_tensor(index, device=self.device)] = \
                torch.as_tensor(value).to(self.device, self.dtype)
        return out

    def _parse_observations(self, observation: Any) -> dict[int, tuple[int, Tensor]]:
        """{object index: (tick, point cloud [P, d] on the device)}: checked, depth images processed."""
        shared = isinstance(observation, DepthImage) or (
            isinstance(observation, Sequence) and len(observation) > 0
            and all(isinstance(o, DepthImage) for o in observation)) or (
            isinstance(observation, Observation) and observation.points is None)
        given = self._per_object(observation, "observation", shared=shared)
        if shared and len(self.names) > 1 and any(
                image.mask is not None for image in _images_of(observation)):
            raise ValueError(f"depth images with a mask show one object: give them as a mapping name -> images (the "
                             f"objects are {self.names}); images without a mask are cropped around each object")
        clouds = {}
        for b, value in given.items():
            name = self.names[b]
            observed = value if isinstance(value, Observation) else (
                Observation(images=value) if isinstance(value, DepthImage) or (
                    isinstance(value, Sequence) and value and all(isinstance(v, DepthImage) for v in value))
                else Observation(points=value))
            tick = self._tick if observed.tick is None else int(observed.tick)
            if tick > self._tick:
                raise ValueError(f"observation of object {name!r} is stamped tick {tick}, in the future (the current "
                                 f"tick is {self._tick})")
            if tick < self._tick - len(self._past):
                raise ValueError(f"observation of object {name!r} is stamped tick {tick}, older than the kept history "
                                 f"(ticks {self._tick - len(self._past)}..{self._tick}; history={self.history})")
            if observed.points is not None:
                points = observed.points
                if points.ndim != 2 or points.shape[1] != self.dim:
                    raise ValueError(f"observation points of object {name!r} must be [P, {self.dim}], got "
                                     f"{list(points.shape)}")
            else:
                points = self._depth_cloud(b, observed.images, tick)
            clouds[b] = (tick, torch.as_tensor(points).to(self.device, self.dtype))
        return clouds

    def _depth_cloud(self, b: int, images: Sequence[DepthImage], tick: int) -> np.ndarray:
        """Object b's point cloud from depth images of `tick`, cropped around its state kept for that tick."""
        if self.depth is None:
            self.depth = DepthProcessing.for_model(self.model)
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


def _images_of(observation: Any) -> tuple[DepthImage, ...]:
    """The depth images of a bare observation (a DepthImage, a list of them, an `Observation`)."""
    if isinstance(observation, DepthImage):
        return (observation,)
    if isinstance(observation, Observation):
        return tuple(observation.images)
    return tuple(observation)


def _float_array(value: Any, what: str, finite: bool = True) -> np.ndarray:
    """float64 array of a numeric array or tensor; ValueError naming `what` otherwise (or when not finite)."""
    if isinstance(value, Tensor):
        value = value.detach().cpu().numpy()
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be an array of numbers, got {type(value).__name__}") from None
    if finite and not np.isfinite(array).all():
        raise ValueError(f"{what}: NaN or inf values")
    return array


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

"""The numerical failures that ggns reports (each names where it happened). Defined without importing
torch, so that the command line can tell them from other errors without paying torch's import time
when a command fails early (a bad preset is refused in about a second)."""
from __future__ import annotations


class SimulationError(RuntimeError):
    """Numerical trouble in the simulator (non-finite state, no convergence), with where it happened."""


class RolloutError(RuntimeError):
    """A rollout produced non-finite positions, or a node escaped the scene; `step` is the prediction
    step (state step -> step + 1) where it happened."""

    def __init__(self, message: str, step: int | None = None):
        super().__init__(message)
        self.step = step


class OnlineDivergence(RolloutError):
    """An `OnlineSimulator` prediction that is not finite or left the scene: `object` names the object (its
    name in the simulator), `step` the tick predicted from (tick -> tick + 1); the simulator's state is as
    it was before the call."""

    def __init__(self, message: str, step: int | None = None, object: object = None):
        super().__init__(message, step)
        self.object = object

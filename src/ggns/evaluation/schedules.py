"""Point-cloud schedules: which prediction steps of a rollout see a point cloud.

Prediction step `s` (0 <= s <= T-2) predicts state s+1 from state s; when it uses points,
it gets the point cloud observed at state s. Text forms (`parse_schedule`, `str`):
"every:K" (K >= 1), "first:M" (M >= 0) and "never". Each schedule names its metric family
(`Schedule.key`: k<K>, first<M>, never), the suffix of its metrics (rollout_mse_<key>). A model
without point clouds gets every schedule as `Never` (`effective_schedule`, the one place that
rule lives).
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported where a mask is made: a sweep's own process reads schedules without torch
    import torch


def _count(value, name: str, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


class Schedule(ABC):
    """Decides per prediction step whether the model gets the point cloud of its input state."""

    @abstractmethod
    def uses_points(self, step: int) -> bool:
        """Whether prediction step `step` (state step -> step+1) uses the point cloud of state `step`."""

    @property
    @abstractmethod
    def key(self) -> str:
        """The metric-name suffix of this schedule: EveryK(5) -> "k5", Never() -> "never", FirstM(3) -> "first3"."""

    def mask(self, num_steps: int) -> torch.Tensor:
        """`uses_points` for steps 0..num_steps-1 (num_steps = T-1 predictions), bool [num_steps]."""
        import torch

        _count(num_steps, "num_steps", 0)
        return torch.tensor([self.uses_points(s) for s in range(num_steps)], dtype=torch.bool)


@dataclass(frozen=True)
class EveryK(Schedule):
    """A point cloud every k-th step, starting at step 0 (k = 1: every step)."""

    k: int

    def __post_init__(self) -> None:
        _count(self.k, "k", 1)

    def uses_points(self, step: int) -> bool:
        _count(step, "step", 0)
        return step % self.k == 0

    @property
    def key(self) -> str:
        return f"k{self.k}"

    def __str__(self) -> str:
        return f"every:{self.k}"


@dataclass(frozen=True)
class Never(Schedule):
    """Mesh-only prediction throughout."""

    def uses_points(self, step: int) -> bool:
        _count(step, "step", 0)
        return False

    @property
    def key(self) -> str:
        return "never"

    def __str__(self) -> str:
        return "never"


@dataclass(frozen=True)
class FirstM(Schedule):
    """Point clouds for the first m predictions (steps 0..m-1), then blind (the m+10 setting)."""

    m: int

    def __post_init__(self) -> None:
        _count(self.m, "m", 0)

    def uses_points(self, step: int) -> bool:
        _count(step, "step", 0)
        return step < self.m

    @property
    def key(self) -> str:
        return f"first{self.m}"

    def __str__(self) -> str:
        return f"first:{self.m}"


def parse_schedule(text: str | Schedule) -> Schedule:
    """Parse "every:K", "first:M" or "never" (the inverse of `str(schedule)`); a `Schedule` is returned as it is,
    so that every function taking either calls this alone."""
    if isinstance(text, Schedule):
        return text
    name, sep, arg = text.strip().partition(":")
    if name in ("every", "first") and sep:
        try:
            n = int(arg)
        except ValueError:
            raise ValueError(f"point-cloud schedule {text!r}: {arg!r} is not an integer") from None
        return EveryK(n) if name == "every" else FirstM(n)
    if name == "never" and not sep:
        return Never()
    raise ValueError(
        f"unknown point-cloud schedule {text!r}; expected 'every:K' (K >= 1), 'first:M' (M >= 0) or 'never'"
    )


# the paper's test rollouts: a point cloud every 1, 2, 5 and 10 steps, and never (`TestEvaluation`'s default)
PAPER_SCHEDULES = ("every:1", "every:2", "every:5", "every:10", "never")


def effective_schedule(schedule: Schedule | str, uses_points: bool) -> Schedule:
    """The schedule a model really runs: `schedule` for a model with point clouds, `Never()` for one
    without (it never sees a point cloud, whatever the schedule says)."""
    schedule = parse_schedule(schedule)
    return schedule if uses_points else Never()


def effective_schedules(schedules, uses_points: bool) -> list[Schedule]:
    """`effective_schedule` of each, once per metric family (`key`), in order."""
    chosen = [effective_schedule(s, uses_points) for s in schedules]
    return list({s.key: s for s in chosen}.values())

"""Planner interface: ``plan(problem) -> PlanResult``; every planner (density, search, sampling, MPC, oracle)
implements it and returns the same structured result.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..control.reference import Reference
from ..density.base import DensityTrajectory
from ..risk.collision import CollisionReport
from .problem import PlanningProblem

__all__ = ["PlanStatus", "PlanResult", "Planner"]


class PlanStatus(str, enum.Enum):
    """Outcome of a planning run."""

    #: a plan was produced
    SUCCESS = "success"
    #: the planner ran but produced no usable plan (e.g. non-finite cost, solver failure without iterate)
    FAILED = "failed"
    #: the time limit was reached without an acceptable plan
    TIMEOUT = "timeout"
    #: an exception was caught and recorded (benchmarks never crash on one planner)
    ERROR = "error"


def _to_list(v: Any) -> Any:
    if isinstance(v, Tensor):
        return v.detach().cpu().tolist()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, dict):
        return {k: _to_list(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_to_list(x) for x in v]
    return v


@dataclass
class PlanResult:
    """What a planner returns.

    Attributes:
        planner: planner name.
        status: :class:`PlanStatus`.
        params: ``(nu, n_segments)`` reference parameters (``None`` when the planner has none, e.g. MPC).
        reference: the planned reference trajectory (batch shape ``()``), or ``None``.
        states: ``(T, nx)`` planned nominal state trajectory on the planning grid (reference or MPC prediction).
        samples: predicted sample trajectories with log-densities for the final plan (density planners; where
            an exact check reports the plan, its exact trajectories with the log-densities that
            ``extras["exact_check"]["log_density"]`` names: ``DensityPlannerConfig.exact_log_density``).
        cost: unweighted final cost terms and the weighted total (evaluation form: no goal-far factor).
        cost_history: per stage, per term, one value per iteration (the objective actually optimised).
        collision: collision probability of the final sample cloud with its standard error (:class:`CollisionReport`).
        timings: wall times [s] per stage and ``"total"``.
        iterations: iterations per stage.
        message: human-readable detail (e.g. why it failed).
        extras: planner-specific data (JSON-serialisable).
    """

    planner: str
    status: PlanStatus
    params: Tensor | None = None
    reference: Reference | None = None
    states: Tensor | None = None
    samples: DensityTrajectory | None = None
    cost: dict[str, float] = field(default_factory=dict)
    cost_history: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    collision: CollisionReport | None = None
    timings: dict[str, float] = field(default_factory=dict)
    iterations: dict[str, int] = field(default_factory=dict)
    message: str = ""
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == PlanStatus.SUCCESS

    def summary(self) -> dict[str, Any]:
        """JSON-serialisable summary (no sample clouds)."""
        return {
            "planner": self.planner,
            "status": self.status.value,
            "message": self.message,
            "params": _to_list(self.params),
            "cost": self.cost,
            "collision_probability": None if self.collision is None else self.collision.to_dict(),
            "timings": self.timings,
            "iterations": self.iterations,
            "states": _to_list(self.states),
            "cost_history": _to_list(self.cost_history),
            "extras": _to_list(self.extras),
        }


class Planner(ABC):
    """Base class of all planners."""

    #: short name used on the command line and in results
    name: str = "planner"

    @abstractmethod
    def plan(self, problem: PlanningProblem) -> PlanResult:
        """Plan for ``problem``; never raises for solver trouble (status says what happened)."""

    def prepare(self, problem: PlanningProblem) -> None:
        """Start work of :meth:`plan` for ``problem`` that needs no earlier result, for a caller with an idle core
        that will plan next (the ``plan`` command); the plan is the same with or without. Default: nothing."""
        return None

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"


def as_numpy(t: Tensor | None) -> np.ndarray | None:
    return None if t is None else t.detach().cpu().numpy()


def tensor_or_none(v: Any, like: Tensor) -> Tensor | None:
    return None if v is None else torch.as_tensor(v, dtype=like.dtype, device=like.device)

"""Planners: one interface, ``plan(problem) -> PlanResult``."""

from .base import Planner, PlanResult, PlanStatus
from .density_planner import DensityPlanner, DensityPlannerConfig, sample_initial_states
from .optim import BatchedAdam
from .problem import PlanningProblem

__all__ = [
    "Planner",
    "PlanResult",
    "PlanStatus",
    "PlanningProblem",
    "DensityPlanner",
    "DensityPlannerConfig",
    "BatchedAdam",
    "sample_initial_states",
]

"""Planners: one interface, ``plan(problem) -> PlanResult``.

The density planner, the ablation baselines (search, sampling) and the MPC baselines (M0, tube MPC M1-M3, oracle;
these need the optional extra ``mpc``, imported only when such a planner is built).
"""

from .base import Planner, PlanResult, PlanStatus
from .density_planner import DensityPlanner, DensityPlannerConfig, sample_initial_states
from .mpc import MPCConfig, MPCPlanner, MPCStep, MPCWeights, TubeMPCConfig
from .optim import BatchedAdam
from .oracle import OracleConfig, OraclePlanner
from .problem import PlanningProblem
from .sampling import SamplingConfig, SamplingPlanner
from .search import SearchConfig, SearchPlanner

__all__ = [
    "Planner",
    "PlanResult",
    "PlanStatus",
    "PlanningProblem",
    "DensityPlanner",
    "DensityPlannerConfig",
    "BatchedAdam",
    "sample_initial_states",
    "MPCWeights",
    "MPCConfig",
    "TubeMPCConfig",
    "MPCStep",
    "MPCPlanner",
    "OracleConfig",
    "OraclePlanner",
    "SearchConfig",
    "SearchPlanner",
    "SamplingConfig",
    "SamplingPlanner",
]

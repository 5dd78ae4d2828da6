"""Reported costs and collision probabilities of plans, computed the same way for every planner.

The density planner evaluates its final sample cloud with the cost in *evaluation form* (no goal-far factor) and
the collision probability of :class:`~density_planner.risk.collision.CollisionModel` (the problem's ``risk``
settings: importance-weighted by default, the paper's binning on request). The baselines use the same functions:
planners with a sample
cloud (search, sampling) through :func:`evaluate_samples`, single-trajectory planners (MPC, oracle) through
:func:`evaluate_trajectory` (one sample of weight one).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..control.reference import Reference
from ..cost.composite import CostConfig, build_cost
from ..cost.terms import CostInputs
from ..density.base import DensityTrajectory, WeightMode, sample_weights
from ..risk.collision import CollisionReport
from .problem import PlanningProblem

__all__ = ["evaluate_samples", "evaluate_trajectory"]


@torch.no_grad()
def evaluate_samples(
    problem: PlanningProblem,
    ref: Reference,
    traj: DensityTrajectory,
    *,
    cost_config: CostConfig,
    weighting: WeightMode = "density",
    log_q0: Tensor | None = None,
) -> tuple[dict[str, float], CollisionReport]:
    """Evaluation-form cost and collision probability of a predicted sample cloud (reference batch of one).

    ``traj`` has a leading batch dimension of one (as returned by a predictor for one reference).
    """
    device = traj.x.device
    slices = problem.slices(traj.x.shape[-2], device)
    w = sample_weights(traj.log_rho, traj.log_rho0, mode=weighting, log_q0=log_q0)
    inputs = CostInputs(x=traj.x, weights=w, u_ref=ref.u_plan, slices=slices)
    cost = build_cost(problem.scene, cost_config, optimisation=False, device=device, system=problem.system,
                      risk=problem.risk)(inputs).select(0).to_dict()
    coll = problem.collision(device).probability(traj.x[0], slices, log_rho0=traj.log_rho0[0],
                                                 log_q0=None if log_q0 is None else log_q0.reshape(-1),
                                                 log_rho=traj.log_rho[0])
    return cost, coll


@torch.no_grad()
def evaluate_trajectory(
    problem: PlanningProblem,
    states: Tensor,
    inputs: Tensor,
    *,
    cost_config: CostConfig,
) -> tuple[dict[str, float], CollisionReport]:
    """Evaluation-form cost and collision probability of one trajectory ``states (T, nx)`` on the planning grid
    driven by ``inputs (T - 1, nu)`` (the applied or reference inputs on the same grid)."""
    device = states.device
    slices = problem.slices(states.shape[0], device)
    cost_inputs = CostInputs.single(states, inputs, slices)
    cost = build_cost(problem.scene, cost_config, optimisation=False, device=device, system=problem.system,
                      risk=problem.risk)(cost_inputs).to_dict()
    coll = problem.collision(device).probability(states[None], slices)
    return cost, coll

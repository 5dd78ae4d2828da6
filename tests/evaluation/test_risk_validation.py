"""The Monte-Carlo risk check: passes on the importance-sampling estimate, fails on a deliberately biased one."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from density_planner.control.analytic import CarTrackingController
from density_planner.control.reference import make_reference
from density_planner.density.liouville import ExactLiouville
from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.scene import Scene
from density_planner.evaluation.risk_validation import compare_risk, validate_risk
from density_planner.planners.base import PlanResult, PlanStatus
from density_planner.planners.density_planner import sample_initial_states
from density_planner.planners.problem import PlanningProblem


def test_compare_risk_z_scores_and_threshold():
    p = np.array([0.0, 0.10, 0.20, 0.30])
    m = np.array([0.0, 0.11, 0.20, 0.30])
    se = np.array([0.0, 0.005, 0.01, 0.0])
    v = compare_risk(p, se, m, se)
    # step 1: -0.01 / sqrt(2 * 0.005^2) = -1.41; steps 0 and 3 agree exactly with SE 0
    np.testing.assert_allclose(v.z, [0.0, -0.01 / np.sqrt(2 * 0.005**2 + 1e-12), 0.0, 0.0], rtol=1e-6)
    assert v.passed and v.max_abs_z == pytest.approx(1.414, abs=1e-3)
    biased = compare_risk(p + np.array([0, 0, 0, 0.01]), se, m, se)
    assert not biased.passed and biased.to_dict()["steps_beyond_threshold"] == 1
    json.dumps(biased.to_dict())  # JSON-ready (infinite z written as a huge number)
    with pytest.raises(ValueError, match="same length"):
        compare_risk(p, se[:2], m, se)


def _ramp_scene() -> Scene:
    """A static occupancy ramp across the road ahead: every sample sees a different, smoothly varying P_occ."""
    xs = torch.linspace(-12, 12, 241)
    ys = torch.linspace(-30, 10, 401)
    field = (0.6 * torch.sigmoid((xs[:, None] - 0.5) / 0.8) * torch.sigmoid((ys[None, :] + 12) / 1.5))
    grid = OccupancyGrid(field.expand(101, -1, -1).contiguous(), origin=(-12.0, -30.0), cell_size=0.1, dt=0.1)
    return Scene(grid, (0.0, -20.0, 1.5707963, 3.0), (0.0, 5.0), (-9.9, 9.9, -29.9, 9.9), name="ramp")


@pytest.fixture(scope="module")
def tracked_plan():
    """A straight reference, its sample cloud from exact Liouville (300 samples uniform on the support) and the
    importance-sampling estimate of its collision probability."""
    problem = PlanningProblem.from_scene(_ramp_scene(), seed=0)
    controller = CarTrackingController()
    predictor = ExactLiouville(problem.system, controller)
    start = problem.reference_start(torch.float64)
    params = torch.zeros(2, 10, dtype=torch.float64)
    params[0, 2:4] = 0.1  # a slight left turn
    ref = make_reference(problem.system, start, params.unsqueeze(0), problem.parameterization)
    gen = torch.Generator().manual_seed(1)
    x0, log_rho0, log_q0 = sample_initial_states(problem, 300, gen, dtype=torch.float64)
    traj = predictor.predict(x0.unsqueeze(0), log_rho0.unsqueeze(0), ref)
    slices = problem.scene.grid.slice_index(traj.t.double())
    coll = problem.collision().probability(traj.x[0], slices, log_rho0=log_rho0, log_q0=log_q0)
    plan = PlanResult("density", PlanStatus.SUCCESS, params=params, reference=ref.select(0), collision=coll)
    return problem, plan, controller


def test_validator_passes_on_the_importance_estimate(tracked_plan):
    problem, plan, controller = tracked_plan
    assert float(plan.collision.max) > 0.05  # the check is not vacuous
    v = validate_risk(problem, plan, controller, n=2000, seed=3)
    assert v.passed, v.to_dict()["z"]


def test_validator_fails_on_a_biased_estimate(tracked_plan):
    problem, plan, controller = tracked_plan
    coll = plan.collision
    # the paper's mistake in miniature: 10 % too high where the risk is non-zero
    biased = dataclasses.replace(coll, per_slice=coll.per_slice * 1.1)
    v = validate_risk(problem, dataclasses.replace(plan, collision=biased), controller, n=2000, seed=3)
    assert not v.passed

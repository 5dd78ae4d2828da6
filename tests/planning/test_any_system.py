"""The planning pipeline for any system: the density planner, its reported risk and the verdict, parametrised over
the paper's kinematic car, CommonRoad's kinematic single-track model (ks) and a linear double integrator (no
heading, no hidden state, a disc body)."""

from __future__ import annotations

import math

import pytest
import torch
from helpers import block_scene, empty_scene

from density_planner.control.analytic import CarTrackingController, LinearFeedbackController
from density_planner.control.registry import load_controller, model_set
from density_planner.density.distributions import paper_gaussian_mixture
from density_planner.density.liouville import ExactLiouville
from density_planner.evaluation.risk_validation import validate_risk
from density_planner.evaluation.verdict import judge_plan
from density_planner.planners.base import PlanStatus
from density_planner.planners.density_planner import DensityPlanner, DensityPlannerConfig
from density_planner.planners.problem import PlanningProblem
from density_planner.systems.base import Footprint
from density_planner.systems.car import KinematicCar
from density_planner.systems.linear import LinearSystem

FAST = DensityPlannerConfig(n_candidates=30, epochs_init=60, epochs_density=8, n_samples=60, evaluation_samples=60)


def _double_integrator():
    """``x = (p_x, p_y, v_x, v_y)``, ``u = (a_x, a_y)`` in +-3 m/s^2, a disc of 1 m; PD feedback."""
    system = LinearSystem([[0, 0, 1, 0], [0, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0]],
                          [[0, 0], [0, 0], [1, 0], [0, 1]], input_bounds=((-3.0, -3.0), (3.0, 3.0)),
                          footprint=Footprint(1.0, 1.0))
    controller = LinearFeedbackController([[2.0, 0, 2.5, 0], [0, 2.0, 0, 2.5]], (-3.0, -3.0), (3.0, 3.0))
    return system, controller


def _problem(name: str, scene):
    if name == "car":
        system = KinematicCar()
        return PlanningProblem.from_scene(scene, seed=0, system=system), CarTrackingController()
    if name == "ks":
        mset = model_set("ks")
        system = mset.make_system()
        return PlanningProblem.from_scene(scene, seed=0, system=system), load_controller(None, models=mset)
    system, controller = _double_integrator()
    sx, sy, heading, speed = scene.start
    start = (sx, sy, speed * math.cos(heading), speed * math.sin(heading))  # the pose as a double-integrator state
    dist = paper_gaussian_mixture(start, (0.5, 0.5, 0.3, 0.3), torch.Generator().manual_seed(0))
    return PlanningProblem(scene, dist, system), controller


@pytest.mark.parametrize("name", ["car", "double-integrator"])
def test_density_planner_reaches_the_goal_around_an_obstacle(name):
    scene = block_scene()
    problem, controller = _problem(name, scene)
    planner = DensityPlanner(ExactLiouville(problem.system, controller), FAST)
    res = planner.plan(problem)
    assert res.status == PlanStatus.SUCCESS
    pos = problem.system.positions(res.states)
    assert float(torch.linalg.norm(pos[-1] - torch.tensor(scene.goal, dtype=pos.dtype))) < 1.5
    assert res.samples.x.shape[-1] == problem.system.nx and torch.isfinite(res.samples.log_rho).all()
    assert float(res.collision.max) < 0.2
    # the verdict reads the positions (and, where there is one, the heading) through the system
    verdict = judge_plan(scene, res, system=problem.system, dt=problem.parameterization.plan_dt)
    assert verdict.collision_free and verdict.within_model


@pytest.mark.parametrize("name", ["car", "ks", "double-integrator"])
def test_reported_risk_agrees_with_monte_carlo(name):
    """The reported P_coll of a plan through the block's edge equals the Monte-Carlo frequency within 4 standard
    errors at every step (the risk owner is system-agnostic: positions and body from the system)."""
    scene = block_scene()
    problem, controller = _problem(name, scene)
    cfg = DensityPlannerConfig(n_candidates=10, epochs_init=20, epochs_density=2, n_samples=400, evaluation_samples=400)
    res = DensityPlanner(ExactLiouville(problem.system, controller), cfg).plan(problem)
    check = validate_risk(problem, res, controller, n=2000, seed=1, threshold=4.0)
    assert check.passed, check.to_dict()


def test_empty_scene_plan_of_the_double_integrator_keeps_its_input_bounds():
    scene = empty_scene()
    problem, controller = _problem("double-integrator", scene)
    res = DensityPlanner(ExactLiouville(problem.system, controller), FAST).plan(problem)
    assert res.params.shape == (2, 10) and float(res.params.abs().max()) <= 3.0 + 1e-6
    assert float(torch.linalg.norm(res.states[-1, :2] - torch.tensor(scene.goal))) < 1.0

"""The NLP baselines (MPC M0, tube MPC, oracle) for systems other than the car: a linear double integrator
(``x = (p_x, p_y, v_x, v_y)``, no heading, no hidden state, a disc body of 1 m) and the kinematic single-track model
read their dynamics (``f_symbolic``), bounds and speed limit from the system; systems without what they need get one
clear error."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from baseline_scenes import GOAL, block_clearance, block_scene, small_empty

from density_planner.density.distributions import UniformBox
from density_planner.planners.base import PlanStatus
from density_planner.planners.problem import PlanningProblem
from density_planner.systems.base import Footprint, System
from density_planner.systems.car import KinematicCar
from density_planner.systems.linear import LinearSystem
from density_planner.systems.registry import make_system

ca = pytest.importorskip("casadi", reason="the NLP baselines need the optional 'mpc' extra (casadi)")

from density_planner.planners._nlp import NLPModel, position_rate_bound, step_function  # noqa: E402
from density_planner.planners.mpc import MPCConfig, MPCPlanner  # noqa: E402
from density_planner.planners.oracle import OracleConfig, OraclePlanner  # noqa: E402

A = [[0, 0, 1, 0], [0, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0]]
B = [[0, 0], [0, 0], [1, 0], [0, 1]]
V_MAX = 8.0


def _double_integrator(speed_box: bool = True) -> LinearSystem:
    """Inputs (a_x, a_y) in +-3 m/s^2; velocities in +-8 m/s (``speed_box``); a disc of 1 m."""
    inf = math.inf
    bounds = ((-inf, -inf, -V_MAX, -V_MAX), (inf, inf, V_MAX, V_MAX)) if speed_box else None
    return LinearSystem(A, B, input_bounds=((-3.0, -3.0), (3.0, 3.0)), state_bounds=bounds,
                        footprint=Footprint(1.0, 1.0))


class _NoSymbolic(LinearSystem):
    f_symbolic = System.f_symbolic  # a system the NLP baselines cannot model


def _problem(scene, system: System) -> PlanningProblem:
    sx, sy, heading, speed = scene.start
    start = torch.tensor([sx, sy, speed * math.cos(heading), speed * math.sin(heading)], dtype=torch.float64)
    half = torch.tensor([0.1, 0.1, 0.1, 0.1], dtype=torch.float64)
    return PlanningProblem(scene, UniformBox(start - half, start + half), system)


def _goal_distance(states: torch.Tensor) -> float:
    return float(torch.linalg.norm(states[-1, :2].double() - torch.tensor(GOAL, dtype=torch.float64)))


def test_step_function_matches_the_systems_rollout():
    """``F`` (10 Euler steps of f_symbolic) equals :meth:`System.rollout` on the fine grid, for both systems."""
    gen = torch.Generator().manual_seed(0)
    for system, x0 in ((KinematicCar(), torch.tensor([1.0, -2.0, 0.7, 4.0, 0.0])),
                       (_double_integrator(), torch.tensor([1.0, -2.0, 2.5, -1.0]))):
        u = 3 * (2 * torch.rand(system.nu, generator=gen, dtype=torch.float64) - 1)
        F = step_function(ca, system, 0.1, 10)
        nominal = list(system.nominal_indices)
        got = np.asarray(F(x0.double()[nominal].numpy(), u.numpy())).reshape(-1)
        want = system.rollout(x0.double(), u.expand(10, -1), 0.01)[-1, nominal].numpy()
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_nlp_model_and_window_bound():
    car = NLPModel.of(ca, KinematicCar())
    cfg = KinematicCar().config
    assert (car.nn, car.nu, car.position, car.heading) == (4, 2, (0, 1), 2)
    assert car.state_lo[2:] == (cfg.state_min[2], cfg.state_min[3]) and car.state_hi[2:] == (cfg.state_max[2],
                                                                                               cfg.state_max[3])
    # the car: v_max + a_max dt; the double integrator: its velocity box widened by one stage of a_max
    assert position_rate_bound(ca, KinematicCar(), 0.1) == pytest.approx(10.0 + 3.0 * 0.1)
    assert position_rate_bound(ca, _double_integrator(), 0.1) == pytest.approx(V_MAX + 3.0 * 0.1)
    di = NLPModel.of(ca, _double_integrator())
    assert (di.nn, di.heading, di.state_lo[2:]) == (4, None, (-V_MAX, -V_MAX))
    with pytest.raises(ValueError, match="unbounded.*state bounds"):
        position_rate_bound(ca, _double_integrator(speed_box=False), 0.1)


def test_mpc_plans_a_double_integrator_to_the_goal():
    system = _double_integrator()
    scene = small_empty()
    mpc = MPCPlanner(MPCConfig(max_cpu_time=math.inf, max_iter=100))
    res = mpc.plan(_problem(scene, system))
    assert res.status == PlanStatus.SUCCESS, res.message
    assert res.extras["n_failed_steps"] == 0
    assert _goal_distance(res.states) < 1.0  # stops within goal_stop_distance
    assert res.states.shape[1] == 4 and np.asarray(res.extras["predicted_states"][0]).shape == (11, 4)
    inputs = np.asarray(res.extras["applied_inputs"])
    assert inputs.shape[1] == 2 and np.abs(inputs).max() <= 3.0 + 1e-9
    # the velocity box is a constraint of the NLP: the predictions keep it
    assert np.abs(np.concatenate([np.asarray(p)[1:, 2:] for p in res.extras["predicted_states"]])).max() <= V_MAX + 1e-6


def test_tube_mpc_plans_a_double_integrator_to_the_goal():
    res = MPCPlanner(MPCConfig(max_cpu_time=math.inf, max_iter=10, tube_radius=0.5)).plan(
        _problem(small_empty(), _double_integrator()))
    assert res.status == PlanStatus.SUCCESS, res.message
    assert res.extras["tube_precomputed"] and res.extras["n_tube_offsets"] == 81
    assert _goal_distance(res.states) < 1.0


def test_oracle_plans_a_double_integrator_to_the_goal():
    system = _double_integrator()
    scene = small_empty()
    problem = _problem(scene, system)
    res = OraclePlanner(OracleConfig(restarts=1, max_iter=300)).plan(problem)
    assert res.status == PlanStatus.SUCCESS, res.message
    assert res.params.shape == (2, 10) and float(res.params.abs().max()) <= 3.0 + 1e-9
    assert res.states.shape == (101, 4)
    assert _goal_distance(res.states) < 0.1
    # its start is the problem's, the open-loop states are the system's rollout of its parameters
    assert torch.allclose(res.states[0].double(), problem.reference_start(torch.float64).to(res.states.dtype).double())


def test_systems_without_what_the_nlp_needs_get_one_clear_error():
    scene = small_empty()
    no_symbolic = _problem(scene, _NoSymbolic(A, B, input_bounds=((-3.0, -3.0), (3.0, 3.0))))
    for planner in (MPCPlanner(MPCConfig(max_cpu_time=math.inf, n_steps=2)), OraclePlanner(OracleConfig(restarts=1))):
        res = planner.plan(no_symbolic)
        assert res.status == PlanStatus.ERROR and "has no symbolic dynamics" in res.message, res.message
    # no velocity box: the MPC cannot size its occupancy windows (the oracle does not need them)
    res = MPCPlanner(MPCConfig(max_cpu_time=math.inf, n_steps=2)).plan(_problem(scene, _double_integrator(False)))
    assert res.status == PlanStatus.ERROR and "state bounds" in res.message, res.message


def test_start_of_the_car_is_unchanged_by_the_generic_layout():
    """The car's nominal state is (p_x, p_y, theta, v): the MPC accepts the full state (bias dropped) or those 4."""
    problem = PlanningProblem.from_scene(small_empty(), seed=0)
    mpc = MPCPlanner(MPCConfig(max_cpu_time=math.inf, max_iter=5))
    mpc.reset(problem)
    full = problem.reference_start(torch.float64).clone()
    full[4] = 0.1
    a = mpc.solve(full, 0)
    mpc.reset(problem)
    b = mpc.solve(full[:4].numpy(), 0)
    np.testing.assert_array_equal(a.predicted, b.predicted)
    with pytest.raises(ValueError, match="5 \\(the state\\) or 4 \\(the nominal state\\)"):
        mpc.solve(np.zeros(3), 0)


def test_oracle_takes_the_double_integrators_disc_around_a_block():
    """The block lies across the straight line to the goal: the oracle's plan reaches the goal with the 1-m disc
    (radius 0.5 m) clear of it (measured 1.67 m)."""
    res = OraclePlanner(OracleConfig(restarts=2, max_iter=300)).plan(_problem(block_scene(), _double_integrator()))
    assert res.status == PlanStatus.SUCCESS, res.message
    assert _goal_distance(res.states) < 0.1
    assert block_clearance(res.states) > 0.5 + 0.3


@pytest.mark.parametrize("name", ["car", "ks", "double-integrator"])
def test_oracle_plans_every_system_to_the_goal(name):
    scene = small_empty()
    if name == "double-integrator":
        problem = _problem(scene, _double_integrator())
    else:
        problem = PlanningProblem.from_scene(scene, seed=0, system=make_system(name))
    res = OraclePlanner(OracleConfig(restarts=1, max_iter=500)).plan(problem)
    assert res.status == PlanStatus.SUCCESS, res.message
    assert res.states.shape == (101, problem.system.nx) and res.params.shape == (problem.system.nu, 10)
    assert _goal_distance(res.states) < 0.1
    lo, hi = problem.system.input_bounds
    assert bool((res.params >= torch.tensor(lo)[:, None] - 1e-9).all() & (res.params <= torch.tensor(hi)[:, None]
                                                                              + 1e-9).all())


@pytest.mark.slow
def test_mpc_plans_the_single_track_model_to_the_goal():
    """~10 s: the KS speed box (40 m/s) makes the occupancy windows 4 times wider than the car's."""
    problem = PlanningProblem.from_scene(small_empty(), seed=0, system=make_system("ks"))
    res = MPCPlanner(MPCConfig(max_cpu_time=math.inf)).plan(problem)
    assert res.status == PlanStatus.SUCCESS, res.message
    assert _goal_distance(res.states) < 1.0 and res.states.shape[1] == 5

"""Executing plans: tracked references in closed loop (biased and unbiased measurement), MPC and oracle modes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from density_planner.control.analytic import CarTrackingController
from density_planner.control.reference import make_reference
from density_planner.density.distributions import UniformBox
from density_planner.density.liouville import LiouvilleConfig
from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.scene import Scene
from density_planner.evaluation.config import EvaluationConfig
from density_planner.evaluation.simulate import (
    ExecutionMode,
    controller_step_times,
    execute,
    execution_mode,
    monte_carlo,
    track_reference,
)
from density_planner.planners.base import Planner, PlanResult, PlanStatus
from density_planner.planners.problem import PlanningProblem
from density_planner.systems.car import KinematicCar

START = (0.0, -20.0, math.pi / 2, 3.0)


def _problem() -> PlanningProblem:
    grid = OccupancyGrid(torch.zeros(101, 241, 401), origin=(-12.0, -30.0), cell_size=0.1, dt=0.1)
    scene = Scene(grid, START, (0.0, 5.0), (-9.9, 9.9, -29.9, 9.9))
    car = KinematicCar()
    hw = torch.tensor(car.config.initial_error_max, dtype=torch.float64)
    s = torch.tensor((*START, 0.0), dtype=torch.float64)
    return PlanningProblem(scene, UniformBox(s - hw, s + hw), car)


class _RefPlanner(Planner):
    """Plans a fixed reference (gentle left turn, then straight)."""

    name = "ref"

    def plan(self, problem):
        params = torch.zeros(2, 10)
        params[0, :3] = 0.1
        ref = make_reference(problem.system, problem.reference_start(), params, problem.parameterization)
        return PlanResult(self.name, PlanStatus.SUCCESS, params=params, reference=ref, states=ref.x_plan,
                          timings={"total": 1.5})


class _Declared(Planner):
    execution_mode = "open_loop"
    name = "declared"

    def plan(self, problem):  # pragma: no cover - not called
        raise NotImplementedError


def _setup():
    problem = _problem()
    plan = _RefPlanner().plan(problem)
    return problem, plan, CarTrackingController()


def test_tracking_from_the_reference_start_follows_the_reference():
    problem, plan, ctrl = _setup()
    x0 = problem.reference_start(torch.float64)
    run = execute(_RefPlanner(), problem, x0, plan=plan, controller=ctrl, config=EvaluationConfig())
    assert run.states.shape == (101, 5)
    # zero initial error: the closed loop stays on the reference (the Euler reference and the Euler loop agree)
    assert torch.allclose(run.states[:, :2], plan.reference.x_plan[:, :2], atol=1e-3)
    assert torch.allclose(run.planned_inputs, plan.reference.u_plan)
    assert torch.allclose(run.applied_inputs, plan.reference.u_plan, atol=1e-4)
    assert run.step_times.shape == (100,) and np.all(run.step_times > 0)
    assert run.offline_time == 1.5 and run.ok


def test_biased_measurement_changes_the_executed_trajectory():
    problem, plan, ctrl = _setup()
    x0 = problem.reference_start(torch.float64)
    xb = x0.clone()
    xb[4] = 0.15  # heading measured 0.15 rad too large
    unbiased = execute(_RefPlanner(), problem, x0, plan=plan, controller=ctrl, time_online=False)
    biased = execute(_RefPlanner(), problem, xb, plan=plan, controller=ctrl, time_online=False)
    gap = (biased.states[-1, :2] - unbiased.states[-1, :2]).norm()
    assert gap > 0.05  # the controller steers against the bias (0.14 m off after 10 s with the analytic gains)
    assert np.all(unbiased.step_times == 0)


def test_monte_carlo_batched_equals_single_runs():
    problem, plan, ctrl = _setup()
    xs = problem.initial_distribution.sample(5, torch.Generator().manual_seed(0), dtype=torch.float64)
    batch = monte_carlo(_RefPlanner(), problem, xs, plan=plan, controller=ctrl)
    assert len(batch) == 5
    for x0, traj in zip(xs, batch):
        single = execute(_RefPlanner(), problem, x0, plan=plan, controller=ctrl, time_online=False).states
        assert torch.allclose(traj, single, atol=1e-4)
    assert monte_carlo(_RefPlanner(), problem, xs[:0], plan=plan, controller=ctrl) == []


def test_euler_loop_converges_to_rk4_reference_solution():
    """The executed loop at the default 0.01-s Euler step is within 5 cm of a fine RK4 solution (first order)."""
    problem, plan, ctrl = _setup()
    x0 = problem.initial_distribution.sample(3, torch.Generator().manual_seed(1), dtype=torch.float64)
    ref = plan.reference
    euler = track_reference(problem.system, ctrl, ref, x0.float(), config=LiouvilleConfig("euler", 0.01, "structured"))
    rk4 = track_reference(problem.system, ctrl, ref, x0.float(), config=LiouvilleConfig("rk4", 0.01, "structured"))
    assert (euler[..., :2] - rk4[..., :2]).norm(dim=-1).max() < 0.05


def test_controller_step_times_shape():
    problem, plan, ctrl = _setup()
    cfg = LiouvilleConfig("euler", 0.01, "structured")
    fine = track_reference(problem.system, ctrl, plan.reference, problem.reference_start().reshape(1, -1), config=cfg,
                           all_steps=True)[0]
    assert fine.shape == (1001, 5)
    times = controller_step_times(problem.system, ctrl, plan.reference, fine, cfg)
    assert times.shape == (100,) and np.all(times > 0)


def test_a_plan_without_reference_is_a_failed_execution():
    problem, _, ctrl = _setup()
    failed = PlanResult("ref", PlanStatus.FAILED, message="no luck", timings={"total": 2.0})
    run = execute(_RefPlanner(), problem, problem.reference_start(torch.float64), plan=failed, controller=ctrl)
    assert not run.ok and run.states.shape[0] == 0 and "no luck" in run.message
    with pytest.raises(ValueError, match="plan="):
        execute(_RefPlanner(), problem, problem.reference_start(torch.float64))


def test_execution_modes():
    assert execution_mode(_RefPlanner()) == ExecutionMode.TRACK
    assert execution_mode(_Declared()) == ExecutionMode.OPEN_LOOP
    pytest.importorskip("casadi")
    from density_planner.planners.mpc import MPCPlanner
    from density_planner.planners.oracle import OraclePlanner

    assert execution_mode(MPCPlanner()) == ExecutionMode.RECEDING
    assert execution_mode(OraclePlanner()) == ExecutionMode.OPEN_LOOP


def test_mpc_execution_uses_plan_from():
    pytest.importorskip("casadi")
    from density_planner.planners.mpc import MPCConfig, MPCPlanner

    problem, _, _ = _setup()
    mpc = MPCPlanner(MPCConfig(max_iter=5, max_cpu_time=math.inf, n_steps=20))
    run = execute(mpc, problem, problem.reference_start(torch.float64))
    assert run.states.shape == (21, 5)
    assert run.planned_inputs.shape == (20, 2) and torch.equal(run.planned_inputs, run.applied_inputs)
    assert run.step_times.shape == (20,) and run.offline_time == 0.0


def test_executed_vehicle_stops_instead_of_reversing():
    """A car ahead of a reference that brakes to rest: the model's flow (``plant=False``, what the density follows)
    carries it backwards, the executed vehicle holds at v = 0 and agrees with the model until its speed reaches 0."""
    from density_planner.density.liouville import simulate_closed_loop

    problem = _problem()
    car = problem.system
    params = torch.zeros(2, 10)
    params[1, 0] = -3.0  # 3 m/s -> rest in 1 s, then stay
    ref = make_reference(car, problem.reference_start(), params, problem.parameterization)
    x0 = torch.tensor([[0.0, -19.5, math.pi / 2, 3.3, 0.0]], dtype=ref.x.dtype)
    cfg = LiouvilleConfig()
    _, model = simulate_closed_loop(car, CarTrackingController(), x0, ref, config=cfg)
    executed = track_reference(car, CarTrackingController(), ref, x0, config=cfg)
    v_model, v_exec = model[0, :, 3], executed[0, :, 3]
    assert float(v_model.min()) < -0.1  # the case exists: the unconstrained model reverses
    assert float(v_exec.min()) == 0.0
    first_stop = int(torch.nonzero(v_model < 0)[0])
    torch.testing.assert_close(executed[0, :first_stop], model[0, :first_stop])
    # at rest it stays where it stopped
    torch.testing.assert_close(executed[0, first_stop:, :2], executed[0, first_stop:first_stop + 1, :2].expand(
        executed.shape[1] - first_stop, 2))


def test_standstill_only_for_vehicles_that_cannot_reverse():
    car = KinematicCar()
    x = torch.tensor([[1.0, 2.0, 0.3, -0.2, 0.01], [1.0, 2.0, 0.3, 0.5, 0.01]], dtype=torch.float64)
    out = car.standstill(x)
    assert car.standstill_index == 3
    torch.testing.assert_close(out[:, 3], torch.tensor([0.0, 0.5], dtype=torch.float64))
    torch.testing.assert_close(out[:, [0, 1, 2, 4]], x[:, [0, 1, 2, 4]])
    from density_planner.systems.linear import LinearSystem

    point = LinearSystem([[0, 0, 1, 0], [0, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0]], [[0, 0], [0, 0], [1, 0], [0, 1]])
    assert point.standstill_index is None
    z = torch.tensor([[0.0, 0.0, -1.0, -1.0]])
    assert torch.equal(point.standstill(z), z)

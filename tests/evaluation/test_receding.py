"""The receding-horizon closed loop (evaluation/receding.py) with a scripted stepwise planner: the plant is the
system's Euler model with the input held per step, the planner sees the (biased) measurement, the run stops at
the goal or after n_steps, exceptions become an ERROR result with the states so far."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from density_planner.density.distributions import UniformBox
from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.scene import Scene
from density_planner.evaluation.receding import ClosedLoopRun, run_receding
from density_planner.planners.base import PlanResult, PlanStatus
from density_planner.planners.problem import PlanningProblem
from density_planner.systems.car import KinematicCar

POSE = (0.0, -20.0, math.pi / 2, 3.0)  # the scene's start: pose and speed
START = (*POSE, 0.0)  # the true state (no heading bias)


@dataclass(frozen=True)
class _Settings:
    stage_dt: float = 0.1
    substeps: int = 10
    biased_measurement: bool = False
    goal_stop_distance: float = 0.0


@dataclass
class _Step:
    input: np.ndarray


class _Scripted:
    """Applies ``inputs[h]`` at step ``h`` and records what it was shown."""

    name = "scripted"

    def __init__(self, inputs: np.ndarray, config: _Settings, fail_at: int | None = None):
        self.inputs, self.config, self.fail_at = inputs, config, fail_at
        self.seen: list[torch.Tensor] = []
        self.resets = 0

    def reset(self, problem: PlanningProblem) -> None:
        self.resets += 1
        self.seen.clear()

    @property
    def n_steps(self) -> int:
        return len(self.inputs)

    def solve(self, state, step):
        if step == self.fail_at:
            raise RuntimeError("solver exploded")
        self.seen.append(torch.as_tensor(state).clone())
        return _Step(self.inputs[step])

    def closed_loop_result(self, problem: PlanningProblem, run: ClosedLoopRun) -> PlanResult:
        status = PlanStatus.ERROR if run.error else PlanStatus.SUCCESS
        return PlanResult(self.name, status, message=run.error,
                          states=torch.stack(run.states) if run.states else None,
                          extras={"inputs": torch.stack(run.inputs) if run.inputs else None, "steps": len(run.steps)})


def _problem(goal=(0.0, 5.0)) -> PlanningProblem:
    grid = OccupancyGrid(torch.zeros(101, 241, 401), origin=(-12.0, -30.0), cell_size=0.1, dt=0.1)
    scene = Scene(grid, POSE, goal, (-9.9, 9.9, -29.9, 9.9))
    car = KinematicCar()
    s = torch.tensor(START, dtype=torch.float64)
    return PlanningProblem(scene, UniformBox(s - 0.1, s + 0.1), car)


def _inputs(n: int) -> np.ndarray:
    h = np.arange(n)
    return np.stack([0.3 * np.sin(0.4 * h), 0.5 * np.cos(0.3 * h)], axis=-1)


def test_plant_is_the_euler_model_with_the_input_held_per_step():
    problem = _problem()
    u = _inputs(12)
    planner = _Scripted(u, _Settings())
    x0 = torch.tensor(START, dtype=torch.float64)
    res = run_receding(planner, problem, x0)
    assert res.status == PlanStatus.SUCCESS and planner.resets == 1
    assert res.states.shape == (13, 5) and res.extras["steps"] == 12
    # one open-loop rollout of the inputs repeated over the 10 sub-steps of every 0.1-s step
    fine = torch.as_tensor(u, dtype=torch.float64).repeat_interleave(10, dim=0)
    expected = problem.system.rollout(x0, fine, 0.01)[::10]
    torch.testing.assert_close(res.states, expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(res.extras["inputs"], torch.as_tensor(u))
    # unbiased: the planner sees the true states before each step
    torch.testing.assert_close(torch.stack(planner.seen), res.states[:-1])


def test_biased_measurement_is_what_the_planner_sees():
    problem = _problem()
    x0 = torch.tensor(START, dtype=torch.float64)
    x0[4] = 0.2  # heading bias of the measurement
    planner = _Scripted(_inputs(5), _Settings(biased_measurement=True))
    res = run_receding(planner, problem, x0)
    seen = torch.stack(planner.seen)
    torch.testing.assert_close(seen, problem.system.measure(res.states[:-1]))
    assert torch.allclose(seen[:, 2] - res.states[:-1, 2], torch.full((5,), 0.2, dtype=torch.float64))
    assert float(res.states[-1, 4]) == pytest.approx(0.2)  # the true state keeps its bias


def test_stops_within_the_goal_distance():
    # straight ahead at 3 m/s from y = -20: within 1 m of (0, -17) after 0.7 s (7 steps, 2.1 m)
    problem = _problem(goal=(0.0, -17.0))
    planner = _Scripted(np.zeros((30, 2)), _Settings(goal_stop_distance=1.0))
    res = run_receding(planner, problem, torch.tensor(START, dtype=torch.float64))
    assert res.status == PlanStatus.SUCCESS and res.states.shape == (8, 5)
    assert float(torch.linalg.norm(res.states[-1, :2] - torch.tensor([0.0, -17.0], dtype=torch.float64))) < 1.0
    assert float(torch.linalg.norm(res.states[-2, :2] - torch.tensor([0.0, -17.0], dtype=torch.float64))) >= 1.0


def test_exceptions_become_an_error_with_the_states_so_far():
    problem = _problem()
    res = run_receding(_Scripted(_inputs(10), _Settings(), fail_at=4), problem,
                       torch.tensor(START, dtype=torch.float64))
    assert res.status == PlanStatus.ERROR and res.message == "RuntimeError: solver exploded"
    assert res.states.shape == (5, 5) and res.extras["steps"] == 4
    bad = run_receding(_Scripted(_inputs(3), _Settings()), problem, torch.zeros(3))
    assert bad.status == PlanStatus.ERROR and "true_state must have 5 entries" in bad.message
    inf = run_receding(_Scripted(np.full((3, 2), np.inf), _Settings()), problem,
                       torch.tensor(START, dtype=torch.float64))
    assert inf.status == PlanStatus.ERROR and "non-finite at step 0" in inf.message

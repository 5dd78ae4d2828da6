"""The receding-horizon closed loop: a planner that solves one step at a time, driven on the true system.

The MPC baselines (M0-M3, :class:`~density_planner.planners.mpc.MPCPlanner`) only solve the NLP of one step from a
given state; this module is the plant around them. :func:`run_receding` repeats, for ``h = 0, 1, ...``:

1. measure the true state ``x`` (the heading biased by ``theta_bias``, :meth:`System.measure`, when the planner's
   configuration has ``biased_measurement``; the true state otherwise);
2. ask the planner for the input of step ``h`` (:meth:`StepwisePlanner.solve`);
3. hold that input for ``stage_dt`` on the true system: ``substeps`` explicit-Euler steps of the system's model
   (:meth:`System.rollout`; the paper's plant is the nominal model, no tracking controller);

and stops after the planner's ``n_steps`` steps or once the position is within ``goal_stop_distance`` of the goal
(0: never early). The planner turns the run into its :class:`~density_planner.planners.base.PlanResult`
(:meth:`StepwisePlanner.closed_loop_result`); an exception stops the run and is reported there, with the states
reached so far. :meth:`MPCPlanner.plan_from` and :meth:`MPCPlanner.plan` call :func:`run_receding`, so the
``plan`` command, the benchmarks' ``RECEDING`` execution (:mod:`.simulate`) and the Python API run the same loop.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor

from ..planners.base import PlanResult
from ..planners.problem import PlanningProblem

__all__ = ["ClosedLoopRun", "StepwisePlanner", "run_receding"]

log = logging.getLogger(__name__)


@dataclass
class ClosedLoopRun:
    """A receding-horizon run (complete, or up to the exception that stopped it).

    Attributes:
        t_start: ``time.perf_counter()`` at the start of the run (before :meth:`StepwisePlanner.reset`).
        states: true states ``(nx,)`` (float64, CPU), the initial state first; one more than ``inputs`` once the
            first step ran.
        inputs: applied inputs ``(nu,)`` (float64), one per step.
        steps: the planner's record of every step (what :meth:`StepwisePlanner.solve` returned).
        error: ``"ExceptionType: message"`` if an exception stopped the run, else ``""``.
    """

    t_start: float
    states: list[Tensor] = field(default_factory=list)
    inputs: list[Tensor] = field(default_factory=list)
    steps: list[Any] = field(default_factory=list)
    error: str = ""


class StepSettings(Protocol):
    """The closed-loop settings :func:`run_receding` reads from the planner's configuration."""

    @property
    def stage_dt(self) -> float: ...  # duration of one step [s]

    @property
    def substeps(self) -> int: ...  # explicit-Euler sub-steps of the plant per step

    @property
    def biased_measurement(self) -> bool: ...  # the planner sees the biased heading

    @property
    def goal_stop_distance(self) -> float: ...  # stop within this distance of the goal [m] (0: never)


class StepResult(Protocol):
    """A step record: at least the applied input ``(nu,)``."""

    @property
    def input(self) -> np.ndarray: ...


class StepwisePlanner(Protocol):
    """A planner that solves one receding-horizon step at a time (:class:`~density_planner.planners.mpc.MPCPlanner`)."""

    name: str

    @property
    def config(self) -> StepSettings: ...

    def reset(self, problem: PlanningProblem) -> None:
        """Bind the problem (scene, goal, time slices) and forget any warm start."""

    @property
    def n_steps(self) -> int:
        """Number of closed-loop steps of the bound problem."""

    def solve(self, state: Tensor, step: int) -> StepResult:
        """The step ``step`` from the measured state ``state (nx,)``; never raises for solver trouble."""

    def closed_loop_result(self, problem: PlanningProblem, run: ClosedLoopRun) -> PlanResult:
        """The planner's result of a finished (or stopped) run."""


def run_receding(planner: StepwisePlanner, problem: PlanningProblem, true_state: Tensor) -> PlanResult:
    """Run ``planner`` in closed loop on ``problem`` from the true initial state ``true_state (nx,)`` (its
    ``theta_bias`` enters the measurement when the planner's configuration has ``biased_measurement``); see the
    module docstring. Never raises: an exception becomes the result's ``ERROR`` status."""
    run = ClosedLoopRun(t_start=time.perf_counter())
    try:
        planner.reset(problem)
        cfg = planner.config
        system = problem.system
        x = torch.as_tensor(true_state, dtype=torch.float64).detach().cpu().reshape(-1).clone()
        if x.shape != (system.nx,):
            raise ValueError(f"true_state must have {system.nx} entries, got shape {tuple(x.shape)}")
        goal = torch.tensor(problem.goal, dtype=torch.float64)
        stop = cfg.goal_stop_distance
        h_sub = cfg.stage_dt / cfg.substeps
        run.states.append(x)
        for h in range(planner.n_steps):
            step = planner.solve(system.measure(x) if cfg.biased_measurement else x, h)
            run.steps.append(step)
            u = torch.as_tensor(step.input, dtype=torch.float64)
            for _ in range(cfg.substeps):  # the plant: a braking car stops (System.standstill)
                x = system.standstill(system.rollout(x, u[None], h_sub)[-1])
            run.states.append(x)
            run.inputs.append(u)
            if not bool(torch.isfinite(x).all()):
                raise FloatingPointError(f"the state became non-finite at step {h}")
            if stop > 0 and float(torch.linalg.norm(system.positions(x) - goal)) < stop:
                break
    except Exception as exc:  # noqa: BLE001 - a benchmark never crashes on one planner
        log.warning("%s failed: %s", planner.name, exc)
        run.error = f"{type(exc).__name__}: {exc}"
    return planner.closed_loop_result(problem, run)

"""Execute a plan from a true initial state: the closed loop that the benchmark scores.

Three ways a planner's output is executed (:class:`~density_planner.planners.registry.ExecutionMode`, declared by
the planner's registration), as in the paper's comparison (§V):

* ``TRACK`` (density, search and sampling planners): the plan is a reference trajectory computed offline from the
  initial *distribution*; the tracking controller follows it in closed loop from the true state, seeing the
  measurement of :meth:`~density_planner.systems.base.System.measure` (for the car: heading-biased) (the true state's
  ``theta_bias`` component is the bias; 0 for the unbiased variant). Explicit Euler at 0.01 s by default
  (the paper's code), the controller evaluated at every step. Many initial states run in one batched call.
* ``RECEDING`` (MPC M0-M3): ``planner.plan_from(problem, true_state)`` runs the MPC step by step from the
  true state in the closed loop of :mod:`.receding` (the planner's configuration says whether it sees the
  biased heading).
* ``OPEN_LOOP`` (oracle): ``planner.plan_from(problem, true_state)`` plans from the true state (it knows it) and
  its inputs are applied open loop; the plant is the nominal model, so the planned trajectory is the executed
  one.

Online time per 0.1-s step: ``TRACK`` = the wall time of the controller evaluations that the executed loop needs
in that step (10 at the default 0.01-s integration step), each evaluation one state as on a car, by the one-state
evaluator a car would run (:class:`~density_planner.control.fast.NumpyC3M` for C3M on the car, compiled where numba
is installed, a planning step's evaluations in one call; the controller itself otherwise); ``RECEDING``
= the whole MPC step (occupancy windows, parameters, IPOPT, warm start), as recorded by the planner; ``OPEN_LOOP``
= 0 (nothing is computed online).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..control.base import TrackingController
from ..control.reference import Reference
from ..density.liouville import LiouvilleConfig, simulate_closed_loop
from ..planners.base import Planner, PlanResult
from ..planners.problem import PlanningProblem
from ..planners.registry import ExecutionMode
from ..systems.base import System
from .config import EvaluationConfig

__all__ = [
    "ExecutionMode",
    "Execution",
    "execution_mode",
    "track_reference",
    "controller_step_times",
    "execute",
    "monte_carlo",
]

log = logging.getLogger(__name__)


def execution_mode(planner: Planner) -> ExecutionMode:
    """The execution mode of ``planner``: its ``execution_mode`` attribute (set by
    :func:`~density_planner.planners.registry.make_planner` from the registration) if it has one, else the
    registration of its name, else ``TRACK`` (an unregistered reference planner)."""
    mode = getattr(planner, "execution_mode", None)
    if mode is not None:
        return ExecutionMode(mode)
    from ..planners.registry import planner_info

    return planner_info(getattr(planner, "name", ""), default=True).execution


@dataclass
class Execution:
    """One executed run.

    Attributes:
        states: ``(T, nx)`` executed states on the planning grid (0.1 s); ``T`` is 101 for 10 s, fewer when an MPC
            stopped early at the goal.
        planned_inputs: ``(T - 1, nu)`` the inputs the method plans (the reference inputs of a tracked plan; the
            applied inputs of MPC and oracle) on the planning grid: the paper's ``J_I`` is computed on these.
        applied_inputs: ``(T - 1, nu)`` the inputs actually applied at the planning-grid times.
        step_times: ``(T - 1,)`` online computation time per planning step [s].
        offline_time: planning time before the run starts [s] (tracked plans: the whole plan; MPC: per-scene
            precomputation only; oracle: the whole plan).
        plan: the planner's result (for MPC and oracle: the result of ``plan_from`` the true state).
        ok: the planner produced a usable solution.
        message: why not, when it did not.
    """

    states: Tensor
    planned_inputs: Tensor
    applied_inputs: Tensor
    step_times: np.ndarray
    offline_time: float
    plan: PlanResult
    ok: bool = True
    message: str = ""


def _liouville_config(config: EvaluationConfig, problem: PlanningProblem) -> LiouvilleConfig:
    # the executed vehicle: the configured fixed step
    return LiouvilleConfig(integrator=config.integrator, dt=config.dt, output_dt=problem.parameterization.plan_dt)


@torch.no_grad()
def track_reference(
    system: System,
    controller: TrackingController,
    reference: Reference,
    x0: Tensor,
    *,
    config: LiouvilleConfig,
    all_steps: bool = False,
) -> Tensor:
    """Closed-loop trajectories ``(N, T, nx)`` of the true initial states ``x0 (N, nx)`` tracking ``reference``
    (batch shape ``()``); one batched call for all states. The executed vehicle: its physical limits hold
    (``plant=True`` of :func:`simulate_closed_loop`)."""
    if reference.batch_shape != ():
        raise ValueError(f"reference must be a single trajectory (batch shape ()), got {tuple(reference.batch_shape)}")
    _, x = simulate_closed_loop(system, controller, x0, reference, config=config, all_steps=all_steps, plant=True)
    return x


@torch.no_grad()
def controller_step_times(
    system: System,
    controller: TrackingController,
    reference: Reference,
    fine_states: Tensor,
    config: LiouvilleConfig,
    stages: int = 1,
) -> np.ndarray:
    """Wall time [s] of the controller evaluations per planning step, one state at a time (as on the car).

    ``fine_states (K + 1, nx)`` are the executed states at every integration step of ``config.dt``; each is
    measured and fed to the controller with the reference at that time (``stages`` evaluations per integration
    step: 1 for Euler, 4 for RK4). A C3M controller on the car is evaluated by its torch-free one-state form
    (:class:`~density_planner.control.fast.NumpyC3M`, equal to it to 1e-6), a planning step's evaluations in one
    call (:meth:`~density_planner.control.fast.NumpyC3M.evaluate_each`, each one state), as the online loop
    (``drive``) runs it; any other controller one call per evaluation. Returns ``(n_plan - 1,)`` sums over the
    integration steps of every planning step.
    """
    from ..control.c3m import C3MController
    from ..control.fast import NumpyC3M

    n_steps = fine_states.shape[0] - 1
    every = config.save_every
    n_plan = n_steps // every
    x_ref, u_ref = reference.stage_values(config.dt, n_steps, (0.0,))
    x_hat = system.measure(fine_states)
    if n_plan == 0:
        return np.empty(0)
    if isinstance(controller, C3MController) and NumpyC3M.supports(system):
        fast = NumpyC3M(controller)
        # the state, reference and input of every evaluation, grouped by planning step
        rep = np.repeat(np.arange(n_plan * every), stages)
        xh, xr, ur = (a.detach().cpu().double().numpy()[rep].reshape(n_plan, every * stages, -1)
                      for a in (x_hat[:n_steps], x_ref[:, 0], u_ref[:, 0]))
        fast.evaluate_each(xh[0, :1], xr[0, :1], ur[0, :1])  # the first call of a process loads the compiled code
        out = np.empty(n_plan)
        for p in range(n_plan):
            t0 = time.perf_counter()
            fast.evaluate_each(xh[p], xr[p], ur[p])
            out[p] = time.perf_counter() - t0
        return out
    times = np.empty(n_steps)
    for k in range(n_steps):
        t0 = time.perf_counter()
        for _ in range(stages):
            controller(x_hat[k : k + 1], x_ref[k, 0].unsqueeze(0), u_ref[k, 0].unsqueeze(0))
        times[k] = time.perf_counter() - t0
    return times[: n_plan * every].reshape(-1, every).sum(-1)


def _applied_inputs(system: System, controller: TrackingController, reference: Reference, states: Tensor) -> Tensor:
    """Controller outputs at the planning-grid states ``(T, nx)`` -> ``(T - 1, nu)``."""
    x_ref = reference.x_plan[: states.shape[0] - 1]
    u_ref = reference.u_plan[: states.shape[0] - 1]
    with torch.no_grad():
        return controller(system.measure(states[:-1]), x_ref, u_ref)


def _track(
    problem: PlanningProblem, plan: PlanResult, true_state: Tensor, controller: TrackingController,
    config: EvaluationConfig, time_online: bool
) -> Execution:
    system = problem.system
    ref = plan.reference
    if ref is None:
        raise ValueError(f"plan of {plan.planner!r} has no reference trajectory to track")
    lcfg = _liouville_config(config, problem)
    x0 = true_state.to(dtype=ref.x.dtype, device=ref.x.device).reshape(1, -1)
    fine = track_reference(system, controller, ref, x0, config=lcfg, all_steps=True)[0]
    states = fine[:: lcfg.save_every]
    applied = _applied_inputs(system, controller, ref, states)
    stages = 4 if config.integrator == "rk4" else 1
    if time_online:
        step_times = controller_step_times(system, controller, ref, fine, lcfg, stages)
    else:
        step_times = np.zeros(states.shape[0] - 1)
    return Execution(
        states=states,
        planned_inputs=ref.u_plan[: states.shape[0] - 1],
        applied_inputs=applied,
        step_times=step_times,
        offline_time=float(plan.timings.get("total", float("nan"))),
        plan=plan,
        ok=plan.ok,
        message=plan.message,
    )


def _from_plan_from(planner: Planner, problem: PlanningProblem, true_state: Tensor, mode: ExecutionMode) -> Execution:
    plan_from = getattr(planner, "plan_from", None)
    if plan_from is None:
        raise ValueError(f"planner {planner.name!r} has no plan_from(problem, true_state) for {mode.value} execution")
    result: PlanResult = plan_from(problem, true_state)
    states = result.states
    nu = problem.system.nu
    if states is None or states.shape[0] < 2:
        empty = torch.zeros(0, nu)
        return Execution(states=states if states is not None else torch.zeros(0, problem.system.nx),
                         planned_inputs=empty, applied_inputs=empty, step_times=np.zeros(0),
                         offline_time=float(result.timings.get("total", float("nan"))), plan=result, ok=False,
                         message=result.message or "no trajectory")
    if mode == ExecutionMode.RECEDING:
        applied = result.extras.get("applied_inputs")
        if applied is None:
            applied = result.extras.get("applied_inputs_plan", [])  # older MPC results
        inputs = torch.as_tensor(applied, dtype=states.dtype)
        if inputs.numel() // nu != states.shape[0] - 1:
            raise ValueError(f"{planner.name}: {inputs.numel() // nu} applied inputs for {states.shape[0]} states")
        step_times = np.asarray(result.extras.get("step_times", []), dtype=float)
        # per-scene precomputation (tube disc sums) is offline work; the one-time NLP construction is not counted
        offline = float(result.timings.get("tube_precompute", 0.0))
    else:
        ref = result.reference
        inputs = ref.u_plan[: states.shape[0] - 1] if ref is not None else torch.zeros(states.shape[0] - 1, nu)
        step_times = np.zeros(states.shape[0] - 1)
        offline = float(result.timings.get("total", float("nan")))
    inputs = inputs.reshape(-1, nu)[: states.shape[0] - 1].to(states)
    return Execution(states=states, planned_inputs=inputs, applied_inputs=inputs, step_times=step_times,
                     offline_time=offline, plan=result, ok=result.ok, message=result.message)


def execute(
    planner: Planner,
    problem: PlanningProblem,
    true_state: Tensor,
    *,
    plan: PlanResult | None = None,
    controller: TrackingController | None = None,
    config: EvaluationConfig | None = None,
    time_online: bool = True,
) -> Execution:
    """Execute ``planner`` from ``true_state (nx,)`` (see the module docstring).

    Args:
        plan: for ``TRACK`` planners, the plan to execute (computed once offline and reused for every true state);
            ignored otherwise (MPC and oracle plan from the true state).
        controller: the tracking controller (``TRACK`` only).
        time_online: measure the controller's online time (``TRACK``; otherwise zeros).
    """
    config = config or EvaluationConfig()
    mode = execution_mode(planner)
    if mode == ExecutionMode.TRACK:
        if plan is None or controller is None:
            raise ValueError("executing a tracked reference needs plan= and controller=")
        if plan.reference is None:
            nu = problem.system.nu
            return Execution(states=torch.zeros(0, problem.system.nx), planned_inputs=torch.zeros(0, nu),
                             applied_inputs=torch.zeros(0, nu), step_times=np.zeros(0),
                             offline_time=float(plan.timings.get("total", float("nan"))), plan=plan, ok=False,
                             message=plan.message or "the planner returned no reference")
        return _track(problem, plan, true_state, controller, config, time_online)
    return _from_plan_from(planner, problem, true_state, mode)


def monte_carlo(
    planner: Planner,
    problem: PlanningProblem,
    initial_states: Tensor,
    *,
    plan: PlanResult | None = None,
    controller: TrackingController | None = None,
    config: EvaluationConfig | None = None,
) -> list[Tensor]:
    """Executed trajectories (each ``(T_i, nx)`` on the planning grid) from every row of ``initial_states (M,
    nx)``: tracked references in one batched closed-loop call, MPC and oracle one run per state."""
    config = config or EvaluationConfig()
    if initial_states.shape[0] == 0:
        return []
    mode = execution_mode(planner)
    if mode == ExecutionMode.TRACK:
        if plan is None or plan.reference is None or controller is None:
            return []
        ref = plan.reference
        x0 = initial_states.to(dtype=ref.x.dtype, device=ref.x.device)
        x = track_reference(problem.system, controller, ref, x0, config=_liouville_config(config, problem))
        return list(x.unbind(0))
    out = []
    for x0 in initial_states:
        run = _from_plan_from(planner, problem, x0, mode)
        if run.states.shape[0] >= 1:
            out.append(run.states)
    return out

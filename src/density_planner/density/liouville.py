"""Closed-loop simulation and exact Liouville density propagation.

Along every closed-loop trajectory the Liouville equation reduces to the ODE (paper Eq. (2))::

    d/dt x       = f_cl(x, t)
    d/dt log rho = -div f_cl(x, t)

integrated here jointly, in log form (never NaN, unlike the Euler step ``log(1 - dt div f)`` of the paper's
code), with the same explicit scheme and step for both components. The loop runs over time only; all samples
(and all references of a batch) advance together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

import torch
from torch import Tensor

from ..checks import check_choice, check_positive, check_speed_steps
from ..control.base import TrackingController
from ..control.reference import Reference
from ..systems.base import System
from .base import DensityPredictor, DensityTrajectory, expand_log_rho0, expand_samples
from .closed_loop import ClosedLoop, DivergenceMethod
from .integrators import get_integrator

__all__ = ["LiouvilleConfig", "simulate_closed_loop", "propagate_density", "ExactLiouville"]

IntegratorName = Literal["euler", "rk4"]


@dataclass(frozen=True)
class LiouvilleConfig:
    """Numerics of the exact density propagation.

    The default (RK4 at 0.1 s) is both faster and more accurate than Euler at 0.01 s (the paper's scheme); see
    ``benchmarks/bench_liouville.py`` for the measured errors against a fine RK4 solution.
    """

    #: explicit scheme: "euler" (order 1) or "rk4" (order 4)
    integrator: IntegratorName = "rk4"
    #: integration step [s] (the largest: see ``speed_steps``); must divide the output step
    dt: float = 0.1
    #: divergence: "structured" (fast, for control-affine systems with constant B) or "autodiff" (any system)
    divergence: DivergenceMethod = "structured"
    #: time between saved points [s] (the planning grid)
    output_dt: float = 0.1
    #: finer steps for fast references, ``((v, dt_v), ...)`` [m/s, s]: a reference whose highest speed reaches
    #: ``v`` is integrated with a step of at most ``dt_v`` (the largest such step that divides ``output_dt``).
    #: ``None`` (default): the system's own schedule (:attr:`System.liouville_speed_steps`: the car's road domain
    #: refines 0.1 s to 0.05 / 0.025 / 0.02 s from 15 / 20 / 25 m/s, where its controller crosses its turn-rate
    #: saturation within hundredths of a second; other systems and the paper's box keep the fixed step);
    #: ``()``: the fixed step ``dt``; pairs: this schedule for every system. Systems without a speed state, and
    #: references slower than every ``v``, use ``dt``
    speed_steps: tuple[tuple[float, float], ...] | None = None

    def __post_init__(self) -> None:
        check_choice("integrator", self.integrator, ("euler", "rk4"))
        check_choice("divergence", self.divergence, ("structured", "autodiff"))
        check_positive("dt", self.dt)
        check_positive("output_dt", self.output_dt)
        r = self.output_dt / self.dt
        if abs(r - round(r)) > 1e-6 * max(1.0, r) or round(r) < 1:
            raise ValueError(f"output_dt ({self.output_dt}) must be an integer multiple of dt ({self.dt})")
        if self.speed_steps is None:
            return
        object.__setattr__(self, "speed_steps", check_speed_steps("LiouvilleConfig.speed_steps", self.speed_steps))

    @property
    def save_every(self) -> int:
        return int(round(self.output_dt / self.dt))

    def with_step(self, dt: float) -> LiouvilleConfig:
        """This configuration with the fixed step ``dt`` (no schedule)."""
        return replace(self, dt=dt, speed_steps=())

    def _dividing(self, step: float) -> float:
        """The largest step <= ``step`` that divides ``output_dt``."""
        return self.output_dt / math.ceil(self.output_dt / step - 1e-9)

    def schedule(self, system: System | None = None) -> tuple[tuple[float, float], ...]:
        """The step schedule in force: ``speed_steps``, or where it is ``None`` the system's own (none without one)."""
        if self.speed_steps is not None:
            return self.speed_steps
        return () if system is None else system.liouville_speed_steps

    def step_for_speed(self, speed: float, system: System | None = None) -> float:
        """The step [s] of a reference whose highest speed is ``speed`` [m/s]: ``dt`` refined by :meth:`schedule`."""
        dt = self.dt
        for v, step in self.schedule(system):
            if speed >= v:
                dt = min(dt, self._dividing(step))
        return dt

    def steps_for(self, system: System, reference: Reference) -> Tensor | None:
        """Per reference of the batch ``(*batch,)``, the step [s] of :meth:`step_for_speed` for its highest
        speed; ``None`` where every reference gets ``dt`` (no schedule, a system without a speed state, or no
        reference reaching a scheduled speed)."""
        schedule = self.schedule(system)
        if not schedule:
            return None
        speeds = system.speeds(reference.x.detach())
        if speeds is None:
            return None
        top = speeds.abs().amax(dim=-1)
        if not bool((top >= min(v for v, _ in schedule)).any()):
            return None
        dt = torch.full(top.shape, self.dt, dtype=torch.float64, device=top.device)
        for v, step in schedule:
            dt = torch.where(top >= v, dt.clamp(max=self._dividing(step)), dt)
        return dt


def _check_inputs(system: System, x0: Tensor, reference: Reference) -> Tensor:
    return expand_samples(x0, reference, system.nx)


def _integrate(
    closed_loop: ClosedLoop,
    y0: tuple[Tensor, ...],
    reference: Reference,
    config: LiouvilleConfig,
    with_density: bool,
    all_steps: bool,
    plant: bool = False,
) -> tuple[Tensor, list[list[Tensor]]]:
    """Integrate ``y0 = (x0, [log_rho0])`` over the reference horizon; returns the saved times and states.
    ``plant`` (states only): the executed vehicle, held at rest (:meth:`System.standstill`) at every stage and
    after every step. Each reference takes its step from ``config.speed_steps`` (:meth:`LiouvilleConfig.steps_for`;
    a batch of several steps is integrated group by group); ``all_steps`` needs one time grid: the whole batch then
    takes its finest step."""
    if plant and with_density:
        raise ValueError("the plant's standstill is not a smooth flow: no density along it")
    steps = config.steps_for(closed_loop.system, reference)
    if steps is not None:
        values = sorted(set(steps.reshape(-1).tolist()))
        if len(values) > 1 and not all_steps:
            return _integrate_groups(steps, values, y0, reference, lambda y, ref, dt: _integrate(
                closed_loop, y, ref, config.with_step(dt), with_density, False, plant))
        config = config.with_step(values[0])
    integrator = get_integrator(config.integrator)
    horizon = reference.n_steps * reference.dt
    n_steps_f = horizon / config.dt
    n_steps = int(round(n_steps_f))
    if abs(n_steps_f - n_steps) > 1e-6 * max(1.0, n_steps_f):
        raise ValueError(f"dt ({config.dt}) must divide the reference horizon ({horizon} s)")
    save_every = 1 if all_steps else config.save_every
    if n_steps % save_every:
        raise ValueError(f"output_dt ({config.output_dt}) must divide the reference horizon ({horizon} s)")
    x_ref_st, u_ref_st = reference.stage_values(config.dt, n_steps, integrator.stages)
    # one sample axis: the reference broadcasts over the samples of its batch element
    x_ref_st = x_ref_st.unsqueeze(-2)
    u_ref_st = u_ref_st.unsqueeze(-2)
    method = config.divergence

    if with_density:
        def func(y, x_ref, u_ref):
            dx, div = closed_loop.rhs_and_divergence(y[0], x_ref, u_ref, method)
            return dx, -div
    elif plant:  # the stages see the held state too: a car at rest does not creep backwards within a step
        hold = closed_loop.system.standstill

        def func(y, x_ref, u_ref):
            return (closed_loop.rhs(hold(y[0]), x_ref, u_ref),)
    else:
        def func(y, x_ref, u_ref):
            return (closed_loop.rhs(y[0], x_ref, u_ref),)

    saved: list[list[Tensor]] = [[v] for v in y0]
    y = y0
    for n in range(n_steps):
        y = integrator.step(func, y, x_ref_st[n], u_ref_st[n], config.dt)
        if plant:
            y = (closed_loop.system.standstill(y[0]),)
        if (n + 1) % save_every == 0:
            for store, v in zip(saved, y):
                store.append(v)
    dt_save = config.dt * save_every
    t = torch.arange(len(saved[0]), dtype=y0[0].dtype, device=y0[0].device) * dt_save
    return t, saved


def _integrate_groups(
    steps: Tensor, values: list[float], y0: tuple[Tensor, ...], reference: Reference, run
) -> tuple[Tensor, list[list[Tensor]]]:
    """The batch's references grouped by their step ``steps (*batch,)`` (distinct ``values``), each group
    integrated alone by ``run(y0_group, reference_group, step)``, the results put back in the batch's order
    (differentiable like one integration)."""
    batch = y0[0].shape[:-2]
    flat = steps.expand(batch).reshape(-1)
    n = flat.numel()
    params, x_ref, u_ref = (v.expand(*batch, *v.shape[-2:]).reshape(n, *v.shape[-2:])
                            for v in (reference.params, reference.x, reference.u))
    ref = Reference(params, x_ref, u_ref, reference.parameterization)
    flat_y0 = tuple(y.reshape(n, *y.shape[len(batch):]) for y in y0)
    order, parts = [], []
    t = None
    for value in values:
        idx = torch.nonzero(flat == value).squeeze(-1).to(y0[0].device)
        t, saved = run(tuple(y.index_select(0, idx) for y in flat_y0), ref.select(idx), value)
        order.append(idx)
        parts.append(saved)
    assert t is not None
    inverse = torch.argsort(torch.cat(order))
    merged = [[torch.cat([p[c][k] for p in parts]).index_select(0, inverse).reshape(*batch, *parts[0][c][k].shape[1:])
               for k in range(len(parts[0][c]))] for c in range(len(y0))]
    return t, merged


def simulate_closed_loop(
    system: System,
    controller: TrackingController,
    x0: Tensor,
    reference: Reference,
    *,
    config: LiouvilleConfig | None = None,
    all_steps: bool = False,
    plant: bool = False,
) -> tuple[Tensor, Tensor]:
    """Closed-loop trajectories of the true initial states ``x0 (*batch, N, nx)`` tracking ``reference``.

    Returns ``(t (T,), x (*batch, N, T, nx))`` on the output grid (every integration step if ``all_steps``).
    Use ``LiouvilleConfig(integrator="euler", dt=0.01)`` for the paper's scheme. ``plant=True`` simulates the
    executed vehicle: after every step its physical limits hold (:meth:`System.standstill`: a braking car stops
    instead of reversing); ``False`` (default) is the model's flow, the one the density propagation follows.
    """
    config = config or LiouvilleConfig()
    x0 = _check_inputs(system, x0, reference)
    t, saved = _integrate(ClosedLoop(system, controller), (x0,), reference, config, False, all_steps, plant)
    return t, torch.stack(saved[0], dim=-2)


def propagate_density(
    system: System,
    controller: TrackingController,
    x0: Tensor,
    reference: Reference,
    *,
    log_rho0: Tensor | None = None,
    config: LiouvilleConfig | None = None,
    all_steps: bool = False,
) -> DensityTrajectory:
    """Exact Liouville propagation of the density along the closed-loop trajectories from ``x0 (*batch, N, nx)``.

    ``log_rho0 (*batch, N)`` is the log of the initial density at ``x0`` (default 0: the result is then the
    log density *ratio* ``log rho(x(t), t) / rho0(x0)``). Differentiable w.r.t. the reference parameters.
    """
    config = config or LiouvilleConfig()
    x0 = _check_inputs(system, x0, reference)
    if log_rho0 is None:
        log_rho0 = torch.zeros(x0.shape[:-1], dtype=x0.dtype, device=x0.device)
    else:
        log_rho0 = expand_log_rho0(log_rho0, x0)
    closed_loop = ClosedLoop(system, controller)
    t, saved = _integrate(closed_loop, (x0, log_rho0), reference, config, True, all_steps)
    x = torch.stack(saved[0], dim=-2)
    log_rho = torch.stack(saved[1], dim=-1)
    return DensityTrajectory(t=t, x=x, log_rho=log_rho, log_rho0=log_rho0)


class ExactLiouville(DensityPredictor):
    """:class:`DensityPredictor` that integrates the Liouville equation exactly (see :func:`propagate_density`)."""

    name = "exact"

    def __init__(self, system: System, controller: TrackingController, config: LiouvilleConfig | None = None):
        self.system = system
        self.controller = controller
        self.config = config or LiouvilleConfig()

    def predict(self, x0: Tensor, log_rho0: Tensor, reference: Reference) -> DensityTrajectory:
        self._check_output_dt(reference)
        return propagate_density(self.system, self.controller, x0, reference, log_rho0=log_rho0, config=self.config)

    def predict_states(self, x0: Tensor, log_rho0: Tensor, reference: Reference) -> DensityTrajectory:
        """The closed-loop trajectories alone (same integrator and step as :meth:`predict`, hence the same
        states), ``log_rho`` NaN: without the divergence the controller's tangents are not pushed through, about
        1.4x faster with the C3M controller, forward and backward."""
        self._check_output_dt(reference)
        t, x = simulate_closed_loop(self.system, self.controller, x0, reference, config=self.config)
        log_rho0 = expand_log_rho0(log_rho0, x[..., 0, :])
        return DensityTrajectory(t=t, x=x, log_rho=torch.full(x.shape[:-1], math.nan, dtype=x.dtype,
                                 device=x.device), log_rho0=log_rho0)

    def _check_output_dt(self, reference: Reference) -> None:
        plan_dt = reference.parameterization.plan_dt
        if not math.isclose(self.config.output_dt, plan_dt):
            raise ValueError(
                f"LiouvilleConfig.output_dt ({self.config.output_dt}) must equal the planning step ({plan_dt})"
            )

"""Closed-loop simulation and exact Liouville density propagation.

Along every closed-loop trajectory the Liouville equation reduces to the ODE (paper Eq. (2))::

    d/dt x       = f_cl(x, t)
    d/dt log rho = -div f_cl(x, t)

integrated here jointly, in log form (never NaN, unlike the Euler step ``log(1 - dt div f)`` of the paper's
code), with the same explicit scheme and step for both components. The loop runs over time only. With a fixed
step all samples (and all references of a batch) advance together; the error-controlled "dopri5" gives every
sample its own step and evaluates, at each pass, the samples still running.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, cast, get_args

import torch
from torch import Tensor

from ..checks import check_choice, check_positive
from ..control.base import TrackingController
from ..control.reference import Reference
from ..systems.base import System
from .base import DensityPredictor, DensityTrajectory, expand_log_rho0, expand_samples
from .closed_loop import ClosedLoop, DivergenceMethod
from .integrators import DOPRI5, get_integrator

__all__ = ["LiouvilleConfig", "simulate_closed_loop", "propagate_density", "ExactLiouville"]

IntegratorName = Literal["euler", "rk4", "dopri5"]


@dataclass(frozen=True)
class LiouvilleConfig:
    """Numerics of the exact density propagation.

    ``"rk4"`` at 0.1 s is both faster and more accurate than Euler at 0.01 s (the paper's scheme); ``"dopri5"``
    controls its error, per sample, where a closed loop turns fast (the car's road domain); see
    ``benchmarks/bench_liouville.py`` and docs/core.md for the measured errors against a converged solution.
    """

    #: scheme: "euler" (order 1) or "rk4" (order 4) at the fixed step ``dt``; "dopri5": the Dormand-Prince 5(4) pair
    #: with error control (every sample keeps its own step, at most ``dt``, so that the estimated local error of
    #: every state component and of the log-density stays below ``tolerance``); ``None`` (default): the system's
    #: own (:attr:`System.liouville_integrator`: "dopri5" for the car's road domain, whose learned controller
    #: crosses its turn-rate saturation within hundredths of a second at highway speed; "rk4" elsewhere)
    integrator: IntegratorName | None = None
    #: integration step [s] (with "dopri5" the largest and the first tried); must divide the output step
    dt: float = 0.1
    #: divergence: "structured" (fast, for control-affine systems with constant B) or "autodiff" (any system)
    divergence: DivergenceMethod = "structured"
    #: time between saved points [s] (the planning grid)
    output_dt: float = 0.1
    #: "dopri5": largest estimated local error per step, absolute, of every state component (in its unit) and of
    #: the log-density [nats]
    tolerance: float = 5e-5

    def __post_init__(self) -> None:
        if self.integrator is not None:
            check_choice("integrator", self.integrator, get_args(IntegratorName))
        check_choice("divergence", self.divergence, ("structured", "autodiff"))
        check_positive("dt", self.dt)
        check_positive("output_dt", self.output_dt)
        check_positive("tolerance", self.tolerance)
        r = self.output_dt / self.dt
        if abs(r - round(r)) > 1e-6 * max(1.0, r) or round(r) < 1:
            raise ValueError(f"output_dt ({self.output_dt}) must be an integer multiple of dt ({self.dt})")

    @property
    def save_every(self) -> int:
        return int(round(self.output_dt / self.dt))

    def scheme(self, system: System | None = None) -> IntegratorName:
        """The scheme in force: ``integrator``, or where it is ``None`` the system's own ("rk4" without one)."""
        if self.integrator is not None:
            return self.integrator
        if system is None:
            return "rk4"
        scheme = system.liouville_integrator
        check_choice("System.liouville_integrator", scheme, get_args(IntegratorName))
        return cast(IntegratorName, scheme)

    def describe(self, system: System | None = None) -> str:
        """One line naming the scheme and its step (or tolerance), e.g. for the CLI."""
        scheme = self.scheme(system)
        if scheme == "dopri5":
            return f"dopri5 (error-controlled, tolerance {self.tolerance:g}, steps <= {self.dt:g} s)"
        return f"{scheme} at {self.dt:g} s"


def _check_inputs(system: System, x0: Tensor, reference: Reference) -> Tensor:
    return expand_samples(x0, reference, system.nx)


def _n_steps(horizon: float, dt: float, what: str) -> int:
    n_f = horizon / dt
    n = int(round(n_f))
    if abs(n_f - n) > 1e-6 * max(1.0, n_f):
        raise ValueError(f"{what} ({dt}) must divide the reference horizon ({horizon} s)")
    return n


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
    after every step. The scheme is :meth:`LiouvilleConfig.scheme`; "dopri5" saves the output grid only and has no
    plant mode (the hold is not a smooth flow): both need a fixed step."""
    if plant and with_density:
        raise ValueError("the plant's standstill is not a smooth flow: no density along it")
    scheme = config.scheme(closed_loop.system)
    if scheme == "dopri5":
        if all_steps or plant:
            raise ValueError("LiouvilleConfig: the error-controlled 'dopri5' has no common time grid of all steps "
                             "and no plant mode; choose a fixed step, e.g. LiouvilleConfig(integrator='rk4')")
        return _integrate_adaptive(closed_loop, y0, reference, config, with_density)
    integrator = get_integrator(scheme)
    horizon = reference.n_steps * reference.dt
    n_steps = _n_steps(horizon, config.dt, "dt")
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


#: step-size control of "dopri5": safety factor and the bounds of one change of the step
_SAFETY, _SHRINK_MIN, _GROW_MAX = 0.9, 0.2, 5.0


def _integrate_adaptive(
    closed_loop: ClosedLoop,
    y0: tuple[Tensor, ...],
    reference: Reference,
    config: LiouvilleConfig,
    with_density: bool,
) -> tuple[Tensor, list[list[Tensor]]]:
    """:func:`_integrate` with the error-controlled Dormand-Prince 5(4) pair (:data:`~.integrators.DOPRI5`).

    Every sample (row) keeps its own clock and step: a step is accepted where the estimated local error of every
    component is at most ``config.tolerance`` (else retried shorter), the next step is ``h (0.9 / err)^(1/5)``
    (at most 5x longer, 5x shorter, and ``config.dt``), and no step passes the next output time, where the row's
    state is saved. Only rows still running are evaluated. The step sizes are chosen without gradient (as in any
    error-controlled solver) and the solution is differentiable along them: every update is out of place.
    """
    pair = DOPRI5
    x0 = y0[0]
    batch, n_samples, nx = x0.shape[:-2], x0.shape[-2], x0.shape[-1]
    n_ref = math.prod(batch)
    horizon = reference.n_steps * reference.dt
    n_out = _n_steps(horizon, config.output_dt, "output_dt")  # dt divides output_dt (LiouvilleConfig), hence this
    params, x_ref, u_ref = (v.expand(*batch, *v.shape[-2:]).reshape(n_ref, *v.shape[-2:])
                            for v in (reference.params, reference.x, reference.u))
    flat_ref = Reference(params, x_ref, u_ref, reference.parameterization)
    m = n_ref * n_samples
    device = x0.device
    ref_rows = torch.arange(n_ref, device=device).repeat_interleave(n_samples)
    y = [x0.reshape(m, nx)] + ([y0[1].reshape(m)] if with_density else [])
    method = config.divergence

    def func(ys, t, left, rows):
        x_ref, u_ref = flat_ref.values_at(rows, t, left)
        if with_density:
            dx, div = closed_loop.rhs_and_divergence(ys[0], x_ref, u_ref, method)
            return [dx, -div], u_ref
        return [closed_loop.rhs(ys[0], x_ref, u_ref)], u_ref

    t = torch.zeros(m, dtype=torch.float64, device=device)
    h = torch.full((m,), config.dt, dtype=torch.float64, device=device)
    k_next = torch.ones(m, dtype=torch.long, device=device)  # index of the next output time per row
    k1, _ = func(y, t, False, ref_rows)
    out_rows: list[Tensor] = []
    out_k: list[Tensor] = []
    out_vals: list[list[Tensor]] = [[] for _ in y]
    active = torch.arange(m, device=device)
    while active.numel():
        rows = ref_rows[active]
        t_a = t[active]
        h_prop = h[active]
        h_a = torch.minimum(h_prop, k_next[active].to(torch.float64) * config.output_dt - t_a)
        if bool((h_a < 1e-9 * config.dt).any()):
            raise FloatingPointError(
                "exact Liouville ('dopri5'): the step size underflowed (the closed loop is not finite or not "
                "integrable there); check the initial states and the reference, or use a fixed step "
                "(LiouvilleConfig(integrator='rk4'))")
        hd = h_a.to(x0.dtype)
        y_a = [v.index_select(0, active) for v in y]
        ks = [[k.index_select(0, active) for k in k1]]
        left = torch.ones_like(active, dtype=torch.bool)
        u_last = None
        for i in range(1, len(pair.stages)):
            y_i = [v + _weighted(hd, pair.a[i], [k[c] for k in ks]) for c, v in enumerate(y_a)]
            k_i, u_last = func(y_i, t_a + pair.stages[i] * h_a, left, rows)
            ks.append(k_i)
        y_new = y_i  # FSAL: the last stage is evaluated at the 5th-order solution
        err = torch.stack([(_weighted(hd, pair.error, [k[c] for k in ks]).abs().reshape(len(active), -1)
                            .amax(-1)) for c in range(len(y))]).amax(0).detach().to(torch.float64) / config.tolerance
        ok = err <= 1.0  # NaN is never accepted: the step then shrinks until it underflows (error above)
        factor = (_SAFETY * err.clamp(min=1e-12) ** (-1.0 / pair.order)).clamp(_SHRINK_MIN, _GROW_MAX)
        factor = torch.where(torch.isnan(factor), torch.full_like(factor, _SHRINK_MIN), factor)
        h_new = h_a * factor
        # a step cut short by an output time, accepted, keeps the proposal it was cut from
        h_new = torch.where(ok & (h_a < h_prop), torch.maximum(h_new, h_prop), h_new)
        h = h.index_put((active,), h_new.clamp(max=config.dt))
        acc = active[ok]
        if acc.numel():
            t_acc = t_a[ok] + h_a[ok]
            k_acc = k_next[acc]
            landed = (t_acc - k_acc.to(torch.float64) * config.output_dt).abs() <= 1e-9 * config.dt
            t_acc = torch.where(landed, k_acc.to(torch.float64) * config.output_dt, t_acc)
            t = t.index_put((acc,), t_acc)
            y = [v.index_put((acc,), vn[ok]) for v, vn in zip(y, y_new)]
            k1 = [k.index_put((acc,), kn[ok]) for k, kn in zip(k1, ks[-1])]
            if bool(landed.any()):
                rows_l = acc[landed]
                out_rows.append(rows_l)
                out_k.append(k_acc[landed])
                for store, vn in zip(out_vals, y_new):
                    store.append(vn[ok][landed])
                k_next = k_next.index_put((rows_l,), k_acc[landed] + 1)
            # where the input switches at the new time, the next step's first stage takes its right limit
            assert u_last is not None
            _, u_right = flat_ref.values_at(ref_rows[acc], t_acc, False)
            switched = acc[(u_right != u_last[ok]).any(-1) & (k_next[acc] <= n_out)]
            if switched.numel():
                k_sw, _ = func([v.index_select(0, switched) for v in y], t.index_select(0, switched), False,
                               ref_rows[switched])
                k1 = [k.index_put((switched,), kn) for k, kn in zip(k1, k_sw)]
        active = active[k_next[active] <= n_out]
    rows_all = torch.cat(out_rows) if out_rows else torch.zeros(0, dtype=torch.long, device=device)
    k_all = torch.cat(out_k) if out_k else torch.zeros(0, dtype=torch.long, device=device)
    saved: list[list[Tensor]] = []
    for v0, store in zip(y0, out_vals):
        flat0 = v0.reshape(m, -1)
        grid = flat0.new_zeros(m, n_out + 1, flat0.shape[-1])
        grid = grid.index_put((torch.arange(m, device=device), torch.zeros(m, dtype=torch.long, device=device)),
                              flat0)
        if store:
            grid = grid.index_put((rows_all, k_all), torch.cat(store).reshape(len(rows_all), -1))
        grid = grid.reshape(*batch, n_samples, n_out + 1, *v0.shape[len(batch) + 1:])
        saved.append(list(grid.unbind(len(batch) + 1)))
    t_out = torch.arange(n_out + 1, dtype=x0.dtype, device=device) * config.output_dt
    return t_out, saved


def _weighted(h: Tensor, coefficients: tuple[float, ...], ks: list[Tensor]) -> Tensor:
    """``h sum_j c_j k_j`` (``h`` per row, broadcast over the trailing dimensions of ``k_j``)."""
    total = sum(c * k for c, k in zip(coefficients, ks) if c != 0.0)
    assert isinstance(total, Tensor)
    return h.reshape(-1, *([1] * (total.ndim - 1))) * total


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

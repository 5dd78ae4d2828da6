"""Closed-loop simulation and exact Liouville density propagation.

Along every closed-loop trajectory the Liouville equation reduces to the ODE (paper Eq. (2))::

    d/dt x       = f_cl(x, t)
    d/dt log rho = -div f_cl(x, t)

integrated here jointly, in log form (never NaN, unlike the Euler step ``log(1 - dt div f)`` of the paper's
code), with the same explicit scheme and step for both components. The loop runs over time only. With a fixed
step all samples (and all references of a batch) advance together; the error-controlled schemes ("rk43",
"dopri5") give every sample its own step and evaluate, at each pass, the samples still running.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import torch
from torch import Tensor

from ..checks import check_choice, check_positive
from ..control.base import TrackingController
from ..control.reference import Reference
from ..systems.base import LiouvilleScheme, System
from .base import DensityPredictor, DensityTrajectory, expand_log_rho0, expand_samples
from .closed_loop import ClosedLoop, DivergenceMethod
from .integrators import PAIRS, EmbeddedPair, get_integrator

__all__ = ["LiouvilleConfig", "simulate_closed_loop", "propagate_density", "ExactLiouville"]

IntegratorName = LiouvilleScheme  # the schemes by name (one list, the systems')
LogDensityRule = Literal["quadrature", "coupled"]


@dataclass(frozen=True)
class LiouvilleConfig:
    """Numerics of the exact density propagation.

    ``"rk4"`` at 0.1 s is both faster and more accurate than Euler at 0.01 s (the paper's scheme); ``"rk43"`` and
    ``"dopri5"`` control their error, per sample, where a closed loop turns fast or sweeps through its input
    saturation (the car's road domain); see ``benchmarks/bench_liouville.py`` and docs/core.md for the measured
    errors against a converged solution.
    """

    #: scheme: "euler" (order 1) or "rk4" (order 4) at the fixed step ``dt``; error-controlled (every sample keeps
    #: its own step, at most ``dt``, so that the estimated local error of every state component and of the
    #: log-density stays below ``tolerance`` and the controller's raw input crosses its saturation's bend in steps
    #: of at most ``saturation_step``): "rk43" (RK4 with an embedded order-3 estimate, four evaluations per step)
    #: or "dopri5" (the Dormand-Prince 5(4) pair, six); ``None`` (default): the system's own
    #: (:attr:`System.liouville_integrator`: "rk43" for the car's road domain, whose learned controller sweeps
    #: through its turn-rate saturation within hundredths of a second at highway speed; "rk4" elsewhere)
    integrator: IntegratorName | None = None
    #: integration step [s] (error-controlled: the largest and the first tried); must divide the output step
    dt: float = 0.1
    #: divergence: "structured" (fast, for control-affine systems with constant B) or "autodiff" (any system)
    divergence: DivergenceMethod = "structured"
    #: time between saved points [s] (the planning grid)
    output_dt: float = 0.1
    #: error-controlled: largest estimated local error per step, absolute, of every state component (in its unit)
    #: and of the log-density [nats]; ``None``: the scheme's own (:attr:`EmbeddedPair.tolerance`: 3e-3 for "rk43",
    #: 5e-5 for "dopri5")
    tolerance: float | None = None
    #: error-controlled, with a smooth saturation: largest move of the controller's raw input through the
    #: saturation's bend per step, in widths of its tail (:meth:`SmoothSaturation.tail_span`), checked over the
    #: step's stages and, before the step, on the move extrapolated at the last step's rate (a step shortened before
    #: a bend rather than rejected in it); 0 leaves the bend to the error estimate alone, whose stages can straddle
    #: a fast sweep through it (docs/core.md, "Error control"; 1 until stop 56, when steps were only rejected)
    saturation_step: float = 2.0
    #: error-controlled, with the log-density: how it is integrated. "quadrature" (default): as the integral it is,
    #: ``log rho(t + h) = log rho(t) - h (d_0 + 4 d_m + d_1) / 6`` (Simpson's rule) with the divergence ``d`` at the
    #: step's two ends (the last stage, shared with the next step) and at its middle (the state there from the
    #: pair's continuous extension), so the other stages need the closed loop's field only, not its divergence
    #: (the divergence's two tangents are ~2/3 of an evaluation's cost); the step is controlled by the states'
    #: error estimate and the saturation step (without one, e.g. a hard clip, also by the log-density's own
    #: estimate, Simpson's rule against the trapezoid's). "coupled": the log-density as one more component of the
    #: pair, with the divergence at every stage and its own error estimate (stop 55's scheme). docs/core.md,
    #: "Error control"
    log_density_rule: LogDensityRule = "quadrature"

    def __post_init__(self) -> None:
        if self.integrator is not None:
            check_choice("integrator", self.integrator, get_args(IntegratorName))
        check_choice("divergence", self.divergence, ("structured", "autodiff"))
        check_positive("dt", self.dt)
        check_positive("output_dt", self.output_dt)
        if self.tolerance is not None:
            check_positive("tolerance", self.tolerance)
        check_choice("log_density_rule", self.log_density_rule, get_args(LogDensityRule))
        if not self.saturation_step >= 0:
            raise ValueError(f"saturation_step must be >= 0 (0: off), got {self.saturation_step}")
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
        check_choice("System.liouville_integrator", scheme, get_args(IntegratorName))  # a system's own may err
        return scheme

    def pair(self, system: System | None = None) -> EmbeddedPair | None:
        """The embedded pair of an error-controlled scheme in force (``None`` for a fixed step)."""
        return PAIRS.get(self.scheme(system))

    def tolerance_of(self, pair: EmbeddedPair) -> float:
        """``tolerance``, or where it is ``None`` the pair's own."""
        return pair.tolerance if self.tolerance is None else self.tolerance

    def describe(self, system: System | None = None) -> str:
        """One line naming the scheme and its step (or tolerance), e.g. for the CLI."""
        scheme, pair = self.scheme(system), self.pair(system)
        if pair is not None:
            return (f"{scheme} (error-controlled, tolerance {self.tolerance_of(pair):g}, steps <= {self.dt:g} s, "
                    f"saturation step {self.saturation_step:g})")
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
    after every step. The scheme is :meth:`LiouvilleConfig.scheme`; an error-controlled one saves the output grid
    only and has no plant mode (the hold is not a smooth flow): both need a fixed step."""
    if plant and with_density:
        raise ValueError("the plant's standstill is not a smooth flow: no density along it")
    scheme = config.scheme(closed_loop.system)
    pair = config.pair(closed_loop.system)
    if pair is not None:
        if all_steps or plant:
            raise ValueError(f"LiouvilleConfig: the error-controlled {scheme!r} has no common time grid of all "
                             "steps and no plant mode; choose a fixed step, e.g. LiouvilleConfig(integrator='rk4')")
        return _integrate_adaptive(closed_loop, y0, reference, config, with_density, pair)
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


#: step-size control of the error-controlled schemes: safety factor and the bounds of one change of the step
_SAFETY, _SHRINK_MIN, _GROW_MAX = 0.9, 0.2, 5.0


def _integrate_adaptive(
    closed_loop: ClosedLoop,
    y0: tuple[Tensor, ...],
    reference: Reference,
    config: LiouvilleConfig,
    with_density: bool,
    pair: EmbeddedPair,
) -> tuple[Tensor, list[list[Tensor]]]:
    """:func:`_integrate` with an error-controlled embedded pair (:data:`~.integrators.PAIRS`).

    Every sample (row) keeps its own clock and step. A step is accepted where the estimated local error of every
    component is at most the tolerance and, with a smooth saturation, where the controller's raw input
    moves by at most ``config.saturation_step`` tail widths through the saturation's bend
    (:meth:`~density_planner.control.base.SmoothSaturation.tail_span`, over the stages); else it is retried
    shorter. A proposed step whose raw input, extrapolated at the last accepted step's rate, would move further
    through the bend is shortened before it is tried. The next step is ``h (0.9 / err)^(1/order)`` (at most 5x
    longer, 5x shorter, and ``config.dt``).
    Steps land on the reference's input switches (:meth:`Reference.next_switch`) and on the horizon in equal steps
    (the next step's first stage at a switch, the field with the input's right limit, is evaluated in the call of the
    last stage of the step that lands there);
    output times inside a step are read from the pair's continuous extension. With ``config.log_density_rule =
    "quadrature"`` the log-density follows Simpson's rule along each step (its divergence at the step's ends and
    middle; the other stages evaluate the field only) and its values inside a step the integral of the quadratic
    through those three rates (:func:`_simpson_interpolate`). Only rows still running are
    evaluated. The step sizes are chosen without gradient (as in any error-controlled solver) and the solution is
    differentiable along them: every update is out of place.
    """
    x0 = y0[0]
    batch, n_samples, nx = x0.shape[:-2], x0.shape[-2], x0.shape[-1]
    n_ref = math.prod(batch)
    horizon = reference.n_steps * reference.dt
    n_out = _n_steps(horizon, config.output_dt, "output_dt")  # dt divides output_dt (LiouvilleConfig), hence this
    params, x_ref, u_ref = (v.expand(*batch, *v.shape[-2:]).reshape(n_ref, *v.shape[-2:])
                            for v in (reference.params, reference.x, reference.u))
    flat_ref = Reference(params, x_ref, u_ref, reference.parameterization)
    switches = flat_ref.switch_table()
    m = n_ref * n_samples
    device = x0.device
    ref_rows = torch.arange(n_ref, device=device).repeat_interleave(n_samples)
    y = [x0.reshape(m, nx)] + ([y0[1].reshape(m)] if with_density else [])
    method = config.divergence
    system, controller = closed_loop.system, closed_loop.controller
    resolve = config.saturation_step > 0 and controller.saturation is not None
    eps = 1e-9 * config.dt
    tolerance = config.tolerance_of(pair)

    # the log-density by Simpson's rule along the states' steps: the divergence at the ends and the middle only
    quadrature = with_density and config.log_density_rule == "quadrature"

    def func(ys, refs, divergence=with_density):
        x_ref, u_ref = refs
        if divergence:
            dx, div, raw = closed_loop.rhs_divergence_with_raw(ys[0], x_ref, u_ref, method)
            return [dx, -div], raw.detach()
        dx, raw = closed_loop.rhs_with_raw(ys[0], x_ref, u_ref)
        return [dx], raw.detach()

    t = torch.zeros(m, dtype=torch.float64, device=device)
    h = torch.full((m,), config.dt, dtype=torch.float64, device=device)
    k_next = torch.ones(m, dtype=torch.long, device=device)  # index of the next output time per row
    k1, z1 = func(y, flat_ref.values_at(ref_rows, t, False))
    z_rate = torch.zeros_like(z1)
    out_rows: list[Tensor] = []
    out_k: list[Tensor] = []
    out_vals: list[list[Tensor]] = [[] for _ in y]
    active = torch.arange(m, device=device)
    while active.numel():
        rows = ref_rows[active]
        t_a = t[active]
        h_prop = h[active]
        y_a = [v.index_select(0, active) for v in y]
        z0 = z1.index_select(0, active)
        if resolve:
            x_hat_a = system.measure(y_a[0]).detach()  # sets the saturation's bounds (look-ahead and span)
            # the saturation step, looking ahead: the raw input's move over the proposed step, extrapolated at the last
            # accepted step's rate, may cross the saturation's bend by at most saturation_step tail widths (a step
            # shortened before it reaches a bend instead of rejected in it)
            z_end = z0 + z_rate.index_select(0, active) * h_prop.to(z0.dtype).unsqueeze(-1)
            ahead = controller.tail_span(torch.minimum(z0, z_end), torch.maximum(z0, z_end), x_hat_a)
            assert ahead is not None  # resolve: the controller has a smooth saturation
            ahead = ahead.to(torch.float64)
            h_prop = torch.where(ahead > config.saturation_step,
                                 h_prop * (_SAFETY * config.saturation_step / ahead.clamp(min=1e-12)), h_prop)
        t_stop = torch.clamp(flat_ref.next_switch(switches, rows, t_a), max=horizon)
        # land on the stop in equal steps no longer than the proposal (no sliver of a step before a switch)
        gap = t_stop - t_a
        h_a = gap / torch.ceil(gap / h_prop - 1e-6).clamp(min=1.0)
        if bool((h_a < eps).any()):
            raise FloatingPointError(
                f"exact Liouville ({pair.name!r}): the step size underflowed (the closed loop is not finite or not "
                "integrable there); check the initial states and the reference, or use a fixed step "
                "(LiouvilleConfig(integrator='rk4'))")
        hd = h_a.to(x0.dtype)
        # where the step ends: on its stop where it lands within eps of it
        on_stop = (t_a + h_a - t_stop).abs() <= eps
        t_end = torch.where(on_stop, t_stop, t_a + h_a)
        # rows whose step lands on an input switch short of the horizon: the next step's first stage is the field
        # there with the reference's right limit, evaluated in the last stage's call (the same state; wasted only
        # where the step is rejected)
        sw_i = torch.nonzero(on_stop & (t_stop < horizon - eps)).squeeze(-1)  # indices into the active rows
        ks = [[k.index_select(0, active) for k in k1]]
        z_lo = z_hi = z0
        left = torch.ones_like(active, dtype=torch.bool)
        # the reference (its left limits) once per fraction of the step at which a stage or the middle is evaluated
        # (RK4's second and third stages and the middle share t + h/2, its last two stages t + h)
        refs = {c: flat_ref.values_at(rows, t_a + c * h_a, left)
                for c in sorted(set(pair.stages[1:]) | ({0.5} if quadrature else set()))}
        z_last = None
        n_stages = len(pair.stages)
        for i in range(1, n_stages):
            # with the quadrature the stages before the last propagate the states only (no divergence)
            inner = quadrature and i < n_stages - 1
            y_i = [v + _weighted(hd, pair.a[i], [k[c] for k in ks]) for c, v in enumerate(y_a[:1] if quadrature
                                                                                              else y_a)]
            if i == n_stages - 1:
                # the last stage, in one call with the step's middle from the stages so far (quadrature) and the
                # next step's first stage where the step lands on a switch
                xs, rs = [y_i[0]], [refs[pair.stages[i]]]
                if quadrature and pair.midpoint:
                    xs.append(y_a[0] + _weighted(hd, pair.midpoint, [k[0] for k in ks]))
                    rs.append(refs[0.5])
                if sw_i.numel():
                    xs.append(y_i[0].index_select(0, sw_i))
                    rs.append(flat_ref.values_at(rows.index_select(0, sw_i), t_stop.index_select(0, sw_i), False))
                one = len(xs) == 1
                k_all, z_all = func([xs[0] if one else torch.cat(xs)],
                                    rs[0] if one else [torch.cat(v) for v in zip(*rs)], with_density)
                sizes = [len(x) for x in xs]
                parts = [list(c) for c in zip(*(k.split(sizes) for k in k_all))]
                z_parts = list(z_all.split(sizes))
                k_i, z_last = parts[0], z_parts[0]
                if quadrature and pair.midpoint:
                    k_mid, z_mid = parts[1], z_parts[1]
                k_sw, z_sw = parts[-1], z_parts[-1]  # used only where sw_i is not empty
            else:
                k_i, z_last = func(y_i, refs[pair.stages[i]], with_density and not inner)
            ks.append(k_i)
            z_lo, z_hi = torch.minimum(z_lo, z_last), torch.maximum(z_hi, z_last)
        y_new = y_i  # the last stage is evaluated at the propagated solution (its row of a is b)
        if quadrature:  # the divergence in the middle of the step, at the continuous extension's state there
            if not pair.midpoint:
                half = torch.full_like(h_a, 0.5)
                x_mid = pair.interpolate(y_a[0], y_new[0], [k[0] for k in ks], h_a, half)
                k_mid, z_mid = func([x_mid], refs[0.5], True)
            z_lo, z_hi = torch.minimum(z_lo, z_mid), torch.maximum(z_hi, z_mid)
            d_ends = (ks[0][1], k_mid[1], ks[-1][1])  # d log rho / dt = -div at theta = 0, 1/2, 1
            y_new = [y_new[0], y_a[1] + _weighted(hd, (1 / 6, 2 / 3, 1 / 6), list(d_ends))]
        controlled = 1 if quadrature else len(y)  # the components the pair's error estimate controls
        err = torch.stack([(_weighted(hd, pair.error, [k[c] for k in ks]).abs().reshape(len(active), -1)
                            .amax(-1)) for c in range(controlled)]).amax(0).detach().to(torch.float64) / tolerance
        if quadrature and not resolve:
            # no saturation step to resolve where the divergence bends (a hard clip's jump, or saturation_step = 0):
            # the log-density's own estimate, Simpson's rule against the trapezoid's, which sees a kink inside a step
            gap = _weighted(hd, (1 / 3, -2 / 3, 1 / 3), list(d_ends)).abs().detach().to(torch.float64)
            err = torch.maximum(err, gap / tolerance)
        if resolve:
            span = controller.tail_span(z_lo, z_hi, x_hat_a)
            assert span is not None
            err = torch.maximum(err, (span.to(torch.float64) / config.saturation_step) ** pair.order)
        ok = err <= 1.0  # NaN is never accepted: the step then shrinks until it underflows (error above)
        factor = (_SAFETY * err.clamp(min=1e-12) ** (-1.0 / pair.order)).clamp(_SHRINK_MIN, _GROW_MAX)
        factor = torch.where(torch.isnan(factor), torch.full_like(factor, _SHRINK_MIN), factor)
        h_new = h_a * factor
        # a step cut short by a switch or the horizon, accepted, keeps the proposal it was cut from
        h_new = torch.where(ok & (h_a < h_prop), torch.maximum(h_new, h_prop), h_new)
        h = h.index_put((active,), h_new.clamp(max=config.dt))
        ok_i = torch.nonzero(ok).squeeze(-1)  # indices into the active rows (one mask-to-index for all reads)
        acc = active.index_select(0, ok_i)
        if acc.numel():
            def pick(v: Tensor, index: Tensor = ok_i) -> Tensor:
                return v.index_select(0, index)

            t0_acc, h_acc, t_acc = pick(t_a), pick(h_a), pick(t_end)
            y0_acc, y1_acc = [pick(v) for v in y_a], [pick(v) for v in y_new]
            ks_acc = [[pick(k[c]) for k in ks] for c in range(controlled)]  # per component, the stages
            if quadrature:  # the log-density's: its rate at theta = 0, 1/2, 1
                ks_acc.append([pick(d) for d in d_ends])
            # the output times inside (t0, t_acc], from the continuous extension
            k_acc = k_next.index_select(0, acc)
            while True:
                t_k = k_acc.to(torch.float64) * config.output_dt
                due = torch.nonzero((k_acc <= n_out) & (t_k <= t_acc + eps)).squeeze(-1)
                if not due.numel():
                    break
                theta = ((pick(t_k, due) - pick(t0_acc, due)) / pick(h_acc, due)).clamp(0.0, 1.0)
                out_rows.append(pick(acc, due))
                k_due = pick(k_acc, due)
                out_k.append(k_due)
                for c, store in enumerate(out_vals):
                    rule = _simpson_interpolate if quadrature and c == 1 else pair.interpolate
                    store.append(rule(pick(y0_acc[c], due), pick(y1_acc[c], due),
                                      [pick(k, due) for k in ks_acc[c]], pick(h_acc, due), theta))
                k_acc = k_acc.index_put((due,), k_due + 1)
            k_next = k_next.index_put((acc,), k_acc)
            t = t.index_put((acc,), t_acc)
            y = [v.index_put((acc,), vn) for v, vn in zip(y, y1_acc)]
            k1 = [k.index_put((acc,), stages[-1]) for k, stages in zip(k1, ks_acc)]
            assert z_last is not None
            if resolve:  # the raw input's rate over the accepted step, for the next step's look ahead
                z_rate = z_rate.index_put((acc,), (pick(z_last) - z1.index_select(0, acc))
                                          / h_acc.to(z1.dtype).unsqueeze(-1))
            z1 = z1.index_put((acc,), pick(z_last))
            # where the input switches at the new time (the step landed on its stop, a switch of the table short of
            # the horizon), the next step's first stage takes its right limit (evaluated with the last stage)
            if sw_i.numel():
                taken = torch.nonzero(ok.index_select(0, sw_i)).squeeze(-1)  # the landing rows accepted
                if taken.numel():
                    switched = active.index_select(0, sw_i.index_select(0, taken))
                    k1 = [k.index_put((switched,), kn.index_select(0, taken)) for k, kn in zip(k1, k_sw)]
                    z1 = z1.index_put((switched,), z_sw.index_select(0, taken))
        active = active[t[active] < horizon - eps]
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


def _simpson_interpolate(y0: Tensor, y1: Tensor, rates: Sequence[Tensor], h: Tensor, theta: Tensor) -> Tensor:
    """The log-density at ``t + theta h`` inside a step integrated by Simpson's rule: ``y0`` plus the integral of
    the quadratic through its rates ``(d_0, d_m, d_1)`` at ``theta = 0, 1/2, 1`` (at ``theta = 1`` this is Simpson's
    ``y1``); ``h``, ``theta`` per row. The signature of :meth:`EmbeddedPair.interpolate`."""
    d0, dm, d1 = rates
    shape = (-1, *([1] * (y0.ndim - 1)))
    h, th = h.to(y0.dtype).reshape(shape), theta.to(y0.dtype).reshape(shape)
    return y0 + h * th * (d0 + th * ((-3 * d0 + 4 * dm - d1) / 2 + th * (2 * d0 - 4 * dm + 2 * d1) / 3))


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

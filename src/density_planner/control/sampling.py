"""Seeded sampling of references, initial errors and tracking states in the boxes of ``docs/spec.md`` §1.

* :func:`sample_feasible_references`: random piecewise-constant reference inputs ``clamp(2 N(0, 1), -3, 3)`` from
  start states uniform in the reference-start box, keeping only references that stay in the state box (all
  rejected ones are redrawn together, a bounded number of times).
* :func:`sample_initial_errors`: uniform initial errors in the XE0 box (with or without heading bias).
* :func:`sample_tracking_states`: ``(x, x_hat, x_ref, u_ref)`` for training and checking the contraction
  controller: references in the state box, errors in the XE box, inputs in the input box, bias in +-pi/8.

All draws use an explicit ``torch.Generator`` on the CPU in float64 and are converted afterwards, so the same
seed gives the same numbers for every dtype and device.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..systems.base import System
from ..systems.car import ACC, BIAS, OMEGA, CarConfig, KinematicCar, V
from .reference import PiecewiseConstantInputs, Reference, make_reference

__all__ = [
    "sample_feasible_references",
    "sample_initial_errors",
    "sample_box",
    "TrackingSamples",
    "sample_tracking_states",
    "box_violation_fraction",
]

logger = logging.getLogger(__name__)


def _as_float64(values: Sequence[float] | Tensor, name: str) -> Tensor:
    t = torch.as_tensor(values, dtype=torch.float64)
    if t.ndim != 1 or not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} must be a finite 1-D sequence of numbers, got {values!r}")
    return t


def sample_box(n: int, low: Sequence[float] | Tensor, high: Sequence[float] | Tensor,
               generator: torch.Generator) -> Tensor:
    """``n`` points uniform in the box ``[low, high]``, float64 on the CPU, shape ``(n, len(low))``."""
    lo, hi = _as_float64(low, "low"), _as_float64(high, "high")
    if lo.shape != hi.shape or bool((lo > hi).any()):
        raise ValueError("sample_box: low and high must have equal length and low <= high")
    return lo + (hi - lo) * torch.rand(n, lo.numel(), generator=generator, dtype=torch.float64)


def box_violation_fraction(x: Tensor, low: Sequence[float], high: Sequence[float]) -> Tensor:
    """Fraction of the time steps of ``x (*batch, T, nx)`` where any component leaves ``[low, high]``."""
    lo = torch.as_tensor(low, dtype=x.dtype, device=x.device)
    hi = torch.as_tensor(high, dtype=x.dtype, device=x.device)
    outside = ((x < lo) | (x > hi)).any(dim=-1)
    return outside.to(x.dtype).mean(dim=-1)


def sample_feasible_references(
    system: System,
    n: int,
    generator: torch.Generator,
    *,
    param_scale: float | Sequence[float] | None = None,
    start_low: Sequence[float] | None = None,
    start_high: Sequence[float] | None = None,
    state_low: Sequence[float] | None = None,
    state_high: Sequence[float] | None = None,
    max_violation: float = 0.01,
    max_attempts: int = 200,
    parameterization: PiecewiseConstantInputs | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> Reference:
    """``n`` random references that stay in the state box.

    Parameters are ``clamp(param_scale N(0, 1), input_min, input_max)`` of shape ``(n, nu, n_segments)``
    (``param_scale``: one number or one per input; default ``system.config.reference_input_scale`` where the
    system's configuration has one, else 2, the paper's); starts are uniform in ``[start_low, start_high]``
    (default: the reference-start box ``system.config.reference_start_min/max``). A reference is rejected if
    it leaves ``[state_low, state_high]`` (default: the system's state box X_MIN/X_MAX) on more than
    ``max_violation`` of its fine-grid states; only the rejected ones are redrawn, all together, at most
    ``max_attempts`` times.

    Raises:
        ValueError: invalid arguments, or fewer than ``n`` feasible references after ``max_attempts`` rounds.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    cfg = getattr(system, "config", None)
    if param_scale is None:
        param_scale = getattr(cfg, "reference_input_scale", 2.0)
    scale = _as_float64([param_scale] * system.nu if isinstance(param_scale, (int, float)) else param_scale,
                        "param_scale")
    if scale.numel() != system.nu or not bool((scale > 0).all()):
        raise ValueError(f"param_scale must be > 0 (one number or one per input), got {param_scale!r}")
    if not 0 <= max_violation < 1:
        raise ValueError(f"max_violation must be in [0, 1), got {max_violation!r}")
    if max_attempts < 1:
        raise ValueError(f"max_attempts must be >= 1, got {max_attempts!r}")
    par = parameterization or PiecewiseConstantInputs()
    if start_low is None or start_high is None:
        if not hasattr(cfg, "reference_start_min"):
            raise ValueError(f"{type(system).__name__} defines no reference-start box (config.reference_start_min/"
                             "max); pass start_low and start_high")
    s_lo = start_low if start_low is not None else getattr(cfg, "reference_start_min")  # noqa: B009
    s_hi = start_high if start_high is not None else getattr(cfg, "reference_start_max")  # noqa: B009
    x_lo = system.state_bounds[0] if state_low is None else state_low
    x_hi = system.state_bounds[1] if state_high is None else state_high
    u_lo = torch.as_tensor(system.input_bounds[0], dtype=torch.float64)[:, None]
    u_hi = torch.as_tensor(system.input_bounds[1], dtype=torch.float64)[:, None]

    starts = torch.empty(n, system.nx, dtype=torch.float64)
    params = torch.empty(n, system.nu, par.n_segments, dtype=torch.float64)
    todo = torch.arange(n)
    drawn = 0
    for _ in range(max_attempts):
        m = int(todo.numel())
        st = sample_box(m, s_lo, s_hi, generator)
        p = scale[:, None] * torch.randn(m, system.nu, par.n_segments, generator=generator, dtype=torch.float64)
        p = torch.maximum(torch.minimum(p, u_hi), u_lo)
        if isinstance(cfg, CarConfig) and math.isfinite(cfg.lateral_accel_max):
            p[:, OMEGA] = _lateral_limited_turn_rates(system, cfg, st[:, V], p, par, generator)
        drawn += m
        ref = make_reference(system, st, p, par)
        ok = box_violation_fraction(ref.x, x_lo, x_hi) <= max_violation
        starts[todo[ok]] = st[ok]
        params[todo[ok]] = p[ok]
        todo = todo[~ok]
        if todo.numel() == 0:
            break
    if todo.numel():
        raise ValueError(
            f"could only sample {n - todo.numel()} of {n} feasible references in {max_attempts} attempts "
            f"(acceptance rate {(n - todo.numel()) / drawn:.3f}); widen the state box or lower param_scale"
        )
    logger.debug("sampled %d feasible references from %d draws (acceptance %.3f)", n, drawn, n / drawn)
    return make_reference(system, starts.to(dtype=dtype, device=device), params.to(dtype=dtype, device=device), par)


def _lateral_limited_turn_rates(system: System, cfg: CarConfig, v0: Tensor, p: Tensor,
                                par: PiecewiseConstantInputs, generator: torch.Generator) -> Tensor:
    """Turn rates ``(m, S)`` of references under a lateral-acceleration limit: on segment ``k`` uniform in
    ``+-turn_rate_limit(max(|v_k|, |v_k+1|))``, with ``v_k`` the speed at the segment's start (from the
    acceleration parameters ``p[:, ACC]``, held at rest once it stops as ``system``'s roll-out holds it,
    :meth:`~density_planner.systems.base.System.held_speeds`), so that ``|omega| <= turn_rate_limit(|v|)`` at every
    instant (the bound decreases with the speed, and ``v`` is linear within a segment, or linear and then 0)."""
    acc = p[:, ACC]
    v = torch.cat([v0[:, None], v0[:, None] + torch.cumsum(acc * par.segment_duration, dim=-1)], dim=-1)
    v = system.held_speeds(v)
    v_seg = torch.maximum(v[:, :-1].abs(), v[:, 1:].abs())
    frac = 2.0 * torch.rand(v_seg.shape, generator=generator, dtype=torch.float64) - 1.0
    return cfg.turn_rate_limit(v_seg) * frac


def sample_initial_errors(
    n: int,
    generator: torch.Generator,
    *,
    box: Sequence[float] | None = None,
    with_bias: bool = True,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> Tensor:
    """``n`` initial errors ``(n, len(box))`` uniform in ``[-box, box]`` (default: the car's XE0,
    ``CarConfig().initial_error_max``; other systems pass ``system.initial_error_max``).

    With ``with_bias=False`` the car's heading-bias component is zero; the other components are the same draws as
    with the bias, so the two variants are directly comparable for one seed (car boxes only).
    """
    half = _as_float64(CarConfig().initial_error_max if box is None else box, "box")
    if bool((half < 0).any()):
        raise ValueError(f"box half-widths must be >= 0, got {half.tolist()}")
    e = sample_box(n, -half, half, generator)
    if not with_bias:
        e[:, BIAS] = 0.0
    return e.to(dtype=dtype, device=device)


@dataclass
class TrackingSamples:
    """Sampled tracking situations, all ``(n, 5)`` car states except ``u_ref (n, 2)``.

    Attributes:
        x: true states ``x_ref + e`` (the bias in the last component).
        x_hat: biased measurements ``[p_x, p_y, theta + bias, v, 0]`` of ``x``.
        x_ref: reference states (bias 0).
        u_ref: reference inputs.
    """

    x: Tensor
    x_hat: Tensor
    x_ref: Tensor
    u_ref: Tensor

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> TrackingSamples:
        return TrackingSamples(*(t.to(dtype=dtype, device=device) for t in (self.x, self.x_hat, self.x_ref,
                                                                             self.u_ref)))

    def __len__(self) -> int:
        return int(self.x.shape[0])


def sample_tracking_states(
    n: int,
    generator: torch.Generator,
    car: CarConfig | None = None,
    *,
    error_box: Sequence[float] | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
    min_speed: float = 0.0,
) -> TrackingSamples:
    """Samples for the contraction conditions (``docs/spec.md`` §1 boxes).

    ``x_ref`` uniform in the state box X_MIN/X_MAX (positions included, bias 0), the error ``e`` uniform in
    ``[-error_box, error_box]`` (default XE: +-(2 m, 2 m, 1 rad, 1 m/s, pi/8 rad), whose last entry is the heading
    bias), ``u_ref`` uniform in the input box; with a lateral-acceleration limit (road domain) the turn rate is
    uniform in ``+-turn_rate_limit(v_ref)``.

    ``min_speed > 0`` redraws the samples whose true speed ``v_ref + e_v`` is below it: their true speed becomes
    uniform in ``[min_speed, v_max]``, the reference speed ``v - e_v`` clamped to the box (training only: the
    contraction condition cannot hold at standstill).
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    car = car or CarConfig()
    system = KinematicCar(car)
    lo = list(car.state_min)
    hi = list(car.state_max)
    lo[BIAS] = hi[BIAS] = 0.0
    x_ref = sample_box(n, lo, hi, generator)
    half = _as_float64(car.error_max if error_box is None else error_box, "error_box")
    e = sample_box(n, -half, half, generator)
    u_ref = sample_box(n, car.input_min, car.input_max, generator)
    if min_speed > 0:
        slow = (x_ref[:, V] + e[:, V]) < min_speed
        v_true = min_speed + (hi[V] - min_speed) * torch.rand(n, generator=generator, dtype=torch.float64)
        v_ref = torch.clamp(v_true - e[:, V], lo[V], hi[V])
        x_ref[:, V] = torch.where(slow, v_ref, x_ref[:, V])
        e[:, V] = torch.where(slow, v_true - v_ref, e[:, V])
    if math.isfinite(car.lateral_accel_max):
        u_ref[:, OMEGA] = car.turn_rate_limit(x_ref[:, V]) * (2.0 * torch.rand(n, generator=generator,
                                                                              dtype=torch.float64) - 1.0)
    x = x_ref + e
    x_hat = system.measure(x)
    return TrackingSamples(x, x_hat, x_ref, u_ref).to(dtype=dtype, device=device)

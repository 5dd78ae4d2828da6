"""Tracking-controller interface: ``u = controller(x_measured, x_ref, u_ref)``.

A tracking controller maps the *measured* state (for the car: the heading-biased measurement, see
:meth:`density_planner.systems.KinematicCar.measure`), the reference state and the reference (feed-forward)
input to the applied input, clipped to the input bounds. Tensors are batch-first and broadcast:
``x_hat (*batch, nx)``, ``x_ref (*batch, nx)``, ``u_ref (*batch, nu)`` -> ``u (*batch, nu)``.

For the exact Liouville density the closed-loop divergence needs directional derivatives of ``u`` w.r.t. the
state. :meth:`TrackingController.forward_with_tangents` returns them for a stack of tangent directions; the
default uses ``torch.func.jvp`` and learned controllers override it with a hand-written forward-mode pass.
"""

from __future__ import annotations

import functools
import math
from abc import abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

__all__ = ["TrackingController", "SmoothSaturation", "soft_clip", "soft_clip_value"]


def soft_clip(z: Tensor, knee_lo: Tensor, knee_hi: Tensor, ceil_lo: Tensor, ceil_hi: Tensor
              ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Smooth saturation: the identity on ``[knee_lo, knee_hi]``, a tanh tail towards ``ceil_lo`` / ``ceil_hi``::

        s(z) = knee_hi + d tanh((z - knee_hi) / d),   d = ceil_hi - knee_hi,   for z > knee_hi  (mirrored below)

    ``s`` is twice continuously differentiable (the tanh has zero curvature at 0), strictly increasing and
    strictly inside ``(ceil_lo, ceil_hi)``. Needs ``ceil_lo < knee_lo <= knee_hi < ceil_hi`` (broadcasting).

    Returns ``(s, ds/dz, ds/dknee, ds/dceil)``: the last two are the derivatives with respect to the bound that is
    active on each side (``knee_hi`` / ``ceil_hi`` above, ``knee_lo`` / ``ceil_lo`` below, zero inside).
    """
    s, (d_hi, w_hi, t_hi), (d_lo, w_lo, t_lo) = _soft_clip_parts(z, knee_lo, knee_hi, ceil_lo, ceil_hi)
    q_hi, q_lo = t_hi * t_hi, t_lo * t_lo
    g_hi, g_lo = 1.0 - q_hi, 1.0 - q_lo
    ds = g_hi - q_lo  # 1 - tanh^2 of the side beyond its knee (one of t_hi, t_lo is zero), 1 inside
    # s = k + d tanh((z - k) / d) with d = c - k: ds/dk = 1 - t + g (w - 1), ds/dc = t - g w; each side's terms are
    # exactly zero where it is not beyond its knee (t = w = 0, g = 1), so their sum is the active side's
    dk = (1.0 - t_hi + g_hi * (w_hi - 1.0)) + (1.0 - t_lo + g_lo * (w_lo - 1.0))
    dc = (t_hi - g_hi * w_hi) + (t_lo - g_lo * w_lo)
    return s, ds, dk, dc


def soft_clip_value(z: Tensor, knee_lo: Tensor, knee_hi: Tensor, ceil_lo: Tensor, ceil_hi: Tensor) -> Tensor:
    """The value of :func:`soft_clip` alone (the same bits; a third of its operations)."""
    return _soft_clip_parts(z, knee_lo, knee_hi, ceil_lo, ceil_hi)[0]


def _soft_clip_parts(z: Tensor, knee_lo: Tensor, knee_hi: Tensor, ceil_lo: Tensor, ceil_hi: Tensor
                     ) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor], tuple[Tensor, Tensor, Tensor]]:
    """``s`` of :func:`soft_clip` and, per side, its tail's width ``d``, the scaled excess ``w`` over the knee (zero
    where the side is not beyond it) and ``tanh(w)``: branch-free, the clamp's identity inside plus each side's
    tail (zero where the side is not beyond its knee)."""
    d_hi, d_lo = ceil_hi - knee_hi, knee_lo - ceil_lo
    w_hi, w_lo = torch.relu((z - knee_hi) / d_hi), torch.relu((knee_lo - z) / d_lo)
    t_hi, t_lo = torch.tanh(w_hi), torch.tanh(w_lo)
    s = torch.clamp(z, knee_lo, knee_hi) + d_hi * t_hi - d_lo * t_lo
    return s, (d_hi, w_hi, t_hi), (d_lo, w_lo, t_lo)


@functools.lru_cache(maxsize=64)
def _box_tensors(bounds: tuple[tuple[float, ...], ...], turn_index: int | None, dtype: torch.dtype,
                 device: torch.device) -> tuple[Tensor, ...]:
    """The constant bounds as tensors ``(nu,)`` of a dtype and device, and the turn channel's mask (cached: the
    closed loop asks for them at every evaluation)."""
    out = tuple(torch.tensor(b, dtype=dtype, device=device) for b in bounds)
    mask = torch.zeros(len(bounds[0]), dtype=torch.bool, device=device)
    if turn_index is not None:
        mask[turn_index] = True
    return (*out, mask)


@dataclass(frozen=True)
class SmoothSaturation:
    """Smooth bound of a controller's output (instead of the hard clip): the identity on the reference input box
    ``[input_min, input_max]`` and a C^2 tanh tail (:func:`soft_clip`) towards the actuator limits ``[actuator_min,
    actuator_max]``. Optionally the turn-rate channel's box shrinks with speed (lateral-acceleration limit,
    :func:`density_planner.systems.car.turn_rate_limit`): knee ``+-turn_rate_limit(v, input_max, a_lat)`` and
    ceiling ``+-turn_rate_limit(v, actuator_max, a_lat_act)``, with ``v`` the measured speed ``x_hat[speed_index]``.

    A reference input inside the reference box passes unchanged, so an unbiased reference is still tracked
    exactly, and the closed loop stays smooth: the exact Liouville integration stays accurate (docs/core.md).
    """

    input_min: tuple[float, ...]
    input_max: tuple[float, ...]
    actuator_min: tuple[float, ...]
    actuator_max: tuple[float, ...]
    #: index of the turn-rate input whose box depends on the speed, and of the speed in the measured state
    turn_index: int = 0
    speed_index: int = 3
    #: lateral-acceleration limits of the knee and the ceiling [m/s^2] (inf: no speed dependence)
    lateral_accel_max: float = math.inf
    actuator_lateral_accel_max: float = math.inf

    @classmethod
    def from_car(cls, car) -> SmoothSaturation | None:
        """The saturation of a :class:`~density_planner.systems.car.CarConfig` (``None`` for a hard clip)."""
        if car is None or getattr(car, "actuator_min", None) is None:
            return None
        return cls(tuple(car.input_min), tuple(car.input_max), tuple(car.actuator_min), tuple(car.actuator_max),
                   lateral_accel_max=float(car.lateral_accel_max),
                   actuator_lateral_accel_max=float(car.actuator_lateral_accel_max))

    @property
    def speed_dependent(self) -> bool:
        return math.isfinite(self.lateral_accel_max)

    def _box(self, like: Tensor) -> tuple[Tensor, ...]:
        """The constant bounds ``(k_lo, k_hi, c_lo, c_hi)`` as ``(nu,)`` tensors and the turn channel's mask."""
        return _box_tensors((self.input_min, self.input_max, self.actuator_min, self.actuator_max),
                            self.turn_index if self.speed_dependent else None, like.dtype, like.device)

    def _bounds_pair(self, lo: Tensor, hi: Tensor, turn: Tensor, x_hat: Tensor, omega_max: float, a_lat: float
                     ) -> tuple[Tensor, Tensor]:
        """One pair of bounds (knees or ceilings), the turn channel's from the speed: ``+-L(v)``."""
        if not self.speed_dependent:
            return lo, hi
        lim = _turn_limit(x_hat[..., self.speed_index].unsqueeze(-1), omega_max, a_lat)[0]
        return torch.where(turn, -lim, lo), torch.where(turn, lim, hi)

    def _knees(self, u: Tensor, x_hat: Tensor) -> tuple[Tensor, Tensor]:
        k_lo, k_hi, _, _, turn = self._box(u)
        return self._bounds_pair(k_lo, k_hi, turn, x_hat, self.input_max[self.turn_index], self.lateral_accel_max)

    def _ceilings(self, u: Tensor, x_hat: Tensor) -> tuple[Tensor, Tensor]:
        _, _, c_lo, c_hi, turn = self._box(u)
        return self._bounds_pair(c_lo, c_hi, turn, x_hat, self.actuator_max[self.turn_index],
                                 self.actuator_lateral_accel_max)

    def _limits(self, u: Tensor, x_hat: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None, Tensor | None]:
        """Knee and ceiling bounds (broadcasting with ``u (*batch, nu)``) and their derivatives w.r.t. the speed
        (turn channel; ``None`` without a speed dependence)."""
        k_lo, k_hi, c_lo, c_hi, turn = self._box(u)
        if not self.speed_dependent:
            return k_lo, k_hi, c_lo, c_hi, None, None
        v = x_hat[..., self.speed_index].unsqueeze(-1)
        i = self.turn_index
        k, dk = _turn_limit_and_slope(v, self.input_max[i], self.lateral_accel_max)
        c, dc = _turn_limit_and_slope(v, self.actuator_max[i], self.actuator_lateral_accel_max)
        # the turn channel is symmetric: its lower bounds are the negated upper ones
        return (torch.where(turn, -k, k_lo), torch.where(turn, k, k_hi), torch.where(turn, -c, c_lo),
                torch.where(turn, c, c_hi), dk[..., 0], dc[..., 0])

    def beyond_knees(self, u: Tensor, x_hat: Tensor, knees: tuple[Tensor, Tensor] | None = None) -> bool:
        """Whether any input of ``u (*batch, nu)`` lies outside the reference box (the knees ``(k_lo, k_hi)``,
        compared as :func:`soft_clip` compares them). Where none does, the saturation is the identity with unit
        derivative and zero derivatives with respect to the bounds: :meth:`__call__` and :meth:`with_tangents` then
        return their inputs (the same values as the whole computation), skipping its tensor operations (most
        steps of a closed loop that tracks its reference)."""
        k_lo, k_hi = self._knees(u, x_hat) if knees is None else knees
        return bool(((u > k_hi) | (u < k_lo)).any())

    def tail_span(self, z_lo: Tensor, z_hi: Tensor, x_hat: Tensor) -> Tensor:
        """How far the raw input moves through the curved part of the saturation over a stretch of time.

        ``z_lo, z_hi (*batch, nu)`` are the smallest and largest raw input seen (e.g. over the stages of an
        integration step), ``x_hat`` the measured state that sets the bounds. The curved part of a channel is its
        tail next to a knee, ``[k, k + 3 d]`` above (``d`` the tail's width, ceiling minus knee; ``tanh`` has bent
        to within 2 % of its asymptote at ``3 d``) and its mirror below. Returns ``(*batch,)``: the largest
        ``(z_hi - z_lo) / d`` over the channels whose span meets a curved part, zero where none does. An
        integrator that keeps it below ~1 per step resolves the saturation's bend however fast the raw input
        sweeps through it (docs/core.md)."""
        (k_lo, k_hi), (c_lo, c_hi) = self._knees(z_hi, x_hat), self._ceilings(z_hi, x_hat)
        d_hi, d_lo = c_hi - k_hi, k_lo - c_lo
        span = z_hi - z_lo
        hit_hi = (z_hi >= k_hi) & (z_lo <= k_hi + 3.0 * d_hi)
        hit_lo = (z_lo <= k_lo) & (z_hi >= k_lo - 3.0 * d_lo)
        zero = torch.zeros_like(span)
        ratio = torch.maximum(torch.where(hit_hi, span / d_hi, zero), torch.where(hit_lo, span / d_lo, zero))
        return ratio.amax(-1)

    def __call__(self, u: Tensor, x_hat: Tensor) -> Tensor:
        knees = self._knees(u, x_hat)
        if not self.beyond_knees(u, x_hat, knees):  # the identity
            return u
        return soft_clip_value(u, *knees, *self._ceilings(u, x_hat))

    def with_tangents(self, u: Tensor, du: Tensor, x_hat: Tensor, dx_hat: Tensor) -> tuple[Tensor, Tensor]:
        """Saturated ``u`` and its tangents from those of the raw law ``du (K, *batch, nu)`` and of the measured
        state ``dx_hat (K, *batch, nx)`` (through the speed-dependent turn-rate box)."""
        k_lo, k_hi, c_lo, c_hi, dk, dc = self._limits(u, x_hat)
        if not self.beyond_knees(u, x_hat, (k_lo, k_hi)):  # the identity: du as the whole computation shapes it
            return u, du.expand(torch.broadcast_shapes(du.shape, u.shape))
        s, ds, dsk, dsc = soft_clip(u, k_lo, k_hi, c_lo, c_hi)
        out = ds * du
        if dk is not None:
            assert dc is not None  # both turn-rate slopes exist together (_limits)
            i = self.turn_index
            # bounds of the turn channel: +-k(v), +-c(v); above the knee d s / d v = dsk k' + dsc c', below the
            # mirrored bounds move with -k', -c' (dsk = dsc = 0 inside)
            slope = dsk[..., i] * dk + dsc[..., i] * dc
            slope = torch.where(u[..., i] < 0, -slope, slope)
            turn = self._box(u)[-1]
            out = out + torch.where(turn, (slope * dx_hat[..., self.speed_index]).unsqueeze(-1), 0.0)
        return s, out


def _turn_limit(v: Tensor, omega_max: float, a_lat: float) -> tuple[Tensor, Tensor]:
    """``L(v) = (omega_max^-4 + (|v| / a_lat)^4)^(-1/4)`` and ``q = L^-4``."""
    r4 = (v / a_lat) ** 4
    q = omega_max ** -4 + r4
    return q ** -0.25, q


def _turn_limit_and_slope(v: Tensor, omega_max: float, a_lat: float) -> tuple[Tensor, Tensor]:
    """``L(v)`` (:func:`_turn_limit`) and ``dL/dv``."""
    lim, q = _turn_limit(v, omega_max, a_lat)
    slope = -(q ** -1.25) * (v ** 3) / a_lat ** 4
    return lim, slope


class TrackingController(nn.Module):
    """Base class: implement :meth:`raw` (the unclipped control law); clipping and tangents are handled here."""

    # buffers (registered in __init__)
    input_min: Tensor
    input_max: Tensor

    def __init__(self, input_min: Sequence[float], input_max: Sequence[float],
                 saturation: SmoothSaturation | None = None):
        super().__init__()
        self.register_buffer("input_min", torch.as_tensor(input_min, dtype=torch.get_default_dtype()))
        self.register_buffer("input_max", torch.as_tensor(input_max, dtype=torch.get_default_dtype()))
        #: smooth output bound (``None``: hard clip to ``[input_min, input_max]``, the paper's controller)
        self.saturation = saturation

    @property
    def nu(self) -> int:
        return int(self.input_min.numel())

    @abstractmethod
    def raw(self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor) -> Tensor:
        """Unclipped control law."""

    def raw_with_tangents(
        self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor, dx_hat: Tensor
    ) -> tuple[Tensor, Tensor]:
        """``raw`` and its directional derivatives w.r.t. ``x_hat`` along ``dx_hat (K, *batch, nx)``.

        Returns ``(u (*batch, nu), du (K, *batch, nu))``. Generic forward-mode version (one ``jvp`` per tangent).
        """
        def fn(x: Tensor) -> Tensor:
            return self.raw(x, x_ref, u_ref)

        u = None
        dus = []
        for d in dx_hat.unbind(0):
            u, du = torch.func.jvp(fn, (x_hat,), (d.expand_as(x_hat),))[:2]
            dus.append(du)
        if u is None:
            u = fn(x_hat)
        return u, torch.stack(dus, 0) if dus else u.new_zeros((0, *u.shape))

    def _bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        return self.input_min.to(like), self.input_max.to(like)

    def forward(self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor) -> Tensor:
        return self.bound(self.raw(x_hat, x_ref, u_ref), x_hat)

    def bound(self, u: Tensor, x_hat: Tensor) -> Tensor:
        """The applied input from the raw law's ``u (*batch, nu)``: the smooth saturation, or the hard clip."""
        if self.saturation is not None:
            return self.saturation(u, x_hat)
        lo, hi = self._bounds(u)
        return torch.clamp(u, lo, hi)

    def forward_with_tangents(
        self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor, dx_hat: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Bounded input and its directional derivatives (hard clip: zero in channels where it is active; smooth
        saturation: chain rule through :class:`SmoothSaturation`)."""
        u, du = self.raw_with_tangents(x_hat, x_ref, u_ref, dx_hat)
        return self.bound_with_tangents(u, du, x_hat, dx_hat)

    def bound_with_tangents(self, u: Tensor, du: Tensor, x_hat: Tensor, dx_hat: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`bound` and its tangents from the raw law's ``u``, ``du (K, *batch, nu)``."""
        if self.saturation is not None:
            return self.saturation.with_tangents(u, du, x_hat, dx_hat)
        lo, hi = self._bounds(u)
        inside = (u > lo) & (u < hi)
        return torch.clamp(u, lo, hi), du * inside.to(du.dtype)

    def tail_span(self, z_lo: Tensor, z_hi: Tensor, x_hat: Tensor) -> Tensor | None:
        """:meth:`SmoothSaturation.tail_span` of this controller's saturation; ``None`` for the hard clip (its
        kink has no width to resolve: an error-controlled integrator meets it by its error estimate alone)."""
        if self.saturation is None:
            return None
        return self.saturation.tail_span(z_lo, z_hi, x_hat)

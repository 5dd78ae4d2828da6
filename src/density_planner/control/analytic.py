"""Hand-written tracking controllers that need no trained weights.

* :class:`CarTrackingController`: a smooth nonlinear feedback for the kinematic car (Kanayama-style: errors
  expressed in the reference's body frame, heading error through ``sin``), clipped to the input bounds.
* :class:`LinearFeedbackController`: ``u = u_ref - K (x_hat - x_ref)``, for linear test systems.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..systems.car import ACC, OMEGA, PX, PY, THETA, CarConfig, V
from .base import SmoothSaturation, TrackingController

__all__ = ["CarTrackingGains", "CarTrackingController", "LinearFeedbackController"]


@dataclass(frozen=True)
class CarTrackingGains:
    """Gains of :class:`CarTrackingController` (units: 1/s for heading/speed, 1/s^2 for position errors)."""

    #: heading gain: omega -= k_theta sin(theta_hat - theta_ref)
    k_theta: float = 2.0
    #: lateral gain scaled by the reference speed: omega -= (k_lat v_ref + k_lat0) e_lat
    k_lat: float = 0.6
    #: lateral gain at standstill [1/(m s)]
    k_lat0: float = 0.3
    #: speed gain: a -= k_v (v - v_ref)
    k_v: float = 1.5
    #: longitudinal position gain: a -= k_long e_long
    k_long: float = 1.0

    def __post_init__(self) -> None:
        for name in ("k_theta", "k_lat", "k_lat0", "k_v", "k_long"):
            if getattr(self, name) < 0:
                raise ValueError(f"CarTrackingGains.{name} must be >= 0")


class CarTrackingController(TrackingController):
    """Smooth nonlinear tracking feedback for the kinematic car.

    With the position error rotated into the reference frame, ``e_long = cos(th_r) dx + sin(th_r) dy`` and
    ``e_lat = -sin(th_r) dx + cos(th_r) dy``::

        omega = omega_ref - (k_lat v_ref + k_lat0) e_lat - k_theta sin(theta_hat - theta_ref)
        a     = a_ref - k_v (v - v_ref) - k_long e_long

    then clipped to the input bounds. It uses only the measured state ``x_hat``, so a heading bias leaves a
    steady lateral offset of about ``k_theta sin(bias) / (k_lat v_ref + k_lat0)``.
    """

    def __init__(self, gains: CarTrackingGains | None = None, car: CarConfig | None = None):
        car = car or CarConfig()
        super().__init__(car.input_min, car.input_max, SmoothSaturation.from_car(car))
        #: the car domain the controller is for (its speed range bounds where it may be used)
        self.car = car
        self.gains = gains or CarTrackingGains()

    def raw(self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor) -> Tensor:
        g = self.gains
        dx = x_hat[..., PX] - x_ref[..., PX]
        dy = x_hat[..., PY] - x_ref[..., PY]
        th_r = x_ref[..., THETA]
        c, s = torch.cos(th_r), torch.sin(th_r)
        e_long = c * dx + s * dy
        e_lat = -s * dx + c * dy
        e_th = x_hat[..., THETA] - th_r
        e_v = x_hat[..., V] - x_ref[..., V]
        omega = u_ref[..., OMEGA] - (g.k_lat * x_ref[..., V] + g.k_lat0) * e_lat - g.k_theta * torch.sin(e_th)
        acc = u_ref[..., ACC] - g.k_v * e_v - g.k_long * e_long
        omega, acc = torch.broadcast_tensors(omega, acc)
        return torch.stack([omega, acc], dim=-1)

    def raw_with_tangents(self, x_hat, x_ref, u_ref, dx_hat):
        # hand-written forward mode: the references do not depend on the state
        g = self.gains
        th_r = x_ref[..., THETA]
        c, s = torch.cos(th_r), torch.sin(th_r)
        e_th = x_hat[..., THETA] - th_r
        k_lat = g.k_lat * x_ref[..., V] + g.k_lat0
        d_long = c * dx_hat[..., PX] + s * dx_hat[..., PY]
        d_lat = -s * dx_hat[..., PX] + c * dx_hat[..., PY]
        d_omega = -k_lat * d_lat - g.k_theta * torch.cos(e_th) * dx_hat[..., THETA]
        d_acc = -g.k_v * dx_hat[..., V] - g.k_long * d_long
        u = self.raw(x_hat, x_ref, u_ref)
        d_omega, d_acc = torch.broadcast_tensors(d_omega, d_acc)
        du = torch.stack([d_omega, d_acc], dim=-1)
        return u, du.expand(dx_hat.shape[0], *u.shape)


class LinearFeedbackController(TrackingController):
    """``u = u_ref - K (x_hat - x_ref)`` with a constant gain ``K (nu, nx)``; unbounded unless bounds are given."""

    K: Tensor  # buffer

    def __init__(
        self,
        K: Sequence[Sequence[float]],
        input_min: Sequence[float] | None = None,
        input_max: Sequence[float] | None = None,
    ):
        k = torch.as_tensor(K, dtype=torch.float64)
        if k.ndim != 2:
            raise ValueError(f"K must be a matrix (nu, nx), got shape {tuple(k.shape)}")
        inf = float("inf")
        super().__init__(input_min or (-inf,) * k.shape[0], input_max or (inf,) * k.shape[0])
        self.register_buffer("K", k)

    def raw(self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor) -> Tensor:
        k = self.K.to(x_hat)
        return u_ref - (x_hat - x_ref) @ k.T

    def raw_with_tangents(self, x_hat, x_ref, u_ref, dx_hat):
        k = self.K.to(x_hat)
        return self.raw(x_hat, x_ref, u_ref), -(dx_hat @ k.T)

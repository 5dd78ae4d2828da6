"""Tracking controller of the kinematic single-track model (:mod:`density_planner.systems.ks`) and its model set.

:class:`KSTrackingController` is smooth hand-written feedback (no trained weights), built like the car's
:class:`~density_planner.control.analytic.CarTrackingController` but steering through the steering angle:

1. errors in the reference's body frame: ``e_long = cos(psi_r) dx + sin(psi_r) dy``, ``e_lat = -sin(psi_r) dx +
   cos(psi_r) dy``, ``e_psi = psi - psi_r``;
2. a desired path curvature: the reference's ``tan(delta_r) / l_wb`` corrected by a lateral and a heading term whose
   gains are set by a look-ahead distance ``L = L0 + T_L v_r`` (the lateral error then decays like a critically
   damped oscillator over the distance ``L``, i.e. within about ``L / v`` seconds)::

       kappa = tan(delta_r) / l_wb - e_lat / L^2 - 2 sin(e_psi) / L

3. the desired steering angle ``delta_d = atan(l_wb kappa)``, bent smoothly into the vehicle's steering range
   (identity on ``+-steering_use * delta_max``, a C^2 tanh tail up to ``delta_max``);
4. inputs: ``v_delta = v_delta_r + k_delta (delta_d - delta)`` and ``a = a_r - k_v (v - v_r) - k_long e_long``,
   bounded by the smooth saturation of :class:`~density_planner.control.base.SmoothSaturation` (identity on the
   reference input box, tanh tail up to the actuator limits).

On the reference (zero error) it returns ``u_ref`` exactly. The whole law is infinitely differentiable except for
the C^2 saturation knees, so the exact Liouville equation (which needs the closed loop's divergence) applies. Its
tangents (for that divergence) are written out by hand: one pass for all directions instead of one
``torch.func.jvp`` each (about 30 times faster).

The module registers the model set ``"ks"`` (the KS system's ``road`` domain, for every scene kind) and the
controller ``"analytic"`` of the system ``"ks"``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..systems.base import System
from ..systems.ks import ACC, DELTA, PSI, PX, PY, STEER_RATE, KinematicSingleTrack, KSConfig, V
from .base import SmoothSaturation, TrackingController, soft_clip
from .registry import ModelSet, register_controller, register_model_set

__all__ = ["KSTrackingGains", "KSTrackingController"]


@dataclass(frozen=True)
class KSTrackingGains:
    """Gains of :class:`KSTrackingController`."""

    #: look-ahead distance at standstill [m]
    lookahead_min: float = 4.0
    #: look-ahead time [s]: the look-ahead distance grows by this times the reference speed
    lookahead_time: float = 0.8
    #: steering-angle gain [1/s]: v_delta -= k_delta (delta - delta_d)
    k_delta: float = 3.0
    #: speed gain [1/s]: a -= k_v (v - v_ref)
    k_v: float = 1.5
    #: longitudinal position gain [1/s^2]: a -= k_long e_long
    k_long: float = 1.0

    def __post_init__(self) -> None:
        for name in ("lookahead_min", "k_delta"):
            if not getattr(self, name) > 0:
                raise ValueError(f"KSTrackingGains.{name} must be > 0")
        for name in ("lookahead_time", "k_v", "k_long"):
            if getattr(self, name) < 0:
                raise ValueError(f"KSTrackingGains.{name} must be >= 0")


class KSTrackingController(TrackingController):
    """Smooth tracking feedback for the kinematic single-track model (module docstring)."""

    def __init__(self, gains: KSTrackingGains | None = None, config: KSConfig | None = None):
        config = config or KSConfig()
        super().__init__(config.input_min, config.input_max,
                         SmoothSaturation(tuple(config.input_min), tuple(config.input_max),
                                          tuple(config.actuator_min), tuple(config.actuator_max),
                                          turn_index=STEER_RATE, speed_index=V))
        #: the KS domain the controller is for
        self.config = config
        self.gains = gains or KSTrackingGains()
        self.wheelbase = config.params.wheelbase
        d = config.steering_max
        self.steer_knee, self.steer_ceiling = config.steering_use * d, d

    def _law(self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor):
        """The raw inputs and the intermediate values their tangents need."""
        g, lwb = self.gains, self.wheelbase
        dx = x_hat[..., PX] - x_ref[..., PX]
        dy = x_hat[..., PY] - x_ref[..., PY]
        psi_r = x_ref[..., PSI]
        c, s = torch.cos(psi_r), torch.sin(psi_r)
        e_long = c * dx + s * dy
        e_lat = -s * dx + c * dy
        e_psi = x_hat[..., PSI] - psi_r
        look = g.lookahead_min + g.lookahead_time * x_ref[..., V].abs()
        kappa = torch.tan(x_ref[..., DELTA]) / lwb - e_lat / look ** 2 - 2.0 * torch.sin(e_psi) / look
        z = lwb * kappa
        delta_d = torch.atan(z)
        knee = torch.full_like(delta_d, self.steer_knee)
        ceil = torch.full_like(delta_d, self.steer_ceiling)
        delta_d, d_clip = soft_clip(delta_d, -knee, knee, -ceil, ceil)[:2]
        rate = u_ref[..., STEER_RATE] + g.k_delta * (delta_d - x_hat[..., DELTA])
        acc = u_ref[..., ACC] - g.k_v * (x_hat[..., V] - x_ref[..., V]) - g.k_long * e_long
        rate, acc = torch.broadcast_tensors(rate, acc)
        return torch.stack([rate, acc], dim=-1), (c, s, e_psi, look, z, d_clip)

    def raw(self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor) -> Tensor:
        return self._law(x_hat, x_ref, u_ref)[0]

    def raw_with_tangents(self, x_hat, x_ref, u_ref, dx_hat):
        # hand-written forward mode (one pass for all K tangents; the references do not depend on the state)
        g, lwb = self.gains, self.wheelbase
        u, (c, s, e_psi, look, z, d_clip) = self._law(x_hat, x_ref, u_ref)
        d_long = c * dx_hat[..., PX] + s * dx_hat[..., PY]
        d_lat = -s * dx_hat[..., PX] + c * dx_hat[..., PY]
        d_kappa = -d_lat / look ** 2 - 2.0 * torch.cos(e_psi) * dx_hat[..., PSI] / look
        d_delta_d = d_clip * lwb * d_kappa / (1.0 + z * z)
        d_rate = g.k_delta * (d_delta_d - dx_hat[..., DELTA])
        d_acc = -g.k_v * dx_hat[..., V] - g.k_long * d_long
        d_rate, d_acc = torch.broadcast_tensors(d_rate, d_acc)
        du = torch.stack([d_rate, d_acc], dim=-1)
        return u, du.expand(dx_hat.shape[0], *u.shape)


# ------------------------------------------------------------------------------------ registrations
register_model_set(ModelSet(
    "ks", None, "kinematic single-track model of the BMW 320i in road traffic: v in [0, 40] m/s, the vehicle's "
    "steering limits, smooth saturation", system="ks", domain="road", default_controller="analytic",
    scene_kinds=("random", "file", "commonroad", "ind"), density_suffix="_ks"))


@register_controller("ks", "analytic")
def _ks_analytic(system: System, mset: ModelSet) -> TrackingController:
    if not isinstance(system, KinematicSingleTrack):
        raise ValueError(f"the ks controller needs the KinematicSingleTrack system, got {type(system).__name__}")
    return KSTrackingController(config=system.config)

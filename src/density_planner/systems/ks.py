"""Kinematic single-track model (KS) of the CommonRoad vehicle models, with the parameters of a named vehicle.

State ``x = [p_x, p_y, delta, v, psi]`` (m, m, rad, m/s, rad) in CommonRoad's order (position, steering angle of
the front wheels, speed, yaw angle), input ``u = [v_delta, a]`` (steering rate [rad/s], longitudinal acceleration
[m/s^2])::

    p_x'   = v cos(psi)
    p_y'   = v sin(psi)
    delta' = v_delta
    v'     = a
    psi'   = v tan(delta) / l_wb

with the wheelbase ``l_wb = a + b`` (distances of the centre of gravity to the front and rear axle) of the vehicle
(CommonRoad vehicle models documentation, "Kinematic Single-Track Model", version 2020a). Control-affine with
``a(x) = [v cos psi, v sin psi, 0, 0, v tan(delta) / l_wb]`` and the constant ``B = [e_delta, e_v]``; the drift's
divergence is 0 (no component of ``a`` depends on its own state entry).

**Reference point.** The KS equations describe the centre of the rear axle. CommonRoad's own tools read the
position of a KS state as the centre of the vehicle's rectangle all the same: the solution checker of the
CommonRoad drivability checker builds the ego's collision object from the trajectory's positions with the
vehicle's shape centred on them, and the planning problems' initial states and goals are given for that point.
This system follows CommonRoad: its :attr:`footprint` (``l x w`` of the vehicle) is centred on ``(p_x, p_y)``, so the
verdict of a plan and the collision check of its ``solution.xml`` by CommonRoad's checker look at the same
rectangle. (Read physically, the rectangle turns about its centre rather than about the rear axle; the difference
is a sideways shift of the body's ends by ``b sin(Δpsi)`` over a heading change ``Δpsi``.)

**Limits.** The steering-angle box and the actuators' steering-rate limit are the vehicle's
(``steering.min/max``, ``steering.v_min/v_max``). CommonRoad's KS additionally stops the steering at its limits and
caps the positive acceleration by ``a_max v_switch / v`` above ``v_switch``; here the dynamics stay smooth (needed by
the exact Liouville equation and the learned density) and the tracking controller keeps the state inside the box
(:mod:`density_planner.control.ks`). The acceleration limits are those of the car's road domain (braking -9 m/s^2,
accelerating 4.5 m/s^2, inside the vehicle's ``a_max = 11.5``), docs/systems.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .base import ConfigBoxes, ControlAffineSystem, Footprint
from .registry import register_system

__all__ = ["KSVehicle", "KS_VEHICLES", "KSConfig", "KS_DOMAINS", "ks_domain", "KinematicSingleTrack"]

#: state indices
PX, PY, DELTA, V, PSI = 0, 1, 2, 3, 4
#: input indices
STEER_RATE, ACC = 0, 1

_PI = math.pi


@dataclass(frozen=True)
class KSVehicle:
    """Parameters of a CommonRoad vehicle used by the KS model (values of the CommonRoad vehicle models,
    ``parameters_vehicle{1,2,3}``)."""

    #: CommonRoad vehicle type name (``commonroad.common.solution.VehicleType``)
    name: str
    #: vehicle length / width [m]
    length: float
    width: float
    #: distance from the centre of gravity to the front / rear axle [m]
    a: float
    b: float
    #: steering-angle limits [rad]
    steering_min: float
    steering_max: float
    #: steering-rate limits [rad/s]
    steering_rate_min: float
    steering_rate_max: float
    #: speed limits [m/s]
    v_min: float
    v_max: float
    #: largest acceleration [m/s^2] and the speed above which the positive acceleration falls as ``a_max v_s / v``
    a_max: float
    v_switch: float

    @property
    def wheelbase(self) -> float:
        """``l_wb = a + b`` [m]."""
        return self.a + self.b


#: the CommonRoad vehicle types (1: Ford Escort, 2: BMW 320i, 3: VW Vanagon)
KS_VEHICLES: dict[str, KSVehicle] = {
    "FORD_ESCORT": KSVehicle("FORD_ESCORT", 4.298, 1.674, 0.88392, 1.50876, -0.91, 0.91, -0.4, 0.4, -13.9, 45.8,
                             11.5, 4.755),
    "BMW_320i": KSVehicle("BMW_320i", 4.508, 1.61, 1.1561957064, 1.4227170936, -1.066, 1.066, -0.4, 0.4, -13.9,
                          50.8, 11.5, 7.319),
    "VW_VANAGON": KSVehicle("VW_VANAGON", 4.569, 1.844, 1.1507916024, 1.3211363976, -1.023, 1.023, -0.4, 0.4,
                            -11.2, 41.7, 11.5, 7.824),
}


@dataclass(frozen=True)
class KSConfig:
    """Boxes of the KS model. Units: m, m, rad, m/s, rad; inputs rad/s, m/s^2."""

    #: CommonRoad vehicle type (a key of :data:`KS_VEHICLES`): wheelbase, body, steering limits
    vehicle: str = "BMW_320i"
    #: speed box [m/s] (forward driving)
    speed_min: float = 0.0
    speed_max: float = 40.0
    #: heading box [rad] (kept unwrapped; enters the dynamics and the controller through cos / sin)
    heading_max: float = 4 * _PI
    #: position box [m]
    position_max: float = 1000.0
    #: reference inputs (what a plan may ask): steering rate [rad/s] and acceleration [m/s^2]
    input_min: tuple[float, float] = (-0.3, -6.0)
    input_max: tuple[float, float] = (0.3, 3.0)
    #: actuator limits reached by the controller's smooth saturation (steering rate: the vehicle's, default)
    actuator_min: tuple[float, float] = (-0.4, -9.0)
    actuator_max: tuple[float, float] = (0.4, 4.5)
    #: share of the vehicle's steering-angle limit the controller may command (the rest is the margin of its
    #: smooth saturation); also the planning box of the steering angle
    steering_use: float = 0.9
    #: box of reference start states drawn for controller checks and density training data (any heading, nearly
    #: straight wheels, 0.5-38 m/s)
    reference_start_min: tuple[float, float, float, float, float] = (-10.0, -10.0, -0.1, 0.5, -_PI)
    reference_start_max: tuple[float, float, float, float, float] = (10.0, 10.0, 0.1, 38.0, _PI)
    #: standard deviations of the random reference inputs of those references (clipped to the input box) [rad/s,
    #: m/s^2]: steering rates of 0.1 rad/s keep the steering angle of a 10-s reference within about 0.3 rad
    reference_input_scale: tuple[float, float] = (0.1, 2.0)
    #: half-widths of the initial-error box XE0 (px, py, delta, v, psi)
    initial_error_max: tuple[float, float, float, float, float] = (1.0, 1.0, 0.05, 0.5, 0.2)
    #: planned speeds stay this far inside the speed box [m/s]
    planning_speed_margin: float = 0.1
    #: name of the domain (see :data:`KS_DOMAINS`)
    domain: str = "road"

    def __post_init__(self) -> None:
        if self.vehicle not in KS_VEHICLES:
            raise ValueError(f"KSConfig.vehicle must be one of {', '.join(KS_VEHICLES)}, got {self.vehicle!r}")
        if not 0 <= self.speed_min < self.speed_max:
            raise ValueError("KSConfig needs 0 <= speed_min < speed_max")
        if not all(a < lo <= 0 <= hi < b for a, lo, hi, b in zip(self.actuator_min, self.input_min, self.input_max,
                                                                 self.actuator_max)):
            raise ValueError("KSConfig: the actuator box must strictly contain the reference input box, which must "
                             "contain 0")
        if not 0 < self.steering_use < 1:
            raise ValueError("KSConfig.steering_use must lie in (0, 1)")
        if any(v < 0 for v in self.initial_error_max):
            raise ValueError("KSConfig.initial_error_max must be non-negative")

    @property
    def params(self) -> KSVehicle:
        return KS_VEHICLES[self.vehicle]

    @property
    def steering_max(self) -> float:
        """Largest steering angle [rad] of the state box (the vehicle's limit)."""
        return min(abs(self.params.steering_min), self.params.steering_max)

    @property
    def state_min(self) -> tuple[float, ...]:
        p = self.position_max
        return (-p, -p, -self.steering_max, self.speed_min, -self.heading_max)

    @property
    def state_max(self) -> tuple[float, ...]:
        p = self.position_max
        return (p, p, self.steering_max, self.speed_max, self.heading_max)


def ks_domain(name: str) -> KSConfig:
    """The KS configuration of a named domain."""
    try:
        return KS_DOMAINS[name]()
    except KeyError:
        raise ValueError(f"unknown ks domain {name!r}; valid choices: {', '.join(KS_DOMAINS)}") from None


#: named domains: road traffic with the BMW 320i (CommonRoad vehicle type 2), v in [0, 40] m/s
KS_DOMAINS = {"road": KSConfig}


class KinematicSingleTrack(ConfigBoxes, ControlAffineSystem):
    """CommonRoad's kinematic single-track model; see the module docstring for the equations and conventions."""

    state_names = ("px", "py", "delta", "v", "psi")
    input_names = ("v_delta", "a")
    constant_input_matrix = ((0.0, 0.0), (0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (0.0, 0.0))

    position_indices = (PX, PY)
    heading_index = PSI
    speed_index = V
    acceleration_input = ACC
    turn_rate_input = None
    #: scale of the density planner's step sizes per input (``init_std``, ``lr`` and ``update_clip`` are set for
    #: the car's inputs of +-3; the steering-rate box is a tenth of that)
    input_step_scale = (0.1, 1.0)

    def __init__(self, config: KSConfig | None = None):
        self.config = config or KSConfig()

    @property
    def vehicle(self) -> KSVehicle:
        """The CommonRoad vehicle's parameters."""
        return self.config.params

    @property
    def wheelbase(self) -> float:
        return self.vehicle.wheelbase

    @property
    def footprint(self) -> Footprint:  # type: ignore[override]
        """The vehicle's rectangle ``l x w``, centred on ``(p_x, p_y)`` (CommonRoad's convention, module docstring)."""
        return Footprint(self.vehicle.length, self.vehicle.width)

    def state_from_pose(self, x: float, y: float, heading: float, speed: float) -> tuple[float, ...]:
        """``(x, y, 0, speed, heading)`` with the heading wrapped into ``[-pi, pi)``; straight wheels."""
        psi = (float(heading) + _PI) % (2 * _PI) - _PI
        return (float(x), float(y), 0.0, float(speed), psi)

    def planning_bounds(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Steering angle within ``steering_use`` of the vehicle's limit, speed ``planning_speed_margin`` inside the
        speed box, heading in the state box."""
        inf, m, c = math.inf, self.config.planning_speed_margin, self.config
        d = c.steering_use * c.steering_max
        return (-inf, -inf, -d, c.speed_min + m, -c.heading_max), (inf, inf, d, c.speed_max - m, c.heading_max)

    # ---------------------------------------------------------------- dynamics
    def drift(self, x: Tensor) -> Tensor:
        delta, v, psi = x[..., DELTA], x[..., V], x[..., PSI]
        zero = torch.zeros_like(v)
        return torch.stack([v * torch.cos(psi), v * torch.sin(psi), zero, zero,
                            v * torch.tan(delta) / self.wheelbase], dim=-1)

    def f(self, x: Tensor, u: Tensor) -> Tensor:
        delta, v, psi = x[..., DELTA], x[..., V], x[..., PSI]
        rate, acc = torch.broadcast_tensors(u[..., STEER_RATE], u[..., ACC])
        delta, v, psi, rate, acc = torch.broadcast_tensors(delta, v, psi, rate, acc)
        return torch.stack([v * torch.cos(psi), v * torch.sin(psi), rate, acc,
                            v * torch.tan(delta) / self.wheelbase], dim=-1)

    def drift_divergence(self, x: Tensor) -> Tensor:
        # d(v cos psi)/d px + d(v sin psi)/d py + 0 + 0 + d(v tan(delta) / l)/d psi = 0
        return torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)

    def f_symbolic(self, x, u, ops):
        """KS dynamics for symbolic vectors (CasADi: ``ops = casadi``); every state is nominal."""
        return ops.vertcat(x[V] * ops.cos(x[PSI]), x[V] * ops.sin(x[PSI]), u[STEER_RATE], u[ACC],
                           x[V] * ops.tan(x[DELTA]) / self.wheelbase)

    # ------------------------------------------------------------ references
    def rollout(self, x0: Tensor, u: Tensor, dt: float) -> Tensor:
        """Loop-free explicit-Euler rollout, identical to the step-by-step loop with the plant's hold at rest
        (:meth:`standstill`, :func:`~density_planner.systems.base.hold_speeds`): ``delta`` and ``v`` are exclusive
        cumulative sums of the inputs, ``psi`` one of ``v_k tan(delta_k) / l_wb``, and ``p_x, p_y`` ones of
        ``v_k cos(psi_k)``, ``v_k sin(psi_k)``."""
        batch = torch.broadcast_shapes(x0.shape[:-1], u.shape[:-2])
        x0 = x0.expand(*batch, x0.shape[-1])
        u = u.expand(*batch, *u.shape[-2:])
        delta = _exclusive_cumsum(dt * u[..., STEER_RATE], x0[..., DELTA])
        v = self.held_speeds(_exclusive_cumsum(dt * u[..., ACC], x0[..., V]))
        psi = _exclusive_cumsum(dt * v[..., :-1] * torch.tan(delta[..., :-1]) / self.wheelbase, x0[..., PSI])
        px = _exclusive_cumsum(dt * v[..., :-1] * torch.cos(psi[..., :-1]), x0[..., PX])
        py = _exclusive_cumsum(dt * v[..., :-1] * torch.sin(psi[..., :-1]), x0[..., PY])
        return torch.stack([px, py, delta, v, psi], dim=-1)


def _exclusive_cumsum(increments: Tensor, start: Tensor) -> Tensor:
    """``[start, start + d0, start + d0 + d1, ...]`` along the last axis (length K + 1)."""
    csum = torch.cumsum(increments, dim=-1)
    return torch.cat([start.unsqueeze(-1), start.unsqueeze(-1) + csum], dim=-1)


@register_system("ks", domains=tuple(KS_DOMAINS), description="CommonRoad's kinematic single-track model of the BMW "
                 "320i (x, y, steering angle, speed, heading; inputs steering rate and acceleration)")
def _build_ks(domain: str) -> KinematicSingleTrack:
    return KinematicSingleTrack(ks_domain(domain))

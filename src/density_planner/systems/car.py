"""Kinematic car with a constant, unknown heading-measurement bias (paper §V, "Model description").

State ``x = [p_x, p_y, theta, v, theta_bias]`` (m, m, rad, m/s, rad), input ``u = [omega, a]`` (rad/s, m/s^2)::

    p_x'        = v cos(theta)
    p_y'        = v sin(theta)
    theta'      = omega
    v'          = a
    theta_bias' = 0

Control-affine with ``a(x) = [v cos(theta), v sin(theta), 0, 0, 0]`` and the constant ``B = [e_theta, e_v]``.
The heading is kept unwrapped (as in the paper's code), hence the state box ``theta in [-pi + 0.2, 3 pi - 0.2]``.
The controller sees the biased measurement ``x_hat = [p_x, p_y, theta + theta_bias, v, 0]`` (paper §V).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import get_args

import torch
from torch import Tensor

from ..checks import broadcast_shape, check_choice
from .base import ConfigBoxes, ControlAffineSystem, Footprint, LiouvilleScheme
from .registry import register_system

__all__ = ["KinematicCar", "CarConfig", "CAR_DOMAINS", "car_domain", "turn_rate_limit", "wrap_heading", "PX",
           "PY", "THETA", "V", "BIAS", "OMEGA", "ACC"]

#: state indices
PX, PY, THETA, V, BIAS = 0, 1, 2, 3, 4
#: input indices
OMEGA, ACC = 0, 1

_PI = math.pi


@dataclass(frozen=True)
class CarConfig:
    """Boxes of the car model (``docs/spec.md`` §1). Units: m, m, rad, m/s, rad; inputs rad/s, m/s^2."""

    #: validity box of the state (controller training, reference validity, evaluation of J_B)
    state_min: tuple[float, float, float, float, float] = (-50.0, -50.0, -_PI + 0.2, 0.0, -_PI / 8)
    state_max: tuple[float, float, float, float, float] = (50.0, 50.0, 3 * _PI - 0.2, 10.0, _PI / 8)
    #: input bounds (both the reference inputs and the applied inputs)
    input_min: tuple[float, float] = (-3.0, -3.0)
    input_max: tuple[float, float] = (3.0, 3.0)
    #: half-widths of the tracking-error box XE (controller training)
    error_max: tuple[float, float, float, float, float] = (2.0, 2.0, 1.0, 1.0, _PI / 8)
    #: half-widths of the initial-error box XE0 = 0.5 XE (initial uncertainty of the planner)
    initial_error_max: tuple[float, float, float, float, float] = (1.0, 1.0, 0.5, 0.5, _PI / 16)
    #: box of reference start states used to generate training data (artificial map, any heading, 1-8 m/s)
    reference_start_min: tuple[float, float, float, float, float] = (-12.0, -30.0, 0.0, 1.0, 0.0)
    reference_start_max: tuple[float, float, float, float, float] = (12.0, 10.0, 2 * _PI, 8.0, 0.0)
    #: lateral-acceleration limit of the reference inputs [m/s^2]: ``|omega| <= turn_rate_limit(v)``, a smooth
    #: form of ``min(omega_max, a_lat_max / |v|)`` (see :func:`turn_rate_limit`); ``inf``: no limit (the paper)
    lateral_accel_max: float = math.inf
    #: physical input limits reached by the controller's *smooth* saturation (``None``: hard clip at the input
    #: bounds, the paper's controller). The reference box ``input_min/max`` then lies inside them; the controller
    #: output is the identity there and bends smoothly (C^2, tanh) towards these limits outside
    actuator_min: tuple[float, float] | None = None
    actuator_max: tuple[float, float] | None = None
    #: lateral-acceleration limit of the actuators [m/s^2] (the smooth saturation's ceiling of ``|omega|``)
    actuator_lateral_accel_max: float = math.inf
    #: name of the domain (``"paper"`` or ``"road"``, see :data:`CAR_DOMAINS`; free text for custom boxes)
    domain: str = "paper"
    #: the planned trajectories' speeds should stay this far inside the speed box [m/s] (the bounds cost J_B; the
    #: paper's X_MIN_MP / X_MAX_MP: v in [0.1, 9.9] m/s for the box [0, 10])
    planning_speed_margin: float = 0.1
    #: scheme of exact Liouville for this domain (the default of
    #: :attr:`~density_planner.density.liouville.LiouvilleConfig.integrator`): with the road domain's smooth
    #: saturation the turn-rate band between the reference's and the actuator's limits narrows as ``a_lat / v``, and
    #: the learned controller sweeps through it within hundredths of a second at highway speed, which a fixed 0.1-s
    #: step cannot resolve: the error-controlled "rk43" refines its step there, per sample (docs/core.md, "Error
    #: control")
    liouville_integrator: LiouvilleScheme = "rk4"
    #: body length along the heading [m] (rectangle centred on (p_x, p_y)); 0 with width 0 = point vehicle
    length: float = 4.5
    #: body width [m]
    width: float = 1.8

    def __post_init__(self) -> None:
        Footprint(self.length, self.width)  # validates
        for lo_name, hi_name in [
            ("state_min", "state_max"),
            ("input_min", "input_max"),
            ("reference_start_min", "reference_start_max"),
        ]:
            lo, hi = getattr(self, lo_name), getattr(self, hi_name)
            if any(a > b for a, b in zip(lo, hi)):
                raise ValueError(f"CarConfig.{lo_name} must be <= {hi_name} elementwise")
        for name in ("error_max", "initial_error_max"):
            if any(v < 0 for v in getattr(self, name)):
                raise ValueError(f"CarConfig.{name} must be non-negative")
        if not 0 <= 2 * self.planning_speed_margin < self.state_max[V] - self.state_min[V]:
            raise ValueError("CarConfig.planning_speed_margin must be >= 0 and leave a non-empty speed range")
        for name in ("lateral_accel_max", "actuator_lateral_accel_max"):
            if not getattr(self, name) > 0:
                raise ValueError(f"CarConfig.{name} must be > 0 (inf for no limit), got {getattr(self, name)!r}")
        check_choice("CarConfig.liouville_integrator", self.liouville_integrator, get_args(LiouvilleScheme))
        if (self.actuator_min is None) != (self.actuator_max is None):
            raise ValueError("CarConfig.actuator_min and actuator_max must both be set or both be None")
        if self.actuator_min is not None:
            assert self.actuator_max is not None
            if not all(a < lo <= 0 <= hi < b for a, lo, hi, b in zip(self.actuator_min, self.input_min,
                                                                     self.input_max, self.actuator_max)):
                raise ValueError(
                    "CarConfig: the actuator box must strictly contain the reference input box, which must contain "
                    f"0 (got actuator {self.actuator_min}..{self.actuator_max}, inputs {self.input_min}.."
                    f"{self.input_max})"
                )
            if self.actuator_lateral_accel_max <= self.lateral_accel_max and math.isfinite(self.lateral_accel_max):
                raise ValueError("CarConfig.actuator_lateral_accel_max must exceed lateral_accel_max")

    @property
    def speed_max(self) -> float:
        """Largest speed of the domain [m/s] (upper speed bound of the state box): starts above it are out of the
        domain of the controller and of the density predictors trained for it."""
        return float(self.state_max[V])

    @property
    def smooth_saturation(self) -> bool:
        """Whether the controller output is bounded by a smooth saturation (else a hard clip)."""
        return self.actuator_min is not None

    def turn_rate_limit(self, v: Tensor, actuator: bool = False) -> Tensor:
        """``|omega|`` bound at speed ``v`` of the references (or, with ``actuator``, of the actuators) [rad/s]."""
        if actuator and self.actuator_max is not None:
            return turn_rate_limit(v, self.actuator_max[OMEGA], self.actuator_lateral_accel_max)
        return turn_rate_limit(v, self.input_max[OMEGA], self.lateral_accel_max)

    @classmethod
    def paper(cls) -> CarConfig:
        """The paper's box (``docs/spec.md`` §1): v in [0, 10] m/s, inputs +-3, hard clip, no lateral limit."""
        return cls()

    @classmethod
    def road(cls) -> CarConfig:
        """Road traffic: v in [0, 40] m/s, passenger-car input limits, lateral-acceleration limit (docs/controller.md,
        "Road domain", gives the sources).

        * References (what the planner may ask): ``a in [-6, 3] m/s^2`` (firm braking / brisk acceleration of a
          passenger car), ``|omega| <= min(1 rad/s, 4 m/s^2 / v)`` (a lateral acceleration of 4 m/s^2, the upper
          end of everyday driving).
        * Actuators (reached by the controller's smooth saturation): ``a in [-9, 4.5] m/s^2`` (full braking at a
          tyre-road friction of about 0.9, full acceleration of a typical car in low gear), ``|omega| <= min(
          1.5 rad/s, 8 m/s^2 / v)`` (the friction limit of the lateral acceleration on dry asphalt).
        * Heading unwrapped over +-4 pi (headings enter the controller through cos / sin); positions +-1 km.
        """
        return cls(
            state_min=(-1000.0, -1000.0, -4 * _PI, 0.0, -_PI / 8),
            state_max=(1000.0, 1000.0, 4 * _PI, 40.0, _PI / 8),
            input_min=(-1.0, -6.0),
            input_max=(1.0, 3.0),
            reference_start_min=(-10.0, -10.0, -_PI, 0.5, 0.0),
            reference_start_max=(10.0, 10.0, _PI, 38.0, 0.0),
            lateral_accel_max=4.0,
            actuator_min=(-1.5, -9.0),
            actuator_max=(1.5, 4.5),
            actuator_lateral_accel_max=8.0,
            domain="road",
            liouville_integrator="rk43",
        )


def turn_rate_limit(v: Tensor, omega_max: float, lateral_accel_max: float) -> Tensor:
    """Smooth turn-rate bound ``(omega_max^-4 + (|v| / a_lat_max)^4)^(-1/4)`` [rad/s] at speeds ``v`` [m/s].

    It never exceeds ``min(omega_max, a_lat_max / |v|)`` (the lateral acceleration ``|v omega|`` stays below
    ``a_lat_max``), is within 16 % of it (at the crossing speed ``v = a_lat_max / omega_max``; a few per cent away
    from it), and is infinitely differentiable in ``v``. ``a_lat_max = inf`` gives ``omega_max``.
    """
    if math.isinf(lateral_accel_max):
        return torch.full_like(v, float(omega_max))
    r = v.abs() / lateral_accel_max
    return (omega_max ** -4 + r ** 4) ** -0.25


#: lower end of the heading range :func:`wrap_heading` maps into (the paper's box starts here, docs/spec.md)
_THETA_MIN = -_PI + 0.2


def wrap_heading(theta: float) -> float:
    """Heading [rad] shifted by a multiple of 2 pi into ``[-pi + 0.2, pi + 0.2)``, inside the car's heading box
    (the heading is kept unwrapped, so the box spans more than one turn)."""
    return (theta - _THETA_MIN) % (2 * math.pi) + _THETA_MIN


def car_domain(name: str) -> CarConfig:
    """The car configuration of a named domain (``"paper"`` or ``"road"``)."""
    try:
        return CAR_DOMAINS[name]()
    except KeyError:
        raise ValueError(f"unknown car domain {name!r}; valid choices: {', '.join(CAR_DOMAINS)}") from None


#: named car domains: the paper's box and road traffic (0-40 m/s)
CAR_DOMAINS = {"paper": CarConfig.paper, "road": CarConfig.road}


class KinematicCar(ConfigBoxes, ControlAffineSystem):
    """Kinematic car with heading-measurement bias; see the module docstring for the equations."""

    state_names = ("px", "py", "theta", "v", "theta_bias")
    input_names = ("omega", "a")
    constant_input_matrix = ((0.0, 0.0), (0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (0.0, 0.0))

    position_indices = (PX, PY)
    heading_index = THETA
    speed_index = V
    acceleration_input = ACC
    turn_rate_input = OMEGA
    hidden_states = (BIAS,)

    def __init__(self, config: CarConfig | None = None):
        self.config = config or CarConfig()

    @property
    def footprint(self) -> Footprint:  # type: ignore[override]
        """The car's rectangle ``length x width`` (:class:`CarConfig`), centred on ``(p_x, p_y)``."""
        return Footprint(self.config.length, self.config.width)

    def state_from_pose(self, x: float, y: float, heading: float, speed: float) -> tuple[float, ...]:
        """``(x, y, wrap_heading(heading), speed, 0)``: the heading shifted by a multiple of 2 pi into
        ``[-pi + 0.2, pi + 0.2)``, inside both domains' heading boxes; the bias is 0."""
        return (float(x), float(y), wrap_heading(float(heading)), float(speed), 0.0)

    @property
    def liouville_integrator(self) -> LiouvilleScheme:
        """:attr:`CarConfig.liouville_integrator` (the road domain's: "rk43")."""
        return self.config.liouville_integrator

    def planning_bounds(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Heading in the state box, speed ``config.planning_speed_margin`` inside the speed box, bias free."""
        inf, m = math.inf, self.config.planning_speed_margin
        lo, hi = self.config.state_min, self.config.state_max
        return (-inf, -inf, lo[THETA], lo[V] + m, -inf), (inf, inf, hi[THETA], hi[V] - m, inf)

    def turn_rate_limit(self, v: Tensor) -> Tensor:
        """``|omega|`` bound of the references at speed ``v`` (``config.turn_rate_limit``) [rad/s]."""
        return self.config.turn_rate_limit(v)

    def segment_turn_rate_limits(self, x_ref: Tensor, steps_per_segment: int) -> Tensor:
        """The turn-rate bound of each input segment of a reference roll-out ``x_ref (..., K + 1, nx)`` whose
        segments last ``steps_per_segment`` fine steps: :meth:`turn_rate_limit` at the largest ``|v|`` over the
        segment, its ends included (the bound falls with the speed), ``(..., K / steps_per_segment)`` [rad/s]. A
        reference within it has ``|omega| <= turn_rate_limit(|v|)`` at every instant."""
        m = int(steps_per_segment)
        if m < 1 or (x_ref.shape[-2] - 1) % m:
            raise ValueError(f"segment_turn_rate_limits: {x_ref.shape[-2] - 1} fine steps are not whole segments "
                             f"of {steps_per_segment}")
        v_seg = x_ref[..., V].abs().unfold(-1, m + 1, m).amax(-1)
        return self.turn_rate_limit(v_seg)

    # ---------------------------------------------------------------- dynamics
    def drift(self, x: Tensor) -> Tensor:
        theta, v = x[..., THETA], x[..., V]
        zero = torch.zeros_like(v)
        return torch.stack([v * torch.cos(theta), v * torch.sin(theta), zero, zero, zero], dim=-1)

    def f(self, x: Tensor, u: Tensor) -> Tensor:
        theta, v = x[..., THETA], x[..., V]
        omega, acc = torch.broadcast_tensors(u[..., OMEGA], u[..., ACC])
        theta, v, omega, acc = torch.broadcast_tensors(theta, v, omega, acc)
        return torch.stack(
            [v * torch.cos(theta), v * torch.sin(theta), omega, acc, torch.zeros_like(v)], dim=-1
        )

    def drift_divergence(self, x: Tensor) -> Tensor:
        # d(v cos th)/d px + d(v sin th)/d py + 0 + 0 + 0 = 0
        return torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)

    def f_symbolic(self, x, u, ops):
        """Nominal car ``[v cos(theta), v sin(theta), omega, a]`` of ``x = (p_x, p_y, theta, v)`` (no bias)."""
        return ops.vertcat(x[3] * ops.cos(x[2]), x[3] * ops.sin(x[2]), u[0], u[1])

    # ------------------------------------------------------------- measurement
    def measure(self, x: Tensor) -> Tensor:
        """Biased measurement ``[p_x, p_y, theta + theta_bias, v, 0]`` (paper §V)."""
        return torch.stack(
            [x[..., PX], x[..., PY], x[..., THETA] + x[..., BIAS], x[..., V], torch.zeros_like(x[..., V])], dim=-1
        )

    def measure_jvp(self, x: Tensor, dx: Tensor) -> Tensor:
        return torch.stack(
            [dx[..., PX], dx[..., PY], dx[..., THETA] + dx[..., BIAS], dx[..., V], torch.zeros_like(dx[..., V])],
            dim=-1,
        )

    # ------------------------------------------------------------ references
    def rollout(self, x0: Tensor, u: Tensor, dt: float) -> Tensor:
        """Loop-free explicit-Euler rollout of the nominal car (no bias), identical to the step-by-step loop with the
        plant's hold at rest (:meth:`standstill`: a car that brakes to a stop stays stopped).

        With ``x_{k+1} = x_k + dt f(x_k, u_k)``: ``theta`` and ``v`` are exclusive cumulative sums of the inputs,
        and ``p_x, p_y`` exclusive cumulative sums of ``v_k cos(theta_k)``, ``v_k sin(theta_k)``.
        """
        batch = broadcast_shape(x0.shape[:-1], u.shape[:-2])
        x0 = x0.expand(*batch, x0.shape[-1])
        u = u.expand(*batch, *u.shape[-2:])
        theta = _exclusive_cumsum(dt * u[..., OMEGA], x0[..., THETA])
        v = self.held_speeds(_exclusive_cumsum(dt * u[..., ACC], x0[..., V]))
        px = _exclusive_cumsum(dt * v[..., :-1] * torch.cos(theta[..., :-1]), x0[..., PX])
        py = _exclusive_cumsum(dt * v[..., :-1] * torch.sin(theta[..., :-1]), x0[..., PY])
        bias = x0[..., BIAS].unsqueeze(-1).expand_as(theta)
        return torch.stack([px, py, theta, v, bias], dim=-1)


    def rollout_strided(self, x0: Tensor, u: Tensor, dt: float, stride: int) -> Tensor:
        """Every ``stride``-th state of :meth:`rollout`, computed with block sums (the planner's first stage needs
        only the 0.1-s grid): the same Euler states, fewer operations."""
        k = u.shape[-2]
        if k % stride:
            return super().rollout_strided(x0, u, dt, stride)
        batch = broadcast_shape(x0.shape[:-1], u.shape[:-2])
        x0 = x0.expand(*batch, x0.shape[-1])
        u = u.expand(*batch, *u.shape[-2:])
        theta = _exclusive_cumsum(dt * u[..., OMEGA], x0[..., THETA])
        v = self.held_speeds(_exclusive_cumsum(dt * u[..., ACC], x0[..., V]))
        vc = (dt * v[..., :-1] * torch.cos(theta[..., :-1])).unflatten(-1, (k // stride, stride)).sum(-1)
        vs = (dt * v[..., :-1] * torch.sin(theta[..., :-1])).unflatten(-1, (k // stride, stride)).sum(-1)
        px = _exclusive_cumsum(vc, x0[..., PX])
        py = _exclusive_cumsum(vs, x0[..., PY])
        theta, v = theta[..., ::stride], v[..., ::stride]
        bias = x0[..., BIAS].unsqueeze(-1).expand_as(theta)
        return torch.stack([px, py, theta, v, bias], dim=-1)


    def rollout_piecewise_strided(self, x0: Tensor, params: Tensor, dt: float, steps_per_segment: int,
                                  stride: int) -> Tensor:
        """:meth:`rollout_strided` for piecewise-constant inputs ``params (*batch, nu, S)``, each held for
        ``steps_per_segment`` Euler steps, without building the fine input sequence.

        Within a segment theta and v are linear in the step index, so they are formed by broadcasting from their
        values at the segment starts (no cumulative sum over the fine steps, and a backward pass of broadcasts
        instead of scatters into the fine grid). Equal to ``rollout_strided(x0, inputs(params), dt, stride)`` up to
        floating-point rounding. Returns ``(*batch, S * steps_per_segment // stride + 1, nx)``.
        """
        n = steps_per_segment
        if n % stride:
            raise ValueError(f"steps_per_segment ({n}) must be a multiple of stride ({stride})")
        batch = broadcast_shape(x0.shape[:-1], params.shape[:-2])
        x0 = x0.expand(*batch, x0.shape[-1])
        params = params.expand(*batch, *params.shape[-2:])
        omega, acc = params[..., OMEGA, :], params[..., ACC, :]
        j = dt * torch.arange(n, dtype=params.dtype, device=params.device)
        theta_seg = _exclusive_cumsum(n * dt * omega, x0[..., THETA])  # (*batch, S + 1)
        v_seg = _exclusive_cumsum(n * dt * acc, x0[..., V])
        theta = theta_seg[..., :-1, None] + omega[..., None] * j  # (*batch, S, n)
        v = v_seg[..., :-1, None] + acc[..., None] * j
        # linear within a segment: a negative speed shows at a segment's end
        v_end = v_seg[..., -1:]
        if self.standstill_index is not None and bool((v_seg[..., 1:] < 0).any()):
            v, v_end = _hold_piecewise(v, v_seg)
        blocks = (*theta.shape[:-1], n // stride, stride)
        vc = (dt * v * torch.cos(theta)).reshape(blocks).sum(-1).flatten(-2)
        vs = (dt * v * torch.sin(theta)).reshape(blocks).sum(-1).flatten(-2)
        px = _exclusive_cumsum(vc, x0[..., PX])
        py = _exclusive_cumsum(vs, x0[..., PY])
        theta = torch.cat([theta[..., ::stride].flatten(-2), theta_seg[..., -1:]], dim=-1)
        v = torch.cat([v[..., ::stride].flatten(-2), v_end], dim=-1)
        bias = x0[..., BIAS].unsqueeze(-1).expand_as(theta)
        return torch.stack([px, py, theta, v, bias], dim=-1)


def _hold_piecewise(v: Tensor, v_seg: Tensor) -> tuple[Tensor, Tensor]:
    """:func:`~density_planner.systems.base.hold_speeds` of unheld speeds that are linear within each segment:
    ``v (..., S, n)`` on the fine grid (segment ``s``, step ``i``), ``v_seg (..., S + 1)`` at the segment starts and
    the end. The running minimum ``m_k = min(0, min_{1 <= j <= k} v_j)`` of a piecewise-linear sequence is attained
    at step 1, a segment start or ``k`` itself, so ``v_k - m_k = max(v_k - M_s, 0)`` with ``M_s`` the cumulative
    minimum over ``0``, step 1 and the segment starts up to ``s`` (``S`` values, not the fine grid); the first step
    keeps ``v_0``. Returns the held ``v (..., S, n)`` and the held end speed ``(..., 1)``."""
    first = v[..., 0, 1] if v.shape[-1] > 1 else v_seg[..., 1]  # v_1
    starts = torch.cat([first.clamp(max=0.0).unsqueeze(-1), v_seg[..., 1:-1]], dim=-1)  # (..., S)
    low = torch.cummin(starts, dim=-1).values.unsqueeze(-1)  # (..., S, 1): M_s
    head = torch.cat([v[..., :1, :1], (v[..., :1, 1:] - low[..., :1, :]).clamp(min=0.0)], dim=-1)
    held = torch.cat([head, (v[..., 1:, :] - low[..., 1:, :]).clamp(min=0.0)], dim=-2)
    end = v_seg[..., -1:]
    return held, (end - torch.minimum(low[..., -1, :], v[..., -1, -1:])).clamp(min=0.0)


def _exclusive_cumsum(increments: Tensor, start: Tensor) -> Tensor:
    """``[start, start + d0, start + d0 + d1, ...]`` along the last axis (length K + 1)."""
    csum = torch.cumsum(increments, dim=-1)
    return torch.cat([start.unsqueeze(-1), start.unsqueeze(-1) + csum], dim=-1)


@register_system("car", domains=tuple(CAR_DOMAINS), description="the paper's kinematic car with an unknown heading "
                 "bias (x, y, heading, speed, bias; inputs turn rate and acceleration)")
def _build_car(domain: str) -> KinematicCar:
    return KinematicCar(car_domain(domain))

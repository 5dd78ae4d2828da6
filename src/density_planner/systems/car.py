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

import torch
from torch import Tensor

from ..checks import broadcast_shape
from .base import ControlAffineSystem, Footprint

__all__ = ["KinematicCar", "CarConfig", "PX", "PY", "THETA", "V", "BIAS", "OMEGA", "ACC"]

#: state indices
PX, PY, THETA, V, BIAS = 0, 1, 2, 3, 4
#: input indices
OMEGA, ACC = 0, 1

_PI = math.pi


@dataclass(frozen=True)
class CarConfig:
    """Boxes of the car model (``original.md`` §1). Units: m, m, rad, m/s, rad; inputs rad/s, m/s^2."""

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


class KinematicCar(ControlAffineSystem):
    """Kinematic car with heading-measurement bias; see the module docstring for the equations."""

    state_names = ("px", "py", "theta", "v", "theta_bias")
    input_names = ("omega", "a")
    constant_input_matrix = ((0.0, 0.0), (0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (0.0, 0.0))

    position_indices = (PX, PY)
    heading_index = THETA

    def __init__(self, config: CarConfig | None = None):
        self.config = config or CarConfig()

    @property
    def footprint(self) -> Footprint:  # type: ignore[override]
        """The car's rectangle ``length x width`` (:class:`CarConfig`), centred on ``(p_x, p_y)``."""
        return Footprint(self.config.length, self.config.width)

    @property
    def state_bounds(self):
        return self.config.state_min, self.config.state_max

    @property
    def input_bounds(self):
        return self.config.input_min, self.config.input_max

    # ---------------------------------------------------------------- dynamics
    def drift(self, x: Tensor) -> Tensor:
        theta, v = x[..., THETA], x[..., V]
        zero = torch.zeros_like(v)
        return torch.stack([v * torch.cos(theta), v * torch.sin(theta), zero, zero, zero], dim=-1)

    def input_matrix(self, x: Tensor) -> Tensor:
        return torch.tensor(self.constant_input_matrix, dtype=x.dtype, device=x.device)

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
        """Loop-free explicit-Euler rollout of the nominal car (no bias), identical to the step-by-step loop.

        With ``x_{k+1} = x_k + dt f(x_k, u_k)``: ``theta`` and ``v`` are exclusive cumulative sums of the inputs,
        and ``p_x, p_y`` exclusive cumulative sums of ``v_k cos(theta_k)``, ``v_k sin(theta_k)``.
        """
        batch = broadcast_shape(x0.shape[:-1], u.shape[:-2])
        x0 = x0.expand(*batch, x0.shape[-1])
        u = u.expand(*batch, *u.shape[-2:])
        theta = _exclusive_cumsum(dt * u[..., OMEGA], x0[..., THETA])
        v = _exclusive_cumsum(dt * u[..., ACC], x0[..., V])
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
        v = _exclusive_cumsum(dt * u[..., ACC], x0[..., V])
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
        blocks = (*theta.shape[:-1], n // stride, stride)
        vc = (dt * v * torch.cos(theta)).reshape(blocks).sum(-1).flatten(-2)
        vs = (dt * v * torch.sin(theta)).reshape(blocks).sum(-1).flatten(-2)
        px = _exclusive_cumsum(vc, x0[..., PX])
        py = _exclusive_cumsum(vs, x0[..., PY])
        theta = torch.cat([theta[..., ::stride].flatten(-2), theta_seg[..., -1:]], dim=-1)
        v = torch.cat([v[..., ::stride].flatten(-2), v_seg[..., -1:]], dim=-1)
        bias = x0[..., BIAS].unsqueeze(-1).expand_as(theta)
        return torch.stack([px, py, theta, v, bias], dim=-1)


def _exclusive_cumsum(increments: Tensor, start: Tensor) -> Tensor:
    """``[start, start + d0, start + d0 + d1, ...]`` along the last axis (length K + 1)."""
    csum = torch.cumsum(increments, dim=-1)
    return torch.cat([start.unsqueeze(-1), start.unsqueeze(-1) + csum], dim=-1)

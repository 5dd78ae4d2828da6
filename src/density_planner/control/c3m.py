"""Learned contraction controller (C3M: Sun, Jha, Fan, "Learning Certified Control using Contraction Metric",
CoRL 2020) for the kinematic car.

Controller (architecture of the paper's controller, ``docs/spec.md`` §3)::

    e = x_hat[:4] - x_ref[:4]                        tracking error of the *measured* state [m, m, rad, m/s]
    z = (theta_hat, v_hat, theta_ref, v_ref)         scheduling variables (normalised to about [-1, 1])
    u = u_ref + W2(z) tanh(W1(z) e)                  W1(z): (rank x 4), W2(z): (2 x rank), two tanh MLPs

then clipped to the input bounds (+-3) by :class:`~density_planner.control.base.TrackingController`. With
``e = 0`` the feedback vanishes, so an unbiased reference is tracked exactly.

Metric (the C3M structure for control-affine systems with constant ``B``; state order ``(p_x, p_y, theta, v)``,
``B`` actuates ``(theta, v)``)::

    W(x) = L(x) L(x)^T + w_lb I,     L(x) = [[L_pp,      0      ],
                                             [L_ap(x),   L_aa(x)]]

with a constant ``2 x 2`` block ``L_pp`` and ``L_ap, L_aa`` from a tanh MLP of ``(theta, v)``. The block of ``W``
that belongs to the unactuated states, ``B_perp^T W B_perp = L_pp L_pp^T + w_lb I``, is therefore constant, so the
C3M condition ``B_perp^T (d_b W) B_perp = 0`` holds by construction; ``W >= w_lb I`` everywhere. Any symmetric
positive definite ``W >= w_lb I`` with a constant unactuated block can be written in this form.

Both networks have a hand-written forward-mode pass (primal and tangents pushed through every ``Linear``
layer as separate matrix products), used by the exact Liouville density (:meth:`C3MController.raw_with_tangents`)
and by training (:meth:`C3MController.jacobian`, :meth:`ContractionMetric.with_derivatives`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..errors import CheckpointError
from ..systems.car import PX, PY, THETA, CarConfig, V
from .base import SmoothSaturation, TrackingController

__all__ = [
    "C3MArchitecture",
    "C3MController",
    "ContractionMetric",
    "C3MModel",
    "C3M_KIND",
    "SHIPPED_C3M_WEIGHTS",
    "shipped_c3m_path",
    "load_c3m_model",
    "load_c3m_controller",
    "save_c3m_model",
]

#: ``kind`` entry of the weights' JSON metadata
C3M_KIND = "c3m_car_controller"
#: file name (without suffix) of the shipped weights in ``density_planner/weights``
SHIPPED_C3M_WEIGHTS = "controller_c3m"

#: number of tracked state components (p_x, p_y, theta, v) and of inputs (omega, a)
N_ERR = 4
N_U = 2


@dataclass(frozen=True)
class C3MArchitecture:
    """Shape of the controller and metric networks (everything that determines the ``state_dict``)."""

    #: width of the hidden layers of the controller MLPs W1 and W2
    hidden: int = 128
    #: number of hidden layers of each controller MLP
    n_hidden: int = 2
    #: inner dimension of the feedback ``W2 (2 x rank) tanh(W1 (rank x 4) e)``
    rank: int = 12
    #: width of the hidden layers of the metric MLP
    metric_hidden: int = 128
    #: number of hidden layers of the metric MLP
    metric_n_hidden: int = 2
    #: lower bound of the metric, ``W >= w_lb I`` [dimensionless]
    w_lb: float = 0.1
    #: range of theta [rad] mapped to [-1, 1] at the network inputs (the state box of ``docs/spec.md`` §1)
    theta_range: tuple[float, float] = (-math.pi + 0.2, 3 * math.pi - 0.2)
    #: range of v [m/s] mapped to [-1, 1] at the network inputs
    v_range: tuple[float, float] = (0.0, 10.0)
    #: how headings enter the networks: "sincos" as (cos theta, sin theta) (the dynamics depend on theta only
    #: through these, and theta is unwrapped over two periods), or "raw" as theta mapped from ``theta_range``
    #: to [-1, 1] (the paper's controller)
    angle_encoding: Literal["sincos", "raw"] = "sincos"
    #: if > 0, the speed also enters as ``tanh(v / speed_feature_scale)`` [m/s]: a smooth sign of v that lets the
    #: networks switch steeply near v = 0, where the lateral gains must grow like 1/v and change sign (reversing)
    speed_feature_scale: float = 0.0

    def __post_init__(self) -> None:
        for name in ("hidden", "n_hidden", "rank", "metric_hidden", "metric_n_hidden"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"C3MArchitecture.{name} must be a positive integer, got {value!r}")
        if not (math.isfinite(self.w_lb) and self.w_lb > 0):
            raise ValueError(f"C3MArchitecture.w_lb must be > 0, got {self.w_lb!r}")
        for name in ("theta_range", "v_range"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
                raise ValueError(f"C3MArchitecture.{name} must be (low, high) with low < high, got {(lo, hi)!r}")
        if not (math.isfinite(self.speed_feature_scale) and self.speed_feature_scale >= 0):
            raise ValueError(f"C3MArchitecture.speed_feature_scale must be >= 0, got {self.speed_feature_scale!r}")
        if self.angle_encoding not in ("sincos", "raw"):
            raise ValueError(f"C3MArchitecture.angle_encoding must be 'sincos' or 'raw', got {self.angle_encoding!r}")

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> C3MArchitecture:
        from ..config import from_dict

        return from_dict(cls, data)

    def normalisation(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """``(centre, half-width)`` of ``(theta, v)``: inputs enter the networks as ``(z - centre) / half-width``."""
        (t0, t1), (v0, v1) = self.theta_range, self.v_range
        return ((t0 + t1) / 2, (v0 + v1) / 2), ((t1 - t0) / 2, (v1 - v0) / 2)

    @property
    def n_state_features(self) -> int:
        """Network inputs per (theta, v) pair: 3 for "sincos", 2 for "raw", one more with the speed feature."""
        return (3 if self.angle_encoding == "sincos" else 2) + (1 if self.speed_feature_scale > 0 else 0)


class TanhMLP(nn.Module):
    """``Linear -> tanh -> ... -> Linear`` with a hand-written forward-mode (tangent) pass."""

    def __init__(self, n_in: int, hidden: int, n_hidden: int, n_out: int):
        super().__init__()
        dims = [n_in] + [hidden] * n_hidden + [n_out]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))

    def forward(self, z: Tensor) -> Tensor:
        last = len(self.layers) - 1
        for i, lin in enumerate(self.layers):
            assert isinstance(lin, nn.Linear)
            z = F.linear(z, lin.weight, lin.bias)  # what lin(z) computes, without a module call per layer
            if i < last:
                z = torch.tanh(z)
        return z

    def forward_with_tangents(self, z: Tensor, dz: Tensor) -> tuple[Tensor, Tensor]:
        """Output for ``z (*batch, n_in)`` and its directional derivatives along ``dz (K, *batch', n_in)``.

        ``dz`` may have size-1 batch dimensions; they broadcast after the first activation. The tangents follow
        ``d <- d W^T`` through each ``Linear`` and ``d <- d (1 - y^2)`` through each ``tanh``.
        """
        last = len(self.layers) - 1
        y, d = z, dz
        for i, lin in enumerate(self.layers):
            assert isinstance(lin, nn.Linear)
            w = lin.weight
            y = F.linear(y, w, lin.bias)
            d = torch.matmul(d, w.t())
            if i < last:
                y = torch.tanh(y)
                d = d * (1.0 - y * y)
        return y, d


def _apply(m: Tensor, v: Tensor) -> Tensor:
    """Matrices ``m (..., r, c)`` times vectors ``v (..., c)`` (batch dimensions broadcast): ``(..., r)``. A batched
    matrix product: half the time of the element-wise product and sum over ``(..., r, c)`` on the closed loop's
    small matrices (``12 x 4``, ``2 x 12``)."""
    return torch.matmul(m, v.unsqueeze(-1)).squeeze(-1)


class _StateFeatures:
    """Network inputs from ``(theta, v)`` pairs and their tangents (see ``C3MArchitecture.angle_encoding``)."""

    def __init__(self, arch: C3MArchitecture):
        (self.t0, self.v0), (self.ts, self.vs) = arch.normalisation()
        self.sincos = arch.angle_encoding == "sincos"
        self.vf = float(arch.speed_feature_scale)

    def __call__(self, theta: Tensor, v: Tensor) -> list[Tensor]:
        vn = (v - self.v0) / self.vs
        out = [torch.cos(theta), torch.sin(theta), vn] if self.sincos else [(theta - self.t0) / self.ts, vn]
        if self.vf > 0:
            out.append(torch.tanh(v / self.vf))
        return out

    def tangents(self, theta: Tensor, v: Tensor, d_theta: Tensor, d_v: Tensor) -> list[Tensor]:
        """Tangents of the features along ``(d_theta, d_v)`` at ``(theta, v)``."""
        dvn = d_v / self.vs
        if self.sincos:
            out = [-torch.sin(theta) * d_theta, torch.cos(theta) * d_theta, dvn]
        else:
            out = [d_theta / self.ts, dvn]
        if self.vf > 0:
            sv = torch.tanh(v / self.vf)
            out.append((1.0 - sv * sv) / self.vf * d_v)
        return out


class C3MController(TrackingController):
    """``u = u_ref + W2(z) tanh(W1(z) e)``, clipped to the input bounds (see the module docstring).

    Inputs broadcast: ``x_hat (*batch, nx)`` (``nx >= 4``; the 5-D car state and the 4-D training state both
    work, only ``[p_x, p_y, theta, v]`` is used), ``x_ref (*batch, nx)``, ``u_ref (*batch, 2)``.
    """

    def __init__(self, architecture: C3MArchitecture | None = None, car: CarConfig | None = None):
        car = car or CarConfig()
        super().__init__(car.input_min, car.input_max, SmoothSaturation.from_car(car))
        #: the car domain the controller is for (its speed range bounds where it may be used)
        self.car = car
        if len(car.input_min) != N_U:
            raise ValueError(f"C3MController needs a car with {N_U} inputs, got {len(car.input_min)}")
        self.architecture = architecture or C3MArchitecture()
        arch = self.architecture
        self.rank = arch.rank
        self._features = _StateFeatures(arch)
        n_in = 2 * arch.n_state_features
        self.w1 = TanhMLP(n_in, arch.hidden, arch.n_hidden, arch.rank * N_ERR)
        self.w2 = TanhMLP(n_in, arch.hidden, arch.n_hidden, N_U * arch.rank)

    # ------------------------------------------------------------------ helpers
    def _inputs(self, x_hat: Tensor, x_ref: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Network input ``z (*batch, n_in)`` from ``(theta_hat, v_hat, theta_ref, v_ref)``, the error
        ``e (*batch, 4)`` and the (broadcast) measured state ``x_hat[:4] (*batch, 4)``."""
        x_hat4, x_ref4 = torch.broadcast_tensors(x_hat[..., :N_ERR], x_ref[..., :N_ERR])
        feats = self._features(x_hat4[..., THETA], x_hat4[..., V]) + self._features(x_ref4[..., THETA],
                                                                                     x_ref4[..., V])
        return torch.stack(feats, dim=-1), x_hat4 - x_ref4, x_hat4

    def _z_tangents(self, x_hat4: Tensor, d_theta: Tensor, d_v: Tensor) -> Tensor:
        """Tangents of ``z`` along measured-state tangents ``(d_theta, d_v)`` (the reference is fixed)."""
        dm = self._features.tangents(x_hat4[..., THETA], x_hat4[..., V], d_theta, d_v)
        dm = torch.broadcast_tensors(*dm)
        return torch.stack(list(dm) + [torch.zeros_like(dm[0])] * len(dm), dim=-1)

    def gains(self, x_hat: Tensor, x_ref: Tensor) -> tuple[Tensor, Tensor]:
        """``W1 (*batch, rank, 4)`` and ``W2 (*batch, 2, rank)`` at the given states."""
        z, _, _ = self._inputs(x_hat, x_ref)
        return self.w1(z).unflatten(-1, (self.rank, N_ERR)), self.w2(z).unflatten(-1, (N_U, self.rank))

    # --------------------------------------------------------------- interface
    def raw(self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor) -> Tensor:
        z, e, _ = self._inputs(x_hat, x_ref)
        w1 = self.w1(z).unflatten(-1, (self.rank, N_ERR))
        w2 = self.w2(z).unflatten(-1, (N_U, self.rank))
        h = torch.tanh(_apply(w1, e))
        return u_ref + _apply(w2, h)

    def raw_with_tangents(
        self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor, dx_hat: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Hand-written forward mode: ``(u (*batch, 2), du (K, *batch, 2))`` along ``dx_hat (K, *batch, nx)``.

        With ``s = W1 e``, ``h = tanh(s)``::

            ds = dW1 e + W1 de,   dh = (1 - h^2) ds,   du = dW2 h + W2 dh

        where ``dW1, dW2`` come from the tangent pass through the MLPs along ``dz = (d theta_hat, d v_hat, 0, 0)``.
        """
        z, e, x_hat4 = self._inputs(x_hat, x_ref)
        dz = self._z_tangents(x_hat4, dx_hat[..., THETA], dx_hat[..., V])
        de = dx_hat[..., :N_ERR]
        o1, d1 = self.w1.forward_with_tangents(z, dz)
        o2, d2 = self.w2.forward_with_tangents(z, dz)
        w1, dw1 = o1.unflatten(-1, (self.rank, N_ERR)), d1.unflatten(-1, (self.rank, N_ERR))
        w2, dw2 = o2.unflatten(-1, (N_U, self.rank)), d2.unflatten(-1, (N_U, self.rank))
        h = torch.tanh(_apply(w1, e))
        if all(n == 1 for n in de.shape[1:-1]):  # tangents alike over the batch (the closed loop's): one product
            w1_de = torch.matmul(w1, de.reshape(-1, N_ERR).t()).movedim(-1, 0)
        else:
            w1_de = _apply(w1, de)
        ds = _apply(dw1, e) + w1_de
        dh = (1.0 - h * h) * ds
        u = u_ref + _apply(w2, h)
        du = _apply(dw2, h) + _apply(w2, dh)
        return u, du.expand(dx_hat.shape[0], *u.shape)

    def jacobian(self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor) -> tuple[Tensor, Tensor]:
        """Unclipped input and its Jacobian w.r.t. the measured state: ``(u (*b, 2), du/dx_hat[:4] (*b, 2, 4))``.

        ``K = W2 diag(1 - h^2) W1 + [0, 0, dK_theta, dK_v]``: the position columns come from the error alone, the
        heading and speed columns also from the dependence of ``W1, W2`` on ``z`` (two tangent passes).
        Differentiable w.r.t. the parameters (used by training).
        """
        z, e, x_hat4 = self._inputs(x_hat, x_ref)
        shape = (2, *([1] * (z.ndim - 1)))
        d_theta = torch.tensor([1.0, 0.0], dtype=z.dtype, device=z.device).reshape(shape)
        d_v = torch.tensor([0.0, 1.0], dtype=z.dtype, device=z.device).reshape(shape)
        dz = self._z_tangents(x_hat4, d_theta, d_v)  # tangent 0 along theta_hat, tangent 1 along v_hat
        o1, d1 = self.w1.forward_with_tangents(z, dz)
        o2, d2 = self.w2.forward_with_tangents(z, dz)
        w1, dw1 = o1.unflatten(-1, (self.rank, N_ERR)), d1.unflatten(-1, (self.rank, N_ERR))
        w2, dw2 = o2.unflatten(-1, (N_U, self.rank)), d2.unflatten(-1, (N_U, self.rank))
        h = torch.tanh((w1 * e.unsqueeze(-2)).sum(-1))
        g = 1.0 - h * h
        u = u_ref + (w2 * h.unsqueeze(-2)).sum(-1)
        k_err = w2 @ (g.unsqueeze(-1) * w1)  # (*b, 2, 4): derivative through e
        extra = (dw2 * h.unsqueeze(-2)).sum(-1) + (w2 * (g * (dw1 * e.unsqueeze(-2)).sum(-1)).unsqueeze(-2)).sum(-1)
        zero = torch.zeros_like(extra[0])
        cols = [zero, zero, zero, zero]
        cols[THETA], cols[V] = extra[0], extra[1]
        k = k_err + torch.stack(cols, dim=-1)
        u, k = torch.broadcast_tensors(u.unsqueeze(-1), k)
        return u[..., 0], k

    def extra_repr(self) -> str:
        a = self.architecture
        return f"hidden={a.hidden}, n_hidden={a.n_hidden}, rank={a.rank}"


class ContractionMetric(nn.Module):
    """Dual contraction metric ``W(x) = L L^T + w_lb I`` of the car (see the module docstring).

    Depends on ``(theta, v)`` of the true state ``x (*batch, nx >= 4)``; returns ``(*batch, 4, 4)`` matrices in the
    order ``(p_x, p_y, theta, v)``.
    """

    #: indices of the unactuated (p_x, p_y) and actuated (theta, v) states
    unactuated = (PX, PY)
    actuated = (THETA, V)

    def __init__(self, architecture: C3MArchitecture | None = None):
        super().__init__()
        self.architecture = architecture or C3MArchitecture()
        arch = self.architecture
        self.w_lb = float(arch.w_lb)
        self._features = _StateFeatures(arch)
        self.net = TanhMLP(arch.n_state_features, arch.metric_hidden, arch.metric_n_hidden, 8)
        #: constant factor of the unactuated block
        self.l_pp = nn.Parameter(torch.eye(2))

    def _z(self, x: Tensor) -> Tensor:
        return torch.stack(self._features(x[..., THETA], x[..., V]), dim=-1)

    def _assemble(self, l_pp: Tensor, out: Tensor) -> Tensor:
        """``L (*b, 4, 4)`` from the constant block ``(2, 2)`` (or zeros) and the network output ``(*b, 8)``."""
        batch = out.shape[:-1]
        top = torch.cat([l_pp.expand(*batch, 2, 2), out.new_zeros(*batch, 2, 2)], dim=-1)
        bottom = torch.cat([out[..., :4].unflatten(-1, (2, 2)), out[..., 4:].unflatten(-1, (2, 2))], dim=-1)
        return torch.cat([top, bottom], dim=-2)

    def factor(self, x: Tensor) -> Tensor:
        """``L(x) (*batch, 4, 4)``."""
        return self._assemble(self.l_pp.to(x), self.net(self._z(x)))

    def forward(self, x: Tensor) -> Tensor:
        el = self.factor(x)
        eye = torch.eye(4, dtype=el.dtype, device=el.device)
        return el @ el.transpose(-1, -2) + self.w_lb * eye

    def with_derivatives(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """``W (*b, 4, 4)`` and ``(dW/dtheta, dW/dv)`` stacked as ``(2, *b, 4, 4)`` (the only non-zero partials)."""
        z = self._z(x)
        shape = (2, *([1] * (z.ndim - 1)))
        d_theta = torch.tensor([1.0, 0.0], dtype=z.dtype, device=z.device).reshape(shape)
        d_v = torch.tensor([0.0, 1.0], dtype=z.dtype, device=z.device).reshape(shape)
        dzs = self._features.tangents(x[..., THETA], x[..., V], d_theta, d_v)
        dz = torch.stack(torch.broadcast_tensors(*dzs), dim=-1)
        out, dout = self.net.forward_with_tangents(z, dz)
        dout = dout.expand(2, *out.shape)
        el = self._assemble(self.l_pp.to(z), out)
        del_ = self._assemble(torch.zeros(2, 2, dtype=z.dtype, device=z.device), dout)
        eye = torch.eye(4, dtype=el.dtype, device=el.device)
        w = el @ el.transpose(-1, -2) + self.w_lb * eye
        dw = del_ @ el.transpose(-1, -2)
        dw = dw + dw.transpose(-1, -2)
        return w, dw


class C3MModel(nn.Module):
    """Controller and metric trained together; this is what a weights file stores."""

    def __init__(self, architecture: C3MArchitecture | None = None, car: CarConfig | None = None):
        super().__init__()
        self.architecture = architecture or C3MArchitecture()
        #: the car domain the model is for (boxes, input bounds and saturation)
        self.car = car or CarConfig()
        self.controller = C3MController(self.architecture, self.car)
        self.metric = ContractionMetric(self.architecture)


# ----------------------------------------------------------------------------------------------- weights files
def shipped_c3m_path() -> Path:
    """Path (``.pt``) of the controller weights shipped with the package."""
    return Path(str(resources.files("density_planner") / "weights" / f"{SHIPPED_C3M_WEIGHTS}.pt"))


def save_c3m_model(
    path: str | Path,
    model: C3MModel,
    *,
    config: dict[str, Any] | None = None,
    diagnostics: dict[str, Any] | None = None,
    command: str | None = None,
) -> tuple[Path, Path]:
    """Write ``NAME.pt`` + ``NAME.json`` (see :func:`density_planner.io.checkpoint.save_weights`)."""
    from ..io.checkpoint import save_weights

    return save_weights(
        path,
        model.state_dict(),
        kind=C3M_KIND,
        architecture=model.architecture.to_dict(),
        config=config,
        diagnostics=diagnostics,
        command=command,
    )


def load_c3m_model(
    path: str | Path | None = None, car: CarConfig | None = None
) -> tuple[C3MModel, dict[str, Any]]:
    """Load a weights file written by :func:`save_c3m_model` (default: the shipped weights).

    ``car`` defaults to the domain the weights were trained for (``training_config.domain`` of the JSON,
    ``"paper"`` when absent).

    The architecture is read from the JSON metadata; the ``state_dict`` is checked against the model it
    describes. Returns ``(model, meta)``; the model is in ``eval`` mode with ``requires_grad`` off.

    Raises:
        CheckpointError: missing, corrupt or mismatched files (the message names the file and the field).
    """
    from ..io.checkpoint import check_state_dict, load_weights, weights_paths

    path = shipped_c3m_path() if path is None else Path(path)
    pt_path, json_path = weights_paths(path)
    state, meta = load_weights(pt_path, kind=C3M_KIND)  # reads and validates both files
    try:
        arch = C3MArchitecture.from_dict(meta["architecture"])
    except ValueError as exc:
        raise CheckpointError(f"{json_path}: invalid architecture ({exc})") from exc
    if car is None:
        from ..systems.car import car_domain

        domain = (meta.get("training_config") or {}).get("domain", "paper")
        try:
            car = car_domain(domain)
        except ValueError as exc:
            raise CheckpointError(f"{json_path}: {exc}") from exc
    model = C3MModel(arch, car)
    check_state_dict(model, state, pt_path)
    model.load_state_dict(state)
    model.eval()
    model.requires_grad_(False)
    return model, meta


def load_c3m_controller(path: str | Path | None = None, car: CarConfig | None = None) -> C3MController:
    """The controller of a C3M weights file (default: the shipped weights), ready to use."""
    model, _ = load_c3m_model(path, car)
    return model.controller

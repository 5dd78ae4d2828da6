"""Learned density predictors: networks that replace the Liouville integration (paper §IV-A, §V).

Both architectures predict, for an initial error ``xe0 = x0 - x_ref(0)``, a reference start and the reference
parameters ``p``, the closed-loop error ``xe(t) = x(t) - x_ref(t)`` and the log-density ratio
``L(t) = log rho(x(t), t) - log rho0(x0) = -int_0^t div f_cl`` (paper Eq. (2)) on the planning grid
``t_k = k dt``, ``k = 0..T-1`` (T = 101, dt = 0.1 s), for any registered system:

* ``"pointwise"`` (the paper): an MLP (7 x 150, ReLU) of ``(xe0, reference start, t, p)`` that returns the
  outputs at one time ``t``; a trajectory needs ``T - 1`` evaluations per sample.
* ``"trajectory"`` (ours, the paper's future work): an MLP of ``(xe0, reference start, p)`` that returns the whole
  horizon, ``(T - 1) x n_out`` outputs (the car: 5), in one evaluation per sample.

Layout. The networks read a system's state through its own facts (:class:`DensityLayout`, built from the
:class:`~density_planner.systems.base.System` named by the architecture's ``system``): the planar position
(``position_indices``), the heading (``heading_index``) and the states a plan cannot know (``hidden_states``, the
car's heading bias). Below, ``nx`` is the state dimension; for the car (``px, py, theta, v, bias``) the features
and outputs are exactly those of the paper's set-up, for CommonRoad's kinematic single-track model (``px, py,
delta, v, psi``) the steering angle joins the speed.

Frames. Position errors are expressed in the frame of the reference at the same time, ``(e_long, e_lat) =
R(theta_ref(t))^T (p - p_ref(t))``, both for the initial error (frame of the reference start) and for the outputs
(rotated back with the exactly known reference heading ``theta_ref(t)``). The rotation of the world-frame error
with the reference heading is then no longer something the network has to learn (a system without heading keeps
world axes).

Inputs. The reference start enters through ``(cos theta_ref(0), sin theta_ref(0))`` and its other known states
(the car: ``v_ref(0)``; KS: ``delta_ref(0), v_ref(0)``), never its position: the closed loop is invariant to
translations (the controller sees position *errors*; its gains are scheduled on heading and speed), so the start
position carries no information, and leaving it out lets a predictor trained on the artificial map serve scenes
with any coordinates; the heading enters periodically. The features ``(xe0 [nx], cos, sin, other start states,
p [nu * S])`` are standardised with the mean and standard deviation of the training data (buffers ``in_mean``,
``in_std``; the pointwise net also gets ``(t - t_mid) / t_half``).

Outputs. Known parts are not learned: at ``t = 0`` the output is exactly ``(xe0, 0)``, and the errors of the
hidden states are constant (a bias does not change and the reference has none). The other error components (the
car: ``e_long, e_lat, e_theta, e_v``; KS: ``e_long, e_lat, e_delta, e_v, e_psi``) and ``L`` are predicted as a
per-time linear baseline plus a scaled network residual::

    y_k = A_k f + b_k + s_k * net(f)_k          (per output channel)

with ``A_k, b_k`` the least-squares fit of ``y_k`` on the standardised features ``f`` over the training data and
``s_k`` the standard deviation of what the fit leaves (buffers ``base_weight``, ``base_bias``, ``out_scale``).
This is the output normalisation: the network's targets ``(y_k - A_k f - b_k) / s_k`` have unit variance at every
time step and channel (errors shrink over time under the contraction controller, the log-density ratio grows),
and an untrained network (its last layer starts at zero) already predicts the linear baseline. The pointwise net
interpolates the tables linearly in ``t``.

:class:`LearnedDensity` wraps a trained network as a :class:`~density_planner.density.base.DensityPredictor`:
``x(t) = x_ref(t) + xe(t)``, ``log rho(t) = log rho0 + L(t)``, differentiable w.r.t. the reference parameters
and start (the planner's second stage backpropagates through it).
"""

from __future__ import annotations

import functools
import hashlib
import logging
import math
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..control.reference import Reference
from ..errors import CheckpointError, DomainError
from ..systems.base import System
from .base import DensityPredictor, DensityTrajectory, expand_log_rho0, expand_samples

__all__ = [
    "ARCHITECTURES",
    "DENSITY_KIND",
    "DensityLayout",
    "DensityNetArchitecture",
    "DensityNetwork",
    "LearnedDensity",
    "controller_fingerprint",
    "shipped_density_path",
    "save_density_model",
    "load_density_model",
]

logger = logging.getLogger(__name__)

Arch = Literal["pointwise", "trajectory"]
ARCHITECTURES: tuple[str, ...] = ("trajectory", "pointwise")
#: ``kind`` entry of the weights' JSON metadata
DENSITY_KIND = "density_predictor"


@dataclass(frozen=True)
class DensityLayout:
    """Where a learned predictor finds its inputs and outputs in a system's state: the system's own facts
    (:meth:`of`), never indices of one vehicle model."""

    #: state dimension
    nx: int
    #: indices of the planar position (rotated into the reference's frame)
    position: tuple[int, int]
    #: index of the heading (``None``: no heading; world axes, no heading features)
    heading: int | None
    #: states a plan cannot know (constant error, not learned, not a reference feature)
    hidden: tuple[int, ...]
    #: index of the speed (``None``: none); the training domain is a range of reference start speeds
    speed: int | None = None

    @classmethod
    def of(cls, system: System) -> DensityLayout:
        return cls(system.nx, (int(system.position_indices[0]), int(system.position_indices[1])),
                   system.heading_index, tuple(system.hidden_states), system.speed_index)

    @property
    def rest(self) -> tuple[int, ...]:
        """The non-position states, in state order: the sample features after ``(e_long, e_lat)``."""
        return tuple(i for i in range(self.nx) if i not in self.position)

    @property
    def learned(self) -> tuple[int, ...]:
        """Non-position states whose errors the network predicts (all but the hidden ones), in state order."""
        return tuple(i for i in self.rest if i not in self.hidden)

    @property
    def reference_states(self) -> tuple[int, ...]:
        """States of the reference start that enter as features besides the heading's cos / sin."""
        return tuple(i for i in self.learned if i != self.heading)

    @property
    def n_learned(self) -> int:
        """Error channels per time step: ``(e_long, e_lat)`` and :attr:`learned`."""
        return 2 + len(self.learned)

    @property
    def n_out(self) -> int:
        """Outputs per time step: the error channels and the log-density ratio (the last one)."""
        return self.n_learned + 1

    @property
    def n_reference_start(self) -> int:
        """Reference-start features: cos and sin of the heading (if any) and :attr:`reference_states`."""
        return (0 if self.heading is None else 2) + len(self.reference_states)


@functools.cache
def system_layout(name: str) -> DensityLayout:
    """The :class:`DensityLayout` of the registered system ``name``."""
    from ..systems.registry import make_system

    return DensityLayout.of(make_system(name))


_ACTIVATIONS = {"relu": nn.ReLU, "silu": nn.SiLU, "tanh": nn.Tanh}


@dataclass(frozen=True)
class DensityNetArchitecture:
    """Everything that determines the ``state_dict`` of a :class:`DensityNetwork` (checked on loading)."""

    #: "pointwise" (one time per evaluation, the paper) or "trajectory" (the whole horizon per evaluation)
    arch: Arch = "trajectory"
    #: width of the hidden layers
    hidden: int = 256
    #: number of hidden layers
    layers: int = 3
    #: activation of the hidden layers: "relu", "silu" or "tanh"
    activation: Literal["relu", "silu", "tanh"] = "silu"
    #: points of the planning grid including t = 0
    n_times: int = 101
    #: step of the planning grid [s]
    dt: float = 0.1
    #: reference inputs (channels) and segments per channel: the parameter vector has nu * n_segments entries
    nu: int = 2
    n_segments: int = 10
    #: registered system whose states the network reads and predicts (:class:`DensityLayout`); weights written
    #: before other systems existed are the car's
    system: str = "car"

    def __post_init__(self) -> None:
        if self.arch not in ARCHITECTURES:
            raise ValueError(f"arch must be one of {list(ARCHITECTURES)}, got {self.arch!r}")
        if self.activation not in _ACTIVATIONS:
            raise ValueError(f"activation must be one of {list(_ACTIVATIONS)}, got {self.activation!r}")
        for name in ("hidden", "layers", "n_times", "nu", "n_segments"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if self.n_times < 2:
            raise ValueError(f"n_times must be >= 2, got {self.n_times}")
        if not (math.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"dt must be > 0, got {self.dt!r}")
        self.layout  # noqa: B018 - an unknown system fails here, with the valid choices

    @classmethod
    def default(cls, arch: Arch) -> DensityNetArchitecture:
        """The default sizes: pointwise 7 x 150 ReLU (the paper), trajectory head 3 x 256 SiLU (the paper set's;
        a shipped model set may differ: its JSON file records the architecture and the training command)."""
        if arch == "pointwise":
            return cls(arch="pointwise", hidden=150, layers=7, activation="relu")
        return cls(arch=arch)

    @property
    def layout(self) -> DensityLayout:
        return system_layout(self.system)

    @property
    def n_out(self) -> int:
        """Outputs per time step (error channels and the log-density ratio)."""
        return self.layout.n_out

    @property
    def n_sample_features(self) -> int:
        return self.layout.nx

    @property
    def n_reference_features(self) -> int:
        return self.layout.n_reference_start + self.nu * self.n_segments

    @property
    def n_features(self) -> int:
        return self.n_sample_features + self.n_reference_features

    @property
    def horizon(self) -> float:
        return (self.n_times - 1) * self.dt

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DensityNetArchitecture:
        from ..config import from_dict

        return from_dict(cls, data)


class DensityNetwork(nn.Module):
    """Network with its input/output normalisation (see the module docstring)."""

    # buffers (registered in __init__; stored in the state_dict)
    in_mean: Tensor
    in_std: Tensor
    base_weight: Tensor
    base_bias: Tensor
    out_scale: Tensor

    def __init__(self, architecture: DensityNetArchitecture):
        super().__init__()
        a = self.architecture = architecture
        self.layout = a.layout
        n_in = a.n_features + (1 if a.arch == "pointwise" else 0)
        n_out = a.n_out * (a.n_times - 1) if a.arch == "trajectory" else a.n_out
        act = _ACTIVATIONS[a.activation]
        widths = [n_in] + [a.hidden] * a.layers
        self.first = nn.Linear(n_in, a.hidden)
        body: list[nn.Module] = [act()]
        for w_in, w_out in zip(widths[1:-1], widths[2:]):
            body += [nn.Linear(w_in, w_out), act()]
        self.body = nn.Sequential(*body)
        self.last = nn.Linear(a.hidden, n_out)
        nn.init.zeros_(self.last.weight)
        nn.init.zeros_(self.last.bias)
        f, t = a.n_features, a.n_times
        self.register_buffer("in_mean", torch.zeros(f))
        self.register_buffer("in_std", torch.ones(f))
        self.register_buffer("base_weight", torch.zeros(t, f, a.n_out))
        self.register_buffer("base_bias", torch.zeros(t, a.n_out))
        self.register_buffer("out_scale", torch.ones(t, a.n_out))

    # ------------------------------------------------------------------------------------------- features
    def features(self, xe0: Tensor, ref_start: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
        """Standardised sample features ``s (..., nx)`` and reference features ``r (..., R)`` for rows with one
        reference each (``xe0 (..., nx)``, ``ref_start (..., nx)``, ``params (..., nu, S)``)."""
        ns = self.architecture.n_sample_features
        s = (sample_features(xe0, ref_start, self.layout) - self.in_mean[:ns]) / self.in_std[:ns]
        r = (reference_features(ref_start, params, self.layout) - self.in_mean[ns:]) / self.in_std[ns:]
        return s, r

    def _sample_axis_features(self, xe0: Tensor, ref_start: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
        """Features for samples ``xe0 (*b, N, nx)`` of references ``(*b, nx)``: ``s (*b, N, nx)``, ``r (*b, 1, R)``."""
        s, r = self.features(xe0, ref_start.unsqueeze(-2), params.unsqueeze(-3))
        return s, r

    def _t_feature(self, t: Tensor) -> Tensor:
        half = 0.5 * self.architecture.horizon
        return (t - half) / half

    # --------------------------------------------------------------------------------------- normalisation
    def tables_at(self, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Baseline weight ``(K, F, O)``, bias ``(K, O)`` and scale ``(K, O)`` at times ``t (K,)`` (linear in t; ``O``
        outputs per time)."""
        a = self.architecture
        pos = (t / a.dt).clamp(0, a.n_times - 1)
        lo = pos.floor().long().clamp(max=a.n_times - 2)
        w = (pos - lo.to(pos.dtype)).to(self.base_weight.dtype)
        hi = lo + 1

        def interp(table: Tensor) -> Tensor:
            ww = w.reshape(-1, *([1] * (table.ndim - 1)))
            return table[lo] * (1 - ww) + table[hi] * ww

        return interp(self.base_weight), interp(self.base_bias), interp(self.out_scale)

    def baseline(self, s: Tensor, r: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
        """``A f + b`` for features split into ``s (..., nx)`` and ``r (..., R)``: ``(..., K, O)`` for tables of K
        times (``weight (K, F, O)``)."""
        ns = self.architecture.n_sample_features
        ys = torch.einsum("...f,kfo->...ko", s, weight[:, :ns])
        yr = torch.einsum("...f,kfo->...ko", r, weight[:, ns:])
        return ys + yr + bias

    # ---------------------------------------------------------------------------------------------- network
    def _trunk(self, first: Tensor) -> Tensor:
        return self.last(self.body(first))

    def raw_trajectory(self, s: Tensor, r: Tensor) -> Tensor:
        """Trajectory head: network output ``(..., T - 1, O)`` (normalised residual) for broadcastable ``s, r``."""
        ns = self.architecture.n_sample_features
        w, b = self.first.weight, self.first.bias
        h = F.linear(s, w[:, :ns]) + F.linear(r, w[:, ns:], b)
        out = self._trunk(h)
        return out.reshape(*out.shape[:-1], self.architecture.n_times - 1, self.architecture.n_out)

    def raw_pointwise(self, s: Tensor, r: Tensor, t: Tensor) -> Tensor:
        """Pointwise net: network output ``(..., O)`` (normalised residual) at times ``t`` (broadcastable)."""
        ns = self.architecture.n_sample_features
        nf = self.architecture.n_features
        w, b = self.first.weight, self.first.bias
        h = F.linear(s, w[:, :ns]) + F.linear(r, w[:, ns:nf], b) + self._t_feature(t).unsqueeze(-1) * w[:, nf]
        return self._trunk(h)

    def grid_outputs(self, s: Tensor, r: Tensor, states_only: bool = False) -> Tensor:
        """Outputs ``y (..., T - 1, O)`` (reference frame) at ``t_1 .. t_{T-1}`` from standardised features;
        ``states_only``: the trajectory head leaves out its last output, the log-density ratio (``(..., T - 1, O -
        1)``: a fifth of its last layer's work for the car).

        The trajectory head folds the baseline and the output scale into one affine map of the last hidden layer
        and the features (three matrix products, no per-time element-wise work)."""
        a = self.architecture
        t1, n_out = a.n_times - 1, a.n_out
        if a.arch == "trajectory":
            ns = a.n_sample_features
            w, b = self.first.weight, self.first.bias
            h = self.body(F.linear(s, w[:, :ns]) + F.linear(r, w[:, ns:], b))
            k = n_out - 1 if states_only else n_out  # outputs kept per time
            scale = self.out_scale[1:, :k]  # (T-1, k)
            weight = (scale.unsqueeze(-1) * self.last.weight.reshape(t1, n_out, -1)[:, :k]).reshape(t1 * k, -1)
            bias = (scale * self.last.bias.reshape(t1, n_out)[:, :k] + self.base_bias[1:, :k]).reshape(-1)
            base = self.base_weight[1:, :, :k].permute(0, 2, 1).reshape(t1 * k, -1)  # (T-1 * k, F)
            y = F.linear(h, weight, bias) + F.linear(s, base[:, :ns]) + F.linear(r, base[:, ns:])
            return y.reshape(*y.shape[:-1], t1, k)
        t = torch.arange(1, a.n_times, dtype=s.dtype, device=s.device) * a.dt
        net = self.raw_pointwise(s.unsqueeze(-2), r.unsqueeze(-2), t)  # (..., T-1, O)
        return self.baseline(s, r, self.base_weight[1:], self.base_bias[1:]) + self.out_scale[1:] * net

    def forward(self, xe0: Tensor, ref_start: Tensor, params: Tensor, ref_heading: Tensor,
                states_only: bool = False) -> tuple[Tensor, Tensor]:
        """Predictions on the full grid for samples ``xe0 (*b, N, nx)`` of references ``ref_start (*b, nx)``,
        ``params (*b, nu, S)`` with headings ``ref_heading (*b, T)`` on the grid (zeros for a system without
        heading): world-frame error ``xe (*b, N, T, nx)`` and log-density ratio ``L (*b, N, T)`` (NaN after
        ``t = 0`` with ``states_only`` for the trajectory head, which then skips that output)."""
        s, r = self._sample_axis_features(xe0, ref_start, params)
        y = self.grid_outputs(s, r, states_only=states_only)
        xe_rest, lr_rest = outputs_to_errors(y, xe0, ref_heading[..., 1:].unsqueeze(-2), self.layout)
        xe = torch.cat([xe0.unsqueeze(-2), xe_rest], dim=-2)
        log_ratio = torch.cat([lr_rest.new_zeros(*lr_rest.shape[:-1], 1), lr_rest], dim=-1)
        return xe, log_ratio

    def predict_at(self, xe0: Tensor, ref_start: Tensor, params: Tensor, t: Tensor,
                   ref_heading_t: Tensor) -> tuple[Tensor, Tensor]:
        """Evaluation at arbitrary times ``t (K,)`` in ``[0, horizon]`` (reference headings ``ref_heading_t
        (*b, K)`` at those times): ``xe (*b, N, K, nx)``, ``L (*b, N, K)``. The pointwise net evaluates at ``t``
        directly; the trajectory head interpolates its grid outputs linearly."""
        a = self.architecture
        s, r = self._sample_axis_features(xe0, ref_start, params)
        if a.arch == "trajectory":
            y_grid = self.grid_outputs(s, r)
            y0 = self._initial_outputs(xe0, ref_start)  # exact outputs at t = 0
            y_grid = torch.cat([y0.unsqueeze(-2), y_grid], dim=-2)  # (*b, N, T, O) in the reference frame
            pos = (t / a.dt).clamp(0, a.n_times - 1)
            lo = pos.floor().long().clamp(max=a.n_times - 2)
            w = (pos - lo.to(pos.dtype)).to(y_grid.dtype).unsqueeze(-1)
            y = y_grid[..., lo, :] * (1 - w) + y_grid[..., lo + 1, :] * w
        else:
            weight, bias, scale = self.tables_at(t)
            net = self.raw_pointwise(s.unsqueeze(-2), r.unsqueeze(-2), t.to(s.dtype))
            y = self.baseline(s, r, weight, bias) + scale * net
            y0 = self._initial_outputs(xe0, ref_start).unsqueeze(-2)
            y = torch.where((t == 0).reshape(-1, 1), y0, y)  # t = 0 is known exactly
        return outputs_to_errors(y, xe0, ref_heading_t.unsqueeze(-2), self.layout)

    def _initial_outputs(self, xe0: Tensor, ref_start: Tensor) -> Tensor:
        """The exact outputs at ``t = 0`` ``(*b, N, O)``: the initial error's learned channels in the frame of the
        reference start, log-density ratio 0."""
        lay = self.layout
        body0 = sample_features(xe0, ref_start.unsqueeze(-2), lay)
        body0 = _pick(body0, (0, 1, *(2 + lay.rest.index(i) for i in lay.learned)))
        return torch.cat([body0, body0.new_zeros(*body0.shape[:-1], 1)], dim=-1)


# ---------------------------------------------------------------------------------------------- transforms
def to_reference_frame(dx: Tensor, dy: Tensor, heading: Tensor) -> tuple[Tensor, Tensor]:
    """Longitudinal and lateral components of a world-frame position error in the frame of ``heading``."""
    c, s = torch.cos(heading), torch.sin(heading)
    return c * dx + s * dy, -s * dx + c * dy


def from_reference_frame(e_long: Tensor, e_lat: Tensor, heading: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse of :func:`to_reference_frame`."""
    c, s = torch.cos(heading), torch.sin(heading)
    return c * e_long - s * e_lat, s * e_long + c * e_lat


def _heading(x: Tensor, layout: DensityLayout) -> Tensor:
    """Heading of states ``x (..., nx)`` (zeros for a system without heading: world axes)."""
    if layout.heading is None:
        return x.new_zeros(x.shape[:-1])
    return x[..., layout.heading]


def _pick(x: Tensor, indices: tuple[int, ...]) -> Tensor:
    """``x[..., indices]``, as a slice (a view, the same arithmetic) when the indices are consecutive."""
    if indices and list(indices) == list(range(indices[0], indices[0] + len(indices))):
        return x[..., indices[0]: indices[0] + len(indices)]
    return x[..., list(indices)]


def sample_features(xe0: Tensor, ref_start: Tensor, layout: DensityLayout) -> Tensor:
    """Initial error ``(..., nx)`` with its position part in the frame of the reference start (``ref_start``
    broadcasts with ``xe0``): ``(e_long, e_lat, the other components in state order)``."""
    i, j = layout.position
    el, et = to_reference_frame(xe0[..., i], xe0[..., j], _heading(ref_start, layout))
    return torch.cat([el.unsqueeze(-1), et.unsqueeze(-1), _pick(xe0, layout.rest)], dim=-1)


def reference_features(ref_start: Tensor, params: Tensor, layout: DensityLayout) -> Tensor:
    """``(cos theta_ref(0), sin theta_ref(0), the other known start states, p flattened)``, ``(..., R)``; the car:
    ``(cos, sin, v_ref(0), p)``."""
    parts = []
    if layout.heading is not None:
        th = ref_start[..., layout.heading]
        parts += [torch.cos(th), torch.sin(th)]
    parts += [ref_start[..., k] for k in layout.reference_states]
    return torch.cat([torch.stack(parts, dim=-1), params.flatten(-2)], dim=-1)


def errors_to_outputs(xe: Tensor, log_ratio: Tensor, ref_heading: Tensor, layout: DensityLayout) -> Tensor:
    """Learned outputs ``(..., T, O)`` = ``(e_long, e_lat, the learned components, L)`` of world-frame errors
    ``xe (..., T, nx)``, log-density ratios ``(..., T)`` and reference headings ``(..., T)``."""
    i, j = layout.position
    el, et = to_reference_frame(xe[..., i], xe[..., j], ref_heading)
    return torch.stack([el, et, *(xe[..., k] for k in layout.learned), log_ratio], dim=-1)


def outputs_to_errors(y: Tensor, xe0: Tensor, ref_heading: Tensor,
                      layout: DensityLayout) -> tuple[Tensor, Tensor]:
    """World-frame errors ``(..., K, nx)`` (hidden components copied from ``xe0``) and log-density ratios
    ``(..., K)`` from outputs ``y (..., K, O)`` (NaN from outputs without the last, ``(..., K, O - 1)``);
    ``ref_heading`` broadcasts to ``y.shape[:-1]``."""
    dx, dy = from_reference_frame(y[..., 0], y[..., 1], ref_heading)
    cols: list[Tensor | None] = [None] * layout.nx
    cols[layout.position[0]], cols[layout.position[1]] = dx, dy
    for c, k in enumerate(layout.learned):
        cols[k] = y[..., 2 + c]
    for k in layout.hidden:
        cols[k] = xe0[..., k].unsqueeze(-1).expand_as(dx)
    xe = torch.stack(cols, dim=-1)  # type: ignore[arg-type]
    if y.shape[-1] == layout.n_learned:  # the states only (DensityNetwork.grid_outputs): no log-density
        return xe, torch.full_like(dx, math.nan)
    return xe, y[..., layout.n_learned]


# -------------------------------------------------------------------------------------------------- predictor
def controller_fingerprint(controller: nn.Module) -> str:
    """Short hash identifying a tracking controller: its class, its parameters and buffers, and its gains (if any).

    A learned density predictor is only valid for the controller whose closed loop generated its training data.
    """
    from ..io.checkpoint import hash_state

    h = hashlib.sha256(type(controller).__name__.encode())
    hash_state(h, controller, dtype=torch.float32)
    gains = getattr(controller, "gains", None)
    if gains is not None:
        h.update(repr(gains).encode())
    saturation = getattr(controller, "saturation", None)
    if saturation is not None:  # the hard clip (None) leaves the fingerprints of older weights unchanged
        h.update(repr(saturation).encode())
    return h.hexdigest()[:16]


class LearnedDensity(DensityPredictor):
    """:class:`DensityPredictor` backed by a trained :class:`DensityNetwork` (either architecture)."""

    def __init__(self, model: DensityNetwork, *, meta: dict[str, Any] | None = None,
                 fallback: DensityPredictor | None = None):
        self.model = model.eval().requires_grad_(False)
        self.meta = dict(meta or {})
        self.name = model.architecture.arch
        #: predictor used (with a logged warning) for references outside the training domain; ``None``: refuse
        self.fallback = fallback
        #: the system's state layout the network reads
        self.layout = model.layout
        #: ``(v_min, v_max)`` of the reference start speeds of the training data [m/s] (``None``: unknown)
        self.speed_range = training_speed_range(self.meta, self.layout)

    def domain_problem(self, reference: Reference) -> str | None:
        """Why ``reference`` lies outside the training domain (its start speed outside the training data's range),
        or ``None`` when it lies inside."""
        if self.speed_range is None or self.layout.speed is None:
            return None
        lo, hi = self.speed_range
        par = reference.parameterization
        starts = self.windows(par.n_segments) if par.n_segments >= self.architecture.n_segments else [0]
        v = reference.x.detach()[..., [s * par.steps_per_segment for s in starts], self.layout.speed]
        floor = 0.0 if lo <= STANDSTILL_EXTENSION else lo - _SPEED_TOLERANCE
        bad = (v < floor) | (v > hi + _SPEED_TOLERANCE)
        if not bool(bad.any()):
            return None
        worst = float(v[bad].flatten()[0])
        return (f"reference start speed {worst:.2f} m/s lies outside the speed range [{lo:g}, {hi:g}] m/s the learned "
                f"density predictor {self.name!r} was trained on")

    @property
    def architecture(self) -> DensityNetArchitecture:
        return self.model.architecture

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> LearnedDensity:
        self.model = self.model.to(device=device, dtype=dtype)
        return self

    def mismatch(self, parameterization) -> str | None:
        """Why this predictor cannot predict along references of ``parameterization`` (a
        :class:`~density_planner.control.reference.PiecewiseConstantInputs`), or ``None`` when it can. A network
        never extrapolates in time: it serves the planning step and segment length it was trained for, over its
        own horizon, a shorter one of whole segments (one window with padded inputs, :meth:`_padded_window`) or a
        longer one, which it covers by chaining windows of its own horizon (:meth:`windows`)."""
        a, par = self.architecture, parameterization
        trained = (a.n_times - 1) * a.dt
        if (not math.isclose(par.plan_dt, a.dt, rel_tol=1e-6)
                or not math.isclose(par.segment_duration, trained / a.n_segments, rel_tol=1e-6)):
            return (
                f"the learned density predictor {self.name!r} is trained for a {trained:g}-s horizon ({a.n_times} "
                f"points of {a.dt:g} s, {a.n_segments} segments; other horizons of whole segments are padded or "
                f"chained); "
                f"this plan has {par.horizon:g} s ({par.n_plan} points of {par.plan_dt:g} s, {par.n_segments} "
                f"segments of {par.segment_duration:g} s)"
            )
        return None

    def windows(self, n_segments: int) -> list[int]:
        """First segments of the windows that cover a reference of ``n_segments`` segments.

        The network predicts ``a.n_segments`` segments from a window's start. A longer reference is covered by
        windows starting at ``0, S, 2 S, ...`` (``S`` = the trained segment count), the last one moved back so that
        it ends with the reference (it then overlaps the one before): every window reads genuine reference
        parameters, none padded. Each window starts from the state and log-density the previous one predicted at
        its first segment: the closed loop is time-invariant given the reference (the controller reads the error
        and the reference's state and input), so its flow over ``[t_s, t_s + H]`` is the network's flow from the
        reference state at ``t_s``.
        """
        size = self.architecture.n_segments
        starts = list(range(0, max(n_segments - size, 0) + 1, size))
        if starts[-1] + size < n_segments:
            starts.append(n_segments - size)
        return starts

    def check_parameterization(self, parameterization) -> None:
        """Raise :class:`ValueError` (naming the fix) when :meth:`mismatch` finds one."""
        reason = self.mismatch(parameterization)
        if reason is not None:
            raise ValueError(f"{reason}; use --density exact (exact Liouville) or the planning horizon the "
                             "predictor was trained for")

    def _check_reference(self, reference: Reference) -> None:
        if not isinstance(reference, Reference):
            raise ValueError(f"reference must be a Reference (see make_reference), got {type(reference).__name__}")
        a = self.architecture
        self.check_parameterization(reference.parameterization)
        if reference.params.shape[-2] != a.nu or reference.params.shape[-1] != reference.parameterization.n_segments:
            raise ValueError(
                f"the learned density predictor needs parameters of shape ({a.nu}, n_segments); the reference "
                f"has {tuple(reference.params.shape[-2:])} (use --density exact)"
            )

    def predict(self, x0: Tensor, log_rho0: Tensor, reference: Reference) -> DensityTrajectory:
        fallback = self._fallback_for(reference)
        if fallback is not None:
            return fallback.predict(x0, log_rho0, reference)
        return self._predict(x0, log_rho0, reference)

    def predict_states(self, x0: Tensor, log_rho0: Tensor, reference: Reference) -> DensityTrajectory:
        """The network's prediction without the log-densities along the trajectories (NaN after ``t = 0``: the
        trajectory head skips that output, a fifth of its last layer's work for the car; the pointwise net computes
        them anyway), or the fallback's :meth:`~DensityPredictor.predict_states` outside the training domain."""
        fallback = self._fallback_for(reference)
        if fallback is not None:
            return fallback.predict_states(x0, log_rho0, reference)
        return self._predict(x0, log_rho0, reference, states_only=True)

    def _fallback_for(self, reference: Reference) -> DensityPredictor | None:
        """``None`` when the network serves ``reference``; the fallback (warned once) outside its training domain;
        :class:`DomainError` there without one."""
        self._check_reference(reference)
        problem = self.domain_problem(reference)
        if problem is None:
            return None
        if self.fallback is None:
            raise DomainError(f"{problem}; use --density exact or a predictor trained for this domain "
                              "(--models road for road traffic)")
        if not self._warned:
            logger.warning("%s: using exact Liouville instead", problem)
            self._warned = True
        return self.fallback

    def _predict(self, x0: Tensor, log_rho0: Tensor, reference: Reference,
                 states_only: bool = False) -> DensityTrajectory:
        dtype, device = reference.x.dtype, reference.x.device
        x0 = expand_samples(x0, reference, self.layout.nx)
        log_rho0 = expand_log_rho0(log_rho0, x0)
        p = next(self.model.parameters())
        if p.dtype != dtype or p.device != device:
            self.model = self.model.to(device=device, dtype=dtype)
        # windows of the trained horizon (see windows(); one for a reference of that horizon), each starting from
        # the prediction at its first segment
        par, size = reference.parameterization, self.architecture.n_segments
        per_seg = par.steps_per_segment // par.plan_stride  # planning points per segment
        if par.n_segments < size:  # a shorter reference: one window, padded (see _padded_window)
            xe, lr = self._padded_window(x0, reference, size, per_seg, states_only)
            return DensityTrajectory(t=reference.t_plan, x=reference.x_plan.unsqueeze(-3) + xe,
                                     log_rho=log_rho0.unsqueeze(-1) + lr, log_rho0=log_rho0)
        x_start, log_start = x0, torch.zeros_like(x0[..., 0])
        inputs = reference.segment_inputs  # the applied inputs (a reference that stops stands: no braking at rest)
        xs, logs, prev, covered = [], [], None, 0
        for first in self.windows(par.n_segments):
            k0 = first * per_seg
            if prev is not None:  # the previous window's prediction at this window's start
                px, plog, pk0 = prev
                x_start, log_start = px[..., k0 - pk0, :], plog[..., k0 - pk0]
            ref_x = reference.x_plan[..., k0:k0 + size * per_seg + 1, :]
            ref_start = reference.start if prev is None else ref_x[..., 0, :]  # the first: no roll-out graph
            xe, lr = self._window(x_start, ref_start, inputs[..., first:first + size], ref_x, states_only)
            wx, wlog = ref_x.unsqueeze(-3) + xe, log_start.unsqueeze(-1) + lr
            keep = 0 if prev is None else (covered - first) * per_seg + 1  # points not yet predicted
            xs.append(wx[..., keep:, :])
            logs.append(wlog[..., keep:])
            prev, covered = (wx, wlog, k0), first + size
        x = xs[0] if len(xs) == 1 else torch.cat(xs, dim=-2)
        log_ratio = logs[0] if len(logs) == 1 else torch.cat(logs, dim=-1)
        return DensityTrajectory(t=reference.t_plan, x=x, log_rho=log_rho0.unsqueeze(-1) + log_ratio,
                                 log_rho0=log_rho0)

    def _padded_window(self, x0: Tensor, reference: Reference, size: int, per_seg: int,
                       states_only: bool = False) -> tuple[Tensor, Tensor]:
        """Errors and log-density ratios over a reference of fewer segments than the trained ``size``: the window
        reads the reference's parameters followed by zero inputs (the mode of the training references' inputs,
        which are clamped normal draws) and predicts its whole horizon, of which the reference's own points are
        kept. The closed loop is causal (the state at ``t`` does not depend on inputs after ``t``), so the padding
        changes nothing the exact flow would predict; the network learned that from references whose later
        inputs are independent of the earlier ones (measured: docs/density.md, ``benchmarks/bench_short_density.py``).
        Reference headings past the end (they only turn the discarded outputs into the world frame) repeat the
        last one."""
        par = reference.parameterization
        n = par.n_plan
        params = reference.segment_inputs
        pad = params.new_zeros(*params.shape[:-1], size - par.n_segments)
        x_plan = reference.x_plan
        tail = x_plan[..., -1:, :].expand(*x_plan.shape[:-2], size * per_seg + 1 - n, x_plan.shape[-1])
        xe, lr = self._window(x0, reference.start, torch.cat([params, pad], dim=-1), torch.cat([x_plan, tail], -2),
                              states_only)
        return xe[..., :n, :], lr[..., :n]

    def _window(self, x0: Tensor, start: Tensor, params: Tensor, x_plan: Tensor,
                states_only: bool = False) -> tuple[Tensor, Tensor]:
        """Errors ``(*batch, N, T, nx)`` and log-density ratios ``(*batch, N, T)`` over one trained horizon from
        states ``x0 (*batch, N, nx)``, along the reference that starts at ``start`` with ``params`` (planning-grid
        states ``x_plan``; ``states_only``: see :meth:`predict_states`)."""
        return self.model(x0 - start.unsqueeze(-2), start, params, _heading(x_plan, self.layout), states_only)

    _warned = False


#: reference start speeds this far outside the training range [m/s] are still accepted (float rounding, the
#: planner's start mean against the data's sampled box edge)
_SPEED_TOLERANCE = 0.05

#: a predictor trained from start speeds of at most this much [m/s] also serves starts down to standstill (v = 0).
#: ``benchmarks/bench_standstill_density.py`` measures the road car's shipped trajectory head against exact Liouville
#: per band of start speed (figures in docs/planner.md, "Stopped starts"): below 0.5 m/s its position error is of
#: the same size as at 0.5-2 m/s. Stopped starts otherwise planned with exact Liouville (3-6 min instead of seconds).
STANDSTILL_EXTENSION = 0.5


def training_speed_range(meta: dict[str, Any], layout: DensityLayout | None = None) -> tuple[float, float] | None:
    """``(v_min, v_max)`` of the reference start speeds of a predictor's training data (from its JSON ``data``
    entry; ``layout``: the predictor's system, default the car), or ``None`` when the JSON does not record it or the
    system has no speed state."""
    layout = layout or system_layout("car")
    cfg = ((meta or {}).get("data") or {}).get("config") or {}
    lo, hi = cfg.get("start_low"), cfg.get("start_high")
    if lo is None or hi is None or layout.speed is None or len(lo) != layout.nx or len(hi) != layout.nx:
        return None
    return float(lo[layout.speed]), float(hi[layout.speed])


# ------------------------------------------------------------------------------------------------------ files
def shipped_density_path(arch: str, models: str = "paper") -> Path:
    """Path (``.pt``) of the shipped weights of ``arch`` ("trajectory" or "pointwise") of a model set."""
    if arch not in ARCHITECTURES:
        raise ValueError(f"unknown density architecture {arch!r}; valid choices: {', '.join(ARCHITECTURES)}")
    from ..control.registry import model_set

    suffix = model_set(models).density_suffix
    return Path(str(resources.files("density_planner") / "weights" / f"density_{arch}{suffix}.pt"))


def save_density_model(
    path: str | Path,
    model: DensityNetwork,
    *,
    config: dict[str, Any] | None = None,
    diagnostics: dict[str, Any] | None = None,
    command: str | None = None,
    extra: dict[str, Any] | None = None,
) -> tuple[Path, Path]:
    """Write ``NAME.pt`` (state_dict, normalisation included) and ``NAME.json`` (architecture, training
    configuration, diagnostics, command, and ``extra`` such as the controller fingerprint and data sizes)."""
    from ..io.checkpoint import save_weights

    return save_weights(path, model.state_dict(), kind=DENSITY_KIND, architecture=model.architecture.to_dict(),
                        config=config, diagnostics=diagnostics, command=command, extra=extra)


def load_density_model(path: str | Path, *, arch: str | None = None) -> tuple[DensityNetwork, dict[str, Any]]:
    """Load a weights file written by :func:`save_density_model`; ``arch`` (if given) must match.

    Returns ``(model, meta)`` with the model in ``eval`` mode.

    Raises:
        CheckpointError: missing, corrupt or mismatched files (wrong kind, wrong architecture, bad state_dict).
    """
    from ..io.checkpoint import check_state_dict, load_weights, weights_paths

    pt_path, json_path = weights_paths(path)
    state, meta = load_weights(pt_path, kind=DENSITY_KIND)
    try:
        architecture = DensityNetArchitecture.from_dict(meta["architecture"])
    except (ValueError, TypeError) as exc:
        raise CheckpointError(f"{json_path}: invalid architecture ({exc})") from exc
    if arch is not None and architecture.arch != arch:
        raise CheckpointError(
            f"{json_path}: the weights are of a {architecture.arch!r} density predictor, expected {arch!r}"
        )
    model = DensityNetwork(architecture)
    check_state_dict(model, state, pt_path)
    model.load_state_dict(state)
    bad = [k for k, v in state.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise CheckpointError(f"{pt_path}: non-finite values in {bad[:3]}")
    return model.eval(), meta

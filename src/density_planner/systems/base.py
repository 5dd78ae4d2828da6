"""System interface: continuous-time dynamics ``x' = f(x, u)`` on batch-first tensors.

All methods take tensors with any leading batch shape, ``x: (*batch, nx)`` and ``u: (*batch, nu)``, on any
device and floating dtype, and return tensors of the same dtype/device.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor

#: the exact Liouville schemes by name (:mod:`density_planner.density.integrators`: the fixed steps "euler" and
#: "rk4", the error-controlled pairs "rk43" and "dopri5"); a system names the one its closed loop needs
#: (:attr:`System.liouville_integrator`)
LiouvilleScheme = Literal["euler", "rk4", "rk43", "dopri5"]

__all__ = ["System", "ControlAffineSystem", "Footprint", "ConfigBoxes", "hold_speeds", "LiouvilleScheme"]


def hold_speeds(v: Tensor) -> Tensor:
    """Speeds ``v (..., K + 1)`` of an Euler roll-out made without the standstill hold -> those of the vehicle that
    stops instead of reversing, ``w_0 = v_0``, ``w_{k+1} = max(0, w_k + (v_{k+1} - v_k))`` (:meth:`System.standstill`
    after every step).

    Loop-free (Lindley's recursion): ``w_k = v_k - min(0, min_{1 <= j <= k} v_j)`` for ``k >= 1``, one cumulative
    minimum. Differentiable: where the hold is active the speed no longer depends on the braking that stopped it.
    Returns ``v`` itself when no speed after the first is negative (nothing to hold).
    """
    tail = v[..., 1:]
    if tail.numel() == 0 or not bool((tail < 0).any()):
        return v
    low = torch.cummin(tail, dim=-1).values.clamp(max=0.0)
    return torch.cat([v[..., :1], tail - low], dim=-1)


@dataclass(frozen=True)
class Footprint:
    """The vehicle's body: a rectangle ``length x width`` [m] centred on the position, its long side along the
    heading. ``0 x 0`` is a point (the paper's assumption). A system without heading needs ``length == width``
    (a disc of that diameter, or a point); how collision reads the body is decided in :mod:`density_planner.risk`.
    """

    #: extent along the heading [m]
    length: float = 0.0
    #: extent across the heading [m]
    width: float = 0.0

    def __post_init__(self) -> None:
        for name in ("length", "width"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"footprint {name} must be a finite number >= 0 [m], got {v!r}")

    @property
    def is_point(self) -> bool:
        return self.length == 0 and self.width == 0


class System(ABC):
    """A controlled dynamical system ``x' = f(x, u)``.

    Subclasses set :attr:`state_names`, :attr:`input_names` and the bounds, and implement :meth:`f`. The
    geometric facts used by collision checking live here too: which state entries are the position
    (:attr:`position_indices`) and the heading (:attr:`heading_index`, ``None`` when the system has none), and
    the body (:attr:`footprint`). Code outside the system reads positions with :meth:`positions`, never by
    indexing a state itself.
    """

    #: names of the state components, in order
    state_names: tuple[str, ...] = ()
    #: names of the input components, in order
    input_names: tuple[str, ...] = ()
    #: indices of the planar position (x, y) [m] in the state
    position_indices: tuple[int, int] = (0, 1)
    #: index of the heading [rad] in the state (counter-clockwise from the x axis), ``None`` without heading
    heading_index: int | None = None
    #: index of the speed [m/s] in the state, ``None`` when the system has no speed state
    speed_index: int | None = None
    #: index of the longitudinal acceleration [m/s^2] in the input, ``None`` when no input is one (its bounds give
    #: the reachable distance of road scenes)
    acceleration_input: int | None = None
    #: index of the input that sets the heading rate [rad/s] directly, ``None`` when none does (initial guesses
    #: of route-following references)
    turn_rate_input: int | None = None
    #: indices of states the vehicle cannot measure or know when it plans (the car's heading bias): a reference
    #: starts with them at 0 (:meth:`nominal_state`) and a replan keeps their initial law
    hidden_states: tuple[int, ...] = ()
    #: scale of the density planner's step sizes per input (``init_std``, ``lr``, ``update_clip`` are set for inputs
    #: of about +-3); ``None``: 1 for every input
    input_step_scale: tuple[float, ...] | None = None
    #: the body; a point unless the system says otherwise
    footprint: Footprint = Footprint()

    def positions(self, x: Tensor) -> Tensor:
        """Planar positions ``(..., 2)`` [m] of states ``x (..., nx)`` (a view when the indices are adjacent)."""
        i, j = self.position_indices
        if j == i + 1:
            return x[..., i:j + 1]
        return x[..., [i, j]]

    def headings(self, x: Tensor) -> Tensor | None:
        """Headings ``(...)`` [rad] of states ``x (..., nx)``, or ``None`` for a system without heading."""
        return None if self.heading_index is None else x[..., self.heading_index]

    def speeds(self, x: Tensor) -> Tensor | None:
        """Speeds ``(...)`` [m/s] of states ``x (..., nx)``, or ``None`` for a system without a speed state."""
        return None if self.speed_index is None else x[..., self.speed_index]

    @property
    def liouville_integrator(self) -> LiouvilleScheme:
        """The scheme of exact Liouville that this system's closed loop needs (the default of
        :attr:`~density_planner.density.liouville.LiouvilleConfig.integrator`): "rk4" (the default, a fixed step)
        or "rk43" / "dopri5" (error-controlled, for closed loops that turn within hundredths of a second)."""
        return "rk4"

    @property
    def speed_max(self) -> float:
        """Largest speed of the state box [m/s] (``inf`` without a speed state): starts above it lie outside the
        domain of the controller and of the density predictors trained for the system."""
        if self.speed_index is None:
            return math.inf
        return float(self.state_bounds[1][self.speed_index])

    # ------------------------------------------------------------ scene facts
    def state_from_pose(self, x: float, y: float, heading: float, speed: float) -> tuple[float, ...]:
        """The nominal state (``nx`` numbers) of a vehicle at position ``(x, y)`` [m] with ``heading`` [rad] and
        ``speed`` [m/s]: how a scene's start (a pose and a speed, :class:`~density_planner.environment.scene.Scene`)
        becomes a state. States the pose does not fix (a measurement bias, a steering angle) are 0.

        The default fills :attr:`position_indices`, :attr:`heading_index` and :attr:`speed_index`; a system without
        heading or speed state accepts only ``heading = 0`` / ``speed = 0``. Systems override it where a state
        needs more (e.g. wrapping the heading into the state box)."""
        state = [0.0] * self.nx
        state[self.position_indices[0]], state[self.position_indices[1]] = float(x), float(y)
        for name, index, value in (("heading", self.heading_index, heading), ("speed", self.speed_index, speed)):
            if index is not None:
                state[index] = float(value)
            elif value != 0:
                raise ValueError(f"{type(self).__name__} has no {name} state: a start with {name} {value:g} "
                                 "cannot be represented (use a system with one, e.g. --system car)")
        return tuple(state)

    def pose(self, x: Tensor) -> tuple[float, float, float, float]:
        """``(x, y, heading, speed)`` of one state ``x (nx,)``: the inverse of :meth:`state_from_pose` (heading and
        speed 0 for a system without them); a replan's scene starts there."""
        px, py = (float(v) for v in self.positions(x.detach()))
        h, v = self.headings(x.detach()), self.speeds(x.detach())
        return px, py, 0.0 if h is None else float(h), 0.0 if v is None else float(v)

    @property
    def standstill_index(self) -> int | None:
        """Index of the speed that :meth:`standstill` holds at 0 (``None``: the system can reverse or has no
        speed state)."""
        i = self.speed_index
        return None if i is None or float(self.state_bounds[0][i]) < 0 else i

    def standstill(self, x: Tensor) -> Tensor:
        """The plant's hold at rest: states ``x (..., nx)`` with a negative speed set to 0, for a vehicle that
        cannot reverse (a speed state whose box starts at 0 or above). A braking vehicle stops and stays stopped;
        the model ``x' = f(x, u)`` alone would carry it backwards when its controller brakes at low speed.

        Simulations of the *executed* vehicle (:func:`~density_planner.density.simulate_closed_loop` with
        ``plant=True``, the online runner) apply it after every integration step; the density propagation does
        not (it is the model's flow, whose Liouville equation needs a smooth field). Identity for systems without
        a speed state or with reverse speeds in their box."""
        i = self.standstill_index
        if i is None:
            return x
        return x.index_copy(-1, torch.tensor([i], device=x.device), x[..., i:i + 1].clamp(min=0.0))

    def nominal_state(self, x: Tensor) -> Tensor:
        """``x (..., nx)`` with the states a plan cannot know (:attr:`hidden_states`, e.g. a measurement bias) at 0:
        the start of the reference, i.e. of the nominal trajectory."""
        if not self.hidden_states:
            return x
        return x.index_fill(-1, torch.tensor(self.hidden_states, device=x.device), 0.0)

    @property
    def initial_error_max(self) -> tuple[float, ...]:
        """Half-widths (``nx``) of the box of initial-state uncertainty around a scene's start (the paper's XE0): the
        support of the default initial distribution (:meth:`~density_planner.planners.problem.PlanningProblem.
        from_scene`). Systems that plan from scenes define it."""
        raise NotImplementedError(
            f"{type(self).__name__} defines no initial-error box (initial_error_max); build the PlanningProblem "
            "with an explicit initial_distribution"
        )

    def planning_bounds(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(lower, upper) box (``nx`` each) that planned trajectories should stay in, apart from the position,
        which the scene's planning box bounds (the position entries here are infinite): the bounds cost J_B
        (paper Eq. (6)) penalises leaving it. Default: the state box."""
        lo, hi = (list(map(float, b)) for b in self.state_bounds)
        for i in self.position_indices:
            lo[i], hi[i] = -math.inf, math.inf
        return tuple(lo), tuple(hi)

    # ------------------------------------------------------ symbolic (NLP) form
    @property
    def nominal_indices(self) -> tuple[int, ...]:
        """The states an NLP baseline (MPC, oracle) models: all but :attr:`hidden_states`, in state order."""
        return tuple(i for i in range(self.nx) if i not in self.hidden_states)

    def nominal_index(self, i: int | None) -> int | None:
        """Position of state ``i`` in the nominal state vector of :meth:`f_symbolic` (``None`` passes through)."""
        return None if i is None else self.nominal_indices.index(i)

    def f_symbolic(self, x, u, ops):
        """``x'`` of the nominal states (:attr:`nominal_indices`; hidden states at 0) for symbolic vectors ``x`` and
        ``u`` of a modelling library: ``ops`` is its module (CasADi: ``casadi``, with ``cos``, ``sin``, ``tan``,
        ``vertcat``). NLP baselines need it; a system without it cannot be planned by them."""
        raise NotImplementedError(f"{type(self).__name__} has no symbolic dynamics (f_symbolic): the NLP baselines "
                                  "(MPC, oracle) cannot model it")

    @property
    def nx(self) -> int:
        """State dimension."""
        return len(self.state_names)

    @property
    def nu(self) -> int:
        """Input dimension."""
        return len(self.input_names)

    # ------------------------------------------------------------------ bounds
    @property
    @abstractmethod
    def state_bounds(self) -> tuple[Sequence[float], Sequence[float]]:
        """(lower, upper) validity box of the state, each of length ``nx`` (may contain +-inf)."""

    @property
    @abstractmethod
    def input_bounds(self) -> tuple[Sequence[float], Sequence[float]]:
        """(lower, upper) bounds of the input, each of length ``nu``."""

    @property
    def applied_input_bounds(self) -> tuple[Sequence[float], Sequence[float]]:
        """(lower, upper) bounds of the inputs the plant can actually receive (the actuators); the reference inputs
        stay inside :attr:`input_bounds`. Default: the same box."""
        return self.input_bounds

    def state_bounds_tensor(self, like: Tensor) -> tuple[Tensor, Tensor]:
        lo, hi = self.state_bounds
        return (torch.as_tensor(lo, dtype=like.dtype, device=like.device),
                torch.as_tensor(hi, dtype=like.dtype, device=like.device))

    def input_bounds_tensor(self, like: Tensor) -> tuple[Tensor, Tensor]:
        lo, hi = self.input_bounds
        return (torch.as_tensor(lo, dtype=like.dtype, device=like.device),
                torch.as_tensor(hi, dtype=like.dtype, device=like.device))

    def index(self, name: str) -> int:
        """Index of the state component called ``name``."""
        try:
            return self.state_names.index(name)
        except ValueError:
            raise ValueError(f"unknown state name {name!r}; valid names: {', '.join(self.state_names)}") from None

    # ---------------------------------------------------------------- dynamics
    @abstractmethod
    def f(self, x: Tensor, u: Tensor) -> Tensor:
        """Time derivative ``x'`` for states ``x (*batch, nx)`` and inputs ``u (*batch, nu)``."""

    def measure(self, x: Tensor) -> Tensor:
        """State as seen by the controller (default: the true state)."""
        return x

    def measure_jvp(self, x: Tensor, dx: Tensor) -> Tensor:
        """Directional derivative of :meth:`measure` at ``x`` along tangents ``dx (K, *batch, nx)``."""
        if type(self).measure is System.measure:
            return dx
        out = [torch.func.jvp(self.measure, (x,), (d.expand_as(x),))[1] for d in dx.unbind(0)]
        return torch.stack(out, 0)

    def rollout(self, x0: Tensor, u: Tensor, dt: float) -> Tensor:
        """Explicit-Euler open-loop rollout: ``x0 (*batch, nx)``, ``u (*batch, K, nu)`` -> ``(*batch, K+1, nx)``.

        The roll-out is the plant's: :meth:`standstill` holds a vehicle that cannot reverse at rest after every
        step (a reference that brakes to a stop stays stopped; :meth:`held_inputs` gives the inputs it applied).
        Generic version with a loop over the K steps; systems override it with a loop-free form where one exists.
        """
        batch = torch.broadcast_shapes(x0.shape[:-1], u.shape[:-2])
        x = x0.expand(*batch, x0.shape[-1])
        xs = [x]
        for k in range(u.shape[-2]):
            x = self.standstill(x + dt * self.f(x, u[..., k, :]))
            xs.append(x)
        return torch.stack(xs, dim=-2)

    def rollout_strided(self, x0: Tensor, u: Tensor, dt: float, stride: int) -> Tensor:
        """:meth:`rollout` returned only every ``stride``-th state: ``(*batch, K // stride + 1, nx)``."""
        return self.rollout(x0, u, dt)[..., ::stride, :]

    def held_speeds(self, v: Tensor) -> Tensor:
        """Speeds ``v (..., K + 1)`` of a roll-out computed without the hold -> those of this system's roll-out:
        :func:`hold_speeds` for a vehicle that cannot reverse (:attr:`standstill_index`), else ``v``. The loop-free
        roll-outs of the car and the single-track model call it."""
        return v if self.standstill_index is None else hold_speeds(v)

    def held_inputs(self, x: Tensor, u: Tensor, dt: float) -> Tensor:
        """The inputs ``(*batch, K, nu)`` a roll-out ``x (*batch, K + 1, nx)`` of ``u`` over steps ``dt`` applied:
        where :meth:`standstill` held the vehicle at rest, the acceleration input is replaced by the speed change it
        made, ``(v_{k+1} - v_k) / dt = -v_k / dt`` (0 while standing), so that a controller's feed-forward does not
        brake a reference that has stopped. Assumes the acceleration input drives the speed state (``v' = a``, the
        car and the single-track model); identity for systems without a standstill or an acceleration input, and
        for roll-outs that never stop."""
        i, a = self.standstill_index, self.acceleration_input
        if i is None or a is None:
            return u
        v = x[..., :-1, i]
        held = v + dt * u[..., a] < 0
        if not bool(held.any()):
            return u
        channel = torch.arange(u.shape[-1], device=u.device) == a
        return torch.where(held.unsqueeze(-1) & channel, (-v / dt).unsqueeze(-1), u)


class ControlAffineSystem(System):
    """``x' = a(x) + B(x) u``. Provides :meth:`f`; subclasses implement :meth:`drift` and :meth:`input_matrix`."""

    @abstractmethod
    def drift(self, x: Tensor) -> Tensor:
        """Drift ``a(x)``, shape ``(*batch, nx)``."""

    def input_matrix(self, x: Tensor) -> Tensor:
        """Input matrix ``B(x)``, shape ``(*batch, nx, nu)`` (or ``(nx, nu)`` when constant). Default: the
        :attr:`constant_input_matrix` on ``x``'s dtype and device; systems whose ``B`` depends on ``x`` override it."""
        if self.constant_input_matrix is None:
            raise NotImplementedError(f"{type(self).__name__} defines neither input_matrix nor constant_input_matrix")
        return torch.tensor(self.constant_input_matrix, dtype=x.dtype, device=x.device)

    #: ``B`` as a constant nested list when it does not depend on ``x`` (enables the structured divergence)
    constant_input_matrix: tuple[tuple[float, ...], ...] | None = None

    def f(self, x: Tensor, u: Tensor) -> Tensor:
        b = self.input_matrix(x)
        return self.drift(x) + (b @ u.unsqueeze(-1)).squeeze(-1)

    def drift_divergence(self, x: Tensor) -> Tensor:
        """``tr(da/dx)`` by forward-mode autodiff; systems override it with a closed form."""
        div = torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)
        eye = torch.eye(self.nx, dtype=x.dtype, device=x.device)
        for i in range(self.nx):
            d = torch.func.jvp(self.drift, (x,), (eye[i].expand_as(x),))[1]
            div = div + d[..., i]
        return div


class ConfigBoxes:
    """The boxes of a system whose configuration dataclass (``self.config``) holds them: ``state_min`` /
    ``state_max``, ``input_min`` / ``input_max``, ``actuator_min`` / ``actuator_max`` (``None``: the input box) and
    ``initial_error_max``. Mix it in before :class:`System` (the car and the KS model use it)."""

    config: Any

    @property
    def state_bounds(self) -> tuple[Sequence[float], Sequence[float]]:
        return self.config.state_min, self.config.state_max

    @property
    def input_bounds(self) -> tuple[Sequence[float], Sequence[float]]:
        return self.config.input_min, self.config.input_max

    @property
    def applied_input_bounds(self) -> tuple[Sequence[float], Sequence[float]]:
        """The actuator box where the controller saturates smoothly, else the input box."""
        if self.config.actuator_min is None:
            return self.input_bounds
        return self.config.actuator_min, self.config.actuator_max

    @property
    def initial_error_max(self) -> tuple[float, ...]:
        """The XE0 box of the domain (``config.initial_error_max``)."""
        return tuple(self.config.initial_error_max)

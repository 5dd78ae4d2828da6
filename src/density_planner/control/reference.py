"""Reference trajectories parameterised by piecewise-constant reference inputs (the planner's decision variables).

Parameters ``p`` have shape ``(*batch, nu, n_segments)``: for the car ``(B, 2, 10)``, ten values of ``omega``
and ten of ``a``, each held for one second. They define ``u_ref`` on the fine grid (0.01 s) and, by explicit
Euler integration of the nominal model from a start state, ``x_ref`` (``docs/spec.md`` §2). Both are also
available on the coarser planning grid (0.1 s). Everything is batched over the leading dimensions and
differentiable w.r.t. ``p`` and the start state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..checks import check_positive, check_tensor
from ..systems.base import System

__all__ = ["PiecewiseConstantInputs", "Reference", "make_reference", "plan_grid_reference"]


def _ratio(a: float, b: float, what: str) -> int:
    r = a / b
    n = round(r)
    if n < 1 or abs(r - n) > 1e-6 * max(1.0, abs(r)):
        raise ValueError(f"{what} ({a}) must be a positive integer multiple of {b}")
    return n


@dataclass(frozen=True)
class PiecewiseConstantInputs:
    """Input parameterisation: ``n_segments`` constant values per channel, each held ``segment_duration`` s."""

    #: number of piecewise-constant segments per input channel
    n_segments: int = 10
    #: duration of one segment [s]
    segment_duration: float = 1.0
    #: fine integration step of the reference [s]
    dt: float = 0.01
    #: step of the planning grid on which costs are evaluated [s]
    plan_dt: float = 0.1

    def __post_init__(self) -> None:
        if not isinstance(self.n_segments, int) or self.n_segments < 1:
            raise ValueError(f"n_segments must be a positive integer, got {self.n_segments!r}")
        check_positive("segment_duration", self.segment_duration)
        check_positive("dt", self.dt)
        check_positive("plan_dt", self.plan_dt)
        _ratio(self.segment_duration, self.dt, "segment_duration")
        _ratio(self.plan_dt, self.dt, "plan_dt")

    @property
    def steps_per_segment(self) -> int:
        return _ratio(self.segment_duration, self.dt, "segment_duration")

    @property
    def n_steps(self) -> int:
        """Number of fine steps over the horizon."""
        return self.n_segments * self.steps_per_segment

    @property
    def plan_stride(self) -> int:
        """Fine steps per planning step."""
        return _ratio(self.plan_dt, self.dt, "plan_dt")

    @property
    def horizon(self) -> float:
        """Total duration [s]."""
        return self.n_segments * self.segment_duration

    @property
    def n_plan(self) -> int:
        """Number of planning-grid points including t = 0 (101 for 10 s at 0.1 s)."""
        return self.n_steps // self.plan_stride + 1

    def inputs(self, params: Tensor) -> Tensor:
        """Fine-grid reference inputs ``(*batch, n_steps, nu)`` from ``params (*batch, nu, n_segments)``."""
        return torch.repeat_interleave(params, self.steps_per_segment, dim=-1).transpose(-1, -2)


@dataclass
class Reference:
    """A batch of reference trajectories on the fine grid with views on the planning grid.

    Attributes:
        params: ``(*batch, nu, n_segments)`` parameters.
        x: ``(*batch, K + 1, nx)`` reference states at ``t = k dt``.
        u: ``(*batch, K, nu)`` reference inputs, ``u[k]`` applied on ``[k dt, (k + 1) dt)``.
        parameterization: the :class:`PiecewiseConstantInputs` that produced them.
        origin: ``(*batch, nx)``, the start state as given to :func:`make_reference` (equal to ``x[..., 0, :]``,
            without the roll-out's autograd graph: a start that needs no gradient has none); ``None``: read ``x``.
    """

    params: Tensor
    x: Tensor
    u: Tensor
    parameterization: PiecewiseConstantInputs
    origin: Tensor | None = None

    @property
    def dt(self) -> float:
        return self.parameterization.dt

    @property
    def batch_shape(self) -> torch.Size:
        return self.x.shape[:-2]

    @property
    def n_steps(self) -> int:
        return self.u.shape[-2]

    @property
    def t(self) -> Tensor:
        """Fine time grid ``(K + 1,)``."""
        return torch.arange(self.n_steps + 1, dtype=self.x.dtype, device=self.x.device) * self.dt

    @property
    def x_plan(self) -> Tensor:
        """Reference states on the planning grid, ``(*batch, n_plan, nx)`` (101 points for 10 s at 0.1 s)."""
        return self.x[..., :: self.parameterization.plan_stride, :]

    @property
    def u_plan(self) -> Tensor:
        """Reference inputs sampled on the planning grid, ``(*batch, n_plan - 1, nu)``."""
        return self.u[..., :: self.parameterization.plan_stride, :]

    @property
    def t_plan(self) -> Tensor:
        stride = self.parameterization.plan_stride
        return self.t[::stride]

    @property
    def start(self) -> Tensor:
        """``(*batch, nx)``: the first state. Its gradient in the parameters is zero; read from :attr:`origin` where
        known, a backward pass skips the roll-out's graph there (the learned density predictors' sample features)."""
        return self.x[..., 0, :] if self.origin is None else self.origin

    @property
    def segment_inputs(self) -> Tensor:
        """``(*batch, nu, n_segments)``: per segment, the mean of the inputs the roll-out applied (``u``). Equal to
        ``params`` (exactly) where the reference never stops; where it stops (:meth:`System.held_inputs`), the mean
        braking that brought it to rest and 0 while it stands: the inputs consistent with ``x`` (what the learned
        density predictors read, trained on references whose inputs and states agree)."""
        par = self.parameterization
        applied = self.u - par.inputs(self.params)  # exactly 0 wherever the hold did not act
        if not bool((applied.detach() != 0).any()):  # never stopped: the parameters themselves (no extra graph)
            return self.params
        return self.params + applied.unflatten(-2, (par.n_segments, par.steps_per_segment)).mean(-2).transpose(-1, -2)

    def detach(self) -> Reference:
        return Reference(self.params.detach(), self.x.detach(), self.u.detach(), self.parameterization,
                         None if self.origin is None else self.origin.detach())

    def select(self, index) -> Reference:
        """Sub-batch ``reference.select(i)`` (indexing over the leading batch dimensions)."""
        return Reference(self.params[index], self.x[index], self.u[index], self.parameterization,
                         None if self.origin is None else self.origin[index])

    def stage_values(self, step_dt: float, n_steps: int, stages: tuple[float, ...]) -> tuple[Tensor, Tensor]:
        """Reference states and inputs at the stage times ``n * step_dt + c * step_dt`` of an integrator.

        States are interpolated linearly between fine-grid points (the Euler polygon of the reference, which is
        its exact continuous-time form); inputs are piecewise constant and taken as their left limit at a stage
        time that lies on a switching instant, so that every stage of one step sees the same input segment.

        Returns:
            ``x_ref (n_steps, n_stages, *batch, nx)`` and ``u_ref (n_steps, n_stages, *batch, nu)``.
        """
        ratio = step_dt / self.dt
        if n_steps * ratio > self.n_steps + 1e-6:
            raise ValueError(
                f"integration over {n_steps} steps of {step_dt} s exceeds the reference horizon "
                f"{self.n_steps * self.dt} s"
            )
        device = self.x.device
        steps = torch.arange(n_steps, dtype=torch.float64, device=device)
        c = torch.tensor(stages, dtype=torch.float64, device=device)
        pos = (steps[:, None] + c[None, :]) * ratio  # fine-grid position of each stage time
        lo, frac, u_idx = self._fine_grid_indices(pos, c[None, :] > 0)
        flat_lo, flat_u = lo.reshape(-1), u_idx.reshape(-1)
        x_lo = self.x.index_select(-2, flat_lo)
        x_hi = self.x.index_select(-2, flat_lo + 1)
        w = frac.reshape(-1, 1)
        x_stage = x_lo + w * (x_hi - x_lo)  # (*batch, S, nx)
        u_stage = self.u.index_select(-2, flat_u)
        x_stage = x_stage.movedim(-2, 0).reshape(n_steps, len(stages), *self.batch_shape, self.x.shape[-1])
        u_stage = u_stage.movedim(-2, 0).reshape(n_steps, len(stages), *self.batch_shape, self.u.shape[-1])
        return x_stage, u_stage

    def values_at(self, rows: Tensor, t: Tensor, left: Tensor | bool) -> tuple[Tensor, Tensor]:
        """Reference states and inputs at one time per row, for integrators whose rows keep their own clocks.

        ``rows (M,)`` index the references of a batch flattened to one dimension (``x (B, K + 1, nx)``), ``t (M,)``
        are times [s] (float64). The same convention as :meth:`stage_values`: states interpolated linearly on the
        fine grid, inputs piecewise constant; where ``left`` (a stage inside or at the end of a step), an input
        switching exactly at ``t`` is taken as its left limit, else (a step's first stage) as its right limit.

        Returns ``x_ref (M, nx)`` and ``u_ref (M, nu)``.
        """
        if self.x.ndim != 3:
            raise ValueError(f"values_at needs a batch flattened to one dimension, got x of shape "
                             f"{tuple(self.x.shape)}")
        lo, frac, u_idx = self._fine_grid_indices(t / self.dt, torch.as_tensor(left, device=t.device))
        b, k_x, nx = self.x.shape
        i_lo = rows * k_x + lo  # row-major positions: one gather each (faster than indexing by the index pair)
        flat_x = self.x.reshape(b * k_x, nx)
        x_lo = flat_x.index_select(0, i_lo)
        x_ref = x_lo + frac.unsqueeze(-1) * (flat_x.index_select(0, i_lo + 1) - x_lo)
        k_u = self.u.shape[1]
        return x_ref, self.u.reshape(b * k_u, -1).index_select(0, rows * k_u + u_idx)

    def switch_table(self) -> Tensor:
        """For a batch flattened to one dimension (``u (B, K, nu)``): ``(B, K + 1)`` long, at every fine-grid index
        ``j`` the first index ``j' >= j`` at which the input switches (``u[j'] != u[j' - 1]``), or ``K`` (the
        horizon) where none follows; read by :meth:`next_switch`."""
        b, k_max = self.u.shape[0], self.n_steps
        index = torch.full((b, k_max + 1), k_max, dtype=torch.long, device=self.u.device)
        changes = (self.u[:, 1:] != self.u[:, :-1]).any(-1)
        steps = torch.arange(1, k_max, device=self.u.device).expand(b, -1)
        index[:, 1:k_max] = torch.where(changes, steps, torch.full_like(steps, k_max))
        return index.flip(-1).cummin(-1).values.flip(-1)

    def next_switch(self, table: Tensor, rows: Tensor, t: Tensor) -> Tensor:
        """Time [s] (float64) of the first input switch strictly after ``t (M,)`` for references ``rows (M,)``,
        or the horizon where none follows; ``table`` from :meth:`switch_table`."""
        k_max = self.n_steps
        after = torch.clamp(torch.floor(t / self.dt + 1e-9).long() + 1, max=k_max)
        return table[rows, after].to(torch.float64) * self.dt

    def _fine_grid_indices(self, pos: Tensor, left: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """For fine-grid positions ``pos`` (time / dt, float64): the index of the fine-grid point below, the weight
        of the point above (in the states' dtype), and the index of the input segment (its left limit where
        ``left`` and ``pos`` lies on a switching instant, else its right limit); the convention of
        :meth:`stage_values` and :meth:`values_at`."""
        k_max = self.n_steps
        eps = 1e-9
        lo = torch.clamp(torch.floor(pos + eps), 0, k_max - 1).long()
        frac = (pos - lo).clamp(0.0, 1.0).to(self.x.dtype)
        u_idx = torch.where(left, torch.ceil(pos - eps) - 1, torch.floor(pos + eps))
        return lo, frac, torch.clamp(u_idx, 0, k_max - 1).long()


def _check_input_bounds(system: System, params: Tensor) -> None:
    """Reference inputs outside the system's input bounds are bad input (the controller and the learned models
    only cover the bounded inputs); 1e-6 of round-off is allowed."""
    bounds = getattr(system, "input_bounds", None)
    if bounds is None:
        return
    lo, hi = system.input_bounds_tensor(params)
    p = params.detach()
    tol = 1e-6 * (1.0 + torch.maximum(lo.abs(), hi.abs()))[:, None]
    if bool(((p < lo[:, None] - tol) | (p > hi[:, None] + tol)).any()):
        below = (lo[:, None] - p).amax().item()
        above = (p - hi[:, None]).amax().item()
        raise ValueError(
            f"params must lie within the input bounds of {type(system).__name__}: lower {lo.tolist()}, upper "
            f"{hi.tolist()} per channel (got values up to {max(below, above):.3g} outside); clip them first"
        )


def make_reference(
    system: System,
    start: Tensor,
    params: Tensor,
    parameterization: PiecewiseConstantInputs | None = None,
) -> Reference:
    """Reference trajectories of ``system`` from ``start (*batch, nx)`` for ``params (*batch, nu, n_segments)``.

    The state follows explicit Euler on the fine grid of the nominal model (``system.rollout``, loop-free for the
    car), held at rest once it stops when the system cannot reverse (:meth:`System.standstill`); ``u`` are then the
    inputs the roll-out applied (:meth:`System.held_inputs`: no braking feed-forward at rest), ``params`` the
    commanded ones. Leading dimensions of ``start`` and ``params`` broadcast.
    """
    par = parameterization or PiecewiseConstantInputs()
    params = check_tensor("params", params, last_dims=(system.nu, par.n_segments), min_ndim=2)
    _check_input_bounds(system, params)
    start = check_tensor("start", start, last_dims=(system.nx,), dtype=params.dtype, device=params.device)
    u = par.inputs(params)
    x = system.rollout(start, u, par.dt)
    batch = x.shape[:-2]
    u = system.held_inputs(x, u.expand(*batch, *u.shape[-2:]), par.dt)
    return Reference(params.expand(*batch, *params.shape[-2:]), x, u, par, start.expand(*batch, system.nx))


def plan_grid_reference(
    system: System,
    start: Tensor,
    params: Tensor,
    parameterization: PiecewiseConstantInputs | None = None,
) -> tuple[Tensor, Tensor]:
    """``(x_plan (*batch, n_plan, nx), u_plan (*batch, n_plan - 1, nu))``: :func:`make_reference` on the planning
    grid only (same values, cheaper; used where the fine grid is not needed, e.g. the planner's first stage)."""
    par = parameterization or PiecewiseConstantInputs()
    params = check_tensor("params", params, last_dims=(system.nu, par.n_segments), min_ndim=2)
    start = check_tensor("start", start, last_dims=(system.nx,), dtype=params.dtype, device=params.device)
    piecewise = getattr(system, "rollout_piecewise_strided", None)
    if par.steps_per_segment % par.plan_stride == 0:
        # every segment spans whole planning steps: no fine input sequence needed
        u_plan = torch.repeat_interleave(params, par.steps_per_segment // par.plan_stride, dim=-1).transpose(-1, -2)
        if piecewise is not None:
            x_plan = piecewise(start, params, par.dt, par.steps_per_segment, par.plan_stride)
        else:
            x_plan = system.rollout_strided(start, par.inputs(params), par.dt, par.plan_stride)
    else:
        u = par.inputs(params)
        x_plan = system.rollout_strided(start, u, par.dt, par.plan_stride)
        u_plan = u[..., :: par.plan_stride, :]
    u_plan = u_plan.expand(*x_plan.shape[:-2], *u_plan.shape[-2:])
    # the fine grid's applied input at each planning step (its first fine step), as make_reference samples it
    return x_plan, system.held_inputs(x_plan, u_plan, par.dt)


def horizon_steps(duration: float, dt: float) -> int:
    """Number of steps of size ``dt`` in ``duration`` (must divide exactly)."""
    n = duration / dt
    if abs(n - round(n)) > 1e-6 * max(1.0, n):
        raise ValueError(f"duration {duration} s is not a multiple of dt = {dt} s")
    return int(round(n)) if math.isfinite(n) else 0

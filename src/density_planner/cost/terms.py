"""Cost terms of the density planner (paper §IV-C, Eqs. (4)-(7)); each is a small callable object.

Every term takes a :class:`CostInputs` and returns one value per candidate, shape ``(*batch,)``, unweighted
(the weights ``alpha`` are applied by :class:`~density_planner.cost.composite.WeightedCost`). Sums over samples
use the per-time sample weights ``w_i(t_k)`` (normalised over the samples: ``sum_i w_i(t_k) = 1``), which are the
densities ``rho(x_i(t_k), t_k)`` of the paper (a single trajectory has weight 1).
"""

from __future__ import annotations

import functools
import math
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from ..environment.grid import OccupancyGrid
from ..memory import lazy_zeros
from ..risk.collision import CollisionModel

__all__ = ["CostInputs", "CostTerm", "GoalCost", "InputCost", "BoundsCost", "CollisionCost", "desired_positions"]


@dataclass
class CostInputs:
    """What the cost terms see.

    Attributes:
        x: ``(*batch, N, T, nx)`` sample states on the planning grid (``N = 1`` for a single trajectory).
        weights: ``(*batch, N, T)`` sample weights, summing to one over ``N`` at every time.
        u_ref: ``(*batch, T - 1, nu)`` reference inputs on the planning grid.
        slices: ``(T,)`` occupancy-grid slice of each planning time.
    """

    x: Tensor
    weights: Tensor
    u_ref: Tensor
    slices: Tensor

    def select(self, index) -> CostInputs:
        """Sub-batch along the first batch dimension (e.g. a boolean candidate mask)."""
        return CostInputs(x=self.x[index], weights=self.weights[index], u_ref=self.u_ref[index], slices=self.slices)

    @staticmethod
    def single(x: Tensor, u_ref: Tensor, slices: Tensor | None = None) -> CostInputs:
        """Inputs for single trajectories ``x (*batch, T, nx)`` with weight one (stage 1 of the planner)."""
        x = x.unsqueeze(-3)
        w = torch.ones(x.shape[:-1], dtype=x.dtype, device=x.device)
        if slices is None:
            slices = torch.arange(x.shape[-2], device=x.device)
        return CostInputs(x=x, weights=w, u_ref=u_ref, slices=slices)


class CostTerm:
    """A cost term ``J(inputs) -> (*batch,)``."""

    name: str = "term"

    def __call__(self, inputs: CostInputs) -> Tensor:  # pragma: no cover - interface
        raise NotImplementedError


class GoalCost(CostTerm):
    """``J_G = sum_i w_i(t_N) ||x_i(t_N) - x_G||^2_{Q_G}`` with ``Q_G = diag(1, 1, 0, 0, 0)`` (paper Eq. (4)) [m^2].

    ``far_factor`` multiplies ``J_G`` while it is at least ``close_threshold`` (the paper's code used 10 when
    ``J_G >= 3 m^2`` during optimisation; not in the paper). Use ``far_factor = 1`` to report the plain cost.
    """

    name = "goal"

    def __init__(self, goal: Sequence[float] | Tensor, *, far_factor: float = 1.0, close_threshold: float = 3.0,
                 positions: Callable[[Tensor], Tensor] | None = None):
        """``positions``: the system's position accessor (:meth:`System.positions`; default the first two
        state entries)."""
        self.positions = positions or (lambda x: x[..., 0:2])
        self.goal = torch.as_tensor(goal, dtype=torch.float64)
        if self.goal.shape != (2,):
            raise ValueError(f"goal must be a position (x, y), got shape {tuple(self.goal.shape)}")
        self.far_factor = float(far_factor)
        self.close_threshold = float(close_threshold)

    def __call__(self, inputs: CostInputs) -> Tensor:
        goal = self.goal.to(inputs.x)
        d2 = (self.positions(inputs.x[..., -1, :]) - goal).pow(2).sum(-1)  # (*batch, N)
        j = (inputs.weights[..., -1] * d2).sum(-1)
        if self.far_factor != 1.0:
            j = j * torch.where(j.detach() >= self.close_threshold, self.far_factor, 1.0)
        return j


class InputCost(CostTerm):
    """``J_I = sum_{k=0}^{N-1} ||u_ref(t_k)||^2_{Q_I}``, ``Q_I = I`` (paper Eq. (5)), on the 0.1-s grid."""

    name = "input"

    def __call__(self, inputs: CostInputs) -> Tensor:
        return inputs.u_ref.pow(2).sum(dim=(-1, -2))


class BoundsCost(CostTerm):
    """``J_B = sum_{i,k} w_i(t_k) (||x - x_min||^2_{Q_min} + ||x - x_max||^2_{Q_max})`` (paper Eq. (6)).

    Only violated components count (``Q_min``/``Q_max`` select them). Infinite bounds never count.
    """

    name = "bounds"

    def __init__(self, low: Sequence[float] | Tensor, high: Sequence[float] | Tensor):
        self.low = torch.as_tensor(low, dtype=torch.float64)
        self.high = torch.as_tensor(high, dtype=torch.float64)
        if self.low.shape != self.high.shape or self.low.ndim != 1:
            raise ValueError("bounds low and high must be vectors of the same length")
        if bool((self.low > self.high).any()):
            raise ValueError("bounds low must be <= high")
        self._cast: dict[tuple[torch.dtype, torch.device], tuple[Tensor, Tensor]] = {}  # bounds per dtype, device

    def violation(self, x: Tensor) -> Tensor:
        """Squared violation per sample and time, ``(*batch, N, T)``: the squared distance of ``x`` to the box,
        component by component (``x`` minus its clamp into the box; infinite bounds clamp nothing)."""
        low, high = self._bounds(x)
        return _box_excess(self._leading(x, low), low, high).square().sum(-1)

    def _bounds(self, x: Tensor) -> tuple[Tensor, Tensor]:
        key = (x.dtype, x.device)
        bounds = self._cast.get(key)
        if bounds is None:
            bounds = self._cast[key] = (self.low.to(x), self.high.to(x))
        return bounds

    @staticmethod
    def _leading(x: Tensor, low: Tensor) -> Tensor:
        n = low.shape[0]  # bounds shorter than the state bound its leading components
        return x if x.shape[-1] == n else x[..., :n]

    def __call__(self, inputs: CostInputs) -> Tensor:
        # the gradient in closed form (2 w (x - clamp(x))): autograd's clamp backward costs ~5 passes more over the
        # sample cloud (500 x 101 x 5 values per stage-2 iteration)
        low, high = self._bounds(inputs.x)
        return _BoundsPenalty.apply(self._leading(inputs.x, low), inputs.weights, low, high)


def _box_excess(x: Tensor, low: Tensor, high: Tensor) -> Tensor:
    """``x`` minus its clamp into the box ``[low, high]``."""
    return x - torch.clamp(x, low, high)


class _BoundsPenalty(torch.autograd.Function):
    """:class:`BoundsCost`'s value ``sum w ||x - clamp(x)||^2`` over samples and times, with the gradients
    ``2 w (x - clamp(x))`` in ``x`` and ``||x - clamp(x)||^2`` in ``w``, each scaled by the incoming gradient."""

    @staticmethod
    def forward(ctx, x: Tensor, w: Tensor, low: Tensor, high: Tensor):
        d = _box_excess(x, low, high)
        v = d.square().sum(-1)
        ctx.save_for_backward(d, w, v)
        ctx.shapes = (x.shape, x.dtype, w.shape)
        return (w * v).sum(dim=(-1, -2))

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor):
        d, w, v = ctx.saved_tensors
        x_shape, x_dtype, w_shape = ctx.shapes
        g = grad.reshape(*grad.shape, 1, 1)
        gx = gw = None
        if ctx.needs_input_grad[0]:
            gx = (d * (2.0 * w * g).unsqueeze(-1)).sum_to_size(x_shape).to(x_dtype)
        if ctx.needs_input_grad[1]:
            gw = (v * g).sum_to_size(w_shape)
        return gx, gw, None, None


def _gather(grid: OccupancyGrid, k: Tensor, i: Tensor, j: Tensor, fill: float) -> Tensor:
    """``probs[k, i, j]`` with ``fill`` for indices outside the map (broadcasting long tensors)."""
    _, nx, ny = grid.shape
    inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
    return grid.cell_values(k, i.clamp(0, nx - 1), j.clamp(0, ny - 1)).masked_fill_(~inside, fill)


def _stencil_differences(grid: OccupancyGrid, k: Tensor, c: Tensor, scales: Tensor, fill: float) -> Tensor:
    """``((P[i+s, j] - P[i-s, j]) / 2, (P[i, j+s] - P[i, j-s]) / 2)`` for every scale: ``(..., S, 2)``."""
    unit = torch.tensor([[1, 0], [-1, 0], [0, 1], [0, -1]], device=c.device)
    nb = c[..., None, None, :] + scales[:, None, None] * unit  # (..., S, 4, 2)
    vals = _gather(grid, k[..., None, None], nb[..., 0], nb[..., 1], fill)  # (..., S, 4)
    return torch.stack([vals[..., 0] - vals[..., 1], vals[..., 2] - vals[..., 3]], dim=-1) / 2


@torch.no_grad()
def desired_positions(
    grid: OccupancyGrid,
    xy: Tensor,
    k: Tensor,
    *,
    beta: float,
    plateau_scales: Sequence[int] = (),
    fill: float = 1.0,
) -> tuple[Tensor, Tensor]:
    """The paper's desired positions (Eqs. (8)-(9)) and the occupancy of each sample's cell.

    ``c_des = c - beta G(c, t_k)``: ``c`` is the nearest cell of ``xy (..., 2)``, ``G`` the central difference
    ``(P[c + 1] - P[c - 1]) / 2`` per cell (the true gradient, :meth:`OccupancyGrid.gradient`). Where ``G = 0``
    but ``P > 0`` (inside a plateau of an obstacle, where the gradient gives no direction) the difference
    ``(P[c + s] - P[c - s]) / 2`` over the wider stencils ``s`` in ``plateau_scales`` is used, the first that is
    non-zero (as the paper's code does), so that samples deep inside an obstacle are still pushed out. Cells
    outside the map read ``fill``.

    Returns:
        ``(p_des (..., 2) [m], P_occ (...,) at the sample's cell)``, both without gradient.
    """
    c = torch.round(grid.world_to_cell(xy)).long()  # unclamped: cells outside the map read ``fill``
    k = torch.as_tensor(k, device=xy.device).long().expand(c.shape[:-1])
    p = _gather(grid, k, c[..., 0], c[..., 1], fill)
    grad = _stencil_differences(grid, k, c, torch.ones(1, dtype=torch.long, device=c.device), fill)[..., 0, :]
    # plateau cells (occupied, zero gradient): wider stencils, only where needed (usually few samples)
    need = (grad == 0).all(-1) & (p > 0)
    if plateau_scales and bool(need.any()):
        scales = torch.tensor(plateau_scales, dtype=torch.long, device=c.device)
        g = _stencil_differences(grid, k[need], c[need], scales, fill)  # (n, S, 2)
        nonzero = (g != 0).any(-1)
        first = nonzero.to(torch.uint8).argmax(-1)  # first non-zero scale (0 when none: zero push)
        grad[need] = g[torch.arange(g.shape[0], device=c.device), first]
    c_des = c.to(xy.dtype) - beta * grad.to(xy.dtype)
    return grid.cell_to_world(c_des), p.to(xy.dtype)


class _DesiredPositionMemo:
    """Per-cell memo of :func:`desired_positions` for cells inside the map.

    ``p_des`` and ``P_occ`` depend only on the sample's cell ``(k, i, j)`` (and the dtype), and an optimisation
    moves its samples by little from one iteration to the next, so most cells repeat. The values of every cell
    seen so far are kept in a dense table over the grid (allocated uninitialised, so only the memory pages of
    visited cells are ever touched) with a mask of known cells; new cells are computed with
    :func:`desired_positions` itself, so the results are identical. Positions outside the map are computed
    directly every time.
    """

    #: no memo for grids with more cells than this (the mask alone takes this many bytes; the table is allocated
    #: uninitialised, so only the pages of visited cells become resident). The 268M cells of the default
    #: CommonRoad grid budget (``commonroad.memory_budget_gib = 1`` of float32): the suite's large urban
    #: scenes sit at that budget, and without the memo their collision term took 20x longer (0.22 s instead
    #: of 0.01 s per stage-2 iteration on USA_Lanker-2_20)
    MAX_CELLS = 1 << 28

    def __init__(self, grid: OccupancyGrid, beta: float, plateau_scales: tuple[int, ...]):
        # weakly: the memo lives in the grid's cache, and a strong reference back would make a cycle that only the
        # cyclic garbage collector frees (a replan's full-size grids then outlived it: drive peaked at 10 GB on
        # DEU_Muc-19_1, 5 GB with the cycle broken); every user of the memo holds the grid itself
        self._grid = weakref.ref(grid)
        self.beta = beta
        self.plateau_scales = plateau_scales
        self._table: Tensor | None = None
        self._known: Tensor | None = None

    @property
    def grid(self) -> OccupancyGrid:
        grid = self._grid()
        if grid is None:
            raise RuntimeError("the grid of this desired-position memo no longer exists")
        return grid

    @classmethod
    def shared(cls, grid: OccupancyGrid, beta: float, plateau_scales: tuple[int, ...]) -> _DesiredPositionMemo:
        """The memo of ``grid`` for these settings, cached on the grid: the collision terms of one scene (the
        stage-1, stage-2 and report objectives each build one) share their table and mask, which are allocated
        once per scene and filled once (the values are a function of the cell alone)."""
        key = ("desired_position_memo", float(beta), tuple(plateau_scales))
        memo = grid._cache.get(key)
        if memo is None:
            memo = _WindowMemo.of(grid, beta, plateau_scales) or cls(grid, beta, plateau_scales)
            grid._cache[key] = memo
        return memo

    @property
    def enabled(self) -> bool:
        t, nx, ny = self.grid.shape
        return t * nx * ny <= self.MAX_CELLS

    def root(self, k: Tensor) -> tuple[_DesiredPositionMemo, Tensor]:
        """``(memo, slices)``: the memo whose table this one reads, and the slices of its grid that are slices
        ``k`` (long) of this memo's grid (``(self, k)`` for a memo of its own)."""
        return self, k

    def storage(self, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
        """``(table (L, 3), known (L,))`` over the ``L = T NX NY`` cells: each known cell's desired position and
        occupancy, in ``dtype`` (allocated on the first use of a dtype and device, which forgets the others')."""
        if self._table is None or self._table.dtype != dtype or self._table.device != torch.device(device):
            t, nx, ny = self.grid.shape
            self._table = torch.empty(t * nx * ny, 3, dtype=dtype, device=device)
            self._known = lazy_zeros((t * nx * ny,), torch.bool, device)  # only visited cells' pages touched
        assert self._known is not None
        return self._table, self._known

    def fill(self, lin: Tensor) -> None:
        """Compute and store the cells ``lin`` (flat indices ``(k NX + i) NY + j``, repeats allowed) of the table
        (:meth:`storage`, already allocated)."""
        assert self._table is not None and self._known is not None
        grid = self.grid
        _, nx, ny = grid.shape
        new = torch.unique(lin)
        kk, rem = new // (nx * ny), new % (nx * ny)
        cells = torch.stack([rem // ny, rem % ny], dim=-1).to(self._table.dtype)
        p_des, p = desired_positions(grid, grid.cell_to_world(cells), kk, beta=self.beta,
                                     plateau_scales=self.plateau_scales)
        self._table[new, :2] = p_des
        self._table[new, 2] = p
        self._known[new] = True

    def __call__(self, xy: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
        grid = self.grid
        t, nx, ny = grid.shape
        c = torch.round(grid.world_to_cell(xy)).long()
        k = torch.as_tensor(k, device=xy.device).long().expand(c.shape[:-1])
        inside = (c[..., 0] >= 0) & (c[..., 0] < nx) & (c[..., 1] >= 0) & (c[..., 1] < ny)
        table, known = self.storage(xy.dtype, xy.device)
        lin = ((k * nx + c[..., 0].clamp(0, nx - 1)) * ny + c[..., 1].clamp(0, ny - 1)).reshape(-1)
        flat_inside = inside.reshape(-1)
        # index_select / masked_select: 2-4x faster than advanced indexing for these flat gathers
        missing = flat_inside & ~known.index_select(0, lin)
        if bool(missing.any()):
            self.fill(lin.masked_select(missing))
        values = table.index_select(0, lin)
        if not bool(flat_inside.all()):
            out = ~flat_inside
            flat_xy = xy.reshape(-1, 2)
            p_des, p = desired_positions(grid, flat_xy[out], k.reshape(-1)[out], beta=self.beta,
                                         plateau_scales=self.plateau_scales)
            values[out, :2] = p_des
            values[out, 2] = p
        values = values.reshape(*c.shape[:-1], 3)
        return values[..., :2], values[..., 2]


class _WindowMemo(_DesiredPositionMemo):
    """The memo of a window's slices (:meth:`OccupancyGrid.window`, and the grids derived from one row by row:
    :func:`~density_planner.risk.body.body_grid`) read through its parent's memo: slice ``k`` of the window is slice
    ``min(k0 + k, T - 1)`` of the parent, the same cells with the same values (the stencils are spatial), so the
    replans of one scene share one table and each starts with the cells the earlier ones saw."""

    def __init__(self, grid: OccupancyGrid, parent: _DesiredPositionMemo, k0: int):
        super().__init__(grid, parent.beta, parent.plateau_scales)
        self.parent, self.k0, self.last = parent, int(k0), parent.grid.n_slices - 1

    @classmethod
    def of(cls, grid: OccupancyGrid, beta: float, plateau_scales: tuple[int, ...]) -> _WindowMemo | None:
        """The window memo of ``grid`` when it is a window of a grid with the same cells whose memo is enabled;
        else ``None``."""
        rec = grid._cache.get(grid.WINDOW_OF)
        if rec is None:
            return None
        base, k0, _ = rec
        if (base.device != grid.device or base.shape[1:] != grid.shape[1:] or base.origin != grid.origin
                or base.cell_size != grid.cell_size):
            return None
        parent = _DesiredPositionMemo.shared(base, beta, plateau_scales)
        return cls(grid, parent, k0) if parent.enabled else None

    @property
    def enabled(self) -> bool:
        return True

    def root(self, k: Tensor) -> tuple[_DesiredPositionMemo, Tensor]:
        return self.parent.root((k + self.k0).clamp(max=self.last))

    def __call__(self, xy: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
        memo, k = self.root(torch.as_tensor(k, device=xy.device).long())
        return memo(xy, k)


class CollisionCost(CostTerm):
    """The paper's differentiable collision risk ``J_C`` (Eq. (10)) for the vehicle's body [m^2]::

        J_C = sum_{i,k} w_i(t_k) sum_j P_j ||c_ij(t_k) - c_des,ij(t_k)||^2

    over the disc centres ``c_ij`` of the body (:meth:`CollisionModel.centres`; one centre, the position, for a
    point vehicle as in the paper), with ``P_j`` the disc-dilated occupancy at the centre's cell and ``c_des`` from
    :func:`desired_positions` on the disc-dilated grid (step ``beta`` in cells). ``P_j`` and ``c_des`` are
    constants; gradients flow through the centres (positions *and* heading) and the weights. It is the
    optimisation surrogate (reported as the *collision cost*), not a probability. With ``memo`` (default) the
    desired positions of the cells already seen are reused (identical values; the planner's iterations revisit
    most cells). For a body (several discs) with the memo, on the CPU in float32 / float64 and with numba
    installed (the ``fast`` extra), ``fused`` (default) evaluates the term and its gradients in closed form in two
    compiled passes (:mod:`._jit`; the same value and gradients to round-off,
    ``tests/planning/test_collision_kernels.py``; a stage-2 iteration on 500 samples x 101 times x 4 discs: 4.4 ms
    instead of 10.6 ms forward, and the backward pass only scales the stored gradients). The point vehicle's tensor
    path is already as fast (one centre, no heading: 1.8 ms with its gradient against 2.0 ms compiled).

    Args:
        collision: the collision model (grid, system, body); an :class:`OccupancyGrid` means a point vehicle.
    """

    name = "collision"

    def __init__(self, collision: CollisionModel | OccupancyGrid, *, beta: float = 100.0,
                 plateau_scales: Sequence[int] = (), memo: bool = True, fused: bool = True):
        if not math.isfinite(beta) or beta < 0:
            raise ValueError(f"beta must be a finite number >= 0, got {beta}")
        if isinstance(collision, OccupancyGrid):
            collision = CollisionModel(collision)
        self.collision = collision
        self.grid = collision.body_grid
        self.beta = float(beta)
        self.plateau_scales = tuple(int(s) for s in plateau_scales)
        self._memo = _DesiredPositionMemo.shared(self.grid, self.beta, self.plateau_scales) if memo else None
        if self._memo is not None and not self._memo.enabled:
            self._memo = None
        self.fused = bool(fused)

    @torch.no_grad()
    def desired(self, pos: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
        """``(p_des (..., 2), P_occ (...))`` of positions ``pos (..., 2)`` in slices ``k`` (no gradient)."""
        if self._memo is not None:
            return self._memo(pos, k)
        return desired_positions(self.grid, pos, k, beta=self.beta, plateau_scales=self.plateau_scales)

    def __call__(self, inputs: CostInputs) -> Tensor:
        """``J_C (*batch,)``. The occupancy and desired positions are read without autograd. With the memo (or for a
        point vehicle) every disc centre is read at once; without it (grids above ``_DesiredPositionMemo.MAX_CELLS``)
        only the states with a disc centre in an occupied cell are evaluated again on the autograd graph (the others
        contribute zero value and zero gradient, ``P_j = 0``). Both give the value and gradients of the full sum;
        the selection's boolean masks cost more than the memo lookups they save (random scene 0, 500 samples, the
        body, one evaluation with gradient: 27 ms selected, 17 ms reading every centre)."""
        x, w = inputs.x, inputs.weights
        if self.fused and self._memo is not None and not self.collision.is_point and x.device.type == "cpu" \
                and x.dtype in _FUSED_DTYPES and _jit_kernels() is not None:
            out = self.kernels(x, w, inputs.slices)
            if out is not None:
                return _FusedCollision.apply(x, w, *out)
        if self._memo is not None or self.collision.is_point:
            centres = self.collision.centres(x)  # (*batch, N, T, m, 2), on the autograd graph
            read, k = self._reads(centres.detach(), inputs.slices)
            p_des, p_occ = self.desired(read, k.expand(read.shape[:-1]))  # free cells: P_occ = 0
            d = centres - p_des  # squares summed per coordinate: a reduction over the trailing axis of 2 is slower
            return (w * ((d[..., 0].square() + d[..., 1].square()) * p_occ).sum(-1)).sum(dim=(-1, -2))
        return self._selected(x, w, inputs.slices)

    def kernels(self, x: Tensor, w: Tensor, slices: Tensor) -> tuple[Tensor, Tensor, Tensor] | None:
        """The value ``(*batch,)`` and its gradients in ``x`` and in ``w`` (broadcast to ``x.shape[:-1]``: each
        batch entry's own) from the compiled kernels (:mod:`._jit`; CPU, float32 / float64, with the memo), or
        ``None`` where a disc centre lies off the grid (a point vehicle beyond the map: the tensor path reads those
        directly)."""
        jit = _jit_kernels()
        assert jit is not None and self._memo is not None
        batch, (n, t, nx_state) = x.shape[:-3], x.shape[-3:]
        dtype = x.dtype
        # time before samples (the kernels' layout)
        xn = x.detach().reshape(-1, n, t, nx_state).transpose(1, 2).contiguous().numpy()
        wn = w.detach().to(dtype).expand(x.shape[:-1]).reshape(-1, n, t).transpose(1, 2).contiguous().numpy()
        system, cover = self.collision.system, self.collision.cover
        pos_i, pos_j = (0, 1) if system is None else system.position_indices
        head = -1 if cover.n == 1 and cover.offsets[0] == 0.0 else system.heading_index  # type: ignore[union-attr]
        if head is None:
            raise ValueError("a footprint with several discs needs a heading")
        np_dtype = xn.dtype.type
        offsets = np.asarray(cover.offsets, dtype=np_dtype)
        unit = np.array([1.0, 0.0], dtype=np_dtype)
        k = slices.to("cpu").long().clamp(0, self.grid.n_slices - 1)
        memo, k = self._memo.root(k)
        table, known = memo.storage(dtype, x.device)
        grid = memo.grid
        _, gnx, gny = grid.shape
        lin = np.empty((xn.shape[0], t, n, cover.n), dtype=np.int64)
        clamp = not self.collision.is_point
        bounds = np.asarray(self.collision.grid.bounds, dtype=np_dtype)
        value = np.empty(xn.shape[0], dtype=np.float64)
        grad_x = np.zeros_like(xn)
        grad_w = np.empty_like(wn)
        missing, inside = jit.cells(xn, pos_i, pos_j, head, offsets, unit, np.asarray(grid.origin, dtype=np_dtype),
                                    np_dtype(grid.cell_size), gnx, gny, k.numpy(), bounds, clamp, known.numpy(), lin)
        if not inside:
            return None
        if missing:
            flat = torch.from_numpy(lin).reshape(-1)
            memo.fill(flat.masked_select(~known.index_select(0, flat)))
        jit.accumulate(xn, wn, lin, table.numpy(), pos_i, pos_j, head, offsets, unit, value, grad_x, grad_w)
        gx = torch.from_numpy(grad_x).transpose(1, 2).reshape(x.shape)
        gw = torch.from_numpy(grad_w).transpose(1, 2).reshape(x.shape[:-1])
        return torch.from_numpy(value).to(dtype).reshape(batch), gx, gw

    def _reads(self, centres: Tensor, slices: Tensor) -> tuple[Tensor, Tensor]:
        """Where disc centres ``(..., T, m, 2)`` read the grid (beyond the border, the border: CollisionModel) and
        their slices ``(T, 1)`` (clamped to the grid)."""
        read = centres if self.collision.is_point else self.collision.clamp_to_map(centres)
        return read, slices.to(centres.device).clamp(0, self.grid.n_slices - 1)[:, None]

    def _selected(self, x: Tensor, w: Tensor, slices: Tensor) -> Tensor:
        """:meth:`__call__` evaluated on the states with a disc centre in an occupied cell only."""
        with torch.no_grad():
            centres = self.collision.centres(x.detach())  # (*batch, N, T, m, 2)
        read, k = self._reads(centres, slices)
        with torch.no_grad():
            # only centres in occupied cells contribute: the desired positions are looked up for those alone
            # (most of a cloud is usually in free space; identical values)
            kk = k.expand(read.shape[:-1])
            c = torch.round(self.grid.world_to_cell(read)).long()
            occupied = _gather(self.grid, kk, c[..., 0], c[..., 1], 1.0) > 0
            d2 = x.new_zeros(x.shape[:-1])  # (*batch, N, T)
            if not bool(occupied.any()):
                return (w * d2).sum(dim=(-1, -2))
            p_des, p_occ = self.desired(read[occupied], kk[occupied])
            # the states with an occupied disc centre, and their discs' desired positions / occupancies
            active = occupied.any(-1)
            sub = occupied[active]  # (K, m)
            p_des_a = centres[active].clone()
            p_occ_a = x.new_zeros(sub.shape)
            p_des_a[sub], p_occ_a[sub] = p_des, p_occ
        if torch.is_grad_enabled() and x.requires_grad:
            c = self.collision.centres(x[active])  # (K, m, 2), on the autograd graph
        else:
            c = centres[active]
        d2 = d2.index_put((active,), ((c - p_des_a).pow(2).sum(-1) * p_occ_a).sum(-1))
        return (w * d2).sum(dim=(-1, -2))


#: dtypes of the compiled collision kernels
_FUSED_DTYPES = (torch.float32, torch.float64)


@functools.cache
def _jit_kernels():
    """The collision cost's compiled kernels: those compiled ahead of time (:mod:`._aot`, built by ``make install``)
    where they exist for this source, else numba's just-in-time ones (:mod:`._jit`), else ``None`` (numba, the
    ``fast`` extra, is not installed)."""
    from . import _aot

    compiled = _aot.load()
    if compiled is not None:
        return compiled
    try:
        from . import _jit
    except ImportError:  # pragma: no cover - numba is an optional extra
        return None
    return _jit


def load_collision_kernels(dtype: torch.dtype = torch.float32) -> bool:
    """Load :class:`CollisionCost`'s compiled kernels for states of ``dtype`` now (~1 ms where :mod:`._aot` built
    them; else numba's import and its cached machine code, ~0.4-0.5 s in a fresh process, which the first evaluation
    of a body's collision cost pays otherwise); returns whether they are available (float32 / float64)."""
    jit = _jit_kernels()
    if jit is None or dtype not in _FUSED_DTYPES:
        return False
    jit.warm_up((np.float32 if dtype == torch.float32 else np.float64,))
    return True


class _FusedCollision(torch.autograd.Function):
    """:class:`CollisionCost`'s value on the autograd graph of ``x`` and ``w`` from the gradients the compiled
    kernels computed with it (:meth:`CollisionCost.kernels`): the backward pass only scales them."""

    @staticmethod
    def forward(ctx, x: Tensor, w: Tensor, value: Tensor, gx: Tensor, gw: Tensor):
        ctx.save_for_backward(gx, gw)
        ctx.w_shape = w.shape
        return value.clone()

    @staticmethod
    @once_differentiable  # the stored gradients are constants: no second derivatives on this path
    def backward(ctx, grad: Tensor):
        gx, gw = ctx.saved_tensors
        gx_out = gx * grad.reshape(*grad.shape, 1, 1, 1) if ctx.needs_input_grad[0] else None
        gw_out = None
        if ctx.needs_input_grad[1]:
            gw_out = (gw * grad.reshape(*grad.shape, 1, 1)).sum_to_size(ctx.w_shape)
        return gx_out, gw_out, None, None, None

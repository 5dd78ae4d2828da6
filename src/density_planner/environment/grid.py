"""Time-varying occupancy grid ``P_occ(c_x, c_y, t_k)`` (paper §IV-B): pure tensors, no plotting, no I/O
beyond npz.

Conventions (the one place where world <-> cell transforms live):

* ``probs[k, i, j]`` is the probability that the cell centred at
  ``x = origin[0] + i * cell_size``, ``y = origin[1] + j * cell_size`` is occupied at time ``t0 + k * dt``.
  Index order is (time, x, y); cell centres lie on the lattice points, so a map ``x in [-12, 12]``,
  ``y in [-30, 10]`` with 0.1-m cells has exactly 241 x 401 cells.
* Continuous cell coordinates ``c = (xy - origin) / cell_size`` (dimensionless, in cells): integer values are
  cell centres. ``cell_index`` rounds them to the nearest cell.
* :meth:`OccupancyGrid.lookup` interpolates bilinearly between the four surrounding cell centres of one slice;
  positions outside the lattice hull ``[xmin, xmax] x [ymin, ymax]`` get ``fill`` (default 1.0: "outside the
  map is occupied").
* :meth:`OccupancyGrid.gradient` is the central difference of ``probs`` in probability **per cell** (divide by
  ``cell_size`` for probability per metre), one-sided at the borders.
"""

from __future__ import annotations

import math
from dataclasses import InitVar, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from density_planner.errors import DataError
from density_planner.io.atomic import atomic_save_npz

__all__ = ["OccupancyGrid", "lattice_size", "GRID_FORMAT_VERSION"]

#: version of the ``.npz`` layout written by :meth:`OccupancyGrid.save`
GRID_FORMAT_VERSION = 1

#: tolerance on the [0, 1] range check (float32 round-off of summed probabilities)
_RANGE_TOL = 1e-6


def read_cells(values: Tensor, k: Tensor, i: Tensor, j: Tensor) -> Tensor:
    """``values[k, i, j]`` of a ``(T, NX, NY)`` tensor at long indices broadcast together (inside it: no checks),
    by one ``index_select`` on the flat tensor: 2-4x faster here than advanced indexing."""
    _, nx, ny = values.shape
    lin = (k * nx + i) * ny + j
    return values.reshape(-1).index_select(0, lin.reshape(-1)).reshape(lin.shape)


def lattice_size(lo: float, hi: float, cell_size: float) -> int:
    """Number of lattice points (cell centres) from ``lo`` to ``hi`` inclusive at spacing ``cell_size`` [m].

    ``hi - lo`` must be a whole number of cells (up to 1e-6 cells of round-off).
    """
    n = (hi - lo) / cell_size
    if not math.isfinite(n) or n < 0:
        raise ValueError(f"invalid extent [{lo}, {hi}] with cell size {cell_size}")
    r = round(n)
    if abs(n - r) > 1e-6:
        raise ValueError(
            f"extent [{lo}, {hi}] m is not a whole number of {cell_size}-m cells ({n:.6f} cells)"
        )
    return int(r) + 1


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """Occupancy probabilities over (time, x, y) with the geometry needed to query them.

    Attributes:
        probs: ``(T, NX, NY)`` probabilities in [0, 1] (float32 unless given float64; numpy arrays are
        converted).
            Treated as immutable: the cached gradient is not invalidated by in-place edits.
        origin: world position ``(x, y)`` [m] of the centre of cell ``(0, 0)``.
        cell_size: edge length of a (square) cell [m].
        dt: time between slices [s].
        t0: time of slice 0 [s].
        in_range: (argument only) the caller vouches that ``probs`` holds finite values in [0, 1] (a grid derived
            from a checked one, the importers' rasteriser, which clamps finite footprints): the pass over every
            cell that checks it is skipped (0.05-0.1 s on the suite's largest grids). Shapes and geometry are
            checked either way.
    """

    probs: Tensor
    origin: tuple[float, float]
    cell_size: float
    dt: float = 0.1
    t0: float = 0.0
    in_range: InitVar[bool] = False
    _cache: dict[Any, Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def drop_caches(self) -> None:
        """Forget what was derived from this grid and kept on it (its gradient, the road users' grid, the body's
        dilated grids): each is a full-size copy, recomputed on the next use. Long runs that plan on many grids
        (``drive``) call it when a grid's plan is done. A :meth:`window` keeps the record of its parent."""
        parent = self._cache.get(self.WINDOW_OF)
        self._cache.clear()
        if parent is not None:
            self._cache[self.WINDOW_OF] = parent

    def __post_init__(self, in_range: bool = False) -> None:
        probs = self.probs
        if isinstance(probs, np.ndarray):
            if not np.issubdtype(probs.dtype, np.number) and probs.dtype != np.bool_:
                raise ValueError(f"OccupancyGrid.probs must be numeric, got dtype {probs.dtype}")
            probs = torch.from_numpy(np.ascontiguousarray(probs))
        if not isinstance(probs, Tensor):
            raise ValueError(
                f"OccupancyGrid.probs must be a tensor or numpy array, got {type(probs).__name__}"
            )
        if probs.dtype not in (torch.float32, torch.float64):
            probs = probs.to(torch.float32)
        if probs.ndim != 3:
            raise ValueError(f"OccupancyGrid.probs must have shape (T, NX, NY), got {tuple(probs.shape)}")
        if probs.shape[0] < 1 or probs.shape[1] < 2 or probs.shape[2] < 2:
            raise ValueError(
                f"OccupancyGrid.probs needs >= 1 slice and >= 2 cells per axis, got {tuple(probs.shape)}"
            )
        lo, hi = 0.0, 1.0  # in_range: the bounds vouched for (value_range)
        if not in_range:
            lo_t, hi_t = torch.aminmax(probs)  # one pass; NaN propagates into both
            lo, hi = float(lo_t), float(hi_t)
            if not (math.isfinite(lo) and math.isfinite(hi)):
                bad = int((~torch.isfinite(probs)).sum())
                raise ValueError(f"OccupancyGrid.probs contains {bad} NaN or infinite value(s)")
            if lo < -_RANGE_TOL or hi > 1 + _RANGE_TOL:
                raise ValueError(f"OccupancyGrid.probs must lie in [0, 1], got values in [{lo:.6g}, {hi:.6g}]")
        try:
            origin = (float(self.origin[0]), float(self.origin[1]))
            if len(self.origin) != 2:
                raise TypeError
        except (TypeError, IndexError, ValueError):
            raise ValueError(
                f"OccupancyGrid.origin must be two numbers (x, y), got {self.origin!r}"
            ) from None
        if not all(math.isfinite(v) for v in origin):
            raise ValueError(f"OccupancyGrid.origin must be finite, got {origin}")
        for name in ("cell_size", "dt"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not math.isfinite(value)
                or value <= 0
            ):
                raise ValueError(f"OccupancyGrid.{name} must be a finite number > 0, got {value!r}")
        if isinstance(self.t0, bool) or not isinstance(self.t0, (int, float)) or not math.isfinite(self.t0):
            raise ValueError(f"OccupancyGrid.t0 must be a finite number, got {self.t0!r}")
        object.__setattr__(self, "probs", probs.clamp(0.0, 1.0) if (lo < 0 or hi > 1) else probs)
        self._remember_range((max(lo, 0.0), min(hi, 1.0)))
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "cell_size", float(self.cell_size))
        object.__setattr__(self, "dt", float(self.dt))
        object.__setattr__(self, "t0", float(self.t0))

    def value_range(self) -> tuple[float, float]:
        """``(lo, hi)`` with every value of :attr:`probs` in ``[lo, hi]`` (NaN if it holds one): its minimum and
        maximum from one pass over the grid, or ``(0, 1)`` where the constructor's caller vouched for that range
        (``in_range``); remembered from the constructor until the tensor is changed in place (its version counter:
        a torch operation's edit is seen, one through a numpy view of the same memory is not).
        :func:`~density_planner.environment.scene.validate_scene` reads it for every problem set up on a scene (a
        road scene's grid: ~0.07 s per pass)."""
        probs = self.probs
        hit = self._cache.get(self._RANGE)
        if hit is not None and hit[0] == self._range_key(probs):
            return hit[1]
        lo_t, hi_t = torch.aminmax(probs)  # one pass; NaN propagates into both
        return self._remember_range((float(lo_t), float(hi_t)))

    #: ``_cache`` key of :meth:`value_range`
    _RANGE = "value_range"

    @staticmethod
    def _range_key(probs: Tensor) -> tuple:
        return probs.data_ptr(), probs._version, tuple(probs.shape), tuple(probs.stride())

    def _remember_range(self, rng: tuple[float, float]) -> tuple[float, float]:
        self._cache[self._RANGE] = (self._range_key(self.probs), rng)
        return rng

    # ------------------------------------------------------------------ geometry
    @property
    def shape(self) -> tuple[int, int, int]:
        """``(T, NX, NY)``."""
        return tuple(self.probs.shape)  # type: ignore[return-value]

    @property
    def n_slices(self) -> int:
        return int(self.shape[0])

    @property
    def device(self) -> torch.device:
        return self.probs.device

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` [m]: the first and last cell centres along each axis."""
        _, nx, ny = self.shape
        x0, y0 = self.origin
        return (x0, x0 + (nx - 1) * self.cell_size, y0, y0 + (ny - 1) * self.cell_size)

    @property
    def times(self) -> Tensor:
        """``(T,)`` slice times [s] (float64, CPU)."""
        return self.t0 + self.dt * torch.arange(self.n_slices, dtype=torch.float64)

    @property
    def xs(self) -> Tensor:
        """``(NX,)`` x coordinates of the cell centres [m] (float64, CPU)."""
        return self.origin[0] + self.cell_size * torch.arange(self.shape[1], dtype=torch.float64)

    @property
    def ys(self) -> Tensor:
        """``(NY,)`` y coordinates of the cell centres [m] (float64, CPU)."""
        return self.origin[1] + self.cell_size * torch.arange(self.shape[2], dtype=torch.float64)

    def world_to_cell(self, xy: Tensor) -> Tensor:
        """Continuous cell coordinates ``(xy - origin) / cell_size`` of positions ``(..., 2)`` [m] (same
        dtype)."""
        xy = _as_float_tensor("xy", xy, self.device)
        origin = torch.tensor(self.origin, dtype=xy.dtype, device=xy.device)
        return (xy - origin) / self.cell_size

    def cell_to_world(self, c: Tensor) -> Tensor:
        """World positions [m] of continuous (or integer) cell coordinates ``(..., 2)``."""
        c = _as_float_tensor("c", c, self.device)
        origin = torch.tensor(self.origin, dtype=c.dtype, device=c.device)
        return origin + c * self.cell_size

    def cell_index(self, xy: Tensor) -> tuple[Tensor, Tensor]:
        """Nearest cell of positions ``(..., 2)``: ``(index (..., 2) long, clamped to the grid; inside (...)
        bool)``.

        ``inside`` is True when the rounded index lies in the grid before clamping, i.e. the position is
        within half a cell of the lattice hull.
        """
        c = torch.round(self.world_to_cell(xy)).long()
        size = torch.tensor(self.shape[1:], device=c.device)
        inside = ((c >= 0) & (c < size)).all(dim=-1)
        idx = torch.minimum(c.clamp(min=0), size - 1)
        return idx, inside

    @property
    def t_end(self) -> float:
        """Time of the last slice [s]: ``t0 + (T - 1) dt``."""
        return self.t0 + (self.n_slices - 1) * self.dt

    def slice_index(self, t: float | Tensor, *, clamp: bool = False) -> Tensor:
        """Index of the slice nearest to the ABSOLUTE time ``t`` [s] (scalar or tensor; long tensor, CPU).

        This is the one conversion from time to slice: every planner, cost and metric goes through it (or
        :meth:`slices_for`). Times are absolute, on the grid's own clock (slice 0 is at :attr:`t0`); a plan
        starting at ``t_start`` reads ``t_start + k * plan_dt``, never ``k * plan_dt``.

        Raises :class:`ValueError` naming the grid's time span when a time lies outside ``[t0, t_end]`` (up to
        1e-6 slices of round-off). ``clamp=True`` holds the first / last slice instead: only for look-ahead
        that deliberately runs past the end of the scene (e.g. the MPC's prediction stages after the plan's
        horizon), never for the horizon itself.
        """
        t = torch.as_tensor(t, dtype=torch.float64).cpu()
        pos = (t - self.t0) / self.dt
        if not clamp and pos.numel():
            lo, hi = float(pos.min()), float(pos.max())
            tol = 1e-6
            if not (math.isfinite(lo) and math.isfinite(hi)) or lo < -tol or hi > self.n_slices - 1 + tol:
                t_lo, t_hi = float(t.min()), float(t.max())
                raise ValueError(
                    f"time {t_lo:g}" + (f"-{t_hi:g}" if t_hi != t_lo else "") + f" s lies outside the occupancy "
                    f"grid's time span [{self.t0:g}, {self.t_end:g}] s ({self.n_slices} slices of {self.dt:g} s)"
                )
        return torch.round(pos).long().clamp(0, self.n_slices - 1)

    def slices_for(self, t_start: float, dt: float, n: int, *, clamp: bool = False) -> Tensor:
        """Slices ``(n,)`` (long, CPU) of the absolute times ``t_start + k dt``, ``k = 0 .. n - 1`` [s].

        Raises :class:`ValueError` when the times leave the grid's span, e.g. "planning from 5 s over 10 s needs
        occupancy up to 15 s, the grid ends at 10 s" (see :meth:`check_span`); ``clamp`` as in
        :meth:`slice_index`.
        """
        if not clamp:
            self.check_span(t_start, (n - 1) * dt)
        times = float(t_start) + float(dt) * torch.arange(int(n), dtype=torch.float64)
        return self.slice_index(times, clamp=True)

    def check_span(self, t_start: float, duration: float) -> None:
        """Raise :class:`ValueError` unless ``[t_start, t_start + duration]`` [s] lies inside the grid's span."""
        t_start, duration = float(t_start), float(duration)
        tol = 1e-6 * self.dt
        if not (math.isfinite(t_start) and math.isfinite(duration)) or duration < 0:
            raise ValueError(f"invalid time window: start {t_start} s, duration {duration} s")
        if t_start < self.t0 - tol or t_start + duration > self.t_end + tol:
            raise ValueError(
                f"planning from {t_start:g} s over {duration:g} s needs occupancy for "
                f"[{t_start:g}, {t_start + duration:g}] s, but the occupancy grid covers [{self.t0:g}, "
                f"{self.t_end:g}] s; shorten the horizon (planning.horizon) or build a longer scene"
            )

    # ------------------------------------------------------------------ queries
    def cell_values(self, k: Tensor, i: Tensor, j: Tensor) -> Tensor:
        """P_occ of the cells ``(k, i, j)`` (long tensors, broadcast together, already inside the grid: no checks,
        the hot paths' read), in the grid's dtype. One ``index_select`` on the flat grid, 2-4x faster here than
        advanced indexing."""
        return read_cells(self.probs, k, i, j)

    def lookup(self, xy: Tensor, k: int | Tensor, *, fill: float = 1.0) -> Tensor:
        """P_occ at positions ``xy (..., 2)`` [m] in slice(s) ``k`` (int or long tensor broadcastable to
        ``xy[..., 0]``).

        Bilinear in space between the four surrounding cell centres, differentiable w.r.t. ``xy`` (piecewise
        linear: the derivative jumps at cell centres). Positions outside the lattice hull get ``fill``
        (default 1.0, "outside the map is occupied"), with zero gradient. The result has ``xy``'s dtype and
        the broadcast shape.
        """
        xy = _as_float_tensor("xy", xy, self.device)
        if xy.shape[-1:] != (2,):
            raise ValueError(f"xy must have trailing dimension 2, got shape {tuple(xy.shape)}")
        k = torch.as_tensor(k, device=xy.device)
        if k.is_floating_point() or k.dtype == torch.bool:
            raise ValueError(f"slice index k must be an integer (tensor), got dtype {k.dtype}")
        T, NX, NY = self.shape
        if k.numel() and (int(k.min()) < 0 or int(k.max()) >= T):
            raise ValueError(
                f"slice index k must lie in [0, {T - 1}], got values in [{int(k.min())}, {int(k.max())}]"
            )
        c = self.world_to_cell(xy)
        cx, cy = c[..., 0], c[..., 1]
        inside = (cx >= 0) & (cx <= NX - 1) & (cy >= 0) & (cy <= NY - 1)
        # lower corner, kept one cell inside so that the upper neighbour exists (fraction 1 at the last
        # centre)
        i0 = torch.floor(cx.detach()).clamp(0, NX - 2).long()
        j0 = torch.floor(cy.detach()).clamp(0, NY - 2).long()
        fx = (cx - i0.to(cx.dtype)).clamp(0.0, 1.0)
        fy = (cy - j0.to(cy.dtype)).clamp(0.0, 1.0)
        i0, j0, kb, fx, fy, inside = torch.broadcast_tensors(i0, j0, k.long(), fx, fy, inside)
        # the four corners (i0 + a, j0 + b) in one read
        p00, p01, p10, p11 = self.cell_values(kb, torch.stack([i0, i0, i0 + 1, i0 + 1]),
                                              torch.stack([j0, j0 + 1, j0, j0 + 1])).to(xy.dtype)
        value = (1 - fx) * ((1 - fy) * p00 + fy * p01) + fx * ((1 - fy) * p10 + fy * p11)
        return torch.where(inside, value, torch.full_like(value, fill))

    def gradient(self) -> Tensor:
        """``(T, NX, NY, 2)`` spatial gradient ``(dP/di, dP/dj)`` in probability per CELL (cached).

        Central differences ``(P[i+1] - P[i-1]) / 2`` inside, one-sided ``P[1] - P[0]`` and
        ``P[N-1] - P[N-2]`` at the borders (``torch.gradient`` with unit spacing). Divide by ``cell_size`` for
        probability per metre. This is the true gradient (the paper's code stored its negative).
        """
        grad = self._cache.get("gradient")
        if grad is None or grad.device != self.device:
            gx, gy = torch.gradient(self.probs, dim=(1, 2), edge_order=1)
            grad = torch.stack((gx, gy), dim=-1)
            self._cache["gradient"] = grad
        return grad

    def max_over_time(self) -> Tensor:
        """``(NX, NY)`` maximum occupancy over all slices."""
        return self.probs.amax(dim=0)

    def slice(self, k: int) -> Tensor:
        """``(NX, NY)`` view of slice ``k`` (negative indices count from the end)."""
        T = self.n_slices
        if not -T <= int(k) < T:
            raise ValueError(f"slice index k must lie in [{-T}, {T - 1}], got {k}")
        return self.probs[int(k)]

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> OccupancyGrid:
        """Copy on ``device`` and/or with ``dtype`` (float32 or float64); returns ``self`` when nothing
        changes."""
        probs = self.probs.to(device=device, dtype=dtype)
        if probs is self.probs:
            return self
        return OccupancyGrid(probs, self.origin, self.cell_size, self.dt, self.t0, in_range=True)

    def with_probs(self, probs: Tensor) -> OccupancyGrid:
        """Same geometry with new probabilities (validated)."""
        return OccupancyGrid(probs, self.origin, self.cell_size, self.dt, self.t0)

    #: key of :meth:`window`'s record of where a window's slices come from (``(parent, k0, n)``)
    WINDOW_OF = "window_of"

    def window(self, k0: int, n: int) -> OccupancyGrid:
        """Slices ``k0 .. k0 + n - 1`` as a grid whose slice 0 is at ``t0 + k0 dt`` (past the last slice, the last
        one is held). The window remembers its parent (``_cache[WINDOW_OF]``), so grids derived slice by slice
        (the body's dilated grid, the masked grid: :mod:`density_planner.risk.body`) are read from the parent's
        cached ones instead of being derived again for every window (online replans: one dilation per scene, not
        one per replan)."""
        k0, n = int(k0), int(n)
        if k0 < 0 or n < 1:
            raise ValueError(f"a window needs k0 >= 0 and n >= 1 slices, got k0 = {k0}, n = {n}")
        out = OccupancyGrid(self.window_rows(self.probs, k0, n), self.origin, self.cell_size, self.dt,
                            self.t0 + k0 * self.dt, in_range=True)
        out._cache[self.WINDOW_OF] = (self, k0, n)
        return out

    @staticmethod
    def window_rows(probs: Tensor, k0: int, n: int) -> Tensor:
        """Rows ``k0 .. k0 + n - 1`` of ``probs (T, ...)``, the last row held past the end (a view when they all
        exist)."""
        if k0 + n <= probs.shape[0]:
            return probs[k0 : k0 + n]
        idx = torch.arange(k0, k0 + n, device=probs.device).clamp(max=probs.shape[0] - 1)
        return probs.index_select(0, idx)

    # ------------------------------------------------------------------ files
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain numpy arrays of the grid (the ``.npz`` layout of :meth:`save`)."""
        return {
            "probs": self.probs.detach().to("cpu", torch.float32).numpy(),
            "origin": np.asarray(self.origin, dtype=np.float64),
            "cell_size": np.asarray(self.cell_size, dtype=np.float64),
            "dt": np.asarray(self.dt, dtype=np.float64),
            "t0": np.asarray(self.t0, dtype=np.float64),
            "grid_format_version": np.asarray(GRID_FORMAT_VERSION),
        }

    @classmethod
    def from_arrays(cls, arrays: Any, *, source: str = "arrays") -> OccupancyGrid:
        """Inverse of :meth:`to_arrays` (a mapping of arrays, e.g. an open ``np.load`` result)."""
        missing = [k for k in ("probs", "origin", "cell_size", "dt") if k not in arrays]
        if missing:
            raise DataError(f"{source}: not an occupancy grid file (missing array(s) {missing})")
        try:
            probs = np.asarray(arrays["probs"], dtype=np.float32)
            ox, oy = (float(v) for v in np.asarray(arrays["origin"], dtype=np.float64).reshape(-1))
            origin = (ox, oy)
            t0 = float(arrays["t0"]) if "t0" in arrays else 0.0
            return cls(torch.from_numpy(probs), origin, float(arrays["cell_size"]), float(arrays["dt"]), t0)
        except (ValueError, TypeError) as exc:
            raise DataError(f"{source}: invalid occupancy grid ({exc})") from exc

    def save(self, path: str | Path) -> Path:
        """Write the grid to a compressed ``.npz`` atomically (probabilities stored as float32)."""
        return atomic_save_npz(path, **self.to_arrays())

    @classmethod
    def load(cls, path: str | Path) -> OccupancyGrid:
        """Read a grid written by :meth:`save`; raises :class:`DataError` on a missing or malformed file."""
        from density_planner.io.npz import read_npz

        path = Path(path)
        if not path.is_file():
            raise DataError(f"occupancy grid file not found: {path}")
        return cls.from_arrays(read_npz(path, what="occupancy grid"), source=str(path))

    def __repr__(self) -> str:
        T, NX, NY = self.shape
        xmin, xmax, ymin, ymax = self.bounds
        return (
            f"OccupancyGrid({T}x{NX}x{NY}, x=[{xmin:g}, {xmax:g}] m, y=[{ymin:g}, {ymax:g}] m, "
            f"cell={self.cell_size:g} m, dt={self.dt:g} s, {self.probs.dtype}, {self.device})"
        )


def _as_float_tensor(name: str, value: Any, device: torch.device) -> Tensor:
    if not isinstance(value, Tensor):
        value = torch.as_tensor(
            np.asarray(value, dtype=np.float64) if not isinstance(value, np.ndarray) else value
        )
    if not value.is_floating_point():
        value = value.to(torch.get_default_dtype())
    if value.device != device:
        raise ValueError(
            f"{name} is on {value.device} but the occupancy grid is on {device}; use grid.to(device)"
        )
    return value

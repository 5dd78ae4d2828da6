"""Start/goal sampler for recorded scenes (inD, CommonRoad without a planning problem).

The rules mirror the artificial scenes (``docs/spec.md`` §8), on free cells of an arbitrary map:

* the start is the centre of a cell inside the planning box whose +-``check_half_width`` square has
  max P_occ <= ``start_max_occupancy`` at t = 0;
* the goal is the centre of a cell inside the planning box whose square has
  max P_occ <= ``goal_max_occupancy`` in the last slice;
* the start-goal distance lies in ``distance_range`` (10-70 m);
* the start heading points at the goal, perturbed uniformly by up to +-``heading_jitter``; the speed is
  uniform in ``speed_range``; the square around the look-ahead point
  ``start + v * lookahead_time * (cos, sin)`` has max P_occ <= ``lookahead_max_occupancy`` in the slice at
  ``lookahead_time``.

Candidates are drawn in vectorised batches from a seeded stream (identical on every machine); after
``max_attempts`` candidates without success a :class:`~density_planner.errors.DataError` says which test
failed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from density_planner.errors import DataError

from ._rng import Stream
from .grid import OccupancyGrid

__all__ = ["StartGoalConfig", "sample_start_goal", "free_mask"]


@dataclass(frozen=True)
class StartGoalConfig:
    """Rules of the start/goal sampler (see the module docstring). Lengths in m, times in s."""

    #: accepted start-goal distance range [m]
    distance_range: tuple[float, float] = (10.0, 70.0)
    #: half-width of the square around a point whose maximum P_occ is tested [m]
    check_half_width: float = 0.5
    #: maximum P_occ around the start at t = 0
    start_max_occupancy: float = 0.1
    #: maximum P_occ around the goal in the last slice
    goal_max_occupancy: float = 0.1
    #: look-ahead time for the start test [s]
    lookahead_time: float = 1.0
    #: maximum P_occ around the look-ahead point
    lookahead_max_occupancy: float = 0.3
    #: start speed range [m/s]
    speed_range: tuple[float, float] = (1.0, 9.0)
    #: the start heading is the direction to the goal plus a uniform perturbation in +-heading_jitter [rad]
    heading_jitter: float = 0.5
    #: candidates drawn before giving up
    max_attempts: int = 5000
    #: candidates drawn per vectorised batch
    batch: int = 500

    def __post_init__(self) -> None:
        lo, hi = self.distance_range
        if not 0 <= lo <= hi:
            raise ValueError(
                f"StartGoalConfig.distance_range must be (min, max) with 0 <= min <= max, got {(lo, hi)}"
            )
        lo, hi = self.speed_range
        if not 0 <= lo <= hi:
            raise ValueError(
                f"StartGoalConfig.speed_range must be (min, max) with 0 <= min <= max, got {(lo, hi)}"
            )
        for name in ("check_half_width", "lookahead_time", "heading_jitter"):
            if getattr(self, name) < 0:
                raise ValueError(f"StartGoalConfig.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("start_max_occupancy", "goal_max_occupancy", "lookahead_max_occupancy"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"StartGoalConfig.{name} must lie in [0, 1], got {getattr(self, name)}")
        if self.max_attempts < 1 or self.batch < 1:
            raise ValueError("StartGoalConfig.max_attempts and batch must be >= 1")


def window_max(slice_: torch.Tensor | np.ndarray, half: int, *, outside: float = 1.0, margin: int = 0) -> np.ndarray:
    """Max of an occupancy slice ``(NX, NY)`` over the ``(2 half + 1)^2`` square around every cell (float32); cells
    outside the map count as ``outside`` (1: occupied; 0: ignored, since P_occ >= 0). ``margin`` > 0 also covers the
    ``margin`` cells around the map: the result is ``(NX + 2 margin, NY + 2 margin)``, cell ``(i, j)`` at
    ``[i + margin, j + margin]``."""
    x = slice_.detach().float().cpu().numpy() if isinstance(slice_, torch.Tensor) else np.asarray(slice_, np.float32)
    padded = np.pad(x, half + margin, constant_values=outside) if half + margin else x.copy()
    k = 2 * half + 1
    # separable: a square max is a max over rows of maxes over columns; k shifted maxima per axis (exact)
    n0 = padded.shape[0] - k + 1
    rows = padded[:n0].copy()
    for d in range(1, k):
        np.maximum(rows, padded[d : d + n0], out=rows)
    n1 = rows.shape[1] - k + 1
    out = rows[:, :n1].copy()
    for d in range(1, k):
        np.maximum(out, rows[:, d : d + n1], out=out)
    return out


def free_mask(grid: OccupancyGrid, k: int, max_occupancy: float, half_width: float) -> np.ndarray:
    """``(NX, NY)`` bool: cells whose +-``half_width`` [m] square has max P_occ <= ``max_occupancy`` in slice
    k."""
    half = int(round(half_width / grid.cell_size))
    return window_max(grid.slice(k), half) <= max_occupancy


def sample_start_goal(
    grid: OccupancyGrid,
    planning_box: tuple[float, float, float, float],
    *,
    seed: int,
    config: StartGoalConfig | None = None,
) -> tuple[tuple[float, float, float, float], tuple[float, float]]:
    """Draw a start pose and speed ``(x, y, heading, speed)`` and a goal ``(x, y)`` on free cells; see the module
    docstring."""
    cfg = config or StartGoalConfig()
    rng = Stream(seed)
    xs, ys = grid.xs.numpy(), grid.ys.numpy()
    bx0, bx1, by0, by1 = planning_box
    in_box = ((xs >= bx0) & (xs <= bx1))[:, None] & ((ys >= by0) & (ys <= by1))[None, :]
    half = int(round(cfg.check_half_width / grid.cell_size))
    start_ok = (window_max(grid.slice(0), half) <= cfg.start_max_occupancy) & in_box
    goal_ok = (window_max(grid.slice(-1), half) <= cfg.goal_max_occupancy) & in_box
    k_look = int(grid.slice_index(grid.t0 + cfg.lookahead_time, clamp=True))
    look_max = window_max(grid.slice(k_look), half)
    start_cells = np.argwhere(start_ok)
    goal_cells = np.argwhere(goal_ok)
    if start_cells.size == 0:
        raise DataError(
            f"no free start cell (P_occ <= {cfg.start_max_occupancy} within +-{cfg.check_half_width} m at "
            "t=0) "
            f"inside the planning box {planning_box}"
        )
    if goal_cells.size == 0:
        raise DataError(
            f"no free goal cell (P_occ <= {cfg.goal_max_occupancy} within +-{cfg.check_half_width} m in "
            "the last "
            f"slice) inside the planning box {planning_box}"
        )
    x0, y0, h = grid.origin[0], grid.origin[1], grid.cell_size
    nx, ny = look_max.shape
    drawn, n_dist = 0, 0
    while drawn < cfg.max_attempts:
        n = min(cfg.batch, cfg.max_attempts - drawn)
        drawn += n
        s = start_cells[rng.integers(0, len(start_cells) - 1, n)]
        g = goal_cells[rng.integers(0, len(goal_cells) - 1, n)]
        jitter = rng.uniform(-cfg.heading_jitter, cfg.heading_jitter, n)
        speed = rng.uniform(cfg.speed_range[0], cfg.speed_range[1], n)
        sx, sy = x0 + s[:, 0] * h, y0 + s[:, 1] * h
        gx, gy = x0 + g[:, 0] * h, y0 + g[:, 1] * h
        dist = np.hypot(gx - sx, gy - sy)
        ok_dist = (dist >= cfg.distance_range[0]) & (dist <= cfg.distance_range[1])
        n_dist += int(ok_dist.sum())
        theta = np.arctan2(gy - sy, gx - sx) + jitter
        lx = np.rint((sx + speed * cfg.lookahead_time * np.cos(theta) - x0) / h).astype(np.int64)
        ly = np.rint((sy + speed * cfg.lookahead_time * np.sin(theta) - y0) / h).astype(np.int64)
        inside = (lx >= 0) & (lx < nx) & (ly >= 0) & (ly < ny)
        look = np.ones(n)
        look[inside] = look_max[lx[inside], ly[inside]]
        ok = ok_dist & (look <= cfg.lookahead_max_occupancy)
        if ok.any():
            i = int(np.argmax(ok))
            start = (float(sx[i]), float(sy[i]), float(theta[i]), float(speed[i]))
            return start, (float(gx[i]), float(gy[i]))
    reason = (
        f"no free start/goal cells are {cfg.distance_range[0]:g}-{cfg.distance_range[1]:g} m apart"
        if n_dist == 0
        else f"the 1-s look-ahead point was occupied (P_occ > {cfg.lookahead_max_occupancy}) for all of them"
    )
    raise DataError(
        f"start/goal sampler (seed {seed}): no valid pair in {cfg.max_attempts} attempts: {reason}"
    )

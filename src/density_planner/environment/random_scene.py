"""Random artificial scenes, as in the paper's code (``docs/spec.md`` §8): a street with random boxes.

A scene is a 24 m x 40 m street (x in [-12, 12], y in [-30, 10] m, 0.1-m cells, 241 x 401 cells) over 10 s
(101 slices of 0.1 s) with

* two walls x in [-12, -7] and x in [7, 12] over the whole length, certainty 1, spread 30 cells;
* 4-7 static and 6-9 moving boxes: width, height in {0.5, 0.6, ..., 3.9} m, lower-left corner
  x in {-7, ..., 6}, y in {-23, ..., 4} m (integers), certainty in {0.3, ..., 0.9}, spread in {1, ..., 29}
  cells, velocity components in {-2, -1, 0, 1} cells per slice (= m/s at 0.1 m and 0.1 s);
* the "square" occupancy profile of one box: ``c * max(0, s - d) / s``, with ``c`` the certainty, ``s`` the
  spread and ``d`` the Chebyshev distance in cells from the box (0 inside): a plateau ``c`` on the box and a
  linear ramp down to ``c / s`` at ``s - 1`` cells (the paper's code adds ``c / s`` on the box grown by
  ``0 ... s-1`` cells, which is the same sum);
* moving boxes are shifted by ``(vx, vy)`` cells per slice; what leaves the grid is lost and nothing enters
  from outside (zero fill), exactly like shifting the slice-0 array;
* ``P_occ = clamp(sum over walls and boxes, 0, 1)``.

A box covers the cells whose indices lie between ``index(x)`` and ``index(x + width)`` inclusive (same along
y), with ``index(v) = floor((v - min) / cell + 0.5 + 0.001)`` (the code's rounding with its +0.001).

Start and goal: seeds below 20 use the fixed start ``(0, -28, 1.5 rad, 3 m/s)`` and goal ``(0, 8)``. Other seeds
draw a start uniformly in x in [-5, 5], y in [5, 10], theta in [-2.1, -0.5] rad, v in [1, 9] m/s and a goal in
x in [-5, 5], y in [-30, -20] (driving "down" the street) and accept the pair when the distance is 10-70 m,
max P_occ within +-0.5 m of the start at t = 0 is <= 0.1, max P_occ within +-0.5 m of the 1-s look-ahead point
``start + v * 1 s * (cos theta, sin theta)`` in the slice at t = 1 s is <= 0.3 and max P_occ within +-0.5 m of
the goal at t = 10 s is <= 0.1; after ``max_attempts`` rejected pairs a :class:`ValueError` is raised.

Randomness: one ``numpy.random.PCG64(seed)`` stream, whose raw 64-bit outputs NumPy guarantees to be identical
on every machine and version; uniform numbers and integers are derived from them here (not through
``Generator`` methods, whose algorithms may change between NumPy versions). Draw order: number of static
boxes, number of moving boxes, then per box (static first) width, height, x, y, certainty, spread (and vx, vy
for moving boxes), then start/goal candidates. The paper's code used the global RNG, so the scenes differ from
it for the same seed; the distribution is the same.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch

from density_planner.checks import check_seed
from density_planner.config import to_dict
from density_planner.memory import check_memory

from ._rng import Stream
from .grid import OccupancyGrid, lattice_size
from .sampling import window_max
from .scene import Scene

__all__ = ["RandomSceneConfig", "BoxObstacle", "random_scene", "random_obstacles", "rasterise_boxes"]


@dataclass(frozen=True)
class RandomSceneConfig:
    """Every number of the random artificial scenes (``docs/spec.md`` §8). Lengths in m unless stated."""

    #: x extent of the map [m]: first and last cell centre
    x_range: tuple[float, float] = (-12.0, 12.0)
    #: y extent of the map [m]
    y_range: tuple[float, float] = (-30.0, 10.0)
    #: cell edge [m]
    cell_size: float = 0.1
    #: number of time slices (t = 0 ... (n_slices - 1) * dt)
    n_slices: int = 101
    #: time between slices [s]
    dt: float = 0.1
    #: x extents [m] of the walls, each over the whole y range
    wall_x_ranges: tuple[tuple[float, float], ...] = ((-12.0, -7.0), (7.0, 12.0))
    #: occupancy plateau of the walls
    wall_certainty: float = 1.0
    #: ramp length of the walls [cells]
    wall_spread: int = 30
    #: inclusive range of the number of static boxes (the code's ``randint(4, 8)``)
    n_static: tuple[int, int] = (4, 7)
    #: inclusive range of the number of moving boxes (``randint(6, 10)``)
    n_dynamic: tuple[int, int] = (6, 9)
    #: inclusive range of box widths and heights [m], on a grid of ``size_step``
    size_range: tuple[float, float] = (0.5, 3.9)
    #: step of the box sizes [m]
    size_step: float = 0.1
    #: inclusive integer range of the lower-left corner x [m]
    corner_x_range: tuple[int, int] = (-7, 6)
    #: inclusive integer range of the lower-left corner y [m]
    corner_y_range: tuple[int, int] = (-23, 4)
    #: inclusive range of box certainties (plateau occupancy), on a grid of ``certainty_step``
    certainty_range: tuple[float, float] = (0.3, 0.9)
    #: step of the certainties
    certainty_step: float = 0.1
    #: inclusive range of box spreads [cells]
    spread_range: tuple[int, int] = (1, 29)
    #: inclusive range of each velocity component of moving boxes [cells per slice] (``randint(-2, 2)``)
    velocity_range: tuple[int, int] = (-2, 1)
    #: seeds below this use the fixed start and goal
    fixed_start_seeds: int = 20
    #: fixed start pose and speed (x, y, heading, speed) [m, m, rad, m/s]
    fixed_start: tuple[float, float, float, float] = (0.0, -28.0, 1.5, 3.0)
    #: fixed goal position [m]
    fixed_goal: tuple[float, float] = (0.0, 8.0)
    #: lower corner of the random start box (p_x, p_y, theta, v)
    start_box_min: tuple[float, float, float, float] = (-5.0, 5.0, -2.1, 1.0)
    #: upper corner of the random start box (p_x, p_y, theta, v)
    start_box_max: tuple[float, float, float, float] = (5.0, 10.0, -0.5, 9.0)
    #: random goal box (xmin, xmax, ymin, ymax)
    goal_box: tuple[float, float, float, float] = (-5.0, 5.0, -30.0, -20.0)
    #: accepted start-goal distance range [m]
    distance_range: tuple[float, float] = (10.0, 70.0)
    #: half-width of the square around a point whose maximum P_occ is tested [m]
    check_half_width: float = 0.5
    #: maximum P_occ around the start at t = 0
    start_max_occupancy: float = 0.1
    #: look-ahead time for the start test [s]
    lookahead_time: float = 1.0
    #: maximum P_occ around the look-ahead point at t = lookahead_time
    lookahead_max_occupancy: float = 0.3
    #: maximum P_occ around the goal at the last slice
    goal_max_occupancy: float = 0.1
    #: start/goal pairs drawn before giving up
    max_attempts: int = 1000
    #: box the positions must stay in, (xmin, xmax, ymin, ymax) (X_MIN_MP / X_MAX_MP of ``docs/spec.md`` §1)
    planning_box: tuple[float, float, float, float] = (-9.9, 9.9, -29.9, 9.9)

    def __post_init__(self) -> None:
        for name in (
            "x_range",
            "y_range",
            "n_static",
            "n_dynamic",
            "size_range",
            "corner_x_range",
            "corner_y_range",
            "certainty_range",
            "spread_range",
            "velocity_range",
            "distance_range",
        ):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(
                    f"RandomSceneConfig.{name} must be (min, max) with min <= max, got {(lo, hi)}"
                )
        for name in ("cell_size", "dt", "size_step", "certainty_step", "check_half_width"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RandomSceneConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.n_slices < 1:
            raise ValueError(f"RandomSceneConfig.n_slices must be >= 1, got {self.n_slices}")
        if self.n_static[0] < 0 or self.n_dynamic[0] < 0:
            raise ValueError("RandomSceneConfig.n_static / n_dynamic must be >= 0")
        if self.spread_range[0] < 1 or self.wall_spread < 1:
            raise ValueError("RandomSceneConfig spreads must be >= 1 cell")
        if self.size_range[0] < 0:
            raise ValueError("RandomSceneConfig.size_range must be >= 0")
        for name in ("certainty_range",):
            lo, hi = getattr(self, name)
            if lo < 0 or hi > 1:
                raise ValueError(f"RandomSceneConfig.{name} must lie in [0, 1], got {(lo, hi)}")
        if not 0 <= self.wall_certainty <= 1:
            raise ValueError(
                f"RandomSceneConfig.wall_certainty must lie in [0, 1], got {self.wall_certainty}"
            )
        if self.max_attempts < 1:
            raise ValueError(f"RandomSceneConfig.max_attempts must be >= 1, got {self.max_attempts}")
        if any(a > b for a, b in zip(self.start_box_min, self.start_box_max, strict=True)):
            raise ValueError("RandomSceneConfig.start_box_min must be <= start_box_max elementwise")
        g = self.goal_box
        if g[0] > g[1] or g[2] > g[3]:
            raise ValueError(f"RandomSceneConfig.goal_box must be (xmin, xmax, ymin, ymax), got {g}")
        for name, rng in (("x_range", self.x_range), ("y_range", self.y_range)):
            try:
                lattice_size(rng[0], rng[1], self.cell_size)
            except ValueError as exc:
                raise ValueError(f"RandomSceneConfig.{name}: {exc}") from None

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(T, NX, NY)`` of the generated grid."""
        return (
            self.n_slices,
            lattice_size(*self.x_range, self.cell_size),
            lattice_size(*self.y_range, self.cell_size),
        )


@dataclass(frozen=True)
class BoxObstacle:
    """An axis-aligned box with the "square" occupancy profile, optionally moving by whole cells per slice.

    Attributes:
        x, y: lower-left corner [m]; width, height: extent along x and y [m];
        certainty: plateau occupancy in [0, 1]; spread: ramp length [cells] (>= 1);
        vx, vy: velocity [cells per slice]; kind: ``"wall"``, ``"static"`` or ``"dynamic"``.
    """

    x: float
    y: float
    width: float
    height: float
    certainty: float
    spread: int
    vx: int = 0
    vy: int = 0
    kind: str = "static"


def _draw_obstacles(rng: Stream, cfg: RandomSceneConfig) -> list[BoxObstacle]:
    n_static = rng.integer(*cfg.n_static)
    n_dynamic = rng.integer(*cfg.n_dynamic)
    boxes = []
    for b in range(n_static + n_dynamic):
        dynamic = b >= n_static
        w = rng.on_grid(*cfg.size_range, cfg.size_step)
        h = rng.on_grid(*cfg.size_range, cfg.size_step)
        x = float(rng.integer(*cfg.corner_x_range))
        y = float(rng.integer(*cfg.corner_y_range))
        c = rng.on_grid(*cfg.certainty_range, cfg.certainty_step)
        s = rng.integer(*cfg.spread_range)
        vx = rng.integer(*cfg.velocity_range) if dynamic else 0
        vy = rng.integer(*cfg.velocity_range) if dynamic else 0
        boxes.append(BoxObstacle(x, y, w, h, c, s, vx, vy, "dynamic" if dynamic else "static"))
    return boxes


def _walls(cfg: RandomSceneConfig) -> list[BoxObstacle]:
    y0, y1 = cfg.y_range
    return [
        BoxObstacle(a, y0, b - a, y1 - y0, cfg.wall_certainty, cfg.wall_spread, 0, 0, "wall")
        for a, b in cfg.wall_x_ranges
    ]


def random_obstacles(seed: int, config: RandomSceneConfig | None = None) -> list[BoxObstacle]:
    """The random boxes of scene ``seed`` (walls excluded), without rasterising them."""
    cfg = config or RandomSceneConfig()
    return _draw_obstacles(Stream(seed), cfg)


def _index(v: float, lo: float, cell: float) -> int:
    return int(math.floor((v - lo) / cell + 0.5 + 1e-3))


def _box_profile(i_lo: int, i_hi: int, j_lo: int, j_hi: int, c: float, s: int) -> tuple[np.ndarray, int, int]:
    """Square profile of a box on its support window; returns (values (wx, wy), first i, first j)."""
    ii = np.arange(i_lo - s + 1, i_hi + s)
    jj = np.arange(j_lo - s + 1, j_hi + s)
    dx = np.maximum(np.maximum(i_lo - ii, ii - i_hi), 0)
    dy = np.maximum(np.maximum(j_lo - jj, jj - j_hi), 0)
    d = np.maximum(dx[:, None], dy[None, :])
    values = (c / s) * np.maximum(s - d, 0).astype(np.float32)
    return values.astype(np.float32), int(ii[0]), int(jj[0])


def _clip_window(start: int, size: int, n: int) -> tuple[int, int, int, int]:
    """Intersection of ``[start, start + size)`` with ``[0, n)``: (grid from, grid to, window from, window
    to)."""
    a, b = max(start, 0), min(start + size, n)
    return a, b, a - start, b - start


def rasterise_boxes(
    boxes: list[BoxObstacle],
    *,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    cell_size: float,
    n_slices: int,
) -> np.ndarray:
    """``(T, NX, NY)`` float32 ``clamp(sum of box profiles, 0, 1)``, moving boxes shifted per slice (zero
    fill).

    Vectorised per box (its profile is built once on its support window); the only loops are over boxes and,
    for moving boxes, over slices (one slice-add each).
    """
    nx = lattice_size(*x_range, cell_size)
    ny = lattice_size(*y_range, cell_size)
    static = np.zeros((nx, ny), dtype=np.float32)
    moving: list[tuple[np.ndarray, int, int, int, int]] = []
    for box in boxes:
        i_lo, i_hi = _index(box.x, x_range[0], cell_size), _index(box.x + box.width, x_range[0], cell_size)
        j_lo, j_hi = _index(box.y, y_range[0], cell_size), _index(box.y + box.height, y_range[0], cell_size)
        values, i0, j0 = _box_profile(i_lo, i_hi, j_lo, j_hi, box.certainty, box.spread)
        # crop to the grid: content beyond the border does not exist at t = 0 (zero fill when shifting)
        a, b, wa, wb = _clip_window(i0, values.shape[0], nx)
        c, d, wc, wd = _clip_window(j0, values.shape[1], ny)
        if a >= b or c >= d:
            continue
        values = values[wa:wb, wc:wd]
        if box.vx == 0 and box.vy == 0:
            static[a:b, c:d] += values
        else:
            moving.append((values, a, c, box.vx, box.vy))
    out = np.empty((n_slices, nx, ny), dtype=np.float32)
    out[:] = static
    for values, a, c, vx, vy in moving:
        wx, wy = values.shape
        for k in range(n_slices):
            ga, gb, wa, wb = _clip_window(a + vx * k, wx, nx)
            gc, gd, wc, wd = _clip_window(c + vy * k, wy, ny)
            if ga < gb and gc < gd:
                out[k, ga:gb, gc:gd] += values[wa:wb, wc:wd]
    np.clip(out, 0.0, 1.0, out=out)
    return out


def _point_max(window: np.ndarray, cx: float, cy: float, half: int) -> float:
    """Max of a slice over the cells within ``half`` cells of the continuous cell coordinates (cx, cy), read from
    its :func:`~.sampling.window_max` with cells outside the map ignored and a margin of ``half``; 1 when the
    square lies wholly outside the map."""
    i, j = int(round(cx)) + half, int(round(cy)) + half
    if not (0 <= i < window.shape[0] and 0 <= j < window.shape[1]):
        return 1.0
    return float(window[i, j])


def _draw_start_goal(
    rng: Stream, probs: np.ndarray, cfg: RandomSceneConfig, seed: int
) -> tuple[tuple[float, float, float, float], tuple[float, float], int]:
    x0, y0, cell = cfg.x_range[0], cfg.y_range[0], cfg.cell_size
    half = int(round(cfg.check_half_width / cell))
    k_look = min(int(round(cfg.lookahead_time / cfg.dt)), probs.shape[0] - 1)
    first, look, last = (window_max(probs[k], half, outside=0.0, margin=half) for k in (0, k_look, -1))
    lo, hi = cfg.start_box_min, cfg.start_box_max
    for attempt in range(1, cfg.max_attempts + 1):
        sx, sy = rng.uniform(lo[0], hi[0]), rng.uniform(lo[1], hi[1])
        th, v = rng.uniform(lo[2], hi[2]), rng.uniform(lo[3], hi[3])
        gx, gy = rng.uniform(cfg.goal_box[0], cfg.goal_box[1]), rng.uniform(cfg.goal_box[2], cfg.goal_box[3])
        dist = math.hypot(gx - sx, gy - sy)
        if not cfg.distance_range[0] <= dist <= cfg.distance_range[1]:
            continue
        if _point_max(first, (sx - x0) / cell, (sy - y0) / cell, half) > cfg.start_max_occupancy:
            continue
        lx = sx + v * cfg.lookahead_time * math.cos(th)
        ly = sy + v * cfg.lookahead_time * math.sin(th)
        if _point_max(look, (lx - x0) / cell, (ly - y0) / cell, half) > cfg.lookahead_max_occupancy:
            continue
        if _point_max(last, (gx - x0) / cell, (gy - y0) / cell, half) > cfg.goal_max_occupancy:
            continue
        return (sx, sy, th, v), (gx, gy), attempt
    raise ValueError(
        f"random scene seed {seed}: no start/goal pair passed the acceptance tests in {cfg.max_attempts} "
        "attempts "
        "(try another seed or raise max_attempts)"
    )


def random_scene(seed: int, config: RandomSceneConfig | None = None) -> Scene:
    """The random artificial scene number ``seed`` (deterministic on every machine); see the module
    docstring."""
    cfg = config or RandomSceneConfig()
    check_seed("seed", seed)
    nx, ny = lattice_size(*cfg.x_range, cfg.cell_size), lattice_size(*cfg.y_range, cfg.cell_size)
    # the (T, NX, NY) float32 grid plus the static layer and one slice of temporaries
    check_memory(4.0 * (cfg.n_slices + 2) * nx * ny,
                 f"a random scene of {cfg.n_slices} x {nx} x {ny} cells",
                 "raise random_scene.cell_size (or lower random_scene.n_slices)")
    rng = Stream(seed)
    boxes = _draw_obstacles(rng, cfg)
    probs = rasterise_boxes(
        _walls(cfg) + boxes,
        x_range=cfg.x_range,
        y_range=cfg.y_range,
        cell_size=cfg.cell_size,
        n_slices=cfg.n_slices,
    )
    if seed < cfg.fixed_start_seeds:
        start, goal, attempts = cfg.fixed_start, cfg.fixed_goal, 0
    else:
        start, goal, attempts = _draw_start_goal(rng, probs, cfg, seed)
    grid = OccupancyGrid(torch.from_numpy(probs), (cfg.x_range[0], cfg.y_range[0]), cfg.cell_size, cfg.dt)
    meta = {
        "source": "random",
        "seed": int(seed),
        "obstacles": [asdict(b) for b in _walls(cfg) + boxes],
        "start_goal_attempts": attempts,
        "config": to_dict(cfg),
    }
    return Scene(grid, start, goal, cfg.planning_box, name=f"random-{seed}", meta=meta)

"""Goal cost for a goal *region in time* (CommonRoad goal semantics) instead of the paper's goal point at the final
time.

For one goal alternative with position shapes ``G``, time interval ``[t_lo, t_hi]``, optional speed interval
``[v_lo, v_hi]`` and optional heading interval ``[th_lo, th_hi]``, a state ``x`` at time ``t`` has the squared
distance::

    D(x) = d_G(p)^2 + w_v d_V(v)^2 + w_th d_Th(theta)^2

with ``d_G`` the Euclidean distance [m] from the position to the goal shapes (0 inside), ``d_V`` the distance
[m/s] from the speed to its interval and ``d_Th`` the angular distance [rad] from the heading to its interval
(modulo 2 pi); components the goal does not give are 0. The goal cost of a candidate is::

    J_G = sum_i wbar_i min_{k in K} D(x_i(t_k))            [m^2]

where ``K`` are the planning steps whose (absolute) time lies in the goal's time interval and ``wbar_i`` the
sample weights averaged over ``K`` (they sum to one; a single trajectory has weight 1). Hence ``J_G = 0`` exactly
when every sample is inside the goal region at *some* time of the interval: a reference that has reached the goal
may slow down and hold there, or drive through it, at no cost (no incentive to loop back to a point at the last
instant). When no planning step lies in the interval (it starts after the horizon, or ended before the start)
``K`` is the step nearest to it. With several alternatives, ``J_G`` is the smallest over them.

Times are those of the occupancy slices the cost inputs name (``t_k = grid.t0 + slices[k] * grid.dt``, the same
clock as the collision term), so the term needs no extra inputs. Like :class:`~density_planner.cost.terms.GoalCost`
it takes a ``far_factor`` applied while ``J_G >= close_threshold`` during optimisation.

``margin`` shrinks the region for the cost (not for the verdict): shapes are eroded by up to ``margin`` [m] (less
where a shape is too thin to keep a core), a speed interval at each end by up to a quarter of its width (at most
``margin`` m/s) and a heading interval at each end by up to an eighth of its width (at most ``margin / 10`` rad), so
that a plan the optimiser brings to zero cost lies inside the true region with room for the vehicle's tracking
error rather than on its boundary. ``time_margin`` [s] does the
same for the time interval: ``[t_lo + m, t_hi - m]`` with ``m = min(time_margin, (t_hi - t_lo) / 4)`` (an instant
stays an instant), so that an execution that arrives a little late or leaves a little early is still inside it.

Distances to polygons are exact and differentiable (point-to-segment distances to every edge of the goal's
outline, batched; inside by the even-odd rule), so the gradient of ``d_G^2`` is ``2 (p - q)`` with ``q`` the
nearest boundary point.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .terms import CostInputs, CostTerm

__all__ = ["GoalRegionCost", "polygon_edges", "distance_to_polygons"]

#: state indices of the position, heading and speed when no system names them (the car's layout)
_CAR_LAYOUT = (0, 1, 2, 3)


def polygon_edges(shapes: Any, *, simplify: float = 0.0) -> np.ndarray:
    """``(E, 2, 2)`` edges (start, end) [m] of every ring (exteriors and holes) of the polygons in ``shapes``
    (a shapely geometry; lines and points are grown by 1e-3 m to polygons). ``simplify`` > 0 simplifies the
    outline first (topology preserving, tolerance in m)."""
    import shapely

    geom = shapes
    if simplify > 0:
        geom = shapely.simplify(geom, simplify, preserve_topology=True)
    parts = shapely.get_parts(geom)
    polys = []
    for g in parts:
        if g.geom_type == "Polygon":
            polys.append(g)
        elif g.geom_type == "MultiPolygon":
            polys.extend(g.geoms)
        elif not g.is_empty:
            polys.extend(shapely.get_parts(g.buffer(1e-3)))
    edges = []
    for poly in polys:
        for ring in (poly.exterior, *poly.interiors):
            c = np.asarray(ring.coords, dtype=np.float64)
            if c.shape[0] >= 2:
                edges.append(np.stack([c[:-1], c[1:]], axis=1))
    if not edges:
        raise ValueError("goal shapes have no polygon outline")
    return np.concatenate(edges)


def distance_to_polygons(p: Tensor, edges: Tensor) -> Tensor:
    """Distance [m] from points ``p (..., 2)`` to the region bounded by ``edges (E, 2, 2)`` (0 inside, by the
    even-odd rule; differentiable w.r.t. ``p`` outside)."""
    a, b = edges[:, 0], edges[:, 1]  # (E, 2)
    ab = b - a
    ab2 = ab.pow(2).sum(-1).clamp_min(1e-18)
    ap = p[..., None, :] - a  # (..., E, 2)
    u = ((ap * ab).sum(-1) / ab2).clamp(0.0, 1.0)
    q = a + u[..., None] * ab
    d2 = (p[..., None, :] - q).pow(2).sum(-1).min(-1).values  # (...)
    with torch.no_grad():
        y = p[..., 1:2]
        ay, by_ = a[:, 1], b[:, 1]
        crosses = (ay > y) != (by_ > y)
        x_at = a[:, 0] + (y - ay) / torch.where(by_ == ay, torch.ones_like(ay), by_ - ay) * ab[:, 0]
        inside = ((crosses & (p[..., 0:1] < x_at)).sum(-1) % 2) == 1
    # sqrt of a clamped square keeps a finite gradient at the boundary
    return torch.where(inside, torch.zeros_like(d2), d2.clamp_min(1e-12).sqrt())


def _erode(shapes: Any, margin: float) -> Any:
    """``shapes`` eroded by ``margin`` [m], halving it until a non-empty core with at least a quarter of the
    area remains (the shapes themselves when none does)."""
    m = float(margin)
    while m > 0.02:
        core = shapes.buffer(-m)
        if not core.is_empty and core.area >= 0.25 * shapes.area:
            return core
        m *= 0.5
    return shapes


def _wrap(a: Tensor) -> Tensor:
    return torch.atan2(torch.sin(a), torch.cos(a))


class GoalRegionCost(CostTerm):
    """``J_G`` of a goal region in time (see the module docstring); term name ``"goal"``.

    Args:
        goal: a :class:`~density_planner.environment.road.GoalRegion` (or any object with ``shapes``,
            ``time_interval``, ``velocity``, ``orientation`` and ``alternatives``).
        t0, dt: the occupancy grid's clock: slice ``k`` is at ``t0 + k dt`` [s] (absolute).
        velocity_weight: ``w_v`` [m^2 / (m/s)^2]; orientation_weight: ``w_th`` [m^2 / rad^2].
        far_factor, close_threshold: as :class:`~density_planner.cost.terms.GoalCost`.
        simplify: tolerance [m] of the outline simplification (fewer edges, faster).
        margin: shrink the region by up to this much [m] (see the module docstring).
        time_margin: shrink the time interval by up to this much [s] at both ends (see the module docstring).
        layout: state indices ``(x, y, heading, speed)`` (``None``: the system's facts are unknown, the car's
            layout ``(0, 1, 2, 3)``); :func:`~density_planner.cost.road.with_road_terms` passes the system's.
    """

    name = "goal"

    def __init__(self, goal: Any, *, t0: float, dt: float, velocity_weight: float = 1.0,
                 orientation_weight: float = 25.0, far_factor: float = 1.0, close_threshold: float = 3.0,
                 simplify: float = 0.05, margin: float = 0.0, time_margin: float = 0.0,
                 layout: tuple[int, int, int, int] | None = None):
        self.layout = tuple(layout) if layout is not None else _CAR_LAYOUT
        if not (math.isfinite(t0) and math.isfinite(dt) and dt > 0):
            raise ValueError(f"GoalRegionCost needs a finite t0 and dt > 0, got {t0}, {dt}")
        for name, v in (("velocity_weight", velocity_weight), ("orientation_weight", orientation_weight)):
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {v}")
        self.t0, self.dt = float(t0), float(dt)
        self.velocity_weight = float(velocity_weight)
        self.orientation_weight = float(orientation_weight)
        self.far_factor = float(far_factor)
        self.close_threshold = float(close_threshold)
        alternatives = tuple(getattr(goal, "alternatives", ()) or ()) or (goal,)
        self._alts = []
        for name, value in (("margin", margin), ("time_margin", time_margin)):
            if not math.isfinite(value) or value < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {value}")
        for alt in alternatives:
            shapes = getattr(alt, "shapes", None)
            if shapes is not None and margin > 0:
                shapes = _erode(shapes, margin)
            edges = None if shapes is None else torch.as_tensor(polygon_edges(shapes, simplify=simplify))
            vel = getattr(alt, "velocity", None)
            if vel is not None and margin > 0:
                m = min(margin, 0.25 * (float(vel[1]) - float(vel[0])))
                vel = (float(vel[0]) + m, float(vel[1]) - m)
            ori = getattr(alt, "orientation", None)
            if ori is not None:
                lo, hi = float(ori[0]), float(ori[1])
                width = (hi - lo) % (2 * math.pi) if hi < lo else hi - lo
                half = 0.5 * width - min(0.1 * margin, 0.125 * width)
                ori = None if width >= 2 * math.pi - 1e-9 else (lo + 0.5 * width, half)  # centre, half-width
            t_lo, t_hi = float(alt.time_interval[0]), float(alt.time_interval[1])
            m = min(time_margin, 0.25 * (t_hi - t_lo))
            self._alts.append((edges, (t_lo + m, t_hi - m),
                               None if vel is None else (float(vel[0]), float(vel[1])), ori))

    def times(self, slices: Tensor) -> Tensor:
        """Absolute times [s] of the planning steps (float64, CPU)."""
        return self.t0 + slices.detach().to("cpu", torch.float64) * self.dt

    def _steps(self, times: Tensor, interval: tuple[float, float]) -> Tensor:
        tol = 1e-6
        inside = (times >= interval[0] - tol) & (times <= interval[1] + tol)
        if bool(inside.any()):
            return torch.nonzero(inside).flatten()
        gap = torch.clamp(interval[0] - times, min=0) + torch.clamp(times - interval[1], min=0)
        return torch.argmin(gap).reshape(1)

    def squared_distance(self, x: Tensor, alt: int = 0) -> Tensor:
        """``D(x)`` [m^2] of states ``x (..., nx)`` to alternative ``alt`` (ignoring time)."""
        edges, _, vel, ori = self._alts[alt]
        d = x.new_zeros(x.shape[:-1])
        if edges is not None:
            ix, iy = self.layout[:2]
            pos = x[..., ix:ix + 2] if iy == ix + 1 else x[..., [ix, iy]]
            d = d + distance_to_polygons(pos, edges.to(x)).pow(2)
        if vel is not None and self.velocity_weight > 0:
            v = x[..., self.layout[3]]
            d = d + self.velocity_weight * (torch.relu(vel[0] - v) + torch.relu(v - vel[1])).pow(2)
        if ori is not None and self.orientation_weight > 0:
            centre, half = ori
            d = d + self.orientation_weight * torch.relu(_wrap(x[..., self.layout[2]] - centre).abs() - half).pow(2)
        return d

    def __call__(self, inputs: CostInputs) -> Tensor:
        times = self.times(inputs.slices)
        best = None
        for a, (_, interval, _, _) in enumerate(self._alts):
            k = self._steps(times, interval).to(inputs.x.device)
            xs = inputs.x.index_select(-2, k)  # (*batch, N, K, nx)
            d = self.squared_distance(xs, a).min(-1).values  # (*batch, N)
            w = inputs.weights.index_select(-1, k).mean(-1)  # (*batch, N)
            j = (w * d).sum(-1)
            best = j if best is None else torch.minimum(best, j)
        assert best is not None
        if self.far_factor != 1.0:
            best = best * torch.where(best.detach() >= self.close_threshold, self.far_factor, 1.0)
        return best

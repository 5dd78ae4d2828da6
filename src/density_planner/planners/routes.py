"""Route-seeded candidates for the density planner's first stage: references that follow the road.

On a road map the planner's random stage-1 candidates rarely find the road's shape (a T-junction, a lane change,
a long bend); this module gives it candidates that do, built in four steps:

1. **Routes** (:func:`find_routes`): lane sequences through the :class:`~density_planner.environment.lanes.LaneGraph`
   from the lanes under the start (heading-aligned) to the lanes touching the goal region, over successors and
   same-direction lane changes, the ``max_routes`` shortest by length plus ``lane_change_cost`` per change
   (networkx ``shortest_simple_paths``, Yen's algorithm), continued past the goal along the straightest
   successors. A goal without a position gives the lanes ahead.
2. **Paths** (:func:`route_path`): the routes' centre lines joined into one polyline each; a lane change blends
   from one centre line to the next over ``lane_change_length`` (smoothstep, so heading stays continuous).
3. **Speed profiles** (:func:`speed_profiles`): arc length over time for *keep* (the start speed),
   *accelerate* / *decelerate* (ramp at ``acceleration`` to the cruise speed that puts the vehicle at a target
   point of the goal region at a target time of its interval) and *stop* (reach the goal's centre at the start
   of its time interval, then brake and hold), within the speed limits, and every profile held under the path's
   own limit (:func:`path_speed_limit`: curves by lateral acceleration and turn rate, a stop where the lanes end).
4. **Fit** (:func:`fit_reference_parameters`): the target positions and speeds become piecewise-constant reference
   inputs ``(M, nu, n_segments)`` by a batched least-squares fit (Levenberg-Marquardt) through the reference
   roll-out (:func:`~density_planner.control.reference.plan_grid_reference`), started from a segment-by-segment
   guess and projected onto the input bounds after every step.

:func:`route_seed_parameters` runs all four for a :class:`~density_planner.planners.problem.PlanningProblem`
and returns ``None`` on scenes without a lane map (the paper's random scenes), so the planner then behaves
exactly as without seeds.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..checks import check_positive
from ..control.reference import PiecewiseConstantInputs, plan_grid_reference
from ..environment.lanes import LaneGraph, scene_lane_graph
from ..parallel import ForkedCallError, PendingCalls
from ..systems.base import System

__all__ = [
    "RouteSeedConfig",
    "Route",
    "RouteSeeds",
    "find_routes",
    "route_path",
    "speed_profiles",
    "path_speed_limit",
    "cap_profiles",
    "fit_reference_parameters",
    "route_seed_parameters",
    "start_route_seeds",
    "cancel_route_seeds",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RouteSeedConfig:
    """``[density_planner.routes]``: route-seeded stage-1 candidates (used only on scenes with a lane map)."""

    #: add route-following candidates to the random ones where the scene has lanes
    enabled: bool = True
    #: routes kept (the shortest by length plus lane-change cost)
    max_routes: int = 4
    #: extra route length charged per lane change [m] (prefers staying in lane when lengths are equal)
    lane_change_cost: float = 30.0
    #: distance over which a lane change blends from one centre line to the next [m] (at least; longer at speed:
    #: ``max(lane_change_length, lane_change_time * v0)``)
    lane_change_length: float = 25.0
    #: duration of a lane change at the start speed [s]
    lane_change_time: float = 4.0
    #: comfortable acceleration / deceleration of the speed profiles [m/s^2]
    acceleration: float = 1.5
    #: the profiles slow down in curves to keep the lateral acceleration ``v^2 kappa`` below this [m/s^2] (and the
    #: turn rate ``v kappa`` below 90 % of its input bound where the system has one; :func:`path_speed_limit`)
    lateral_acceleration: float = 3.0
    #: at most this many route candidates join the random ones
    max_candidates: int = 48
    #: random stage-1 candidates beside the route seeds (``density_planner.n_candidates`` where a scene has none):
    #: the seeds start on the road towards the goal, the random ones are the fallback. Measured on the CommonRoad
    #: suite with ``epochs_init``: the same plans pass as with 100 random candidates and 100 epochs, stage 1 in 30 %
    #: less time (docs/history.md, stop 30)
    random_candidates: int = 25
    #: stage-1 epochs where route seeds exist (``density_planner.epochs_init`` where a scene has none). 30 passed the
    #: same plans on the CommonRoad suite but lost 4 of 52 online drives, whose rescues run stage 1
    #: (docs/history.md, stop 45)
    epochs_init: int = 50
    #: Levenberg-Marquardt iterations of the fit through the reference roll-out (:func:`fit_reference_parameters`)
    fit_iterations: int = 3
    #: weight of the squared speed error against the squared position error in the fit [m^2 / (m/s)^2]
    fit_speed_weight: float = 1.0
    #: radius [m] of the goal disc around the scene's goal point where the scene has no goal region
    goal_point_radius: float = 2.0
    #: risk-aware speed profiles kept per route (:func:`risk_aware_profiles`: the best of a two-phase family by
    #: the occupancy the body meets along the path, the goal and the effort); 0 = off
    risk_aware: int = 3
    #: weight of the expected time in collision [m^2 / s] against the squared goal miss in that choice (0.1 s at
    #: P_occ = 1 weighs as a 32-m miss: collision first)
    risk_weight: float = 1.0e4
    #: weight of the squared acceleration [m^2 / (m/s^2)^2 / s] in that choice
    effort_weight: float = 0.05
    #: speed levels of the two-phase family (evenly spaced over the system's speed range). Measured on the suite
    #: (docs/history.md, stop 30): 13 levels (3.3 m/s apart for the road car) / 25 (1.7 m/s) gave 60 / 61 successes,
    #: none lost (USA_US101-22_1, whose goal speed lay between two levels, gained)
    profile_speeds: int = 25
    #: times [s] at which the two-phase profiles may switch to their second target speed
    profile_switch_times: tuple[float, ...] = (1.0, 2.0, 4.0, 6.0, 8.0)

    def __post_init__(self) -> None:
        for name in ("max_routes", "max_candidates", "fit_iterations", "profile_speeds", "random_candidates",
                     "epochs_init"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"routes.{name} must be a positive integer, got {v!r}")
        if isinstance(self.risk_aware, bool) or not isinstance(self.risk_aware, int) or self.risk_aware < 0:
            raise ValueError(f"routes.risk_aware must be an integer >= 0, got {self.risk_aware!r}")
        for name in ("risk_weight", "effort_weight"):
            check_positive(f"routes.{name}", getattr(self, name), allow_zero=True)
        if not all(math.isfinite(t) and t > 0 for t in self.profile_switch_times):
            raise ValueError(f"routes.profile_switch_times must be times > 0 [s], got {self.profile_switch_times!r}")
        for name in ("lane_change_length", "lane_change_time", "acceleration", "lateral_acceleration",
                     "goal_point_radius"):
            check_positive(f"routes.{name}", getattr(self, name))
        for name in ("lane_change_cost", "fit_speed_weight"):
            check_positive(f"routes.{name}", getattr(self, name), allow_zero=True)


@dataclass(frozen=True)
class Route:
    """A lane sequence and its path.

    Attributes:
        lane_ids: the lanes in driving order.
        kinds: ``len(lane_ids) - 1`` edge kinds, ``"successor"`` or ``"change"``.
        path: ``(K, 2)`` polyline [m] from the start's projection onto the first lane to the end of the last.
    """

    lane_ids: tuple[int, ...]
    kinds: tuple[str, ...]
    path: np.ndarray = field(repr=False)

    @property
    def n_changes(self) -> int:
        return sum(k == "change" for k in self.kinds)

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.path, axis=0), axis=1).sum())


@dataclass
class RouteSeeds:
    """What :func:`route_seed_parameters` produced.

    Attributes:
        params: ``(M, nu, n_segments)`` fitted reference parameters (inside the input bounds).
        targets: ``(M, T, 2)`` target positions on the planning grid [m].
        speeds: ``(M, T)`` target speeds [m/s].
        labels: one ``"route i: keep|accelerate|decelerate|stop"`` per candidate.
        fit_rms: ``(M,)`` root-mean-square position error of the fit [m].
        routes: the routes.
        seconds: wall time of route search, profiles and fit [s].
    """

    params: Tensor
    targets: Tensor
    speeds: Tensor
    labels: list[str]
    fit_rms: Tensor
    routes: list[Route]
    seconds: float

    def info(self) -> dict[str, Any]:
        """JSON summary (for ``extras`` / logs)."""
        return {
            "n_routes": len(self.routes),
            "routes": [list(r.lane_ids) for r in self.routes],
            "n_candidates": int(self.params.shape[0]),
            "fit_rms_median": float(self.fit_rms.median()) if self.fit_rms.numel() else None,
            "fit_rms_max": float(self.fit_rms.max()) if self.fit_rms.numel() else None,
            "seconds": self.seconds,
        }


# ----------------------------------------------------------------------------------------------- route search
def find_routes(
    graph: LaneGraph,
    start_xy: tuple[float, float],
    start_heading: float | None,
    goal_shapes: Any | None,
    *,
    max_routes: int = 4,
    lane_change_cost: float = 30.0,
    reach: float = 200.0,
    lane_change_length: float = 25.0,
    continue_for: float = 0.0,
) -> list[Route]:
    """The ``max_routes`` shortest lane routes from the start to the goal (see the module docstring).

    Args:
        graph: the lanes.
        start_xy, start_heading: start position [m] and heading [rad] (None: any direction).
        goal_shapes: shapely geometry of the goal positions; ``None`` (a goal without a position): routes along
            the lanes ahead, up to ``reach`` [m] beyond the start.
        reach: path length [m] to cover for goals without a position.
        continue_for: each route goes on past its last (goal) lane along the straightest successors for up to
            this length [m] (:func:`_continuation`), so that a profile that passes the goal early or reaches it
            fast still has a lane under it; where the lanes end sooner the path ends there.

    Returns an empty list when no lane lies under the start or no route reaches the goal lanes.
    """
    import networkx as nx

    starts = graph.lanes_at(start_xy, start_heading)
    if not starts:
        return []
    g = graph.to_networkx(lane_change_cost=lane_change_cost)
    src, dst = ("source",), ("sink",)
    for s in starts:
        g.add_edge(src, s, kind="start", weight=0.0)
    if goal_shapes is not None:
        goals = graph.lanes_touching(goal_shapes)
        if not goals:
            return []
        for lane_id in goals:
            g.add_edge(lane_id, dst, kind="goal", weight=0.0)
    else:
        _add_reach_sinks(graph, g, starts, start_xy, reach, dst)
    routes: list[Route] = []
    try:
        paths = nx.shortest_simple_paths(g, src, dst, weight="weight")
        for nodes in paths:
            lane_ids = tuple(int(n) for n in nodes[1:-1])
            kinds = tuple(g.edges[a, b]["kind"] for a, b in zip(lane_ids[:-1], lane_ids[1:]))
            more = _continuation(graph, lane_ids[-1], continue_for, set(lane_ids))
            lane_ids, kinds = lane_ids + more, kinds + ("successor",) * len(more)
            routes.append(Route(lane_ids, kinds, route_path(graph, lane_ids, kinds, start_xy,
                                                            lane_change_length=lane_change_length)))
            if len(routes) >= max_routes:
                break
    except nx.NetworkXNoPath:
        pass
    return routes


def _add_reach_sinks(graph: LaneGraph, g: Any, starts: list[int], start_xy, reach: float, dst) -> None:
    """Goal without a position: every lane where the distance driven from the start reaches ``reach`` becomes a
    sink (breadth-first over successors; lanes without successors too)."""
    import shapely

    frontier = []
    for s in starts:
        lane = graph[s]
        done = float(lane.centerline.project(shapely.Point(*start_xy)))
        frontier.append((s, lane.length - done))
    seen = set()
    while frontier:
        lane_id, covered = frontier.pop()
        if lane_id in seen:
            continue
        seen.add(lane_id)
        lane = graph[lane_id]
        if covered >= reach or not lane.successors:
            g.add_edge(lane_id, dst, kind="goal", weight=0.0)
            continue
        for nxt in lane.successors:
            frontier.append((nxt, covered + graph[nxt].length))


def _continuation(graph: LaneGraph, last: int, length: float, used: set[int]) -> tuple[int, ...]:
    """Lanes that continue ``last`` for at least ``length`` [m] where the map has them: at each lane end the
    successor whose centre line starts with the smallest turn from the lane's end heading (going straight where
    possible), never a lane already ``used`` (no loops)."""
    out: list[int] = []
    covered, lane_id, seen = 0.0, last, set(used)
    while covered < length:
        lane = graph[lane_id]
        nexts = [n for n in lane.successors if n not in seen]
        if not nexts:
            break
        c = _center(lane)
        h_end = math.atan2(c[-1, 1] - c[-2, 1], c[-1, 0] - c[-2, 0])
        turns = []
        for n in nexts:
            cn = _center(graph[n])
            turns.append(abs(math.remainder(math.atan2(cn[1, 1] - cn[0, 1], cn[1, 0] - cn[0, 0]) - h_end, 2 * math.pi)))
        lane_id = nexts[int(np.argmin(turns))]
        seen.add(lane_id)
        out.append(lane_id)
        covered += graph[lane_id].length
    return tuple(out)


def _center(lane: Any) -> np.ndarray:
    """The centre polyline of a lane (always set once the lane is built)."""
    assert lane.center is not None
    return lane.center


def _resample(line: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Points of the polyline ``line (K, 2)`` at arc-length ``fractions`` in [0, 1]."""
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.clip(fractions, 0.0, 1.0) * cum[-1]
    return np.stack([np.interp(s, cum, line[:, 0]), np.interp(s, cum, line[:, 1])], axis=-1)


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def route_path(
    graph: LaneGraph,
    lane_ids: tuple[int, ...],
    kinds: tuple[str, ...],
    start_xy: tuple[float, float],
    *,
    lane_change_length: float = 25.0,
    spacing: float = 0.5,
) -> np.ndarray:
    """``(K, 2)`` path [m] of a lane route: from the start's projection onto the first lane along the centre
    lines; lanes joined by lane changes form one section in which the path blends from the first lane's centre
    line to the last one's over ``lane_change_length`` (measured on the first lane), as a smoothstep."""
    import shapely

    sections: list[list[int]] = [[lane_ids[0]]]
    for kind, lane_id in zip(kinds, lane_ids[1:]):
        if kind == "change":
            sections[-1].append(lane_id)
        else:
            sections.append([lane_id])
    pieces: list[np.ndarray] = []
    for j, section in enumerate(sections):
        first = graph[section[0]]
        length = max(first.length, 1e-6)
        phi_in = 0.0
        if j == 0:
            phi_in = float(first.centerline.project(shapely.Point(*start_xy))) / length
            phi_in = min(phi_in, 1.0)
        n = max(2, int(math.ceil((1.0 - phi_in) * length / spacing)) + 1)
        phi = np.linspace(phi_in, 1.0, n)
        centres = np.stack([_resample(_center(graph[i]), phi) for i in section])  # (k, n, 2)
        if len(section) == 1:
            pts = centres[0]
        else:
            k = len(section) - 1
            span = min(1.0 - phi_in, k * lane_change_length / length)
            c = k * _smoothstep((phi - phi_in) / max(span, 1e-9))
            lo = np.clip(np.floor(c).astype(int), 0, k - 1)
            frac = (c - lo)[:, None]
            idx = np.arange(n)
            pts = (1.0 - frac) * centres[lo, idx] + frac * centres[lo + 1, idx]
        pieces.append(pts if not pieces else pts[1:] if np.allclose(pts[0], pieces[-1][-1]) else pts)
    path = np.concatenate(pieces)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(path, axis=0), axis=1) > 1e-6])
    path = path[keep]
    if path.shape[0] < 2:  # degenerate: the start sits at the very end of a lane without successors
        lane = graph[lane_ids[-1]]
        d = _center(lane)[-1] - _center(lane)[-2]
        path = np.vstack([path[:1], path[:1] + d / max(np.linalg.norm(d), 1e-9)])
    return path


# --------------------------------------------------------------------------------------------- speed profiles
def _arc(path: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])


def path_points(path: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points [m] at arc lengths ``s`` along ``path``; beyond its ends the path continues straight."""
    cum = _arc(path)
    s = np.asarray(s, dtype=np.float64)
    pts = np.stack([np.interp(s, cum, path[:, 0]), np.interp(s, cum, path[:, 1])], axis=-1)
    d0 = (path[1] - path[0]) / max(np.linalg.norm(path[1] - path[0]), 1e-9)
    d1 = (path[-1] - path[-2]) / max(np.linalg.norm(path[-1] - path[-2]), 1e-9)
    before, after = s < 0, s > cum[-1]
    pts[before] = path[0] + s[before, None] * d0
    pts[after] = path[-1] + (s[after, None] - cum[-1]) * d1
    return pts


Rate = float | tuple[float, float]


def _rate_pair(rate: Rate) -> tuple[float, float]:
    """``(accelerate, brake)`` [m/s^2] of a rate given as one number (both) or as the pair."""
    return (float(rate), float(rate)) if isinstance(rate, (int, float)) else (float(rate[0]), float(rate[1]))


def _ramp(dv: np.ndarray, elapsed: np.ndarray, rate: Rate) -> np.ndarray:
    """The speed change towards ``dv`` after ``elapsed`` seconds of ramping at ``rate`` (accelerating or braking)."""
    up, down = _rate_pair(rate)
    return np.where(dv > 0, np.minimum(dv, up * elapsed), -np.minimum(-dv, down * elapsed))


def _ramp_hold(v0: float, v_c: np.ndarray, tau: np.ndarray, acc: Rate) -> np.ndarray:
    """Speeds ``(C, T)``: from ``v0`` ramp at ``acc`` (one rate, or ``(accelerate, brake)``) to ``v_c (C,)``, then
    hold."""
    return v0 + _ramp(v_c[:, None] - v0, tau[None, :], acc)


def first_distinct_rows(a: np.ndarray) -> np.ndarray:
    """Indices, ascending, of the first occurrence of each distinct row of ``a (N, T)`` (rows compared as floats):
    ``np.sort(np.unique(a, axis=0, return_index=True)[1])`` without its lexicographic sort of whole rows (0.11 s for
    the ~12 500 x 101 speed profiles of a scene; this: ~5 ms). Rows are grouped by an exact integer hash of their
    bits (a wrapping sum: equal rows, equal keys, whatever the order of summation) and each group is checked to hold
    equal rows (where one does not, ``np.unique`` decides)."""
    a = np.ascontiguousarray(a, dtype=np.float64) + 0.0  # -0.0 + 0.0 = 0.0: equal rows have equal bits
    n, t = a.shape
    if n < 2:
        return np.arange(n)
    mult = (np.arange(1, t + 1, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15)) | np.uint64(1)
    key = (a.view(np.uint64) * mult).sum(axis=1, dtype=np.uint64)  # modulo 2**64: exact
    order = np.argsort(key, kind="stable")  # equal keys keep their order: a group's first is its first row
    starts = np.r_[True, key[order[1:]] != key[order[:-1]]]
    first = order[starts]
    later = ~starts
    owner = first[np.cumsum(starts) - 1]  # each row's group's first row
    if not np.array_equal(a[order[later]], a[owner[later]]):  # distinct rows that share a key (not met in practice)
        return np.sort(np.unique(a, axis=0, return_index=True)[1])
    return np.sort(first)


def _integrate(v: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Arc length ``(C, T)`` from speeds on the grid ``tau`` (trapezoid rule, starting at 0)."""
    dt = np.diff(tau)
    return np.concatenate([np.zeros((v.shape[0], 1)), np.cumsum(0.5 * (v[:, 1:] + v[:, :-1]) * dt, axis=1)], axis=1)


def _brake_to(v: np.ndarray, s: np.ndarray, tau: np.ndarray, s_stop: float, acc: float, v_lo: float) -> np.ndarray:
    """The profiles ``v (C, T)`` (arc lengths ``s``) with a brake at ``acc`` from the first time the braking
    distance reaches ``s_stop``, down to ``v_lo``."""
    trigger = s + v * v / (2.0 * acc) >= s_stop
    has = trigger.any(axis=1)
    k = np.where(has, trigger.argmax(axis=1), tau.size - 1)
    t_k = tau[k][:, None]
    v_k = v[np.arange(v.shape[0]), k][:, None]
    brake = np.maximum(v_k - acc * (tau[None, :] - t_k), v_lo)
    return np.where(tau[None, :] >= t_k, np.minimum(v, brake), v)


#: path lengths [m] over which path_speed_limit measures heading changes
_CURVE_WINDOWS = (4.0, 8.0, 16.0, 32.0, 64.0)


def path_speed_limit(path: np.ndarray, v_max: float, *, lateral_acceleration: float, deceleration: float,
                     turn_rate: float | None = None, s_end: float | None = None, spacing: float = 0.5,
                     feel_time: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """The highest speed ``(s, v_lim)`` [m, m/s] at arc lengths ``s`` along ``path`` that the road allows:

    * in curves, with ``dtheta_w(s)`` the heading change over ``w`` metres of path centred on ``s`` (``w`` in
      4, 8, 16, 32, 64 m; a kink between two lanes' centre lines counts as the bend it stands for):

      - lateral acceleration: ``v <= sqrt(lateral_acceleration / kappa_w)``, ``kappa_w = dtheta_w / w``, with the
        curvature averaged over the path the vehicle covers in ``feel_time`` [s] at that speed (the largest window
        ``w <= max(4, v feel_time)``): the vertex noise of recorded lane maps (a 0.06-rad kink every few metres on
        NGSIM highways, curvature 0.015 1/m over 4 m) then limits slow driving only, where it is felt, while a real
        curve limits every speed;
      - turn rate, for a system whose turn rate is an input bounded by ``turn_rate`` [rad/s]: turning
        ``dtheta_w`` within ``w`` metres needs ``v <= turn_rate w / dtheta_w``, for every window (a hard bound);
    * from ``s_end`` on (where the lanes end: the map's edge, a dead end): 0;
    * everywhere ``v_max``; and braking at ``deceleration`` [m/s^2] must reach each limit in time (backward pass:
      ``v_lim(s)^2 = min_{s' >= s} cap(s')^2 + 2 deceleration (s' - s)``).
    Beyond the path's end the last value holds."""
    cum = _arc(path)
    s = np.arange(0.0, max(cum[-1], spacing) + spacing, spacing)
    d = 0.25

    def heading(at: np.ndarray) -> np.ndarray:
        q = path_points(path, at + d) - path_points(path, at - d)
        return np.arctan2(q[:, 1], q[:, 0])

    lateral = np.zeros_like(s)
    cap = np.full_like(s, float(v_max))
    for j, w in enumerate(_CURVE_WINDOWS):
        turn = np.abs(np.remainder(heading(s + 0.5 * w) - heading(s - 0.5 * w) + math.pi, 2 * math.pi) - math.pi)
        kappa = np.maximum(turn / w, 1e-12)
        # the speeds whose window this is: v feel_time in [w, next w) (below 4 m: the first)
        lo = 0.0 if j == 0 else w / feel_time
        hi = _CURVE_WINDOWS[j + 1] / feel_time if j + 1 < len(_CURVE_WINDOWS) else math.inf
        c = np.sqrt(lateral_acceleration / kappa)
        lateral = np.maximum(lateral, np.where(c >= lo, np.minimum(c, hi), 0.0))
        if turn_rate is not None:
            cap = np.minimum(cap, turn_rate * w / np.maximum(turn, 1e-12))
    cap = np.minimum(cap, lateral)
    if s_end is not None:
        cap[s >= s_end] = 0.0
    q = cap**2 + 2.0 * deceleration * s
    v_lim = np.sqrt(np.maximum(np.minimum.accumulate(q[::-1])[::-1] - 2.0 * deceleration * s, 0.0))
    return s, v_lim


def cap_profiles(v: np.ndarray, tau: np.ndarray, limit: tuple[np.ndarray, np.ndarray], *, acceleration: float,
                 deceleration: float, v_lo: float, stop: tuple[float, tuple[np.ndarray, np.ndarray]] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Speed profiles ``v (P, T)`` on the times ``tau`` held under the path's speed limit (:func:`path_speed_limit`)
    where they drive: ``v'(t_k) = min(v(t_k), v_lim(s'(t_{k-1}) + v'(t_{k-1}) dt), v'(t_{k-1}) + acceleration
    dt)``, never braking harder than ``deceleration`` nor below ``v_lo``; the start speed is kept. With
    ``stop = (s_end, limit_with_stop)`` the profiles that would pass ``s_end`` within the times ``tau`` (the end of
    the lanes within the horizon) are held under ``limit_with_stop`` instead: the others need not slow down for
    an end they never reach (a map's edge shortly after a highway goal). Returns the arc lengths ``s' (P, T)``
    (from 0) and speeds ``v' (P, T)``; profiles that stay under the limit come back unchanged."""
    if stop is not None:
        s, out = cap_profiles(v, tau, limit, acceleration=acceleration, deceleration=deceleration, v_lo=v_lo)
        over = s[:, -1] > stop[0]
        if over.any():
            s[over], out[over] = cap_profiles(v[over], tau, stop[1], acceleration=acceleration,
                                              deceleration=deceleration, v_lo=v_lo)
        return s, out
    s_grid, v_lim = limit
    out = np.empty_like(v)
    s = np.zeros_like(v)
    out[:, 0] = v[:, 0]
    for k in range(1, tau.size):
        dt = float(tau[k] - tau[k - 1])
        cap = np.interp(s[:, k - 1] + out[:, k - 1] * dt, s_grid, v_lim)  # at the next step's position
        want = np.minimum(np.minimum(v[:, k], cap), out[:, k - 1] + acceleration * dt)
        out[:, k] = np.maximum(want, np.maximum(out[:, k - 1] - deceleration * dt, v_lo))
        s[:, k] = s[:, k - 1] + 0.5 * (out[:, k - 1] + out[:, k]) * dt
    return s, out


def speed_profiles(
    s0: float,
    v0: float,
    tau: np.ndarray,
    goal_arc: tuple[float, float] | None,
    goal_time: tuple[float, float],
    *,
    v_limits: tuple[float, float],
    acceleration: float,
    max_acceleration: float | None = None,
    cap: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Arc-length profiles along a path (see the module docstring).

    Args:
        s0: arc length of the start [m]; v0: start speed [m/s].
        tau: ``(T,)`` planning times relative to the start [s], increasing from 0.
        goal_arc: ``(s_lo, s_hi)`` arc lengths [m] where the path is inside the goal region (None: no
            position goal; only keep / accelerate / decelerate to the speed limits are made).
        goal_time: ``(t_lo, t_hi)`` goal time interval relative to the start [s], already clipped to
            ``[0, tau[-1]]``.
        v_limits: ``(v_min, v_max)`` [m/s]; acceleration: ramp rate [m/s^2].
        max_acceleration: a harder ramp [m/s^2] used where ``acceleration`` cannot reach a target (it must
            miss by more than 1 m at the comfortable rate).
        cap: ``v (C, T) -> (s, v)``, the road's speed limit (:func:`cap_profiles`, arc lengths from 0): every
            profile is held under it, and the targeted ones are chosen among capped ones, so that a curve on the
            way does not make them late.

    Returns:
        ``s (P, T)`` arc lengths [m], ``v (P, T)`` speeds [m/s] and one label per profile.
    """
    v_lo, v_hi = float(v_limits[0]), float(v_limits[1])
    v0 = float(np.clip(v0, v_lo, v_hi))
    tl, th = goal_time
    cruise = np.linspace(v_lo, v_hi, 129)
    rates = [acceleration] if max_acceleration is None or max_acceleration <= acceleration else \
        [acceleration, float(max_acceleration)]
    v_all = np.concatenate([_ramp_hold(v0, cruise, tau, a) for a in rates])
    if cap is not None:
        v_all = cap(v_all)[1]
    s_all = s0 + _integrate(v_all, tau)
    hard = np.repeat(np.arange(len(rates)) > 0, cruise.size)  # profiles at the harder rate
    profiles: list[np.ndarray] = [np.full_like(tau, v0)[None]]
    labels = ["keep"]

    def reach(s_target: float, t_target: float) -> np.ndarray:
        k = int(np.clip(np.searchsorted(tau, t_target - 1e-9), 0, tau.size - 1))
        best = int(np.argmin(np.abs(s_all[:, k] - s_target) + 1.0 * hard))
        return v_all[best]

    if goal_arc is None:
        for v_c, label in ((v_hi, "accelerate"), (0.5 * (v0 + v_lo), "decelerate")):
            profiles.append(_ramp_hold(v0, np.array([v_c]), tau, acceleration))
            labels.append(label)
    else:
        s_lo, s_hi = goal_arc
        width = s_hi - s_lo
        s_mid = 0.5 * (s_lo + s_hi)
        targets = [(s_mid, tl), (s_mid, 0.5 * (tl + th)), (s_mid, th),
                   (s_lo + 0.2 * width, tl), (s_hi - 0.2 * width, th)]
        for s_t, t_t in targets:
            v = reach(s_t, t_t)
            profiles.append(v[None])
            labels.append("accelerate" if v[-1] > v0 + 0.25 else "decelerate" if v[-1] < v0 - 0.25 else "keep")
        # stop: cruise, then brake at `acceleration` so as to stand still at the goal's centre, and hold; the
        # cruise speed that puts the vehicle nearest to that point at the start of the interval is chosen
        v_stop = _brake_to(v_all, s_all, tau, s_mid, acceleration, v_lo)
        if cap is not None:
            v_stop = cap(v_stop)[1]
        s_stop = s0 + _integrate(v_stop, tau)
        k = int(np.clip(np.searchsorted(tau, tl - 1e-9), 0, tau.size - 1))
        profiles.append(v_stop[int(np.argmin(np.abs(s_stop[:, k] - s_mid) + 1.0 * hard))][None])
        labels.append("stop")
    v = np.concatenate(profiles)
    if cap is not None:
        s_rel, v = cap(v)
        return s0 + s_rel, v, labels
    return s0 + _integrate(v, tau), v, labels


def profile_family(v0: float, tau: np.ndarray, *, v_limits: tuple[float, float], rates: tuple[Rate, ...],
                   n_speeds: int, switch_times: tuple[float, ...]) -> np.ndarray:
    """Speeds ``(C, T)`` of two-phase profiles: from ``v0`` ramp at a rate of ``rates`` towards ``v1``; from the
    switch time on, ramp at a rate of ``rates`` towards ``v2`` (``v1, v2`` on ``n_speeds`` levels of
    ``v_limits``); every combination, switch times past the horizon give one-phase profiles. A rate is one number
    [m/s^2] or an ``(accelerate, brake)`` pair (a car brakes harder than it accelerates)."""
    v_lo, v_hi = float(v_limits[0]), float(v_limits[1])
    levels = np.linspace(v_lo, v_hi, n_speeds)
    horizon = float(tau[-1])
    switches = sorted({min(float(t), horizon) for t in switch_times} | {horizon})
    out = []
    for r1 in rates:
        first = _ramp_hold(float(np.clip(v0, v_lo, v_hi)), levels, tau, r1)  # (n, T)
        for t_s in switches:
            k = int(np.searchsorted(tau, t_s - 1e-9))
            if k >= tau.size - 1:
                out.append(first)
                continue
            v_k = first[:, k]  # (n,)
            for r2 in rates:
                dv = levels[None, :] - v_k[:, None]  # (n1, n2)
                rel = np.maximum(tau[None, None, :] - tau[k], 0.0)
                second = v_k[:, None, None] + _ramp(dv[..., None], rel, r2)
                prof = np.where(tau[None, None, :] >= tau[k], second, first[:, None, :])
                out.append(prof.reshape(-1, tau.size))
    return np.clip(np.concatenate(out), v_lo, v_hi)


def risk_aware_profiles(
    occupancy: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
    path: np.ndarray,
    v0: float,
    tau: np.ndarray,
    goal_arc: tuple[float, float] | None,
    goal_time: tuple[float, float],
    *,
    v_limits: tuple[float, float],
    rates: tuple[Rate, ...],
    n_speeds: int,
    switch_times: tuple[float, ...],
    n_keep: int,
    risk_weight: float,
    effort_weight: float,
    goal_speed: tuple[float, float] | None = None,
    speed_limit: tuple[np.ndarray, np.ndarray] | None = None,
    stop: tuple[float, tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``n_keep`` best of :func:`profile_family` along ``path`` by a cost that sees the scene's occupancy.

    Each profile ``s(t)`` puts the vehicle on the path (heading along it); ``occupancy(xy (C, T, 2), heading
    (C, T), speed (C, T)) -> (C, T)`` is the occupancy its body meets (the problem's collision model). The cost is::

        risk_weight * sum_t P_occ(t) dt  +  d_goal^2  +  effort_weight * sum_t a(t)^2 dt

    with ``d_goal^2`` the smallest, over the times of the goal interval, of the squared distance [m] along the path from
    ``s(t)`` to ``goal_arc`` (0 without a position goal) plus the squared distance [m/s] of the speed ``v(t)`` to
    ``goal_speed`` (the goal's speed interval, shrunk by a quarter of its width, at most 0.5 m/s, like the goal-region
    cost's margin; 1 m^2 per (m/s)^2, the cost's default weight). With ``speed_limit`` (:func:`path_speed_limit`) the
    profiles are first held under the road's limit in curves and, with ``stop``, before the end of the lanes
    (:func:`cap_profiles`).
    Profiles are kept best first, skipping any whose
    speeds differ from a kept one by less than 1 m/s RMS (diverse seeds). Returns ``(s, v, cost)`` of the kept profiles.
    """
    v = profile_family(v0, tau, v_limits=v_limits, rates=rates, n_speeds=n_speeds, switch_times=switch_times)
    # the family repeats profiles (a switch to the speed already held, ramps that end alike): each is scored once,
    # in the family's order (the first of equal profiles is the one the stable ranking below would keep)
    v = v[first_distinct_rows(np.round(v, 9))]
    s = _integrate(v, tau)
    if speed_limit is not None:  # the road's curves and end (path_speed_limit)
        pairs = [_rate_pair(r) for r in rates]
        s, v = cap_profiles(v, tau, speed_limit, acceleration=max(p[0] for p in pairs),
                            deceleration=max(p[1] for p in pairs), v_lo=float(v_limits[0]), stop=stop)
    dt = np.diff(tau, prepend=tau[0])
    xy = path_points(path, s)
    ahead = path_points(path, s + 0.5)
    heading = np.arctan2(ahead[..., 1] - xy[..., 1], ahead[..., 0] - xy[..., 0])
    p_occ = occupancy(xy, heading, v)
    cost = risk_weight * (p_occ * dt).sum(axis=1)
    if goal_arc is not None:
        in_time = (tau >= goal_time[0] - 1e-9) & (tau <= goal_time[1] + 1e-9)
        if not in_time.any():
            in_time = np.abs(tau - goal_time[1]) == np.abs(tau - goal_time[1]).min()
        d = np.maximum(goal_arc[0] - s[:, in_time], 0.0) + np.maximum(s[:, in_time] - goal_arc[1], 0.0)
        miss = d**2
        if goal_speed is not None:
            m = min(0.5, 0.25 * (goal_speed[1] - goal_speed[0]))
            vt = v[:, in_time]
            miss = miss + (np.maximum(goal_speed[0] + m - vt, 0.0) + np.maximum(vt - goal_speed[1] + m, 0.0)) ** 2
        cost = cost + miss.min(axis=1)
    acc = np.diff(v, axis=1) / np.maximum(np.diff(tau), 1e-9)
    cost = cost + effort_weight * (acc**2 * np.diff(tau)).sum(axis=1)
    order = np.argsort(cost, kind="stable")
    kept: list[int] = []
    for i in order:
        if all(np.sqrt(np.mean((v[i] - v[j]) ** 2)) >= 1.0 for j in kept):
            kept.append(int(i))
        if len(kept) >= n_keep:
            break
    idx = np.asarray(kept, dtype=np.int64)
    return s[idx], v[idx], cost[idx]


# --------------------------------------------------------------------------------------------------------- fit
def _unwrap_from(theta0: float, headings: np.ndarray) -> np.ndarray:
    """Headings ``(M, T)`` unwrapped along time and shifted so the first lies within pi of ``theta0``."""
    h = np.unwrap(headings, axis=-1)
    shift = np.round((theta0 - h[..., :1]) / (2 * math.pi)) * 2 * math.pi
    return h + shift


def fit_reference_parameters(
    system: System,
    start: Tensor,
    parameterization: PiecewiseConstantInputs,
    targets: Tensor,
    speeds: Tensor,
    headings: Tensor | None = None,
    *,
    iterations: int = 3,
    speed_weight: float = 1.0,
) -> tuple[Tensor, Tensor]:
    """Reference parameters whose roll-out follows the targets (batched over ``M`` candidates).

    Minimises the least-squares error ``mean_k ||p_k - p*_k||^2 + speed_weight * mean_k (v_k - v*_k)^2`` per
    candidate over its ``nu x n_segments`` parameters by Levenberg-Marquardt through
    :func:`~density_planner.control.reference.plan_grid_reference` (any system): the Jacobian of the residuals by
    forward differences (one batched roll-out of ``M (P + 1)`` references, ``P = nu n_segments``), a damped
    Gauss-Newton step per candidate projected onto the input bounds, kept where it lowers that candidate's error
    (the damping then shrinks by 3; else the step is refused and the damping grows by 4). A few iterations reach the
    least-squares optimum that 80 Adam steps did not (suite scenes: median RMS 0.34 -> ~0.1 m on narrow urban lanes,
    where 0.3 m puts the body over the kerb). Works in float64 whatever the targets' dtype. The initial guess reads
    the acceleration (``system.acceleration_input``) and, where the system has one, the turn rate
    (``system.turn_rate_input``) off the targets per segment (needs ``headings (M, T)`` [rad], else they are taken
    from the target positions); other inputs start at 0.

    Args:
        start: ``(nx,)`` reference start state.
        targets: ``(M, T, 2)`` positions [m] on the planning grid (``T = parameterization.n_plan``).
        speeds: ``(M, T)`` speeds [m/s].

    Returns:
        ``params (M, nu, n_segments)`` (dtype of ``targets``) and the root-mean-square position error ``(M,)`` [m].
    """
    par = parameterization
    m, t = targets.shape[0], targets.shape[1]
    if t != par.n_plan or speeds.shape != (m, t):
        raise ValueError(f"targets must be (M, {par.n_plan}, 2) and speeds (M, {par.n_plan}), got "
                         f"{tuple(targets.shape)} and {tuple(speeds.shape)}")
    out_dtype, device = targets.dtype, targets.device
    dtype = torch.float64
    targets, speeds = targets.to(dtype), speeds.to(dtype)
    lo, hi = system.input_bounds
    low = torch.tensor(lo, dtype=dtype, device=device)[:, None]
    high = torch.tensor(hi, dtype=dtype, device=device)[:, None]
    stride = par.steps_per_segment // par.plan_stride if par.steps_per_segment % par.plan_stride == 0 else None
    # initial guess: per-segment heading and speed changes of the target
    if headings is None:
        d = targets[:, 1:] - targets[:, :-1]
        h = torch.atan2(d[..., 1], d[..., 0])
        headings = torch.cat([h, h[:, -1:]], dim=1)
    ih, iv = system.heading_index, system.speed_index
    if ih is None or iv is None or system.acceleration_input is None:
        raise ValueError(f"route seeds need a system with heading, speed and an acceleration input; "
                         f"{type(system).__name__} lacks one")
    theta = torch.as_tensor(_unwrap_from(float(start[ih]), headings.detach().cpu().double().numpy()))
    theta[:, 0] = float(start[ih])  # the reference starts at the vehicle's own heading
    theta = theta.to(dtype=dtype, device=device)
    seg_t = torch.linspace(0, t - 1, par.n_segments + 1, device=device).round().long()
    if stride is not None:
        seg_t = torch.arange(par.n_segments + 1, device=device) * stride
    dur = par.segment_duration
    start = start.to(dtype=dtype, device=device)
    omega = (theta[:, seg_t[1:]] - theta[:, seg_t[:-1]]) / dur
    acc = (speeds[:, seg_t[1:]] - speeds[:, seg_t[:-1]]) / dur
    acc = acc.clone()
    acc[:, 0] = acc[:, 0] + (speeds[:, 0] - start[iv]) / dur  # start speed differs from the profile's
    params = torch.zeros(m, system.nu, par.n_segments, dtype=dtype, device=device)
    params[:, system.acceleration_input] = acc
    if system.turn_rate_input is not None:
        params[:, system.turn_rate_input] = omega
    params = torch.maximum(torch.minimum(params, high), low)
    w_v = math.sqrt(speed_weight)
    if stride is not None:
        params = _segment_by_segment(system, start, par, stride, params, targets, speeds, theta, low, high, w_v)

    def residuals(p: Tensor, rep: int) -> Tensor:
        """``(M * rep, R)`` residuals of ``p (M * rep, nu, S)`` (candidate-major) with ``|r|^2`` the error."""
        x, _ = plan_grid_reference(system, start, p, par)
        x = x.reshape(m, rep, t, -1)
        pos = (system.positions(x) - targets[:, None]).reshape(m, rep, -1)
        spd = w_v * (x[..., iv] - speeds[:, None])
        return (torch.cat([pos, spd], dim=-1) / math.sqrt(t)).reshape(m * rep, -1)

    with torch.no_grad():
        params, r = _levenberg_marquardt(residuals, params, low, high, iterations)
        pos_err = r[:, : 2 * t].pow(2).sum(-1)  # the position part of |r|^2: mean_k ||p_k - p*_k||^2
    return params.to(out_dtype).contiguous(), pos_err.sqrt().to(out_dtype)


def _damped_step(jac: Tensor, r: Tensor, lam: Tensor) -> Tensor:
    """Levenberg-Marquardt step ``(B, P)`` for residuals ``r (B, R)`` with Jacobian ``jac (B, P, R)`` (transposed)
    and damping ``lam (B,)`` (Marquardt's scaling by the diagonal, plus a floor for flat directions)."""
    hess = jac @ jac.transpose(1, 2)
    grad = jac @ r.unsqueeze(-1)
    diag = torch.diagonal(hess, dim1=1, dim2=2)
    damp = lam[:, None] * (diag + 1e-9 * diag.mean(-1, keepdim=True) + 1e-12)
    return torch.linalg.solve(hess + torch.diag_embed(damp), grad).squeeze(-1)


def _levenberg_marquardt(residuals: Callable[[Tensor, int], Tensor], u: Tensor, low: Tensor, high: Tensor,
                         iterations: int, eps: float = 1e-6) -> tuple[Tensor, Tensor]:
    """``iterations`` Levenberg-Marquardt steps on ``u (M, *shape)``, batched over the ``M`` candidates, projected
    onto ``[low, high]``: ``residuals(p (M * rep, *shape), rep) -> (M * rep, R)`` (candidate-major); the Jacobian by
    forward differences in one call with ``rep = P`` (one probe per parameter); a step is kept where it lowers that
    candidate's ``|r|^2`` (its damping then shrinks by 3; else it grows by 4). Returns ``u`` and its residuals."""
    m, shape = u.shape[0], u.shape[1:]
    n_p = shape.numel()
    eye = torch.eye(n_p, dtype=u.dtype, device=u.device)
    lam = torch.full((m,), 1e-3, dtype=u.dtype, device=u.device)
    r = residuals(u, 1)
    err = r.pow(2).sum(-1)
    for _ in range(iterations):
        probes = (u.reshape(m, 1, n_p) + eps * eye).reshape(m * n_p, *shape)
        jac = (residuals(probes, n_p).reshape(m, n_p, -1) - r[:, None]) / eps  # (M, P, R)
        trial = torch.maximum(torch.minimum(u - _damped_step(jac, r, lam).reshape(m, *shape), high), low)
        r_trial = residuals(trial, 1)
        err_trial = r_trial.pow(2).sum(-1)
        better = err_trial < err
        u = torch.where(better.reshape(m, *([1] * len(shape))), trial, u)
        r = torch.where(better[:, None], r_trial, r)
        err = torch.where(better, err_trial, err)
        lam = torch.where(better, lam / 3.0, lam * 4.0)
    return u, r


def _segment_by_segment(system: System, start: Tensor, par: PiecewiseConstantInputs, stride: int, params: Tensor,
                        targets: Tensor, speeds: Tensor, theta: Tensor, low: Tensor, high: Tensor, w_v: float,
                        iterations: int = 3, heading_weight: float = 2.0, window: int = 2) -> Tensor:
    """Initial guess for the fit, one segment after the other as a tracking controller would: from the state the
    earlier segments reach, the inputs of the next ``window`` segments are fitted (a few damped Gauss-Newton steps)
    to their targets, the window's end heading pulled towards the target's (``heading_weight`` [m/rad]), and the
    first segment's inputs are kept (receding horizon: fitting one segment alone over-corrects and oscillates). So
    the errors of one segment do not carry over into the next as they do when all are read off the targets at
    once."""
    import dataclasses

    m, nu, n_seg = params.shape
    ih, iv = system.heading_index, system.speed_index
    x = start.expand(m, -1)
    out = params.clone()
    for j in range(n_seg):
        part = dataclasses.replace(par, n_segments=min(window, n_seg - j))
        n = part.n_segments * stride
        sl = slice(j * stride + 1, j * stride + n + 1)

        def residuals(u: Tensor, rep: int, x0: Tensor = x, part: PiecewiseConstantInputs = part, sl: slice = sl,
                      n: int = n) -> Tensor:
            xs, _ = plan_grid_reference(system, x0.repeat_interleave(rep, dim=0), u, part)
            xs = xs.reshape(m, rep, n + 1, -1)[:, :, 1:]
            pos = (system.positions(xs) - targets[:, None, sl]).reshape(m, rep, -1)
            spd = w_v * (xs[..., iv] - speeds[:, None, sl])
            head = heading_weight * (xs[..., -1, ih] - theta[:, None, sl.stop - 1])
            return torch.cat([pos, spd, head.unsqueeze(-1)], dim=-1).reshape(m * rep, -1)

        u, _ = _levenberg_marquardt(residuals, out[:, :, j:j + part.n_segments], low, high, iterations)
        out[:, :, j:j + part.n_segments] = u  # the later segments of the window are the next window's start
        x = plan_grid_reference(system, x, u, part)[0][:, stride]
    return out


# ------------------------------------------------------------------------------------------------ for a problem
Interval = tuple[float, float]


def _goal_of(problem: Any, radius: float) -> tuple[Any | None, Interval | None, Interval | None]:
    """``(goal shapes, absolute goal time interval or None, goal speed interval or None)`` of the problem's scene."""
    import shapely

    road = getattr(problem.scene, "road", None)
    goal = getattr(road, "goal", None)
    if goal is not None:
        speed = getattr(goal, "velocity", None)
        return goal.shapes, tuple(goal.time_interval), None if speed is None else (float(speed[0]), float(speed[1]))
    gx, gy = problem.scene.goal
    return shapely.Point(gx, gy).buffer(radius), None, None


def _body_occupancy(problem: Any, dtype: torch.dtype, device: torch.device | str
                    ) -> Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """``(xy (C, T, 2), heading (C, T), speed (C, T)) -> (C, T)``: the occupancy the problem's body meets at those
    poses on the planning times (:meth:`~density_planner.risk.collision.CollisionModel.occupancy`)."""
    system = problem.system
    model = problem.collision(device)
    slices = problem.slices(device=device)
    ix, iy = system.position_indices

    def occupancy(xy: np.ndarray, heading: np.ndarray, speed: np.ndarray) -> np.ndarray:
        x = torch.zeros((*heading.shape, system.nx), dtype=dtype, device=device)
        x[..., ix] = torch.as_tensor(xy[..., 0], dtype=dtype, device=device)
        x[..., iy] = torch.as_tensor(xy[..., 1], dtype=dtype, device=device)
        x[..., system.heading_index] = torch.as_tensor(heading, dtype=dtype, device=device)
        x[..., system.speed_index] = torch.as_tensor(speed, dtype=dtype, device=device)
        return model.occupancy(x, slices[: heading.shape[-1]]).cpu().numpy().astype(np.float64)

    return occupancy


#: route seeds being computed in forked processes (:func:`start_route_seeds`): per problem, under their settings
#: (:func:`_seed_key`)
_PENDING = PendingCalls()


def _seed_key(config: RouteSeedConfig, dtype: torch.dtype, device: torch.device | str) -> tuple:
    return config, dtype, str(torch.device(device))


def start_route_seeds(problem: Any, config: RouteSeedConfig | None = None, *, dtype: torch.dtype = torch.float32,
                      device: torch.device | str = "cpu") -> bool:
    """Start part of :func:`route_seed_parameters` (same arguments, default lanes and speed limits) in a forked
    process (:class:`~density_planner.parallel.ForkedCall`), for a caller with an idle core: the candidates of every
    second route (the route search done in both processes). The next :func:`route_seed_parameters` call for the
    same problem, configuration, dtype and device computes the other routes' candidates meanwhile, takes those, and
    fits them all: the seeds computed in one process on one torch thread, bit for bit (each route's candidates are
    the same computation wherever they are made). The ``plan`` command starts it once the problem is set up
    (:meth:`~density_planner.planners.density_planner.DensityPlanner.prepare`): route search, risk-aware profiles
    and fit take 0.3-4 s on suite scenarios, which stage 1 waits for. Returns whether a process was started (not on
    a GPU, without ``fork``, with the seeds disabled, or while one is already computing them for ``problem``);
    :func:`cancel_route_seeds` ends one whose candidates nobody takes."""
    cfg = config or RouteSeedConfig()
    if not cfg.enabled or torch.device(device).type != "cpu" or _PENDING.keys(problem):
        return False
    # the route search's graph library imported once, here, for both processes (~0.08 s each otherwise): the caller
    # then waits less for what runs meanwhile (the road's distance field), the forked process starts with it
    import networkx  # noqa: F401

    return _PENDING.start(problem, _seed_key(cfg, dtype, device), _forked_candidates, problem, cfg, dtype, device)


def cancel_route_seeds(problem: Any) -> None:
    """End the process :func:`start_route_seeds` started for ``problem`` if its candidates were not taken."""
    _PENDING.cancel(problem)


#: the routes whose candidates :func:`start_route_seeds`'s process makes: every second one, from the second
_FORKED_ROUTES = slice(1, None, 2)


def _forked_candidates(problem: Any, config: RouteSeedConfig, dtype: torch.dtype, device: str
                       ) -> dict[int, _Candidates]:
    """Target of :func:`start_route_seeds`'s process: the candidates of the routes ``_FORKED_ROUTES``."""
    plan = _seed_plan(problem, config, None, None, dtype, device)
    if plan is None:
        return {}
    return {r: _route_candidates(plan, r) for r in range(len(plan.routes))[_FORKED_ROUTES]}


@dataclass
class _SeedPlan:
    """What every route's candidates need (:func:`_seed_plan`)."""

    problem: Any
    config: RouteSeedConfig
    routes: list[Route]
    start: Tensor
    tau: np.ndarray
    sv: float
    v_limits: tuple[float, float]
    a_max: float
    a_brake: float
    turn_max: float | None
    end_room: float
    shapes: Any
    goal_time: tuple[float, float]
    goal_speed: Any
    occupancy: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None
    dtype: torch.dtype
    device: torch.device | str
    t0: float


#: one route's candidates: ``(xy (P, T, 2), v (P, T), heading (P, T), labels)``
_Candidates = tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]


def route_seed_parameters(
    problem: Any,
    config: RouteSeedConfig | None = None,
    *,
    lane_graph: LaneGraph | None = None,
    v_limits: tuple[float, float] | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> RouteSeeds | None:
    """Route-following candidate parameters for ``problem`` (see the module docstring), or ``None`` where the
    scene has no lane map, the seeds are disabled, no lane lies under the start, or no route reaches the goal.

    Args:
        lane_graph: the lanes (default: :func:`scene_lane_graph` of the problem's scene).
        v_limits: ``(v_min, v_max)`` [m/s] of the speed profiles (default: the speed range of the system's
            planning bounds, ``system.planning_bounds()``).
    """
    cfg = config or RouteSeedConfig()
    if not cfg.enabled:
        return None
    call = None
    if lane_graph is None and v_limits is None and _PENDING.keys(problem):
        call = _PENDING.take(problem, _seed_key(cfg, dtype, device))
        _PENDING.cancel(problem)  # candidates started with other settings: nobody takes them
    plan = _seed_plan(problem, cfg, lane_graph, v_limits, dtype, device)
    if plan is None:
        if call is not None:
            call.cancel()
        return None
    routes = range(len(plan.routes))
    # the routes start_route_seeds's process makes meanwhile, if it runs
    forked = routes[_FORKED_ROUTES] if call is not None else range(0)
    made = {r: _route_candidates(plan, r) for r in routes if r not in forked}
    if call is not None:
        try:
            made.update(call.result())
        except ForkedCallError as exc:  # made here instead (the same candidates)
            log.debug("route seeds: %s; computing them here", exc)
    return _fitted_seeds(plan, [made[r] if r in made else _route_candidates(plan, r) for r in routes])


def _seed_plan(problem: Any, cfg: RouteSeedConfig, lane_graph: LaneGraph | None,
               v_limits: tuple[float, float] | None, dtype: torch.dtype, device: torch.device | str
               ) -> _SeedPlan | None:
    """The routes and what every route's candidates need, or ``None`` (no lanes, no route, a system without
    heading, speed and acceleration)."""
    graph = lane_graph if lane_graph is not None else scene_lane_graph(problem.scene)
    if graph is None:
        return None
    t0 = time.perf_counter()
    system, par = problem.system, problem.parameterization
    start = problem.reference_start(torch.float64)
    if system.heading_index is None or system.speed_index is None or system.acceleration_input is None:
        return None  # seeds follow lanes at a speed profile: they need heading, speed and acceleration
    sx, sy = (float(v) for v in system.positions(start))
    sth, sv = float(start[system.heading_index]), float(start[system.speed_index])
    if v_limits is None:
        lo, hi = system.planning_bounds()
        v_limits = (max(float(lo[system.speed_index]), 0.0), float(hi[system.speed_index]))
    tau = np.arange(par.n_plan) * par.plan_dt
    ia = system.acceleration_input
    a_max = 0.9 * min(abs(float(system.input_bounds[0][ia])), abs(float(system.input_bounds[1][ia])))
    a_brake = 0.9 * abs(float(system.input_bounds[0][ia]))  # the hardest braking the profiles use
    horizon = float(tau[-1])
    shapes, interval, goal_speed = _goal_of(problem, cfg.goal_point_radius)
    reach = max(sv, v_limits[1]) * horizon + 10.0
    routes = find_routes(graph, (sx, sy), sth, shapes, max_routes=cfg.max_routes,
                         lane_change_cost=cfg.lane_change_cost, reach=reach, continue_for=reach,
                         lane_change_length=max(cfg.lane_change_length, cfg.lane_change_time * sv))
    if not routes:
        log.info("route seeds: no route from the start to the goal on the lane map")
        return None
    t_start = float(getattr(problem.scene, "t_start", None) or getattr(getattr(problem.scene, "road", None),
                                                                       "t_start", 0.0) or 0.0)
    if interval is None:
        goal_time = (horizon, horizon)
    else:
        rel = (interval[0] - t_start, interval[1] - t_start)
        goal_time = (float(np.clip(rel[0], 0.0, horizon)), float(np.clip(rel[1], 0.0, horizon)))
        if rel[0] > horizon or rel[1] < 0:
            goal_time = (horizon, horizon)
    occupancy = _body_occupancy(problem, dtype, device) if cfg.risk_aware else None
    # where the lanes end (the map's edge, a dead end) the vehicle's front stops 0.5 m short of the path's end
    end_room = 0.5 * float(system.footprint.length) + 0.5
    it = system.turn_rate_input
    turn_max = None if it is None else 0.9 * min(abs(float(system.input_bounds[0][it])),
                                                 abs(float(system.input_bounds[1][it])))
    return _SeedPlan(problem, cfg, routes, start, tau, sv, v_limits, a_max, a_brake, turn_max, end_room, shapes,
                     goal_time, goal_speed, occupancy, dtype, device, t0)


def _route_candidates(plan: _SeedPlan, r: int) -> _Candidates:
    """Route ``r``'s candidates: its speed profiles (and the risk-aware ones) as positions, speeds and headings."""
    import shapely

    cfg, route, tau, v_limits = plan.config, plan.routes[r], plan.tau, plan.v_limits
    cum = _arc(route.path)
    goal_arc = None
    if plan.shapes is not None:
        s_grid = np.arange(0.0, cum[-1] + 1e-9, 0.5)
        pts = path_points(route.path, s_grid)
        inside = np.asarray(shapely.intersects_xy(plan.shapes, pts[:, 0], pts[:, 1]), dtype=bool)
        if inside.any():
            goal_arc = (float(s_grid[inside].min()), float(s_grid[inside].max()))
        else:
            d = np.asarray(shapely.distance(plan.shapes, shapely.points(pts)), dtype=np.float64)
            s_near = float(s_grid[int(np.argmin(d))])
            goal_arc = (s_near, s_near)
    limit, with_end = (path_speed_limit(route.path, v_limits[1], lateral_acceleration=cfg.lateral_acceleration,
                                        deceleration=plan.a_max, turn_rate=plan.turn_max, s_end=end)
                       for end in (None, cum[-1] - plan.end_room))
    stop = (cum[-1] - plan.end_room, with_end)

    def capped(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return cap_profiles(v, tau, limit, acceleration=plan.a_max, deceleration=plan.a_brake, v_lo=v_limits[0],
                            stop=stop)

    s, v, lab = speed_profiles(0.0, plan.sv, tau, goal_arc, plan.goal_time, v_limits=v_limits,
                               acceleration=cfg.acceleration, max_acceleration=plan.a_max, cap=capped)
    if plan.occupancy is not None:
        s_r, v_r, _ = risk_aware_profiles(
            plan.occupancy, route.path, plan.sv, tau, goal_arc, plan.goal_time, v_limits=v_limits,
            rates=(cfg.acceleration, (plan.a_max, plan.a_brake)), n_speeds=cfg.profile_speeds,
            switch_times=cfg.profile_switch_times, n_keep=cfg.risk_aware, risk_weight=cfg.risk_weight,
            effort_weight=cfg.effort_weight, goal_speed=plan.goal_speed, speed_limit=limit, stop=stop)
        s, v = np.concatenate([s_r, s]), np.concatenate([v_r, v])
        lab = [f"risk-aware {i}" for i in range(s_r.shape[0])] + lab
    xy = path_points(route.path, s)  # (P, T, 2)
    ahead = path_points(route.path, s + 0.5)
    h = np.arctan2(ahead[..., 1] - xy[..., 1], ahead[..., 0] - xy[..., 0])
    return xy, v, h, [f"route {r}: {x}" for x in lab]


def _fitted_seeds(plan: _SeedPlan, parts: list[_Candidates]) -> RouteSeeds:
    """Every route's candidates, in route order and at most ``max_candidates``, fitted as reference parameters."""
    cfg, dtype, device = plan.config, plan.dtype, plan.device
    xy, v, h = (np.concatenate([p[i] for p in parts])[: cfg.max_candidates] for i in range(3))
    labels = [x for p in parts for x in p[3]][: cfg.max_candidates]
    targets, speeds = torch.tensor(xy, dtype=dtype, device=device), torch.tensor(v, dtype=dtype, device=device)
    system = plan.problem.system
    params, rms = fit_reference_parameters(system, plan.start.to(dtype=dtype, device=device),
                                           plan.problem.parameterization, targets, speeds,
                                           torch.tensor(h, dtype=dtype, device=device),
                                           iterations=cfg.fit_iterations, speed_weight=cfg.fit_speed_weight)
    seeds = RouteSeeds(params, targets, speeds, labels, rms, plan.routes, time.perf_counter() - plan.t0)
    log.info("route seeds: %d routes, %d candidates, fit rms median %.2f m, %.2f s", len(plan.routes),
             params.shape[0], float(rms.median()), seeds.seconds)
    return seeds

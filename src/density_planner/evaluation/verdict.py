"""The verdict on a plan: did it reach the goal, without collision, on the road, inside the model?

One function, :func:`judge`, shared by ``density-planner plan`` (``plan.json``), the benchmarks (every record of
``bench commonroad``) and the Python API. It judges a state trajectory ``(T, nx)`` on the planning grid
(``t_k = k dt`` after the scene start) and the inputs ``(T - 1, nu)`` that produced it, against the *ground truth*
of the scene, never against the blurred occupancy the planner optimised:

* ``goal_reached``: some state lies in the goal region during its time interval (and inside its velocity and
  orientation intervals where given);
* ``collision_free``: the vehicle rectangle (:func:`vehicle_footprints`) intersects no recorded obstacle's true
  shape at any time step (shapely 2, vectorised over time steps and obstacles);
* ``on_road``: the rectangle stays inside the drivable area (up to :attr:`VerdictConfig.road_tolerance`); where it
  does not, the reason and ``details`` give the first time, the number of steps, and the largest area beyond the
  road's edge [m^2] and depth of a corner beyond it [m];
* ``within_model``: the states (apart from the position, which ``on_road`` covers) and the inputs stay inside the
  system's bounds (up to :attr:`VerdictConfig.model_tolerance`);
* ``p_coll_max``: the planner's own risk figure, reported next to them (not part of the status).

``status`` is ``"success"`` only when all four hold; otherwise ``"failed"`` with one reason per failed part.

Scenes with road data (CommonRoad scenarios: ``scene.road`` is a :class:`~density_planner.environment.road.
RoadScene`) are judged as above. Scenes without road data (random artificial scenes, inD windows, scene files)
have no goal region, no true obstacle shapes and no lanelets; their verdict uses what exists (``basis:
"occupancy"``):

* ``goal_reached``: the final position lies within ``evaluation.max_goal_distance`` (4.5 m, the paper's failure
  rule) of the goal point;
* ``collision_free``: the occupancy probability at the vehicle's position never exceeds
  ``evaluation.collision_threshold`` (0.5: the position is more likely occupied than free);
* ``on_road``: the vehicle's reference point stays inside the map (the grid's extent; the paper's bounds rule);
* ``within_model``: as above.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..environment.road import vehicle_footprints

__all__ = ["VerdictConfig", "Verdict", "judge", "judge_plan", "plan_inputs", "parts_table", "vehicle_footprints",
           "record_verdict", "verdict_failure", "VERDICT_PARTS"]

#: the four parts of a verdict, in the order they are reported
VERDICT_PARTS = ("goal_reached", "collision_free", "on_road", "within_model")


@dataclass(frozen=True)
class VerdictConfig:
    """How plans are judged (TOML section ``[verdict]``)."""

    #: vehicle length [m] when neither the scene (CommonRoad scenarios may name the ego's) nor the system (its
    #: footprint) gives one
    vehicle_length: float = 4.5
    #: vehicle width [m], likewise
    vehicle_width: float = 1.8
    #: the rectangle may leave the drivable area by at most this distance [m] and still count as on the road
    #: (numerical slack of the lanelet union, not a modelling allowance)
    road_tolerance: float = 0.05
    #: relative slack of the state and input bounds in ``within_model`` (integration round-off)
    model_tolerance: float = 1e-4

    def __post_init__(self) -> None:
        for name in ("vehicle_length", "vehicle_width"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"verdict.{name} must be a positive number [m], got {v!r}")
        for name in ("road_tolerance", "model_tolerance"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"verdict.{name} must be a non-negative number, got {v!r}")


@dataclass(frozen=True)
class Verdict:
    """The verdict on one trajectory; :meth:`to_dict` is what ``plan.json`` and the records hold."""

    goal_reached: bool
    collision_free: bool
    on_road: bool
    within_model: bool
    p_coll_max: float
    #: one sentence per failed part, in :data:`VERDICT_PARTS` order
    reasons: tuple[str, ...] = ()
    #: ``"road"`` (true shapes, lanelets, goal region) or ``"occupancy"`` (scenes without road data)
    basis: str = "road"
    #: figures behind the four parts (final distance to the goal region, first collision, off-road distance, ...)
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.goal_reached and self.collision_free and self.on_road and self.within_model

    @property
    def status(self) -> str:
        return "success" if self.ok else "failed"

    def to_dict(self) -> dict[str, Any]:
        return {"status": self.status, **{p: bool(getattr(self, p)) for p in VERDICT_PARTS},
                "p_coll_max": _json_float(self.p_coll_max), "reasons": list(self.reasons), "basis": self.basis,
                "details": {k: _json_value(v) for k, v in self.details.items()}}

    def summary(self) -> str:
        """One line, e.g. ``success`` or ``failed: collision with obstacle 31 at t = 3.4 s; ...``."""
        return self.status if self.ok else "failed: " + "; ".join(self.reasons)


def _json_float(v: float | np.floating) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _json_value(v: Any) -> Any:
    if isinstance(v, (float, np.floating)):
        return _json_float(v)
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, (list, tuple)):
        return [_json_value(x) for x in v]
    return v


def _footprint_size(scene: Any, config: VerdictConfig, system: Any = None) -> tuple[float, float]:
    """``(length, width)`` [m] of the vehicle rectangle: the scenario's ego vehicle (``scene.road``), else the
    system's footprint (where the system defines a non-zero one), else :class:`VerdictConfig`'s."""
    road = getattr(scene, "road", None)
    if road is not None and getattr(road, "vehicle_length", None) and getattr(road, "vehicle_width", None):
        return float(road.vehicle_length), float(road.vehicle_width)
    fp = getattr(system, "footprint", None)
    if fp is not None and getattr(fp, "length", None) and getattr(fp, "width", None):
        return float(fp.length), float(fp.width)
    return config.vehicle_length, config.vehicle_width


# ---------------------------------------------------------------------------------------------------- judge
def judge(
    scene: Any,
    states: Any,
    inputs: Any | None,
    *,
    system: Any,
    dt: float,
    p_coll_max: float = math.nan,
    config: VerdictConfig | None = None,
    evaluation: Any = None,
) -> Verdict:
    """The verdict on ``states (T, nx)`` (state ``k`` at ``k dt`` [s] after the scene start) driven by ``inputs
    (T - 1, nu)`` (``None``: not checked) in ``scene``, for ``system`` (its position, heading and speed indices locate
    them; its bounds define ``within_model``).

    ``evaluation`` (an :class:`~density_planner.evaluation.config.EvaluationConfig`, default one) supplies the goal
    tolerance and the occupancy threshold of scenes without road data (see the module docstring).
    """
    from .config import EvaluationConfig

    config = config or VerdictConfig()
    evaluation = evaluation or EvaluationConfig()
    x = _as_array("states", states, 2)
    if x.shape[0] < 1 or x.shape[1] != system.nx:
        raise ValueError(f"states must have shape (T >= 1, {system.nx}), got {x.shape}")
    u = None if inputs is None else _as_array("inputs", inputs, 2)
    if u is not None and u.size and u.shape[1] != system.nu:
        raise ValueError(f"inputs must have shape (T - 1, {system.nu}), got {u.shape}")
    if not (isinstance(dt, (int, float)) and dt > 0):
        raise ValueError(f"dt must be a positive time step [s], got {dt!r}")
    # positions, heading and speed are the system's facts (a system without heading: an axis-aligned body)
    idx = {"px": system.position_indices[0], "py": system.position_indices[1]}
    if system.heading_index is not None:
        idx["theta"] = system.heading_index
    if system.speed_index is not None:
        idx["v"] = system.speed_index
    xy = np.nan_to_num(x[:, [idx["px"], idx["py"]]], nan=0.0, posinf=0.0, neginf=0.0)  # non-finite: fails below
    theta = np.nan_to_num(x[:, idx["theta"]]) if "theta" in idx else np.zeros(len(x))
    v = x[:, idx["v"]] if "v" in idx else None
    t_rel = dt * np.arange(len(x))
    length, width = _footprint_size(scene, config, system)
    boxes = vehicle_footprints(xy, theta, length, width)
    details: dict[str, Any] = {"vehicle_length": length, "vehicle_width": width, "dt": float(dt),
                               "n_states": int(len(x))}
    reasons: list[str] = []
    finite = bool(np.isfinite(x).all()) and (u is None or bool(np.isfinite(u).all()))
    if not finite:
        reasons.append("the trajectory contains NaN or infinite values")

    road = getattr(scene, "road", None)
    if road is not None:
        basis = "road"
        goal, collision, on_road = _judge_road(road, xy, theta, v, t_rel, boxes, config, details, reasons,
                                              scene.grid.bounds)
    else:
        basis = "occupancy"
        goal, collision, on_road = _judge_occupancy(scene, xy, t_rel, boxes, evaluation, details, reasons)
    within = _judge_model(system, x, u, idx, config, details, reasons, dt)
    return Verdict(goal and finite, collision and finite, on_road and finite, within and finite,
                   p_coll_max=float(p_coll_max), reasons=tuple(reasons), basis=basis, details=details)


def _as_array(name: str, value: Any, ndim: int) -> np.ndarray:
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != ndim:
        raise ValueError(f"{name} must be a {ndim}-d array, got shape {arr.shape}")
    return arr


def _first(mask: np.ndarray) -> int | None:
    hits = np.flatnonzero(mask)
    return int(hits[0]) if hits.size else None


def _spans(mask: np.ndarray, t: np.ndarray, most: int = 3) -> str:
    """The runs of ``mask`` as times ``"0.0-1.4, 3.3-5.8"`` (the first ``most``, then how many more)."""
    k = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    runs = [f"{float(t[a]):.1f}-{float(t[b - 1]):.1f}" for a, b in zip(k[::2], k[1::2])]
    more = f" and {len(runs) - most} more" if len(runs) > most else ""
    return ", ".join(runs[:most]) + more


def _goal_miss(goal: Any, in_space: np.ndarray, t_rel: np.ndarray, v: np.ndarray, theta: np.ndarray,
               t_start: float) -> str:
    """Why states that are in the goal area miss the goal: its time interval, else its speed or heading interval
    (single-alternative goals; several alternatives are named together)."""
    t0, t1 = (float(a) - t_start for a in goal.time_interval)
    span = f"[{t0:.1f}, {t1:.1f}] s"
    if goal.alternatives:
        return (f"in the goal area at t = {float(t_rel[_first(in_space)]):.1f} s but never in one of its "
                f"{len(goal.alternatives)} alternatives (time, velocity, orientation)")
    during = in_space & (t_rel >= t0 - 1e-6) & (t_rel <= t1 + 1e-6)
    if not during.any():
        return f"in the goal area at t = {_spans(in_space, t_rel)} s but never during its time interval {span}"
    parts = []
    if goal.velocity is not None:
        vs = v[during]
        lo, hi = (float(a) for a in goal.velocity)
        if not ((vs >= lo - 1e-9) & (vs <= hi + 1e-9)).any():
            parts.append(f"speed {float(vs.min()):.2f}-{float(vs.max()):.2f} m/s outside [{lo:.2f}, {hi:.2f}]")
    if goal.orientation is not None:
        from ..environment.road import angle_in_interval

        ths = theta[during]
        if not angle_in_interval(ths, goal.orientation).any():
            lo, hi = (float(a) for a in goal.orientation)
            parts.append(f"heading {float(ths.min()):.3f}-{float(ths.max()):.3f} rad outside [{lo:.3f}, {hi:.3f}]")
    what = "; ".join(parts) or "speed and heading each met, never together"
    return f"in the goal area during its time interval {span} but with {what}"


def _judge_road(road: Any, xy, theta, v, t_rel, boxes, config: VerdictConfig, details: dict,
                reasons: list[str], scene_bounds: tuple[float, float, float, float]) -> tuple[bool, bool, bool]:
    import shapely

    t_abs = float(road.t_start) + t_rel
    # goal region during its time interval (velocity / orientation intervals where given)
    goal = road.goal
    inside = np.asarray(goal.contains(xy, t_abs, v, theta), dtype=bool)
    k_goal = _first(inside)
    dist = np.asarray(goal.distance(xy), dtype=np.float64)
    t0, t1 = (float(a) for a in goal.time_interval)
    details.update(goal_time_interval=[t0 - road.t_start, t1 - road.t_start],
                   final_goal_distance=float(dist[-1]), min_goal_distance=float(dist.min()),
                   goal_reached_at=None if k_goal is None else float(t_rel[k_goal]))
    goal_ok = k_goal is not None
    if not goal_ok:
        in_space = dist <= 1e-9
        if in_space.any():
            reasons.append("goal: " + _goal_miss(goal, in_space, t_rel, v, theta, road.t_start))
        else:
            reasons.append(f"goal: never in the goal region (closest {float(dist.min()):.1f} m, final "
                           f"{float(dist[-1]):.1f} m)")
    # true shapes of the recorded obstacles at every time step
    collision_ok = True
    hits = []
    for track in road.obstacles:
        polys = np.asarray(track.polygons_at(t_abs), dtype=object)
        present = np.array([p is not None for p in polys], dtype=bool)
        if not present.any():
            continue
        hit = np.zeros(len(polys), dtype=bool)
        hit[present] = shapely.intersects(boxes[present], np.array(list(polys[present]), dtype=object))
        k = _first(hit)
        if k is not None:
            hits.append((float(t_rel[k]), track.obstacle_id))
    if hits:
        collision_ok = False
        hits.sort()
        t_hit, oid = hits[0]
        details.update(first_collision_time=t_hit, first_collision_obstacle=oid,
                       colliding_obstacles=sorted({h[1] for h in hits}))
        more = f" (and {len(hits) - 1} more obstacle(s))" if len(hits) > 1 else ""
        reasons.append(f"collision: with obstacle {oid} at t = {t_hit:.1f} s{more}")
    # the rectangle inside the drivable area (no drivable area known: inside the map)
    drivable = road.drivable
    if drivable is None:
        return goal_ok, collision_ok, _inside_map(scene_bounds, boxes, t_rel, details, reasons)
    if config.road_tolerance > 0:
        drivable = shapely.buffer(drivable, config.road_tolerance)
    shapely.prepare(drivable)
    covered = shapely.covered_by(boxes, drivable)
    off = ~np.asarray(covered, dtype=bool)
    road_ok = not off.any()
    if not road_ok:
        # how much of the rectangle lies beyond the road's edge and how far its corners reach (the tolerance only
        # decides whether a step is off the road)
        off_boxes = boxes[off]
        area = float(np.max(shapely.area(shapely.difference(off_boxes, road.drivable))))
        corners = shapely.points(shapely.get_coordinates(off_boxes))
        depth = float(np.max(shapely.distance(corners, road.drivable)))
        k = _first(off)
        details.update(off_road_first_time=float(t_rel[k]), off_road_steps=int(off.sum()),
                       off_road_max_area=area, off_road_max_depth=depth)
        reasons.append(f"off road: the vehicle leaves the drivable area at t = {float(t_rel[k]):.1f} s "
                       f"({int(off.sum())} of {len(off)} steps, up to {area:.2g} m^2 and {depth:.2g} m beyond the "
                       "road's edge)")
    return goal_ok, collision_ok, road_ok


def _judge_occupancy(scene: Any, xy, t_rel, boxes, evaluation: Any, details: dict,
                     reasons: list[str]) -> tuple[bool, bool, bool]:
    import shapely
    import torch

    grid = scene.grid
    gx, gy = scene.goal
    final = float(np.hypot(xy[-1, 0] - gx, xy[-1, 1] - gy))
    details.update(final_goal_distance=final, goal_tolerance=float(evaluation.max_goal_distance))
    goal_ok = final <= evaluation.max_goal_distance
    if not goal_ok:
        reasons.append(f"goal: final position {final:.1f} m from the goal (> {evaluation.max_goal_distance:g} m)")
    t0 = grid.t0 if getattr(scene, "t_start", None) is None else float(scene.t_start)  # on the grid's clock
    k = grid.slice_index(torch.as_tensor(t0 + t_rel, dtype=torch.float64), clamp=True)
    p = grid.lookup(torch.as_tensor(np.nan_to_num(xy), dtype=torch.float64, device=grid.device), k.to(grid.device))
    p = p.detach().cpu().numpy()
    details.update(p_occ_max=float(p.max()), collision_threshold=float(evaluation.collision_threshold))
    hit = p > evaluation.collision_threshold
    collision_ok = not hit.any()
    if not collision_ok:
        k0 = _first(hit)
        reasons.append(f"collision: occupancy {float(p[k0]):.2f} > {evaluation.collision_threshold:g} at the "
                       f"vehicle's position at t = {float(t_rel[k0]):.1f} s")
    # the map's extent bounds the position (the paper's bounds rule judges the reference point, not the rectangle:
    # its random scenes start 2 m from the map's edge)
    return goal_ok, collision_ok, _inside_map(grid.bounds, shapely.points(xy), t_rel, details, reasons)


def _inside_map(bounds, geoms, t_rel, details: dict, reasons: list[str]) -> bool:
    """``geoms`` (vehicle rectangles or reference points) inside the box ``bounds = (xmin, xmax, ymin, ymax)``."""
    import shapely

    xmin, xmax, ymin, ymax = bounds
    b = shapely.bounds(geoms)
    out = (b[:, 0] < xmin) | (b[:, 2] > xmax) | (b[:, 1] < ymin) | (b[:, 3] > ymax)
    out |= ~np.isfinite(b).all(axis=1)
    if out.any():
        k0 = _first(out)
        reasons.append(f"off map: the vehicle leaves the map at t = {float(t_rel[k0]):.1f} s")
        details.update(off_road_first_time=float(t_rel[k0]), off_road_steps=int(out.sum()))
    return not out.any()


def _judge_model(system: Any, x: np.ndarray, u: np.ndarray | None, idx: dict, config: VerdictConfig,
                 details: dict, reasons: list[str], dt: float) -> bool:
    lo, hi = (np.asarray(b, dtype=np.float64) for b in system.state_bounds)
    check = np.ones(x.shape[1], dtype=bool)
    check[[idx["px"], idx["py"]]] = False  # positions: on_road / the map judge them
    tol = config.model_tolerance * np.maximum(1.0, np.maximum(np.abs(lo), np.abs(hi)))
    bad_x = ((x < lo - tol) | (x > hi + tol)) & check[None, :]
    problems = []
    names = list(system.state_names)
    for j in np.flatnonzero(bad_x.any(axis=0)):
        k = int(np.argmax(bad_x[:, j]))  # the first violation (the column has one)
        problems.append(f"{names[j]} = {x[k, j]:.6g} at t = {k * dt:.1f} s outside [{lo[j]:.4g}, {hi[j]:.4g}]")
    if u is not None and u.size:
        # inputs the vehicle can receive: the actuator box (wider than the reference box where the controller
        # saturates smoothly, road domain)
        bounds = getattr(system, "applied_input_bounds", system.input_bounds)
        ulo, uhi = (np.asarray(b, dtype=np.float64) for b in bounds)
        utol = config.model_tolerance * np.maximum(1.0, np.maximum(np.abs(ulo), np.abs(uhi)))
        bad_u = (u < ulo - utol) | (u > uhi + utol)
        unames = list(system.input_names)
        for j in np.flatnonzero(bad_u.any(axis=0)):
            k = int(np.argmax(bad_u[:, j]))
            problems.append(f"input {unames[j]} = {u[k, j]:.4g} at t = {k * dt:.1f} s outside [{ulo[j]:.4g}, "
                            f"{uhi[j]:.4g}]")
    details["model_violations"] = problems
    if problems:
        reasons.append("outside the model: " + "; ".join(problems))
    return not problems


# -------------------------------------------------------------------------------------------- plan results
def plan_inputs(result: Any) -> np.ndarray | None:
    """The inputs ``(T - 1, nu)`` behind a :class:`~density_planner.planners.base.PlanResult`'s states: the
    reference inputs of a planned reference, the applied inputs of a receding-horizon run, else ``None``."""
    ref = getattr(result, "reference", None)
    if ref is not None:
        u = ref.u_plan
        u = u.detach().cpu().numpy() if hasattr(u, "detach") else np.asarray(u)
        return u.reshape(-1, u.shape[-1])
    applied = (getattr(result, "extras", None) or {}).get("applied_inputs")
    if applied:
        return np.asarray(applied, dtype=np.float64)
    return None


def judge_plan(scene: Any, result: Any, *, system: Any, dt: float, config: VerdictConfig | None = None,
               evaluation: Any = None) -> Verdict | None:
    """The verdict on a planner's :class:`~density_planner.planners.base.PlanResult` (its planned states and
    inputs); ``None`` when it has no trajectory."""
    if getattr(result, "states", None) is None:
        return None
    x = result.states.detach().cpu().numpy()
    u = plan_inputs(result)
    if u is not None:
        u = u[: max(len(x) - 1, 0)]
    p = getattr(result, "collision", None)
    p_max = float(p.max) if p is not None else math.nan
    return judge(scene, x, u, system=system, dt=dt, p_coll_max=p_max, config=config, evaluation=evaluation)


def parts_table(verdicts: Sequence[Verdict]) -> dict[str, float]:
    """Fraction of ``verdicts`` passing each part and all of them (``"success"``)."""
    n = max(len(verdicts), 1)
    out = {"success": sum(v.ok for v in verdicts) / n}
    out.update({p: sum(bool(getattr(v, p)) for v in verdicts) / n for p in VERDICT_PARTS})
    return out


def record_verdict(scene: Any, states: Any, inputs: Any, plan: Any, system: Any, dt: float,
                   run_config: Any) -> dict[str, Any]:
    """The verdict of a benchmark run as JSON data (``{"error": ...}`` instead of raising: a record is always
    written)."""
    p = getattr(plan, "collision", None)
    try:
        return judge(scene, states, inputs, system=system, dt=dt, p_coll_max=math.nan if p is None else float(p.max),
                     config=getattr(run_config, "verdict", None),
                     evaluation=getattr(run_config, "evaluation", None)).to_dict()
    except Exception as exc:  # noqa: BLE001 - recorded
        return {"status": "error", "error": f"{type(exc).__name__}: {exc}"}


#: failure reasons of a road verdict, per failed part (the benchmark records' ``failure_reason``)
VERDICT_FAILURES = {"goal_reached": "goal", "collision_free": "collision", "on_road": "off_road",
                    "within_model": "outside_model"}


def verdict_failure(verdict: Any, solved: bool) -> tuple[dict[str, bool], str] | None:
    """Failure flags and reason (flagged parts joined by ``+``) of a benchmark run on a road scene from its verdict
    (:func:`record_verdict`): a run fails unless the verdict is a success. ``None`` for runs without a road verdict
    (the paper's scenes keep the thresholds of :func:`~density_planner.evaluation.metrics.failure_flags`)."""
    if not isinstance(verdict, dict) or verdict.get("basis") != "road":
        return None
    flags = {"no_solution": not solved or verdict.get("status") == "error"}
    for part, reason in VERDICT_FAILURES.items():
        flags[reason] = not flags["no_solution"] and not verdict.get(part, False)
    return flags, "+".join(k for k, v in flags.items() if v)

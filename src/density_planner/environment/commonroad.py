"""CommonRoad scenarios (XML, read with commonroad-io, the optional ``commonroad`` extra) -> scene.

:func:`load_commonroad_scene` builds two views of one scenario: the occupancy grid the planners read, and the
exact :class:`~.road.RoadScene` (drivable area, the road users' true shapes over time, the goal region with its
time interval) that plans are judged against. Times are absolute: ``t = time_step * dt`` of the scenario; the
grid's first slice is the planning problem's initial time ``t_start``. Every simplification below is logged
and recorded in ``scene.meta`` (``scene.json``).

1. **Planning problem** (the first one, or ``planning_problem_id``): start = (position, orientation shifted into
   the car's heading box, velocity, bias 0). A missing or non-finite start is an error; a start outside the car
   model's domain (speed above the system's ``state_max``) is refused with one line naming the limit. A scenario
   without a planning problem is refused unless ``sample_start_goal`` (then start and goal are sampled on the
   road, seeded, and the goal region is a disc of ``sampled_goal_radius`` around the sampled goal).
2. **Goal region** (:class:`~.road.GoalRegion`): every goal state's position (rectangle, circle, polygon, shape
   group, or its goal lanelets), time interval, velocity and orientation intervals; alternative goal states
   are kept as alternatives. ``scene.goal`` (the single point today's planners steer to) starts from the point
   reached by following the start lanelet and its first successors at the initial speed until the end of the
   horizon; it is that point for a goal without a position, else the point of the goal region (shrunk by 1 m)
   nearest to it.
3. **Horizon**: ``meta["horizon"]`` = end of the goal's time interval - ``t_start``, capped at ``max_horizon``
   (logged when capped). The grid covers the horizon rounded up to whole seconds (the planners plan whole
   segments), at least ``min_duration``, unless ``n_slices`` is given.
4. **Road**: the drivable area is the union of the lanelets whose type is a road (types in
   ``non_drivable_lanelet_types`` and lanelets whose road users exclude cars are left out), closed
   morphologically over ``gap_close`` (gaps narrower than that, e.g. the numerical seams between
   neighbouring lanelets, become road; the outer boundary does not grow). The area this fills is recorded
   as ``meta["road"]["gap_area_closed_m2"]``. Static obstacles are occupied (1) at every slice.
5. **Traffic lights**: while a light of a lanelet is red or red-yellow, a ``stop_line_depth``-deep strip at the
   lanelet's stop line (or its end when it has none) is occupied (1) and is an obstacle of the road scene
   (kind ``"red_light"``); a light whose strip covers the start at ``t_start`` is skipped (logged).
   ``traffic_lights = false`` ignores them (logged).
6. **Road users**: the dynamic obstacle that coincides with the planning problem's initial state (the
   recorded ego; position within ``ego_tolerance`` at the initial time step) is dropped; ``exclude_obstacles``
   drops others by id (an unknown id is an error). Trajectory predictions are resampled to the slices and,
   past a road user's last recorded state, predicted at constant velocity and heading with a position error
   growing with time (:func:`.footprints.extrapolate_tracks`); they become the split-Gaussian footprints of
   :mod:`.footprints`. Set-based predictions (``occupancySet``) are occupied (1) over every time step they
   cover; past their last set the last set moves on at the initial velocity. A missing velocity is taken from
   the positions' finite differences; a missing orientation from the direction of motion.
7. **Map**: the region the car can reach within the grid's duration (the horizon, at least ``min_duration``;
   start speed, the system's speed and acceleration bounds), cut to the drivable area, plus the goal region and
   ``area_margin``; ``area`` overrides it. The cell
   size is ``cell_size`` unless the grid (``T x NX x NY`` float32) would exceed ``memory_budget_gib``; then the
   smallest multiple of 0.05 m that fits (up to ``max_cell_size``, else an error naming the keys to change).
"""

from __future__ import annotations

import importlib.util
import logging
import math
import warnings
import weakref
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from density_planner.checks import check_seed
from density_planner.config import to_dict
from density_planner.errors import DataError, OptionalDependencyError

from .footprints import (
    ROAD_USER_CLASSES,
    FootprintConfig,
    RoadUserTracks,
    extrapolate_tracks,
    rasterise_road_users,
    resample_tracks,
)
from .grid import OccupancyGrid, lattice_size
from .lanes import remember_lane_graph
from .road import GoalRegion, ObstacleTrack, RoadScene, lattice_in
from .road_sdf import map_ready
from .sampling import StartGoalConfig, sample_start_goal
from .scene import Scene

__all__ = [
    "CommonRoadSceneConfig",
    "load_commonroad_scene",
    "read_commonroad",
    "obstacle_class_id",
    "static_map",
    "offroad_cells",
    "offroad_mask",
    "drivable_area",
    "reach_distance",
]

logger = logging.getLogger(__name__)

#: CommonRoad obstacle types -> class ids of :data:`ROAD_USER_CLASSES` (others: car)
_TYPE_CLASS = {
    "truck": 1,
    "bus": 1,
    "pedestrian": 2,
    "bicycle": 3,
    "motorcycle": 3,
}
#: road users that make a lanelet drivable for a car (CommonRoad ``RoadUser`` values)
_CAR_USERS = {"vehicle", "car"}
_GIB = 2**30


def obstacle_class_id(obstacle_type: Any) -> int:
    """Class id of a CommonRoad ``ObstacleType`` (or its string value)."""
    value = str(getattr(obstacle_type, "value", obstacle_type)).lower()
    return _TYPE_CLASS.get(value, 0)


@dataclass(frozen=True)
class CommonRoadSceneConfig:
    """How a CommonRoad scenario becomes a scene (see the module docstring). Lengths in m, times in s."""

    #: number of slices; 0 = cover the horizon, at least ``min_duration``
    n_slices: int = 0
    #: time between slices [s]
    dt: float = 0.1
    #: the grid covers at least this long [s] (the planners' horizon follows the goal's time interval; one 1-s
    #: segment at least)
    min_duration: float = 1.0
    #: cap on the horizon [s] (the horizon follows the end of the goal's time interval): a bound on memory and
    #: planning time, above the goals of the public CommonRoad scenes seen here (DEU_Muc goals end 20.4 s after the
    #: start; at 20 s DEU_Muc-26_2's goal instant was out of reach)
    max_horizon: float = 30.0
    #: finest cell edge [m]; coarser when the grid would exceed ``memory_budget_gib``
    cell_size: float = 0.1
    #: coarsest cell edge the automatic choice may use [m]
    max_cell_size: float = 1.0
    #: memory budget of the occupancy grid (T x NX x NY float32) [GiB]; a plan holds 4-5x this at its peak (grid,
    #: the road users' grid, their disc-dilated grids; 4.0 GB on CHN_Sha-15_1, 5.4 GB on USA_Lanker-1_1; 0.25 for
    #: machines with less memory: about 1.3 GB), and scene building time grows with it. 1 GiB gives the suite's
    #: long-horizon urban scenes 0.4-m cells instead of 0.8 m (at 0.8 m the body's dilation closes the gaps of a
    #: queue): 25 -> 29 of 67 suite successes (docs/history.md, stop 23)
    memory_budget_gib: float = 1.0
    #: map area (xmin, xmax, ymin, ymax) [m]; empty = reachable region + goal + margin (module docstring)
    area: tuple[float, ...] = ()
    #: margin around the reachable region and the goal [m]
    area_margin: float = 10.0
    #: gaps between drivable lanelets narrower than this are closed [m]
    gap_close: float = 0.3
    #: lanelet types that are not drivable (CommonRoad ``LaneletType`` values)
    non_drivable_lanelet_types: tuple[str, ...] = ("sidewalk", "crosswalk", "bicycleLane")
    #: red and red-yellow traffic lights block their lanelet's stop line
    traffic_lights: bool = True
    #: depth of the blocked strip at a stop line [m]
    stop_line_depth: float = 1.0
    #: add static obstacles (occupancy 1) to the static map
    include_static_obstacles: bool = True
    #: cells outside the drivable area are occupied (1): the occupancy then also holds the road's edge (the
    #: planners without a road term keep to the road through it); false: the road users only (the collision
    #: probability is then the probability of hitting a road user; used by the calibration check)
    offroad_occupied: bool = True
    #: half-widths of the planner's initial uncertainty on the scenario (the measurement error law of the scene):
    #: position [m] (both axes), heading [rad], speed [m/s], written to ``scene.meta["initial_error"]``; a system's
    #: states the pose does not fix (the car's heading bias) keep the system's XE0 box. Default: lane-level
    #: localisation and automotive-grade heading and speed (docs/environments.md); ``None``: the system's XE0 box
    #: (the paper's: +-1 m, +-0.5 rad, +-0.5 m/s)
    initial_error: tuple[float, float, float] | None = (0.5, 0.05, 0.3)
    #: the initial law is conditioned on the car's body being inside the drivable area (the localisation error
    #: combined with the map: a start 0.5 m from the kerb cannot be 0.6 m beyond it), written to
    #: ``scene.meta["initial_on_road"]``; skipped (logged) when the recorded start itself is off the road
    initial_on_road: bool = True
    #: a cell counts as off the road only when its centre lies more than this far outside the drivable area [m];
    #: None: half the cell's diagonal, which offsets the grid's quantisation (the body's disc-dilated grid is
    #: conservative by up to a cell) so that a narrow lane stays open at coarse cells; the exact road edge is the
    #: road barrier's and the verdict's (``cost.road``, ``on_road``)
    offroad_margin: float | None = None
    #: drop the dynamic obstacle that coincides with the planning problem's initial state (the recorded ego)
    drop_ego: bool = True
    #: position tolerance of that match [m]
    ego_tolerance: float = 1.0
    #: ids of further dynamic or static obstacles to leave out
    exclude_obstacles: tuple[int, ...] = ()
    #: scenarios whose start lies farther than this from the origin (e.g. UTM coordinates, where float32 has
    #: 0.5-m resolution), or so far that the vehicle could leave the system's position bounds at its top speed
    #: before the goal's time interval ends (the road car's +-1 km box), are translated to a local frame: scene
    #: coordinates = file coordinates - frame_offset (``meta["frame_offset"]``, a multiple of 100 m, so the local
    #: start lies within 50 m of the origin) [m]; 0 = never
    recenter_above: float = 10_000.0
    #: id of the planning problem to use; negative = the one with the smallest id
    planning_problem_id: int = -1
    #: sample start and goal on the road (seeded) instead of using the planning problem; needed without one
    sample_start_goal: bool = False
    #: radius of the goal region around a sampled goal [m]
    sampled_goal_radius: float = 2.0
    #: horizon of a sampled start/goal pair [s]
    sampled_horizon: float = 10.0
    #: the ego vehicle's length and width [m] when the run's system is a point (CommonRoad planning problems do not
    #: give them); a system with a body uses its own footprint (``system.footprint``: the one owner of the size)
    vehicle_length: float = 4.5
    vehicle_width: float = 1.8
    #: footprint model of the dynamic obstacles (incl. the growth of the prediction error): by default each road
    #: user's own rectangle with a 0.2-m position error (``model = "shape"``; the recorded futures are the
    #: scenario's ground truth); ``footprint.model = "gaussian"`` is the paper's "length + 1 m" Gaussian
    footprint: FootprintConfig = field(default_factory=lambda: FootprintConfig(model="shape"))
    #: start/goal sampler rules (``sample_start_goal``)
    start_goal: StartGoalConfig = field(default_factory=StartGoalConfig)
    #: seed of the start/goal sampler
    seed: int = 0

    def __post_init__(self) -> None:
        if self.n_slices < 0:
            raise ValueError(f"CommonRoadSceneConfig.n_slices must be >= 0, got {self.n_slices}")
        for name in ("dt", "cell_size", "max_cell_size", "memory_budget_gib", "max_horizon", "ego_tolerance",
                     "stop_line_depth", "sampled_goal_radius", "sampled_horizon"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"CommonRoadSceneConfig.{name} must be > 0, got {value}")
        if self.max_cell_size < self.cell_size:
            raise ValueError("CommonRoadSceneConfig.max_cell_size must be >= cell_size")
        if self.initial_error is not None and (
                len(self.initial_error) != 3 or not all(math.isfinite(v) and v > 0 for v in self.initial_error)):
            raise ValueError("CommonRoadSceneConfig.initial_error must be None or three numbers > 0 (position [m], "
                             f"heading [rad], speed [m/s]), got {self.initial_error!r}")
        if self.offroad_margin is not None and not (math.isfinite(self.offroad_margin) and self.offroad_margin >= 0):
            raise ValueError(
                f"CommonRoadSceneConfig.offroad_margin must be None or >= 0 [m], got {self.offroad_margin}")
        if self.area and (
            len(self.area) != 4 or self.area[0] >= self.area[1] or self.area[2] >= self.area[3]
        ):
            raise ValueError(
                f"CommonRoadSceneConfig.area must be (xmin, xmax, ymin, ymax) with min < max, got {self.area}"
            )
        for name in ("area_margin", "gap_close", "min_duration", "vehicle_length", "vehicle_width"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"CommonRoadSceneConfig.{name} must be >= 0, got {value}")
        if not (self.vehicle_length > 0 and self.vehicle_width > 0):
            raise ValueError("CommonRoadSceneConfig.vehicle_length and vehicle_width must be > 0")
        check_seed("CommonRoadSceneConfig.seed", self.seed)


# ------------------------------------------------------------------------------------------------- reading
def _require(reader: bool = False) -> tuple[Any, Any]:
    """``(commonroad-io's CommonRoadFileReader or None, shapely)``; the reader's import (~0.2 s) only with ``reader``
    (a file read by :mod:`density_planner.prefetch` needs none). :class:`OptionalDependencyError` without
    commonroad-io."""
    try:
        import shapely
        import shapely.affinity  # noqa: F401  (submodules the importers use)
        import shapely.ops  # noqa: F401

        if reader:
            from commonroad.common.file_reader import CommonRoadFileReader

            return CommonRoadFileReader, shapely
        if importlib.util.find_spec("commonroad") is None:
            raise ImportError("No module named 'commonroad'")
    except ImportError as exc:
        raise OptionalDependencyError("commonroad-io", "commonroad", "reading CommonRoad scenarios") from exc
    return None, shapely


def read_commonroad(path: str | Path) -> tuple[Any, Any]:
    """``(scenario, planning_problem_set)`` of a CommonRoad XML file; :class:`DataError` when it is not
    one."""
    _require()
    path = Path(path)
    if not path.is_file():
        raise DataError(f"CommonRoad file not found: {path}")
    try:  # the root element only (commonroad-io parses the whole file below; parsing it twice cost ~0.4 s)
        with open(path, "rb") as fh:
            _, root = next(ET.iterparse(fh, events=("start",)))
    except (ET.ParseError, OSError, UnicodeDecodeError, StopIteration) as exc:
        raise DataError(f"{path} is not a CommonRoad scenario (not valid XML: {exc})") from exc
    if root.tag != "commonRoad":
        raise DataError(
            f"{path} is not a CommonRoad scenario (root element <{root.tag}>, expected <commonRoad>)"
        )
    from ..prefetch import take_commonroad_read

    prefetched = take_commonroad_read(path)  # read by the command line's second process meanwhile, if it was
    if prefetched is not None:
        return prefetched
    reader_cls, _ = _require(reader=True)
    try:
        with warnings.catch_warnings():  # NaN coordinates: shapely warns inside commonroad-io; checked below
            warnings.simplefilter("ignore", RuntimeWarning)
            return reader_cls(str(path)).open()
    except Exception as exc:  # commonroad-io raises many kinds of errors on malformed content
        if isinstance(exc, ET.ParseError) or type(exc).__name__ in ("XMLSyntaxError", "ParseError"):
            raise DataError(f"{path} is not a CommonRoad scenario (not valid XML: {exc})") from exc
        raise DataError(f"{path}: cannot read the CommonRoad scenario ({type(exc).__name__}: {exc})") from exc


def _lanelet_polygon(lanelet: Any, shapely: Any, where: str) -> Any:
    left = np.asarray(lanelet.left_vertices, dtype=np.float64)
    right = np.asarray(lanelet.right_vertices, dtype=np.float64)
    if not (np.isfinite(left).all() and np.isfinite(right).all()):
        raise DataError(
            f"{where}: lanelet {lanelet.lanelet_id} has non-finite vertices (NaN or inf in its <x>/<y>); "
            "fix the file"
        )
    poly = shapely.Polygon(np.vstack([left, right[::-1]]))
    if not poly.is_valid:
        poly = shapely.make_valid(poly)
    return poly


def _is_drivable(lanelet: Any, cfg: CommonRoadSceneConfig) -> bool:
    types = {str(getattr(t, "value", t)) for t in (getattr(lanelet, "lanelet_type", None) or ())}
    if types & set(cfg.non_drivable_lanelet_types):
        # a lanelet typed both as a road and e.g. a crosswalk stays a road
        if not types - set(cfg.non_drivable_lanelet_types) - {"unknown"}:
            return False
    users = {str(getattr(u, "value", u)) for u in (getattr(lanelet, "user_one_way", None) or ())}
    users |= {str(getattr(u, "value", u)) for u in (getattr(lanelet, "user_bidirectional", None) or ())}
    return not users or bool(users & _CAR_USERS)


def drivable_area(scenario: Any, config: CommonRoadSceneConfig | None = None, *, where: str = "scenario"
                  ) -> tuple[Any, dict[str, Any]]:
    """``(drivable geometry, notes)``: the union of the drivable lanelets closed over ``gap_close`` (module
    docstring, step 4); ``notes`` counts the lanelets kept / left out and the gap area filled [m^2]."""
    cfg = config or CommonRoadSceneConfig()
    _, shapely = _require()
    lanelets = list(scenario.lanelet_network.lanelets)
    if not lanelets:
        raise DataError(f"{where}: the scenario has no lanelets (no road to plan on)")
    polys, left_out = [], []
    for lanelet in lanelets:
        poly = _lanelet_polygon(lanelet, shapely, where)
        if _is_drivable(lanelet, cfg):
            if not poly.is_empty:
                polys.append(poly)
        else:
            left_out.append(int(lanelet.lanelet_id))
    if not polys:
        raise DataError(
            f"{where}: none of its {len(lanelets)} lanelets is drivable by a car (types "
            f"{sorted(cfg.non_drivable_lanelet_types)} are not); change "
            "--set commonroad.non_drivable_lanelet_types=[...]"
        )
    union = shapely.union_all(polys)
    drivable = union
    if cfg.gap_close > 0:
        r = 0.5 * cfg.gap_close
        drivable = shapely.union(union.buffer(r, join_style="mitre", mitre_limit=2.0).buffer(
            -r, join_style="mitre", mitre_limit=2.0), union)
    drivable = shapely.make_valid(drivable)
    notes = {
        "n_lanelets": len(lanelets),
        "n_drivable_lanelets": len(polys),
        "non_drivable_lanelets": left_out,
        "gap_close_m": cfg.gap_close,
        "gap_area_closed_m2": float(drivable.area - union.area),
        "drivable_area_m2": float(drivable.area),
        "n_holes": int(sum(len(p.interiors) for p in getattr(drivable, "geoms", [drivable])
                           if hasattr(p, "interiors"))),
    }
    return drivable, notes


# --------------------------------------------------------------------------------------------- obstacles
def _num(value: Any) -> float | None:
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        return float(value)
    return None


def _shape_outline(shape: Any, shapely: Any) -> tuple[Any, float, float]:
    """``(outline polygon in the obstacle frame or None for a plain rectangle, length, width)``."""
    from commonroad.scenario.state import InitialState

    radius = _num(getattr(shape, "radius", None))
    length, width = _num(getattr(shape, "length", None)), _num(getattr(shape, "width", None))
    if radius is None and length is not None and width is not None and not getattr(shape, "origin_x_shift", 0):
        if type(shape).__name__ in ("RectObstacleShape", "Rectangle"):
            return None, length, width
    try:
        occ = shape.compute_occupancy_for_state(
            InitialState(time_step=0, position=np.zeros(2), orientation=0.0, velocity=0.0))
        poly = occ.shapely_object
    except Exception:  # older shape classes: fall back to the bounding rectangle
        poly = None
    if poly is None and radius is not None:
        poly = shapely.Point(0.0, 0.0).buffer(radius, quad_segs=8)
    if poly is None:
        if length is None or width is None:
            raise DataError(f"unsupported CommonRoad obstacle shape {type(shape).__name__}")
        return None, length, width
    if poly.geom_type != "Polygon":
        poly = poly.convex_hull
    x0, y0, x1, y1 = poly.bounds
    return poly, max(x1 - x0, 1e-3), max(y1 - y0, 1e-3)


def _point(position: Any) -> np.ndarray | None:
    """``(2,)`` position [m] of a CommonRoad state's ``position``: the point, or the centre of a shape (an uncertain
    position given as a rectangle, circle or polygon); ``None`` when it has neither."""
    centre = getattr(position, "center", None)
    if centre is not None and hasattr(centre, "x") and hasattr(centre, "y"):  # a shapely point
        centre = (centre.x, centre.y)
    if centre is None and hasattr(position, "shapely_object"):
        c = position.shapely_object.centroid
        centre = (c.x, c.y)
    try:
        pos = np.asarray(position if centre is None else centre, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        return None
    return pos if pos.size == 2 else None


def _states(obs: Any) -> list[Any]:
    states = [obs.initial_state]
    trajectory = getattr(getattr(obs, "prediction", None), "trajectory", None)
    if trajectory is not None:
        states += list(trajectory.state_list)
    return states


def _trajectory_arrays(obs: Any, dt: float, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(times (K,), poses (K, 3), speed (K,))`` of an obstacle's initial state and trajectory."""
    rows = {}
    for st in _states(obs):
        step = getattr(st, "time_step", None)
        if not isinstance(step, (int, np.integer)):
            continue
        pos = _point(getattr(st, "position", None))
        if pos is None:
            continue
        rows[int(step)] = (pos[0], pos[1], _num(getattr(st, "orientation", None)), _num(getattr(st, "velocity",
                                                                                                 None)))
    if not rows:
        raise DataError(f"{where}: dynamic obstacle {obs.obstacle_id} has no state with a position")
    steps = np.array(sorted(rows))
    xy = np.array([[rows[s][0], rows[s][1]] for s in steps], dtype=np.float64)
    th = np.array([np.nan if rows[s][2] is None else rows[s][2] for s in steps])
    v = np.array([np.nan if rows[s][3] is None else rows[s][3] for s in steps])
    if not np.isfinite(xy).all():
        raise DataError(f"{where}: dynamic obstacle {obs.obstacle_id} has a non-finite position; fix the file")
    times = steps * dt
    if steps.size > 1:
        vel = np.gradient(xy, times, axis=0)
        th = np.where(np.isfinite(th), th, np.arctan2(vel[:, 1], vel[:, 0]))
        v = np.where(np.isfinite(v), v, np.hypot(vel[:, 0], vel[:, 1]))
    th, v = np.nan_to_num(th), np.nan_to_num(v)
    return times, np.column_stack([xy, th]), v


def _state_at_step(obs: Any, step: int) -> np.ndarray | None:
    for st in _states(obs):
        if getattr(st, "time_step", None) == step:
            return _point(getattr(st, "position", None))
    return None


def _interval(value: Any) -> tuple[float, float] | None:
    if value is None:
        return None
    start, end = _num(getattr(value, "start", None)), _num(getattr(value, "end", None))
    if start is not None and end is not None:
        return (start, end)
    x = _num(value)
    return None if x is None else (x, x)


def _set_based_track(obs: Any, kind: str, dt: float, t_end: float, shapely: Any, fp: FootprintConfig
                     ) -> ObstacleTrack:
    """Set-based prediction -> track of world-frame occupancies, one per scenario time step it covers,
    continued past its last set at the initial velocity (module docstring, step 6)."""
    occ_dict = getattr(obs.prediction, "occupancies", None) or {}
    per_step: dict[int, list[Any]] = {}
    for key, occ in occ_dict.items():
        geom = getattr(occ, "shapely_object", None)
        if geom is None:
            geom = getattr(getattr(occ, "shape", None), "shapely_object", None)
        iv = _interval(key) if not isinstance(key, (int, np.integer)) else (int(key), int(key))
        if geom is None or iv is None:
            continue
        for s in range(int(math.floor(iv[0])), int(math.ceil(iv[1])) + 1):
            per_step.setdefault(s, []).append(geom)
    init = obs.initial_state
    pos = np.asarray(init.position, dtype=np.float64).reshape(-1)
    th0 = _num(getattr(init, "orientation", None)) or 0.0
    v0 = _num(getattr(init, "velocity", None)) or 0.0
    init_poly, length, width = _shape_outline(obs.obstacle_shape, shapely)
    if init_poly is None:
        init_poly = shapely.box(-length / 2, -width / 2, length / 2, width / 2)
    base = shapely.affinity.translate(shapely.affinity.rotate(init_poly, th0, origin=(0, 0), use_radians=True),
                                      *pos)
    per_step.setdefault(int(init.time_step), []).append(base)
    steps = np.array(sorted(per_step))
    geoms = [shapely.union_all(per_step[s]) for s in steps]
    times = list(steps * dt)
    predicted = [False] * len(times)
    std = [0.0] * len(times)
    last = geoms[-1]
    n_extra = int(math.floor((t_end - times[-1]) / dt + 1e-9))
    for i in range(1, n_extra + 1):
        tau = i * dt
        e = fp.prediction_std_rate_along * tau
        moved = shapely.affinity.translate(last, v0 * math.cos(th0) * tau, v0 * math.sin(th0) * tau)
        geoms.append(moved.buffer(e) if e > 0 else moved)
        times.append(times[len(steps) - 1] + tau)
        predicted.append(True)
        std.append(e)
    cents = np.array([[g.centroid.x, g.centroid.y, th0] for g in geoms])
    return ObstacleTrack(int(obs.obstacle_id), kind, length, width, np.array(times), cents,
                         predicted=np.array(predicted), position_std=np.array(std),
                         occupancies=np.array(geoms, dtype=object))


# ---------------------------------------------------------------------------------------------- rasterise
def _rasterise_polygons(out: torch.Tensor, polys_per_slice: list[list[Any]], origin: tuple[float, float],
                        h: float, shapely: Any) -> None:
    """Set ``out[k] = 1`` inside every polygon of slice ``k`` (cell centres; only each polygon's bounding box of
    cells is tested)."""
    _, NX, NY = out.shape
    for k, polys in enumerate(polys_per_slice):
        for poly in polys:
            x0, y0, x1, y1 = poly.bounds
            i0, i1 = max(int(math.floor((x0 - origin[0]) / h)), 0), min(int(math.ceil((x1 - origin[0]) / h)), NX - 1)
            j0, j1 = max(int(math.floor((y0 - origin[1]) / h)), 0), min(int(math.ceil((y1 - origin[1]) / h)), NY - 1)
            if i0 > i1 or j0 > j1:
                continue
            gx, gy = np.meshgrid(origin[0] + h * np.arange(i0, i1 + 1), origin[1] + h * np.arange(j0, j1 + 1),
                                 indexing="ij")
            inside = torch.from_numpy(shapely.contains_xy(poly, gx, gy))
            out[k, i0:i1 + 1, j0:j1 + 1][inside] = 1.0


def offroad_cells(drivable: Any, origin: tuple[float, float], cell_size: float, size: tuple[int, int],
                  margin: float | None = None) -> np.ndarray:
    """``(NX, NY)`` bool: the cells whose centre lies more than ``margin`` [m] outside the drivable area (``None``:
    half the cell's diagonal, :attr:`CommonRoadSceneConfig.offroad_margin`), i.e. the off-road part of the static
    map."""
    margin = cell_size * math.sqrt(0.5) if margin is None else float(margin)
    road = drivable.buffer(margin, quad_segs=2) if margin > 0 else drivable
    return ~lattice_in(road, origin, cell_size, size)


#: off-road masks per road scene and grid geometry (:func:`offroad_mask`; as ``road_sdf``'s cache)
_OFFROAD_MASKS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _offroad_key(grid: OccupancyGrid, margin: float | None) -> tuple:
    _, nx, ny = grid.shape
    return (grid.origin, grid.cell_size, nx, ny, None if margin is None else float(margin))


def offroad_mask(scene: Scene) -> torch.Tensor | None:
    """``(NX, NY)`` bool tensor of the scene grid's cells that its static map marks off the road (as imported:
    :func:`offroad_cells` with the scene's ``offroad_margin``); ``None`` for a scene without a road or one imported
    with ``offroad_occupied = false`` (its grid holds no road edge). Computed once per road scene and grid geometry
    (the online windows share it)."""
    road = scene.road
    if road is None or road.drivable is None:
        return None
    cfg = scene.meta.get("config") or {}
    if not bool(cfg.get("offroad_occupied", True)):
        return None
    _, nx, ny = scene.grid.shape
    key = _offroad_key(scene.grid, cfg.get("offroad_margin"))
    per_road = _OFFROAD_MASKS.setdefault(road, {})
    if key not in per_road:
        per_road[key] = torch.from_numpy(offroad_cells(road.drivable, scene.grid.origin, scene.grid.cell_size,
                                                       (nx, ny), cfg.get("offroad_margin")))
    return per_road[key]


def static_map(
    scenario: Any,
    origin: tuple[float, float],
    cell_size: float,
    size: tuple[int, int],
    config: CommonRoadSceneConfig | None = None,
    *,
    drivable: Any = None,
    static_polygons: list[Any] | None = None,
    offroad: np.ndarray | None = None,
) -> tuple[np.ndarray, int]:
    """``((NX, NY) float32 static occupancy, number of static obstacles drawn)``: 1 outside the drivable area
    (unless ``config.offroad_occupied`` is false) and inside static obstacles, 0 elsewhere, evaluated at the cell
    centres. ``offroad``: :func:`offroad_cells` of this geometry where the caller has it already."""
    cfg = config or CommonRoadSceneConfig()
    _, shapely = _require()
    if drivable is None:
        drivable, _ = drivable_area(scenario, cfg)
    nx, ny = size
    if cfg.offroad_occupied:
        if offroad is None:
            offroad = offroad_cells(drivable, origin, cell_size, size, cfg.offroad_margin)
        static = offroad.astype(np.float32)
    else:
        static = np.zeros((nx, ny), dtype=np.float32)
    if static_polygons is None:
        static_polygons = []
        if cfg.include_static_obstacles:
            for obs in scenario.static_obstacles:
                track = _static_track(obs, shapely)
                if track is not None:
                    static_polygons.append(track.polygons_at(np.array([0.0]))[0])
    if static_polygons:
        static[lattice_in(shapely.union_all(static_polygons), origin, cell_size, size)] = 1.0
    return static, len(static_polygons)


def _static_track(obs: Any, shapely: Any) -> ObstacleTrack | None:
    st = obs.initial_state
    pos = _point(getattr(st, "position", None))
    if pos is None or not np.isfinite(pos).all():
        return None
    th = _num(getattr(st, "orientation", None)) or 0.0
    outline, length, width = _shape_outline(obs.obstacle_shape, shapely)
    kind = str(getattr(obs.obstacle_type, "value", obs.obstacle_type))
    t0 = float(getattr(st, "time_step", 0) or 0)
    return ObstacleTrack(int(obs.obstacle_id), kind, length, width, np.array([t0]), np.array([[pos[0], pos[1], th]]),
                         shape=outline,
                         static=True)


# -------------------------------------------------------------------------------------------------- goal
def _lanelet_union(scenario: Any, ids: list[int], shapely: Any, where: str) -> Any:
    polys = []
    for lid in ids:
        lanelet = scenario.lanelet_network.find_lanelet_by_id(lid)
        if lanelet is None:
            raise DataError(f"{where}: the goal names lanelet {lid}, which is not in the lanelet network")
        polys.append(_lanelet_polygon(lanelet, shapely, where))
    return shapely.union_all(polys) if polys else None


def goal_region(problem: Any, scenario: Any, *, where: str = "scenario") -> GoalRegion:
    """The :class:`~.road.GoalRegion` of a CommonRoad planning problem (module docstring, step 2)."""
    _, shapely = _require()
    dt = float(scenario.dt)
    goal = problem.goal
    lanelet_goals = dict(getattr(goal, "lanelets_of_goal_position", None) or {})
    alternatives = []
    for i, st in enumerate(getattr(goal, "state_list", []) or []):
        geom, lids = None, tuple(int(x) for x in lanelet_goals.get(i, ()))
        pos = getattr(st, "position", None)
        if pos is not None:
            geom = getattr(pos, "shapely_object", None)
            if geom is None:
                centre = np.asarray(getattr(pos, "center", None), dtype=np.float64).reshape(-1)
                if centre.size == 2:
                    geom = shapely.Point(*centre)
        if geom is None and lids:
            geom = _lanelet_union(scenario, list(lids), shapely, where)
        if geom is not None:
            if geom.is_empty or not np.isfinite(shapely.get_coordinates(geom)).all():
                raise DataError(f"{where}: goal state {i} has an empty or non-finite position; fix the file")
            if geom.area == 0:  # a point or line goal: reachable only with a tolerance of the car's size
                geom = geom.buffer(0.5)
        ts = _interval(getattr(st, "time_step", None))
        if ts is None:
            raise DataError(f"{where}: goal state {i} has no time step / interval (required by CommonRoad)")
        vel = _interval(getattr(st, "velocity", None))
        ori = _interval(getattr(st, "orientation", None))
        alternatives.append(GoalRegion(geom, (ts[0] * dt, ts[1] * dt), vel, ori, lids))
    if not alternatives:
        raise DataError(f"{where}: the planning problem has no goal state")
    if len(alternatives) == 1:
        return alternatives[0]
    shapes = [a.shapes for a in alternatives if a.shapes is not None]
    any_anywhere = any(a.shapes is None for a in alternatives)
    union = None if (any_anywhere or not shapes) else shapely.union_all(shapes)
    t_lo = min(a.time_interval[0] for a in alternatives)
    t_hi = max(a.time_interval[1] for a in alternatives)
    lids = tuple(sorted({i for a in alternatives for i in a.lanelet_ids}))
    return GoalRegion(union, (t_lo, t_hi), None, None, lids, alternatives=tuple(alternatives))


def _lane_following_point(scenario: Any, start: tuple[float, ...], distance: float, shapely: Any
                          ) -> tuple[float, float]:
    """The point ``distance`` m ahead of the start along the centre line of its lanelet and first
    successors (the start itself when it is on no lanelet or ``distance`` is 0)."""
    net = scenario.lanelet_network
    xy = np.asarray(start[:2], dtype=np.float64)
    if distance <= 0:
        return float(xy[0]), float(xy[1])
    try:
        ids = net.find_lanelet_by_position([xy])[0]
    except Exception:
        ids = []
    if not ids:
        return float(xy[0] + distance * math.cos(start[2])), float(xy[1] + distance * math.sin(start[2]))
    # the lanelet whose direction is closest to the start heading
    best, best_err = ids[0], math.inf
    for lid in ids:
        c = np.asarray(net.find_lanelet_by_id(lid).center_vertices)
        line = shapely.LineString(c)
        s = line.project(shapely.Point(xy))
        a, b = line.interpolate(max(s - 0.5, 0)), line.interpolate(min(s + 0.5, line.length))
        err = abs(math.remainder(math.atan2(b.y - a.y, b.x - a.x) - start[2], 2 * math.pi))
        if err < best_err:
            best, best_err = lid, err
    pts = [xy]
    lanelet = net.find_lanelet_by_id(best)
    line = shapely.LineString(np.asarray(lanelet.center_vertices))
    s0 = line.project(shapely.Point(xy))
    coords = np.asarray(shapely.get_coordinates(shapely.ops.substring(line, s0, line.length)))
    pts.extend(coords[1:])
    seen = {best}
    while True:
        path = shapely.LineString(np.vstack(pts)) if len(pts) > 1 else None
        if path is not None and path.length >= distance:
            p = path.interpolate(distance)
            return float(p.x), float(p.y)
        succ = [s for s in (lanelet.successor or []) if s not in seen]
        if not succ:
            p = shapely.Point(pts[-1]) if path is None else path.interpolate(path.length)
            return float(p.x), float(p.y)
        lanelet = net.find_lanelet_by_id(succ[0])
        seen.add(succ[0])
        pts.extend(np.asarray(lanelet.center_vertices)[1:])


def _goal_point_near(shapes: Any, xy: tuple[float, float], shapely: Any) -> tuple[float, float]:
    """The point of ``shapes`` nearest to ``xy``, taken from the region shrunk by 1 m (by less where the
    region is narrower), so that today's point-goal planners aim at the near side of a long goal lanelet."""
    p = shapely.Point(xy[0], xy[1])
    inner = shapes
    for depth in (1.0, 0.5, 0.25):
        shrunk = shapes.buffer(-depth)
        if not shrunk.is_empty:
            inner = shrunk
            break
    q = shapely.ops.nearest_points(inner, p)[0]
    return float(q.x), float(q.y)


# ------------------------------------------------------------------------------------------------- helpers
def reach_distance(v0: float, v_max: float, a_max: float, horizon: float) -> float:
    """Largest distance [m] a car starting at ``v0`` covers in ``horizon`` s with acceleration <= ``a_max``
    and speed <= ``v_max`` (accelerate, then cruise)."""
    v0 = min(max(v0, 0.0), v_max)
    if a_max <= 0:
        return v0 * horizon
    t_acc = min((v_max - v0) / a_max, horizon)
    return v0 * t_acc + 0.5 * a_max * t_acc**2 + v_max * (horizon - t_acc)


def _choose_cell(area: tuple[float, float, float, float], n_slices: int, cfg: CommonRoadSceneConfig,
                 where: str) -> float:
    w, h = area[1] - area[0], area[3] - area[2]
    budget_cells = cfg.memory_budget_gib * _GIB / 4.0 / n_slices
    need = math.sqrt(w * h / budget_cells) if budget_cells > 0 else math.inf
    cell = cfg.cell_size

    def fits(c: float) -> bool:  # the lattice adds up to 5 points per axis (ends, snapping, whole coarse cells)
        return (w / c + 5) * (h / c + 5) <= budget_cells

    if not fits(cell):
        cell = max(cell, math.ceil(need / 0.05 - 1e-9) * 0.05)
        while not fits(cell) and cell <= cfg.max_cell_size:
            cell += 0.05
        cell = round(cell, 6)
    if cell > cfg.max_cell_size + 1e-9:
        raise DataError(
            f"{where}: the map ({w:.0f} m x {h:.0f} m, {n_slices} slices) needs cells of {cell:g} m to fit "
            f"{cfg.memory_budget_gib:g} GiB, coarser than max_cell_size = {cfg.max_cell_size:g} m; raise "
            "--set commonroad.memory_budget_gib=..., lower --set commonroad.max_horizon=..., or allow "
            "--set commonroad.max_cell_size=..."
        )
    return cell


def _snap(area: tuple[float, float, float, float], cell: float) -> tuple[float, float, float, float]:
    return (
        round(math.floor(area[0] / cell + 1e-9) * cell, 9),
        round(math.ceil(area[1] / cell - 1e-9) * cell, 9),
        round(math.floor(area[2] / cell + 1e-9) * cell, 9),
        round(math.ceil(area[3] / cell - 1e-9) * cell, 9),
    )


def _model_limits(system: Any) -> tuple[float, float, float, str]:
    """``(v_min, v_max, a_max, description)`` of the system's speed state and acceleration input."""
    if system is None:
        from density_planner.systems.registry import make_system

        system = make_system()
    iv, ia = system.speed_index, system.acceleration_input
    if iv is None or ia is None:
        raise ValueError(f"a CommonRoad scene needs a system with a speed state and an acceleration input; "
                         f"{type(system).__name__} has {'no speed state' if iv is None else 'no acceleration input'}")
    lo, hi = system.state_bounds
    ulo, uhi = system.input_bounds
    return float(lo[iv]), float(hi[iv]), float(max(abs(ulo[ia]), abs(uhi[ia]))), type(system).__name__


def _goal_horizon(problem: Any, dt_src: float, t_start: float, cap: float) -> float:
    """End of the planning problem's goal time intervals after the start [s], at most ``cap`` (``cap`` where the
    goal states give no time)."""
    ends = [iv[1] * dt_src - t_start for st in getattr(getattr(problem, "goal", None), "state_list", None) or ()
            if (iv := _interval(getattr(st, "time_step", None))) is not None]
    return min(max(ends), cap) if ends else cap


def _reach_inside_position_box(system: Any, pos: np.ndarray, reach: float) -> bool:
    """Whether every position within ``reach`` [m] of ``pos`` (the farthest the vehicle can drive before the end of
    its horizon) lies inside the system's position bounds (the road car's +-1 km box; a plan leaving it is outside
    the model)."""
    lo, hi = system.state_bounds
    return all(float(lo[i]) <= float(p) - reach and float(p) + reach <= float(hi[i])
               for i, p in zip(system.position_indices, pos))


# ---------------------------------------------------------------------------------------------------- load
def load_commonroad_scene(path: str | Path, config: CommonRoadSceneConfig | None = None, *,
                          system: Any = None) -> Scene:
    """Scene of the CommonRoad scenario in ``path`` (see the module docstring for every step).

    ``system`` (default: the registry's default system, the kinematic car) supplies the speed and
    acceleration bounds (the reachable map region and the start-domain check). The returned scene carries the
    exact geometry in ``scene.road`` and the suggested planning horizon in ``scene.meta["horizon"]`` [s].
    """
    cfg = config or CommonRoadSceneConfig()
    _, shapely = _require()  # with its submodules affinity and ops (used below)

    path = Path(path)
    scenario, problem_set = read_commonroad(path)
    remember_lane_graph(path, scenario.lanelet_network)  # the planners' route seeds reuse it
    bench_id = str(getattr(scenario, "scenario_id", path.stem))
    where = path.name if bench_id == path.stem else f"{path.name} ({bench_id})"
    dt_src = float(scenario.dt)
    if not (math.isfinite(dt_src) and dt_src > 0):
        raise DataError(f"{where}: the scenario's time step dt = {dt_src} must be a positive number")
    notes: list[str] = []

    def note(msg: str, *args: Any) -> None:
        text = msg % args if args else msg
        logger.info("%s: %s", where, text)
        notes.append(text)

    drivable, road_notes = drivable_area(scenario, cfg, where=where)
    if road_notes["non_drivable_lanelets"]:
        note("%d lanelets are not drivable by a car (types %s or road users without cars) and are left out",
             len(road_notes["non_drivable_lanelets"]), list(cfg.non_drivable_lanelet_types))
    if system is None:
        from density_planner.systems.registry import make_system

        system = make_system()
    v_min, v_max, a_max, model = _model_limits(system)
    body = system.footprint
    if not body.is_point:  # the ego's size is the system's body (road barrier, verdict and risk read the same one)
        cfg = replace(cfg, vehicle_length=body.length, vehicle_width=body.width)

    # -- planning problem: start, goal, horizon
    problem = _planning_problem(problem_set, cfg.planning_problem_id, where)
    if problem is None and not cfg.sample_start_goal:
        raise DataError(
            f"{where}: the file has no planning problem (no start and goal); add one, or sample a start and "
            "goal on its road with --set commonroad.sample_start_goal=true"
        )
    start: tuple[float, float, float, float] | None = None
    frame_offset = (0.0, 0.0)
    t_start = 0.0
    goal: GoalRegion | None = None
    if problem is not None:
        init = problem.initial_state
        step = getattr(init, "time_step", 0)
        if not isinstance(step, (int, np.integer)):
            raise DataError(f"{where}: the planning problem's initial state has no integer time step")
        t_start = float(step) * dt_src
        pos = _point(getattr(init, "position", None))
        th, v = _num(getattr(init, "orientation", None)), _num(getattr(init, "velocity", None))
        if pos is None or th is None or v is None or not (np.isfinite(pos).all() and math.isfinite(th)
                                                            and math.isfinite(v)):
            raise DataError(
                f"{where}: the planning problem's initial state must have a finite position, orientation and "
                f"velocity, got position {None if pos is None else pos.tolist()}, orientation {th}, velocity {v}; "
                "fix the file"
            )
        reach = v_max * _goal_horizon(problem, dt_src, t_start, cfg.max_horizon)
        if cfg.recenter_above > 0 and (float(np.abs(pos).max()) > cfg.recenter_above
                                       or not _reach_inside_position_box(system, pos, reach)):
            frame_offset = (float(100.0 * round(pos[0] / 100.0)), float(100.0 * round(pos[1] / 100.0)))
            scenario.translate_rotate(-np.asarray(frame_offset), 0.0)
            problem_set.translate_rotate(-np.asarray(frame_offset), 0.0)
            drivable, road_notes = drivable_area(scenario, cfg, where=where)
            pos = pos - np.asarray(frame_offset)
            note("coordinates translated by (%.0f, %.0f) m to a local frame (float32 precision); scene coordinates "
                 "= file coordinates - meta.frame_offset", -frame_offset[0], -frame_offset[1])
        start = (float(pos[0]), float(pos[1]), float(th), float(v))
        if not cfg.sample_start_goal:
            if not (v_min - 1e-9 <= v <= v_max + 1e-9):
                raise DataError(
                    f"{where}: start speed {v:.2f} m/s is outside the {model} model's domain "
                    f"({v_min:g} <= v <= {v_max:g} m/s, its state bounds); planning from it is not supported"
                )
            goal = goal_region(problem, scenario, where=where)
            alts = goal.alternatives or (goal,)
            if all(a.velocity is not None and not (a.velocity[0] <= v_max + 1e-9 and a.velocity[1] >= v_min - 1e-9)
                   for a in alts):
                bands = ", ".join(f"[{a.velocity[0]:.2f}, {a.velocity[1]:.2f}]" for a in alts
                                  if a.velocity is not None)
                raise DataError(
                    f"{where}: the goal's velocity interval {bands} m/s lies outside the {model} model's domain "
                    f"({v_min:g} <= v <= {v_max:g} m/s, its state bounds); no plan can reach it"
                )
    if cfg.sample_start_goal:
        horizon = cfg.sampled_horizon
    else:
        assert goal is not None
        horizon = goal.t_end - t_start
        if horizon <= 0:
            raise DataError(
                f"{where}: the goal's time interval [{goal.time_interval[0]:g}, {goal.time_interval[1]:g}] s ends "
                f"before the start (t = {t_start:g} s)"
            )
        if horizon > cfg.max_horizon:
            note("the goal's time interval ends %.1f s after the start; the horizon is capped at "
                 "max_horizon = %g s", horizon, cfg.max_horizon)
            horizon = cfg.max_horizon
    # the grid covers the horizon rounded up to whole seconds (planners plan whole segments), >= min_duration
    n_slices = cfg.n_slices or int(math.ceil(max(math.ceil(horizon - 1e-9), cfg.min_duration) / cfg.dt - 1e-9)) + 1
    t_grid_end = t_start + (n_slices - 1) * cfg.dt

    # -- map region and cell size
    lx0, ly0, lx1, ly1 = drivable.bounds
    if cfg.area:
        a0, a1, a2, a3 = (float(v) for v in cfg.area)  # four numbers (CommonRoadSceneConfig checks)
        area = (a0, a1, a2, a3)
        region_rule = "configured area"
    elif start is not None and not cfg.sample_start_goal:
        span = (n_slices - 1) * cfg.dt  # the grid's duration (the horizon in whole seconds, >= min_duration)
        reach = reach_distance(start[3], v_max, a_max, span)
        disc = shapely.Point(start[0], start[1]).buffer(reach + cfg.area_margin, quad_segs=16)
        parts = [disc.intersection(drivable.buffer(cfg.area_margin)), shapely.Point(start[0], start[1])]
        if goal is not None and goal.shapes is not None:
            parts.append(goal.shapes)
        bx0, by0, bx1, by1 = shapely.union_all([p for p in parts if not p.is_empty]).bounds
        m = cfg.area_margin
        area = (bx0 - m, bx1 + m, by0 - m, by1 + m)
        region_rule = (f"reachable in {span:g} s from {start[3]:.1f} m/s (v <= {v_max:g} m/s, |a| <= "
                       f"{a_max:g} m/s^2: {reach:.0f} m) on the road, plus the goal region and {m:g} m")
    else:
        m = cfg.area_margin
        area = (lx0 - m, lx1 + m, ly0 - m, ly1 + m)
        region_rule = "the whole lanelet network"
    cell = _choose_cell(area, n_slices, cfg, where)
    if cell > cfg.cell_size:
        note("cell size %.2f m (not %g m) keeps the %d-slice grid within memory_budget_gib = %g", cell,
             cfg.cell_size, n_slices, cfg.memory_budget_gib)
    area = _snap(area, cell)
    nx, ny = lattice_size(area[0], area[1], cell), lattice_size(area[2], area[3], cell)
    factor = int(round(cfg.footprint.coarse_cell / cell)) if cfg.footprint.coarse_cell > 0 else 1
    if factor >= 2:  # whole coarse cells: the footprints' coarse lattice then upsamples without a cropping copy
        nx, ny = nx + (-(nx - 1)) % factor, ny + (-(ny - 1)) % factor
        area = (area[0], round(area[0] + (nx - 1) * cell, 9), area[2], round(area[2] + (ny - 1) * cell, 9))
    origin = (area[0], area[2])
    times = t_start + cfg.dt * np.arange(n_slices)
    map_ready(drivable, origin, cell, nx, ny)  # the road's distance field meanwhile, where a caller asks for it

    # -- obstacles
    known = {int(o.obstacle_id) for o in scenario.obstacles}
    unknown = sorted(set(int(i) for i in cfg.exclude_obstacles) - known)
    if unknown:
        raise DataError(
            f"{where}: commonroad.exclude_obstacles names obstacle id(s) {unknown} that are not in the scenario "
            f"(ids: {sorted(known)[:20]}{' ...' if len(known) > 20 else ''})"
        )
    excluded = set(int(i) for i in cfg.exclude_obstacles)
    if excluded:
        note("obstacles %s excluded by commonroad.exclude_obstacles", sorted(excluded))
    dyn = [o for o in scenario.dynamic_obstacles if int(o.obstacle_id) not in excluded]
    dropped_ego = None
    if cfg.drop_ego and start is not None and problem is not None:
        best, best_d = None, math.inf
        for o in dyn:
            p = _state_at_step(o, int(problem.initial_state.time_step))
            if p is not None and np.isfinite(p).all():
                d = float(np.hypot(*(p - np.asarray(start[:2]))))
                if d < best_d:
                    best, best_d = o, d
        if best is not None and best_d <= cfg.ego_tolerance:
            dropped_ego = {"id": int(best.obstacle_id), "distance_m": best_d}
            note("dynamic obstacle %d is the recorded ego (%.2f m from the start at its initial time step) and "
                 "is dropped", best.obstacle_id, best_d)
            dyn = [o for o in dyn if o is not best]
    tracks_true: list[ObstacleTrack] = []
    polys_per_slice: list[list[Any]] = [[] for _ in range(n_slices)]
    traj_obs, info = [], []
    n_set = 0
    for o in dyn:
        kind = str(getattr(o.obstacle_type, "value", o.obstacle_type))
        pred = getattr(o, "prediction", None)
        if pred is not None and getattr(pred, "trajectory", None) is None and hasattr(pred, "occupancies"):
            track = _set_based_track(o, kind, dt_src, t_grid_end, shapely, cfg.footprint)
            n_set += 1
            tracks_true.append(track)
            for k, poly in enumerate(track.polygons_at(times)):
                if poly is not None:
                    polys_per_slice[k].append(poly)
            info.append({"id": int(o.obstacle_id), "type": kind, "prediction": "set-based",
                         "t_last_s": track.t_last_recorded})
            continue
        traj_obs.append(o)
    if n_set:
        note("%d obstacles have set-based predictions: occupied over every time step their sets cover", n_set)
    users, user_tracks, n_pred = _trajectory_users(traj_obs, times, dt_src, t_grid_end, shapely, cfg, where)
    tracks_true.extend(user_tracks)
    for tr in user_tracks:
        info.append({"id": tr.obstacle_id, "type": tr.kind, "class": ROAD_USER_CLASSES[obstacle_class_id(tr.kind)],
                     "length": tr.length, "width": tr.width, "t_last_recorded_s": tr.t_last_recorded,
                     "predicted_after_s": tr.t_last_recorded if np.any(np.asarray(tr.predicted)) else None})
    if n_pred:
        note("%d road users end before the grid (t = %.1f s) and are predicted past their last recorded state "
             "(constant velocity and heading, position std +%g m/s along, +%g m/s across)", n_pred, t_grid_end,
             cfg.footprint.prediction_std_rate_along, cfg.footprint.prediction_std_rate_across)
    statics = []
    if cfg.include_static_obstacles:
        for o in scenario.static_obstacles:
            if int(o.obstacle_id) in excluded:
                continue
            st = _static_track(o, shapely)
            if st is not None:
                statics.append(st)
    tracks_true.extend(statics)

    # -- traffic lights
    lights = _red_light_tracks(scenario, times, start, cfg, shapely, where, note)
    tracks_true.extend(lights)
    for tr in lights:
        for k, poly in enumerate(tr.polygons_at(times)):
            if poly is not None:
                polys_per_slice[k].append(poly)

    # -- rasterise
    offroad = offroad_cells(drivable, origin, cell, (nx, ny), cfg.offroad_margin) if cfg.offroad_occupied else None
    static, n_static = static_map(scenario, origin, cell, (nx, ny), cfg, drivable=drivable,
                                  static_polygons=[t.polygons_at(np.array([t_start]))[0] for t in statics],
                                  offroad=offroad)
    probs = rasterise_road_users(users, origin=origin, cell_size=cell, shape=(n_slices, nx, ny),
                                 config=cfg.footprint, static=torch.from_numpy(static))
    if any(polys_per_slice):
        _rasterise_polygons(probs, polys_per_slice, origin, cell, shapely)
    grid = OccupancyGrid(probs, origin, cell, cfg.dt, t_start, in_range=True)  # the rasteriser's values
    box = (area[0] + 0.1, area[1] - 0.1, area[2] + 0.1, area[3] - 0.1)

    # -- start / goal of the planners
    if cfg.sample_start_goal:
        note("start and goal sampled on the road (seed %d) instead of the planning problem", cfg.seed)
        start, goal_xy = sample_start_goal(grid, box, seed=cfg.seed, config=cfg.start_goal)
        goal = GoalRegion(shapely.Point(*goal_xy).buffer(cfg.sampled_goal_radius), (t_start, t_start + horizon))
        goal_rule = "sampled"
    else:
        assert goal is not None and start is not None
        dist = start[3] * horizon
        ahead = _lane_following_point(scenario, start, dist, shapely)
        if goal.shapes is None:
            goal_xy = ahead
            goal_rule = (f"the goal has no position: the point {dist:.0f} m ahead along the start lane (initial "
                         "speed x horizon)")
            note(goal_rule)
        else:
            goal_xy = _goal_point_near(goal.shapes, ahead, shapely)
            goal_rule = ("the point of the goal region (shrunk by 1 m where it is wider) nearest to the point "
                         f"{dist:.0f} m ahead along the start lane (initial speed x horizon)")
        xmin, xmax, ymin, ymax = grid.bounds
        goal_xy = (min(max(goal_xy[0], xmin), xmax), min(max(goal_xy[1], ymin), ymax))
    road = RoadScene(drivable, tuple(tracks_true), goal, dt_src, t_start, where, cfg.vehicle_length,
                     cfg.vehicle_width, meta={"notes": notes, "frame_offset": list(frame_offset)})
    if offroad is not None:  # offroad_mask's value for this scene (collision reads it): computed once
        _OFFROAD_MASKS.setdefault(road, {})[_offroad_key(grid, cfg.offroad_margin)] = torch.from_numpy(offroad)
    memory = n_slices * nx * ny * 4
    meta = {
        "source": "commonroad",
        "file": str(path),
        "file_name": path.name,
        "scenario_id": bench_id,
        "scenario_dt": dt_src,
        "t_start": t_start,
        "horizon": horizon,
        "frame_offset": list(frame_offset),
        "planning_problem": None if problem is None else int(getattr(problem, "planning_problem_id", -1)),
        "start_goal_sampled": bool(cfg.sample_start_goal),
        "goal": {**goal.to_json_dict(), "point": list(goal_xy), "point_rule": goal_rule},
        "model_domain": {"model": model, "v_min": v_min, "v_max": v_max, "a_max": a_max},
        "initial_error": None if cfg.initial_error is None else dict(zip(("position", "heading", "speed"),
                                                                          map(float, cfg.initial_error))),
        "initial_on_road": bool(cfg.initial_on_road),
        "map": {"area": list(area), "cell_size": cell, "shape": [n_slices, nx, ny], "memory_bytes": memory,
                "region": region_rule},
        "road": road_notes,
        "dropped_ego": dropped_ego,
        "excluded_obstacles": sorted(excluded),
        "n_lanelets": road_notes["n_lanelets"],
        "n_static_obstacles": n_static,
        "n_red_light_phases": len(lights),
        "dynamic_obstacles": info,
        "simplifications": notes,
        "config": to_dict(cfg),
    }
    logger.info("%s: map x [%g, %g], y [%g, %g] m, %g-m cells, %d slices (%.0f MiB): %s", where, area[0], area[1],
                area[2], area[3], cell, n_slices, memory / 2**20, region_rule)
    return Scene(grid, start, goal_xy, box, name=where, meta=meta, road=road)


def _trajectory_users(obstacles: list[Any], times: np.ndarray, dt_src: float, t_end: float, shapely: Any,
                      cfg: CommonRoadSceneConfig, where: str
                      ) -> tuple[RoadUserTracks, list[ObstacleTrack], int]:
    """Road users with trajectory predictions: footprint tracks on the slices (predicted past their last
    state) and exact tracks (recorded states + predicted poses at the slices after them)."""
    n = len(obstacles)
    data = [_trajectory_arrays(o, dt_src, where) for o in obstacles]
    max_step = max([int(round(d[0][-1] / dt_src)) for d in data], default=0)
    n_src = max(max_step + 1, 2)
    dense = {name: np.full((n, n_src), np.nan) for name in ("x", "y", "heading", "speed")}
    for i, (t, poses, v) in enumerate(data):
        idx = np.rint(t / dt_src).astype(np.int64)
        dense["x"][i, idx], dense["y"][i, idx] = poses[:, 0], poses[:, 1]
        dense["heading"][i, idx], dense["speed"][i, idx] = poses[:, 2], v
    res = resample_tracks(dense, np.arange(n_src) * dt_src, times, angles=("heading",))
    shapes = [_shape_outline(o.obstacle_shape, shapely) for o in obstacles]
    dims = np.array([[s[1], s[2]] for s in shapes], dtype=np.float64).reshape(n, 2)
    kinds = [str(getattr(o.obstacle_type, "value", o.obstacle_type)) for o in obstacles]
    cls = np.array([obstacle_class_id(k) for k in kinds], dtype=np.int64)
    ids = np.array([int(o.obstacle_id) for o in obstacles], dtype=np.int64)
    users = RoadUserTracks(res["x"], res["y"], res["heading"], res["speed"], dims[:, 0], dims[:, 1], cls, ids)
    users = extrapolate_tracks(users, times)
    exact, n_pred = [], 0
    for i, (t, poses, v) in enumerate(data):
        later = times[times > t[-1] + 1e-9]
        if later.size:
            tau = later - t[-1]
            th = poses[-1, 2]
            extra = np.column_stack([poses[-1, 0] + v[-1] * math.cos(th) * tau,
                                     poses[-1, 1] + v[-1] * math.sin(th) * tau, np.full(tau.size, th)])
            t_all = np.concatenate([t, later])
            poses_all = np.vstack([poses, extra])
            flags = np.concatenate([np.zeros(t.size, bool), np.ones(later.size, bool)])
            std = np.concatenate([np.zeros(t.size), cfg.footprint.prediction_std_rate_along * tau])
            speeds = np.concatenate([v, np.full(tau.size, v[-1])])
            n_pred += 1
        else:
            t_all, poses_all, flags, std, speeds = t, poses, None, None, v
        exact.append(ObstacleTrack(int(ids[i]), kinds[i], dims[i, 0], dims[i, 1], t_all, poses_all,
                                   predicted=flags, position_std=std, shape=shapes[i][0], speeds=speeds))
    return users, exact, n_pred


def _red_light_tracks(scenario: Any, times: np.ndarray, start: tuple[float, ...] | None,
                      cfg: CommonRoadSceneConfig, shapely: Any, where: str, note: Any) -> list[ObstacleTrack]:
    """One obstacle per (lanelet with a traffic light, red phase inside the grid's time span): a strip at the
    stop line, present while the light is red or red-yellow (module docstring, step 5)."""
    net = scenario.lanelet_network
    lights = {int(tl.traffic_light_id): tl for tl in getattr(net, "traffic_lights", []) or []}
    with_lights = [ll for ll in net.lanelets if getattr(ll, "traffic_lights", None)]
    if not with_lights:
        return []
    if not cfg.traffic_lights:
        note("traffic lights are ignored (commonroad.traffic_lights = false): %d lanelets have one",
             len(with_lights))
        return []
    dt_src = float(scenario.dt)
    steps = np.rint(times / dt_src).astype(np.int64)
    out: list[ObstacleTrack] = []
    start_pt = None if start is None else shapely.Point(start[0], start[1])
    skipped = []
    for ll in with_lights:
        sl = getattr(ll, "stop_line", None)
        if sl is not None and getattr(sl, "start", None) is not None and getattr(sl, "end", None) is not None:
            a, b = np.asarray(sl.start, float), np.asarray(sl.end, float)
        else:
            a, b = np.asarray(ll.left_vertices[-1], float), np.asarray(ll.right_vertices[-1], float)
        seg = b - a
        width = float(np.hypot(*seg))
        if not (width > 0 and np.isfinite(seg).all()):
            continue
        centre = 0.5 * (a + b)
        heading = math.atan2(seg[1], seg[0]) - math.pi / 2  # across the line
        outline = shapely.box(-cfg.stop_line_depth / 2, -width / 2, cfg.stop_line_depth / 2, width / 2)
        strip = shapely.affinity.translate(shapely.affinity.rotate(outline, heading, origin=(0, 0),
                                                                   use_radians=True), *centre)
        red = np.zeros(steps.size, bool)
        for lid in ll.traffic_lights:
            tl = lights.get(int(lid))
            if tl is None or not getattr(tl, "active", True):
                continue
            states = np.array([str(getattr(tl.get_state_at_time_step(int(s)), "value", "")) for s in steps])
            red |= np.isin(states, ("red", "redYellow"))
        if not red.any():
            continue
        if start_pt is not None and red[0] and strip.buffer(0.5 * cfg.vehicle_length).covers(start_pt):
            skipped.append(int(ll.lanelet_id))
            continue
        # contiguous red phases -> one track each
        edges = np.flatnonzero(np.diff(np.concatenate([[0], red.astype(int), [0]])))
        for k0, k1 in zip(edges[::2], edges[1::2]):
            ts = times[k0:k1]
            if ts.size == 1:
                ts = np.array([ts[0], ts[0] + 1e-6])
            tid = -(int(ll.lanelet_id) * 1000 + len(out))  # negative: not a scenario obstacle id
            out.append(ObstacleTrack(tid, "red_light", cfg.stop_line_depth, width, np.array([ts[0], ts[-1]]),
                                     np.array([[centre[0], centre[1], heading]] * 2)))
    if skipped:
        note("red lights of lanelets %s are not applied: the start is at their stop line", skipped)
    if out:
        note("red traffic lights block the stop lines of their lanelets: %d red phases", len(out))
    return out


def _planning_problem(problem_set: Any, wanted: int, where: str) -> Any | None:
    problems = dict(getattr(problem_set, "planning_problem_dict", {}) or {})
    if not problems:
        return None
    if wanted >= 0:
        if wanted not in problems:
            raise DataError(
                f"{where}: planning problem {wanted} is not in the file (ids: {sorted(problems)}); set "
                "--set commonroad.planning_problem_id=ID"
            )
        return problems[wanted]
    return problems[min(problems)]

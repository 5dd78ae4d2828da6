"""CommonRoad scenarios (XML, read with commonroad-io, the optional ``commonroad`` extra) -> occupancy scene.

* Static occupancy: 1 outside the drivable area, the union of all lanelet polygons (left bound followed by the
  reversed right bound, grown by ``lanelet_buffer`` to close the numerical gaps between neighbouring
  lanelets), plus the shapes of static obstacles at their initial state; 0 on the lanelets. Rasterised with
  shapely's vectorised ``contains_xy`` at the cell centres.
* Dynamic obstacles: their initial state and predicted trajectory (position, orientation, velocity) resampled
  linearly from the scenario's time step to the 0.1-s slices, dimensions from their shape (rectangle: length
  and width; circle: the diameter; polygon: its bounding box), class from the obstacle type, footprints and
  clamped sum exactly as for inD (:mod:`.footprints`). Obstacles with set-based predictions contribute their
  initial state only (logged). A missing velocity counts as 0 m/s, a missing orientation as 0 rad.
* Start and goal from the planning problem (the first one, or ``planning_problem_id``): start = (position,
  orientation shifted into the car's heading box, velocity, bias 0); goal = the centroid of the union of the
  goal state positions (or of the goal lanelets), moved to a point inside the region when the centroid falls
  outside. Without a planning problem (or without a goal position) the seeded sampler of :mod:`.sampling` is
  used.
* Map area: ``area`` if given, else the bounding box of start and goal grown by ``area_margin`` and cut to the
  lanelet network's bounding box; without a planning problem the whole lanelet network. The time axis starts
  at the planning problem's initial time step (0 without one).
"""

from __future__ import annotations

import logging
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
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
    rasterise_road_users,
    resample_tracks,
)
from .grid import OccupancyGrid
from .ind import map_lattice
from .sampling import StartGoalConfig, sample_start_goal
from .scene import Scene, wrap_heading

__all__ = [
    "CommonRoadSceneConfig",
    "load_commonroad_scene",
    "read_commonroad",
    "obstacle_class_id",
    "static_map",
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


def obstacle_class_id(obstacle_type: Any) -> int:
    """Class id of a CommonRoad ``ObstacleType`` (or its string value)."""
    value = str(getattr(obstacle_type, "value", obstacle_type)).lower()
    return _TYPE_CLASS.get(value, 0)


@dataclass(frozen=True)
class CommonRoadSceneConfig:
    """How a CommonRoad scenario becomes a scene (see the module docstring). Lengths in m, times in s."""

    #: number of slices
    n_slices: int = 101
    #: time between slices [s]
    dt: float = 0.1
    #: cell edge [m]
    cell_size: float = 0.1
    #: map area (xmin, xmax, ymin, ymax) [m]; empty = around start and goal (see the module docstring)
    area: tuple[float, ...] = ()
    #: margin around the start-goal bounding box [m]
    area_margin: float = 20.0
    #: refuse grids with more cells than this (T * NX * NY; 4 bytes each)
    max_cells: int = 300_000_000
    #: the lanelet union is grown by this [m] to close gaps between neighbouring lanelets
    lanelet_buffer: float = 0.05
    #: add static obstacles (occupancy 1) to the static map
    include_static_obstacles: bool = True
    #: id of the planning problem to use; negative = the one with the smallest id
    planning_problem_id: int = -1
    #: footprint model of the dynamic obstacles
    footprint: FootprintConfig = field(default_factory=FootprintConfig)
    #: start/goal sampler rules (used without a planning problem)
    start_goal: StartGoalConfig = field(default_factory=StartGoalConfig)
    #: seed of the start/goal sampler
    seed: int = 0

    def __post_init__(self) -> None:
        if self.n_slices < 1:
            raise ValueError(f"CommonRoadSceneConfig.n_slices must be >= 1, got {self.n_slices}")
        for name in ("dt", "cell_size"):
            if not getattr(self, name) > 0:
                raise ValueError(f"CommonRoadSceneConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.area and (
            len(self.area) != 4 or self.area[0] >= self.area[1] or self.area[2] >= self.area[3]
        ):
            raise ValueError(
                f"CommonRoadSceneConfig.area must be (xmin, xmax, ymin, ymax) with min < max, got {self.area}"
            )
        if self.area_margin < 0 or self.lanelet_buffer < 0:
            raise ValueError("CommonRoadSceneConfig.area_margin and lanelet_buffer must be >= 0")
        check_seed("CommonRoadSceneConfig.seed", self.seed)


def _require() -> tuple[Any, Any]:
    try:
        import shapely
        from commonroad.common.file_reader import CommonRoadFileReader
    except ImportError as exc:
        raise OptionalDependencyError("commonroad-io", "commonroad", "reading CommonRoad scenarios") from exc
    return CommonRoadFileReader, shapely


def read_commonroad(path: str | Path) -> tuple[Any, Any]:
    """``(scenario, planning_problem_set)`` of a CommonRoad XML file; :class:`DataError` when it is not
    one."""
    reader_cls, _ = _require()
    path = Path(path)
    if not path.is_file():
        raise DataError(f"CommonRoad file not found: {path}")
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path} is not a CommonRoad scenario (not valid XML: {exc})") from exc
    if root.tag != "commonRoad":
        raise DataError(
            f"{path} is not a CommonRoad scenario (root element <{root.tag}>, expected <commonRoad>)"
        )
    try:
        return reader_cls(str(path)).open()
    except Exception as exc:  # commonroad-io raises many kinds of errors on malformed content
        raise DataError(f"{path}: cannot read the CommonRoad scenario ({type(exc).__name__}: {exc})") from exc


def _lanelet_polygons(scenario: Any, shapely: Any) -> list[Any]:
    polys = []
    for lanelet in scenario.lanelet_network.lanelets:
        left = np.asarray(lanelet.left_vertices, dtype=np.float64)
        right = np.asarray(lanelet.right_vertices, dtype=np.float64)
        ring = np.vstack([left, right[::-1]])
        poly = shapely.Polygon(ring)
        if not poly.is_valid:
            poly = poly.buffer(0)
        if not poly.is_empty:
            polys.append(poly)
    return polys


def _shape_dims(shape: Any) -> tuple[float, float]:
    """(length, width) [m] of a CommonRoad obstacle shape (rectangle, circle, polygon, truck shapes)."""
    if hasattr(shape, "radius"):
        return 2.0 * float(shape.radius), 2.0 * float(shape.radius)
    length = getattr(shape, "total_length", None) or getattr(shape, "length", None)
    width = getattr(shape, "width", None)
    if length is not None and width is not None:
        return float(length), float(width)
    vertices = getattr(shape, "vertices", None)
    if vertices is not None:
        v = np.asarray(vertices, dtype=np.float64)
        ext = v.max(axis=0) - v.min(axis=0)
        return float(max(ext)), float(min(ext))
    raise DataError(f"unsupported CommonRoad obstacle shape {type(shape).__name__}")


def _state_values(state: Any) -> tuple[float, float, float, float]:
    pos = np.asarray(getattr(state, "position", None), dtype=np.float64).reshape(-1)
    if pos.size != 2:
        return (math.nan,) * 4
    orientation = getattr(state, "orientation", None)
    velocity = getattr(state, "velocity", None)
    theta = float(orientation) if isinstance(orientation, (int, float)) else 0.0
    speed = float(velocity) if isinstance(velocity, (int, float)) else 0.0
    return float(pos[0]), float(pos[1]), theta, speed


def _dynamic_tracks(scenario: Any, times: np.ndarray) -> tuple[RoadUserTracks, list[dict[str, Any]]]:
    obstacles = list(scenario.dynamic_obstacles)
    dt_src = float(scenario.dt)
    rows: list[list[tuple[int, tuple[float, float, float, float]]]] = []
    max_step = 0
    for obs in obstacles:
        states = [obs.initial_state]
        trajectory = getattr(getattr(obs, "prediction", None), "trajectory", None)
        if trajectory is not None:
            states += list(trajectory.state_list)
        elif getattr(obs, "prediction", None) is not None:
            logger.info(
                "obstacle %s has a set-based prediction: only its initial state is used", obs.obstacle_id
            )
        entries = []
        for st in states:
            step = getattr(st, "time_step", None)
            if not isinstance(step, (int, np.integer)):
                continue
            entries.append((int(step), _state_values(st)))
            max_step = max(max_step, int(step))
        rows.append(entries)
    n = len(obstacles)
    n_src = max(max_step + 1, 2)
    dense = {name: np.full((n, n_src), np.nan) for name in ("x", "y", "heading", "speed")}
    for i, entries in enumerate(rows):
        for step, (x, y, th, v) in entries:
            dense["x"][i, step], dense["y"][i, step] = x, y
            dense["heading"][i, step], dense["speed"][i, step] = th, v
    res = resample_tracks(dense, np.arange(n_src) * dt_src, times, angles=("heading",))
    dims = np.asarray([_shape_dims(o.obstacle_shape) for o in obstacles], dtype=np.float64).reshape(n, 2)
    cls = np.asarray([obstacle_class_id(o.obstacle_type) for o in obstacles], dtype=np.int64)
    ids = np.asarray([int(o.obstacle_id) for o in obstacles], dtype=np.int64)
    tracks = RoadUserTracks(
        res["x"], res["y"], res["heading"], res["speed"], dims[:, 0], dims[:, 1], cls, ids
    )
    info = [
        {
            "id": int(ids[i]),
            "type": str(getattr(obstacles[i].obstacle_type, "value", obstacles[i].obstacle_type)),
            "class": ROAD_USER_CLASSES[int(cls[i])],
            "length": float(dims[i, 0]),
            "width": float(dims[i, 1]),
        }
        for i in range(n)
    ]
    return tracks, info


def _static_obstacle_polygons(scenario: Any, shapely: Any) -> list[Any]:
    polys = []
    for obs in scenario.static_obstacles:
        x, y, th, _ = _state_values(obs.initial_state)
        if not math.isfinite(x):
            continue
        shape = obs.obstacle_shape
        if hasattr(shape, "radius"):
            polys.append(shapely.Point(x, y).buffer(float(shape.radius)))
            continue
        vertices = getattr(shape, "vertices", None)
        if vertices is not None and not hasattr(shape, "length"):
            v = np.asarray(vertices, dtype=np.float64)
        else:
            length, width = _shape_dims(shape)
            v = np.array(
                [
                    [-length / 2, -width / 2],
                    [length / 2, -width / 2],
                    [length / 2, width / 2],
                    [-length / 2, width / 2],
                ]
            )
        c, s = math.cos(th), math.sin(th)
        pts = v @ np.array([[c, s], [-s, c]]) + np.array([x, y])
        polys.append(shapely.Polygon(pts))
    return polys


def static_map(
    scenario: Any,
    origin: tuple[float, float],
    cell_size: float,
    size: tuple[int, int],
    config: CommonRoadSceneConfig | None = None,
    *,
    drivable: Any = None,
) -> tuple[np.ndarray, int]:
    """``((NX, NY) float32 static occupancy, number of static obstacles drawn)``: 1 outside the lanelet union
    and inside static obstacles, 0 elsewhere, evaluated at the cell centres."""
    cfg = config or CommonRoadSceneConfig()
    _, shapely = _require()
    if drivable is None:
        lanelets = _lanelet_polygons(scenario, shapely)
        if not lanelets:
            raise DataError("the scenario has no lanelets (no drivable area)")
        drivable = shapely.union_all(lanelets)
        if cfg.lanelet_buffer > 0:
            drivable = drivable.buffer(cfg.lanelet_buffer)
    nx, ny = size
    xs = origin[0] + cell_size * np.arange(nx)
    ys = origin[1] + cell_size * np.arange(ny)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    shapely.prepare(drivable)
    static = (~shapely.contains_xy(drivable, gx, gy)).astype(np.float32)
    n_static = 0
    if cfg.include_static_obstacles:
        polys = _static_obstacle_polygons(scenario, shapely)
        n_static = len(polys)
        if polys:
            blocked = shapely.union_all(polys)
            shapely.prepare(blocked)
            static[shapely.contains_xy(blocked, gx, gy)] = 1.0
    return static, n_static


def _planning_problem(problem_set: Any, wanted: int) -> Any | None:
    problems = dict(getattr(problem_set, "planning_problem_dict", {}) or {})
    if not problems:
        return None
    if wanted >= 0:
        if wanted not in problems:
            raise DataError(f"planning problem {wanted} not in the scenario (ids: {sorted(problems)})")
        return problems[wanted]
    return problems[min(problems)]


def _goal_point(problem: Any, scenario: Any, shapely: Any) -> tuple[float, float] | None:
    geoms = []
    goal = problem.goal
    for st in getattr(goal, "state_list", []) or []:
        pos = getattr(st, "position", None)
        if pos is None:
            continue
        geom = getattr(pos, "shapely_object", None)
        if geom is None:
            centre = np.asarray(getattr(pos, "center", None), dtype=np.float64).reshape(-1)
            if centre.size == 2:
                geom = shapely.Point(*centre)
        if geom is not None:
            geoms.append(geom)
    if not geoms:
        lanelet_ids = getattr(goal, "lanelets_of_goal_position", None) or {}
        for ids in lanelet_ids.values():
            for lid in ids:
                lanelet = scenario.lanelet_network.find_lanelet_by_id(lid)
                if lanelet is not None:
                    left, right = np.asarray(lanelet.left_vertices), np.asarray(lanelet.right_vertices)
                    geoms.append(shapely.Polygon(np.vstack([left, right[::-1]])).buffer(0))
    if not geoms:
        return None
    region = shapely.union_all(geoms)
    point = region.centroid
    if not region.is_empty and region.area > 0 and not region.contains(point):
        point = region.point_on_surface()
    return float(point.x), float(point.y)


def load_commonroad_scene(path: str | Path, config: CommonRoadSceneConfig | None = None) -> Scene:
    """Scene of the CommonRoad scenario in ``path`` (see the module docstring for every step)."""
    cfg = config or CommonRoadSceneConfig()
    _, shapely = _require()
    path = Path(path)
    scenario, problem_set = read_commonroad(path)
    lanelets = _lanelet_polygons(scenario, shapely)
    if not lanelets:
        raise DataError(f"{path}: the scenario has no lanelets (no drivable area)")
    drivable = shapely.union_all(lanelets)
    if cfg.lanelet_buffer > 0:
        drivable = drivable.buffer(cfg.lanelet_buffer)
    lx0, ly0, lx1, ly1 = drivable.bounds
    problem = _planning_problem(problem_set, cfg.planning_problem_id)
    start = goal = None
    t0 = 0.0
    if problem is not None:
        x, y, th, v = _state_values(problem.initial_state)
        if math.isfinite(x):
            start = (x, y, wrap_heading(th), max(v, 0.0), 0.0)
        step = getattr(problem.initial_state, "time_step", 0)
        t0 = float(step) * float(scenario.dt) if isinstance(step, (int, np.integer)) else 0.0
        goal = _goal_point(problem, scenario, shapely)
    # map area
    if cfg.area:
        area = tuple(float(v) for v in cfg.area)
    elif start is not None and goal is not None:
        m = cfg.area_margin
        area = (
            min(start[0], goal[0]) - m,
            max(start[0], goal[0]) + m,
            min(start[1], goal[1]) - m,
            max(start[1], goal[1]) + m,
        )
        area = (max(area[0], lx0), min(area[1], lx1), max(area[2], ly0), min(area[3], ly1))
        # keep start and goal inside (the lanelet box may cut the margin only)
        area = (
            min(area[0], start[0], goal[0]),
            max(area[1], start[0], goal[0]),
            min(area[2], start[1], goal[1]),
            max(area[3], start[1], goal[1]),
        )
    else:
        area = (lx0, lx1, ly0, ly1)
    area, nx, ny = map_lattice(
        area, cfg.cell_size, cfg.n_slices, cfg.max_cells, f"CommonRoad scenario {path.name}"
    )
    origin = (area[0], area[2])
    static, n_static = static_map(scenario, origin, cfg.cell_size, (nx, ny), cfg, drivable=drivable)
    times = t0 + cfg.dt * np.arange(cfg.n_slices)
    tracks, info = _dynamic_tracks(scenario, times)
    probs = rasterise_road_users(
        tracks,
        origin=origin,
        cell_size=cfg.cell_size,
        shape=(cfg.n_slices, nx, ny),
        config=cfg.footprint,
        static=torch.from_numpy(static),
    )
    grid = OccupancyGrid(probs, origin, cfg.cell_size, cfg.dt, t0)
    box = (area[0] + 0.1, area[1] - 0.1, area[2] + 0.1, area[3] - 0.1)
    sampled = start is None or goal is None
    if sampled:
        logger.info("%s: no usable planning problem, sampling start and goal (seed %d)", path.name, cfg.seed)
        start, goal = sample_start_goal(grid, box, seed=cfg.seed, config=cfg.start_goal)
    bench_id = str(getattr(scenario, "scenario_id", path.stem))
    meta = {
        "source": "commonroad",
        "file": str(path),
        "scenario_id": bench_id,
        "scenario_dt": float(scenario.dt),
        "planning_problem": None if problem is None else int(getattr(problem, "planning_problem_id", -1)),
        "start_goal_sampled": sampled,
        "n_lanelets": len(lanelets),
        "n_static_obstacles": n_static,
        "dynamic_obstacles": info,
        "config": to_dict(cfg),
    }
    return Scene(grid, start, goal, box, name=f"commonroad-{bench_id}", meta=meta)

"""The road scene behind an occupancy grid: drivable area, the road users' true shapes over time, and the goal
region with its time interval, as exact geometry (shapely 2).

The occupancy grid (:mod:`.grid`) is what the planners read; a :class:`RoadScene` is what a plan is *judged*
against (CommonRoad's goal test, ground-truth collision, staying on the road) and what figures draw. It is built
by :func:`density_planner.environment.commonroad.load_commonroad_scene` and attached to
:attr:`density_planner.environment.scene.Scene.road` (``None`` for random, inD and ``.npz`` scenes without
one).

Conventions: positions in m in the scenario's frame; **times are absolute seconds of the scenario**,
``t = time_step * dt`` (so a planning problem starting at time step 20 of a 0.1-s scenario has
``t_start = 2.0``); headings and orientation intervals in rad.

All queries are vectorised over points / times with shapely 2 (``contains_xy``, ``distance``, ``polygons``);
nothing loops over samples in Python.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["GoalRegion", "ObstacleTrack", "RoadScene", "BodyOnRoad", "angle_in_interval", "vehicle_footprints",
           "lattice_in"]

_TWO_PI = 2.0 * math.pi


def _shapely() -> Any:
    import shapely  # a core dependency; imported lazily to keep `import density_planner` light

    return shapely


def lattice_in(geom: Any, origin: tuple[float, float], cell_size: float, size: tuple[int, int], *,
               strict: bool = False, block: int = 16) -> np.ndarray:
    """``(NX, NY)`` bool: whether each lattice point ``origin + cell_size * (i, j)`` lies in the closed geometry
    ``geom`` (``shapely.intersects_xy`` of every point, the same answer), or with ``strict`` in its interior
    (``shapely.contains_xy``). Only the points of the blocks of ``block x block`` points near the boundary are
    tested one by one: a block whose box (its points' bounding box, a quarter cell wider) lies inside ``geom``
    (``contains``; ``contains_properly`` with ``strict``) is inside, one whose box misses it is outside. On a road
    map's million-point lattice that is ~5 times fewer point tests."""
    shapely = _shapely()
    nx, ny = (int(v) for v in size)
    shapely.prepare(geom)
    starts_i, starts_j = np.arange(0, nx, block), np.arange(0, ny, block)
    pad = 0.25 * cell_size
    bx0 = origin[0] + cell_size * starts_i - pad
    bx1 = origin[0] + cell_size * (np.minimum(starts_i + block, nx) - 1) + pad
    by0 = origin[1] + cell_size * starts_j - pad
    by1 = origin[1] + cell_size * (np.minimum(starts_j + block, ny) - 1) + pad
    boxes = shapely.box(bx0[:, None], by0[None, :], bx1[:, None], by1[None, :])  # (blocks_x, blocks_y)
    inside = np.asarray((shapely.contains_properly if strict else shapely.contains)(geom, boxes), dtype=bool)
    mixed = np.asarray(shapely.intersects(geom, boxes), dtype=bool) & ~inside

    def per_point(per_block: np.ndarray) -> np.ndarray:
        return np.repeat(np.repeat(per_block, block, axis=0), block, axis=1)[:nx, :ny]

    out = per_point(inside)
    ii, jj = np.nonzero(per_point(mixed))
    test = shapely.contains_xy if strict else shapely.intersects_xy
    out[ii, jj] = test(geom, origin[0] + cell_size * ii, origin[1] + cell_size * jj)
    return out


def angle_in_interval(theta: np.ndarray, interval: tuple[float, float], *, tol: float = 1e-9) -> np.ndarray:
    """Boolean mask: angle ``theta`` [rad] lies in the closed interval ``[lo, hi]`` modulo 2 pi (an interval
    of width >= 2 pi contains every angle; ``lo > hi`` is read as the interval wrapping through ``lo``)."""
    lo, hi = float(interval[0]), float(interval[1])
    theta = np.asarray(theta, dtype=np.float64)
    width = hi - lo
    if width < 0:
        width = width % _TWO_PI
    if width >= _TWO_PI - tol:
        return np.isfinite(theta)
    d = np.mod(theta - lo, _TWO_PI)
    return (d <= width + tol) | (d >= _TWO_PI - tol)


def _in_interval(x: np.ndarray, interval: tuple[float, float], tol: float) -> np.ndarray:
    return (x >= interval[0] - tol) & (x <= interval[1] + tol)


@dataclass(frozen=True, eq=False)
class GoalRegion:
    """A goal in position, time, velocity and orientation (CommonRoad's ``GoalRegion`` semantics).

    A CommonRoad goal lists alternative states; a planned state reaches the goal when it satisfies *all* given
    components of *one* alternative. Each alternative is itself a :class:`GoalRegion` in :attr:`alternatives`;
    the top-level fields then hold their union / hull (for figures and distance) and :meth:`contains` tests the
    alternatives. With one alternative, :attr:`alternatives` is empty and the fields are that alternative.

    Attributes:
        shapes: union of the goal's position shapes (rectangles, circles, polygons, the goal lanelets), or
            ``None`` when the goal has no position (any position reaches it).
        time_interval: ``(t_lo, t_hi)`` absolute time [s] in which the state must be in the goal.
        velocity: ``(v_lo, v_hi)`` [m/s] or ``None`` (any speed).
        orientation: ``(lo, hi)`` [rad], tested modulo 2 pi, or ``None`` (any heading).
        lanelet_ids: ids of the goal lanelets where the goal was given by lanelets (informational).
        alternatives: the alternative goal states when there is more than one (see above).
    """

    shapes: Any
    time_interval: tuple[float, float]
    velocity: tuple[float, float] | None = None
    orientation: tuple[float, float] | None = None
    lanelet_ids: tuple[int, ...] = ()
    alternatives: tuple[GoalRegion, ...] = ()

    def __post_init__(self) -> None:
        ti = tuple(float(v) for v in self.time_interval)
        if len(ti) != 2 or not (math.isfinite(ti[0]) and math.isfinite(ti[1])) or ti[0] > ti[1]:
            raise ValueError(f"GoalRegion.time_interval must be finite (lo, hi) with lo <= hi, got {ti}")
        object.__setattr__(self, "time_interval", ti)
        for name in ("velocity", "orientation"):
            value = getattr(self, name)
            if value is not None:
                iv = tuple(float(v) for v in value)
                if len(iv) != 2 or not all(math.isfinite(v) for v in iv):
                    raise ValueError(f"GoalRegion.{name} must be a finite (lo, hi) pair, got {value!r}")
                if name == "velocity" and iv[0] > iv[1]:
                    raise ValueError(f"GoalRegion.velocity must have lo <= hi, got {iv}")
                object.__setattr__(self, name, iv)
        object.__setattr__(self, "lanelet_ids", tuple(int(i) for i in self.lanelet_ids))
        object.__setattr__(self, "alternatives", tuple(self.alternatives))
        if self.shapes is not None:
            shapely = _shapely()
            if self.shapes.is_empty:
                raise ValueError("GoalRegion.shapes is empty; use None for a goal without a position")
            shapely.prepare(self.shapes)

    # -- queries ------------------------------------------------------------------------------------------
    def contains(
        self,
        xy: np.ndarray,
        t: np.ndarray,
        v: np.ndarray | None = None,
        theta: np.ndarray | None = None,
        *,
        time_tol: float = 1e-6,
    ) -> np.ndarray:
        """``(N,)`` bool: state ``n`` (position ``xy[n]`` [m], absolute time ``t[n]`` [s], speed ``v[n]``,
        heading ``theta[n]``) is in the goal. Velocity / orientation are tested only where the goal gives them;
        passing ``None`` for a component the goal constrains raises :class:`ValueError`. Boundaries count as
        inside (shapely ``covers``)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        n = xy.shape[0]
        t = np.broadcast_to(np.asarray(t, dtype=np.float64), (n,))
        if self.alternatives:
            out = np.zeros(n, dtype=bool)
            for alt in self.alternatives:  # a handful of alternatives at most
                out |= alt.contains(xy, t, v, theta, time_tol=time_tol)
            return out
        ok = _in_interval(t, self.time_interval, time_tol) & np.isfinite(xy).all(axis=1)
        if self.shapes is not None:
            shapely = _shapely()
            ok &= shapely.intersects_xy(self.shapes, xy[:, 0], xy[:, 1])
        if self.velocity is not None:
            if v is None:
                raise ValueError("GoalRegion.contains: the goal constrains the velocity; pass v")
            ok &= _in_interval(np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)), self.velocity, 1e-9)
        if self.orientation is not None:
            if theta is None:
                raise ValueError("GoalRegion.contains: the goal constrains the orientation; pass theta")
            th = np.broadcast_to(np.asarray(theta, dtype=np.float64), (n,))
            ok &= angle_in_interval(th, self.orientation)
        return ok

    def distance(self, xy: np.ndarray) -> np.ndarray:
        """``(N,)`` Euclidean distance [m] from ``xy`` to the goal shapes (0 inside, 0 everywhere when the goal
        has no position)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.shapes is None:
            return np.zeros(xy.shape[0])
        shapely = _shapely()
        return np.asarray(shapely.distance(self.shapes, shapely.points(xy)), dtype=np.float64)

    def representative_point(self) -> tuple[float, float] | None:
        """A point inside the goal shapes (the centroid where it lies inside, else a point on the surface);
        ``None`` without a position."""
        if self.shapes is None:
            return None
        point = self.shapes.centroid
        if not self.shapes.covers(point):
            point = self.shapes.point_on_surface()
        return float(point.x), float(point.y)

    @property
    def t_end(self) -> float:
        """End of the goal's time interval [s] (absolute)."""
        return self.time_interval[1]

    # -- serialisation ------------------------------------------------------------------------------------
    def to_json_dict(self) -> dict[str, Any]:
        """Plain JSON data (shapes as WKT) that :meth:`from_json_dict` reads back."""
        return {
            "shapes": None if self.shapes is None else self.shapes.wkt,
            "time_interval": list(self.time_interval),
            "velocity": None if self.velocity is None else list(self.velocity),
            "orientation": None if self.orientation is None else list(self.orientation),
            "lanelet_ids": list(self.lanelet_ids),
            "alternatives": [a.to_json_dict() for a in self.alternatives],
        }

    @classmethod
    def from_json_dict(cls, data: dict[str, Any]) -> GoalRegion:
        shapely = _shapely()
        return cls(
            shapes=None if data.get("shapes") is None else shapely.from_wkt(data["shapes"]),
            time_interval=tuple(data["time_interval"]),
            velocity=None if data.get("velocity") is None else tuple(data["velocity"]),
            orientation=None if data.get("orientation") is None else tuple(data["orientation"]),
            lanelet_ids=tuple(data.get("lanelet_ids", ())),
            alternatives=tuple(cls.from_json_dict(a) for a in data.get("alternatives", ())),
        )


def _rectangle(length: float, width: float) -> np.ndarray:
    hl, hw = 0.5 * length, 0.5 * width
    return np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]], dtype=np.float64)


@dataclass(frozen=True, eq=False)
class ObstacleTrack:
    """One road user (or static obstacle) over time: its true shape moved along its poses.

    Attributes:
        obstacle_id: the scenario's id.
        kind: obstacle type (CommonRoad ``ObstacleType`` value, e.g. ``"car"``, ``"pedestrian"``).
        length, width: dimensions [m] of its bounding rectangle (for circles / polygons: of the shape's
            bounding box; the exact outline is :attr:`shape`).
        times: ``(K,)`` absolute times [s], increasing.
        poses: ``(K, 3)`` centre ``x, y`` [m] and heading [rad] at :attr:`times`.
        predicted: ``(K,)`` bool, ``True`` where the pose is a prediction past the last recorded state
            (constant velocity and heading) rather than recorded.
        position_std: ``(K,)`` standard deviation [m] of the position (0 where recorded; grows with the time
            since the last recorded state where predicted).
        shape: outline in the obstacle's own frame (centre at the origin, heading along +x) as a shapely
            polygon; ``None`` = the ``length x width`` rectangle.
        static: the obstacle never moves and is present at every time (``times`` / ``poses`` hold one pose).
        occupancies: ``(K,)`` array of shapely geometries in the world frame for set-based predictions
            (CommonRoad ``occupancySet``), used instead of ``shape`` moved along ``poses``; else ``None``.
        speeds: ``(K,)`` recorded speed [m/s] along the heading at :attr:`times` (what a sensor observes; the
            online prediction propagates it), or ``None`` when unknown.
    """

    obstacle_id: int
    kind: str
    length: float
    width: float
    times: np.ndarray
    poses: np.ndarray
    predicted: np.ndarray | None = None
    position_std: np.ndarray | None = None
    shape: Any = None
    static: bool = False
    occupancies: np.ndarray | None = None
    speeds: np.ndarray | None = None

    def __post_init__(self) -> None:
        times = np.asarray(self.times, dtype=np.float64).reshape(-1)
        poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 3)
        if times.size == 0 or times.shape[0] != poses.shape[0]:
            raise ValueError(
                f"ObstacleTrack {self.obstacle_id}: times ({times.shape[0]}) and poses ({poses.shape[0]}) "
                "must be non-empty and of equal length"
            )
        if times.size > 1 and not np.all(np.diff(times) > 0):
            raise ValueError(f"ObstacleTrack {self.obstacle_id}: times must be strictly increasing")
        if not (np.isfinite(times).all() and np.isfinite(poses).all()):
            raise ValueError(f"ObstacleTrack {self.obstacle_id}: times and poses must be finite")
        if not (self.length > 0 and self.width > 0):
            raise ValueError(
                f"ObstacleTrack {self.obstacle_id}: length and width must be > 0, got {self.length}, "
                f"{self.width}"
            )
        k = times.shape[0]
        pred = np.zeros(k, bool) if self.predicted is None else np.asarray(self.predicted, bool).reshape(-1)
        std = np.zeros(k) if self.position_std is None else np.asarray(self.position_std, float).reshape(-1)
        if pred.shape[0] != k or std.shape[0] != k:
            raise ValueError(f"ObstacleTrack {self.obstacle_id}: predicted / position_std must have {k} entries")
        if self.occupancies is not None:
            occ = np.asarray(self.occupancies, dtype=object).reshape(-1)
            if occ.shape[0] != k:
                raise ValueError(f"ObstacleTrack {self.obstacle_id}: occupancies must have {k} entries")
            object.__setattr__(self, "occupancies", occ)
        if self.speeds is not None:
            speeds = np.asarray(self.speeds, dtype=np.float64).reshape(-1)
            if speeds.shape[0] != k or not np.isfinite(speeds).all():
                raise ValueError(f"ObstacleTrack {self.obstacle_id}: speeds must be {k} finite values")
            speeds.setflags(write=False)
            object.__setattr__(self, "speeds", speeds)
        for name, value in (("times", times), ("poses", poses), ("predicted", pred), ("position_std", std)):
            value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "obstacle_id", int(self.obstacle_id))
        object.__setattr__(self, "length", float(self.length))
        object.__setattr__(self, "width", float(self.width))

    @property
    def outline(self) -> np.ndarray:
        """``(M, 2)`` vertices of the outline in the obstacle frame (rectangle or :attr:`shape`'s exterior)."""
        if self.shape is None:
            return _rectangle(self.length, self.width)
        return np.asarray(self.shape.exterior.coords, dtype=np.float64)[:-1]

    @property
    def t_last_recorded(self) -> float:
        """Time [s] of the last recorded (not predicted) state."""
        assert self.predicted is not None  # set by __post_init__
        rec = np.flatnonzero(~self.predicted)
        return float(self.times[rec[-1]] if rec.size else self.times[0])

    def present(self, t: np.ndarray, *, include_predicted: bool = True, tol: float = 1e-6) -> np.ndarray:
        """``(N,)`` bool: the track has a pose at time ``t`` (between its first and last time)."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if self.static:
            return np.isfinite(t)
        t_end = self.times[-1] if include_predicted else self.t_last_recorded
        return (t >= self.times[0] - tol) & (t <= t_end + tol)

    def poses_at(self, t: np.ndarray) -> np.ndarray:
        """``(N, 3)`` poses linearly interpolated at ``t`` (heading along the shorter arc); NaN where absent."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if self.static or self.times.size == 1:
            out = np.broadcast_to(self.poses[0], (t.size, 3)).copy()
        else:
            x = np.interp(t, self.times, self.poses[:, 0])
            y = np.interp(t, self.times, self.poses[:, 1])
            th = np.unwrap(self.poses[:, 2])
            out = np.stack([x, y, np.interp(t, self.times, th)], axis=1)
        out[~self.present(t)] = np.nan
        return out

    def polygons_at(self, t: np.ndarray, *, include_predicted: bool = True) -> np.ndarray:
        """``(N,)`` object array of shapely polygons: the obstacle's true shape at times ``t`` [s] (``None``
        where it is absent, i.e. before its first or after its last pose; with ``include_predicted=False``
        also after its last recorded state). Set-based tracks return the occupancy of the nearest time."""
        shapely = _shapely()
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        out = np.full(t.size, None, dtype=object)
        mask = self.present(t, include_predicted=include_predicted)
        if not mask.any():
            return out
        if self.occupancies is not None:
            idx = np.clip(np.searchsorted(self.times, t[mask] - 1e-9), 0, self.times.size - 1)
            prev = np.clip(idx - 1, 0, None)
            nearer_prev = np.abs(self.times[prev] - t[mask]) < np.abs(self.times[idx] - t[mask])
            out[mask] = self.occupancies[np.where(nearer_prev, prev, idx)]
            return out
        poses = self.poses_at(t[mask])
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        v = self.outline  # (M, 2)
        px = poses[:, None, 0] + c[:, None] * v[None, :, 0] - s[:, None] * v[None, :, 1]
        py = poses[:, None, 1] + s[:, None] * v[None, :, 0] + c[:, None] * v[None, :, 1]
        out[mask] = shapely.polygons(np.stack([px, py], axis=-1))
        return out

    def to_json_dict(self) -> dict[str, Any]:
        return {
            "obstacle_id": self.obstacle_id,
            "kind": self.kind,
            "length": self.length,
            "width": self.width,
            "times": self.times.tolist(),
            "poses": self.poses.tolist(),
            "predicted": np.asarray(self.predicted).astype(int).tolist(),  # set by __post_init__
            "position_std": np.asarray(self.position_std).tolist(),
            "shape": None if self.shape is None else self.shape.wkt,
            "static": self.static,
            "occupancies": None if self.occupancies is None else [g.wkt for g in self.occupancies],
            "speeds": None if self.speeds is None else self.speeds.tolist(),
        }

    @classmethod
    def from_json_dict(cls, data: dict[str, Any]) -> ObstacleTrack:
        shapely = _shapely()
        occ = data.get("occupancies")
        return cls(
            obstacle_id=data["obstacle_id"],
            kind=str(data["kind"]),
            length=data["length"],
            width=data["width"],
            times=np.asarray(data["times"], dtype=np.float64),
            poses=np.asarray(data["poses"], dtype=np.float64),
            predicted=np.asarray(data["predicted"], dtype=bool),
            position_std=np.asarray(data["position_std"], dtype=np.float64),
            shape=None if data.get("shape") is None else shapely.from_wkt(data["shape"]),
            static=bool(data.get("static", False)),
            occupancies=None if occ is None else np.asarray(shapely.from_wkt(occ), dtype=object),
            speeds=None if data.get("speeds") is None else np.asarray(data["speeds"], dtype=np.float64),
        )


@dataclass(frozen=True, eq=False)
class RoadScene:
    """Exact geometry of a road scenario (see the module docstring).

    Attributes:
        drivable: drivable area (shapely geometry): the union of the road lanelets, with gaps below the
            importer's ``gap_close`` closed.
        obstacles: every road user and static obstacle kept by the importer, with its true shape (ground
            truth for collision checks; the ego's own recording is not among them).
        goal: the goal region.
        dt: the scenario's time step [s].
        t_start: absolute time [s] of the planning problem's initial state.
        source: ``"<file name> (<scenario id>)"``.
        vehicle_length, vehicle_width: the ego's dimensions [m] (from the scenario where given, else
            4.5 x 1.8).
        meta: JSON-serialisable notes of the import (what was simplified).
    """

    drivable: Any
    obstacles: tuple[ObstacleTrack, ...]
    goal: GoalRegion
    dt: float
    t_start: float
    source: str
    vehicle_length: float = 4.5
    vehicle_width: float = 1.8
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "obstacles", tuple(self.obstacles))
        if not (self.dt > 0 and math.isfinite(self.t_start)):
            raise ValueError(f"RoadScene: dt must be > 0 and t_start finite, got {self.dt}, {self.t_start}")
        if not (self.vehicle_length > 0 and self.vehicle_width > 0):
            raise ValueError("RoadScene: vehicle_length and vehicle_width must be > 0")
        if self.drivable is not None:
            _shapely().prepare(self.drivable)

    def obstacle_polygons(self, t: np.ndarray, *, include_predicted: bool = True) -> np.ndarray:
        """``(n_obstacles, N)`` object array of shapely polygons (``None`` where absent) at times ``t``."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        if not self.obstacles:
            return np.empty((0, t.size), dtype=object)
        return np.stack([o.polygons_at(t, include_predicted=include_predicted) for o in self.obstacles])

    def on_road(self, polygons: np.ndarray) -> np.ndarray:
        """Bool mask: each (vehicle) polygon lies inside the drivable area (shapely ``covers``)."""
        return np.asarray(_shapely().covers(self.drivable, polygons), dtype=bool)

    def vehicle_polygons(self, poses: np.ndarray) -> np.ndarray:
        """``(N,)`` shapely rectangles of the ego vehicle (``vehicle_length x vehicle_width``) centred at the
        ``(N, 3)`` poses ``x, y, heading``."""
        track = ObstacleTrack(-1, "ego", self.vehicle_length, self.vehicle_width, np.zeros(1), np.zeros((1, 3)))
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        v = track.outline
        px = poses[:, None, 0] + c[:, None] * v[None, :, 0] - s[:, None] * v[None, :, 1]
        py = poses[:, None, 1] + s[:, None] * v[None, :, 0] + c[:, None] * v[None, :, 1]
        return np.asarray(_shapely().polygons(np.stack([px, py], axis=-1)), dtype=object)

    def to_json_dict(self) -> dict[str, Any]:
        """Plain JSON data (geometry as WKT) that :meth:`from_json_dict` reads back."""
        return {
            "drivable": None if self.drivable is None else self.drivable.wkt,
            "obstacles": [o.to_json_dict() for o in self.obstacles],
            "goal": self.goal.to_json_dict(),
            "dt": self.dt,
            "t_start": self.t_start,
            "source": self.source,
            "vehicle_length": self.vehicle_length,
            "vehicle_width": self.vehicle_width,
            "meta": self.meta,
        }

    @classmethod
    def from_json_dict(cls, data: dict[str, Any]) -> RoadScene:
        shapely = _shapely()
        return cls(
            drivable=None if data.get("drivable") is None else shapely.from_wkt(data["drivable"]),
            obstacles=tuple(ObstacleTrack.from_json_dict(o) for o in data.get("obstacles", ())),
            goal=GoalRegion.from_json_dict(data["goal"]),
            dt=float(data["dt"]),
            t_start=float(data["t_start"]),
            source=str(data["source"]),
            vehicle_length=float(data.get("vehicle_length", 4.5)),
            vehicle_width=float(data.get("vehicle_width", 1.8)),
            meta=dict(data.get("meta", {})),
        )


def vehicle_footprints(xy: np.ndarray, theta: np.ndarray, length: float, width: float) -> np.ndarray:
    """The vehicle rectangles ``length x width`` [m] centred at ``xy (T, 2)`` with headings ``theta (T,)`` [rad],
    as an array of ``T`` shapely polygons (the reference point of the car model is the rectangle's centre, as
    CommonRoad's)."""
    import shapely

    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    theta = np.asarray(theta, dtype=np.float64).reshape(-1)
    c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
    hl, hw = 0.5 * length, 0.5 * width
    lx = np.array([hl, -hl, -hl, hl, hl])[None, :]
    ly = np.array([hw, hw, -hw, -hw, hw])[None, :]
    x = xy[:, :1] + c * lx - s * ly
    y = xy[:, 1:] + s * lx + c * ly
    return shapely.polygons(np.stack([x, y], axis=-1))


@dataclass(frozen=True, eq=False)
class BodyOnRoad:
    """The event "the vehicle's rectangle lies inside the drivable area" as a predicate on states: ``accept(x (N,
    nx)) -> (N,) bool`` (positions at ``position_indices``, heading at ``heading_index``); the verdict's ``on_road``
    test at one time (its ``tolerance``, m, grows the drivable area). Used to condition a scene's initial law on the
    car being on the road (:class:`~density_planner.density.distributions.Conditioned`)."""

    drivable: Any
    length: float
    width: float
    position_indices: tuple[int, int] = (0, 1)
    heading_index: int = 2
    tolerance: float = 0.0
    _area: Any = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        shapely = _shapely()
        area = shapely.buffer(self.drivable, self.tolerance) if self.tolerance > 0 else self.drivable
        shapely.prepare(area)
        object.__setattr__(self, "_area", area)

    def __call__(self, x: Any) -> np.ndarray:
        x = np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x, dtype=np.float64)
        ix, iy = self.position_indices
        boxes = vehicle_footprints(x[:, [ix, iy]], x[:, self.heading_index], self.length, self.width)
        return np.asarray(_shapely().covered_by(boxes, self._area), dtype=bool)

"""Prediction layer between scenes and planners: the occupancy a planner reads when it plans at time ``t``.

An offline plan reads the scene's own occupancy grid, which on recorded traffic (CommonRoad) is the *recorded
future* of every road user, blurred by its footprint model: it is known in advance. A planner that replans online
at time ``t`` may only use what was observed up to ``t``. A :class:`Prediction` returns, for a time ``t`` and a
horizon ``H``, an :class:`~density_planner.environment.grid.OccupancyGrid` *window* covering ``[t, t + H]``
(slice 0 at ``t``, same origin, cell size and slice step as the scene's grid), rendered into the representation
the planners already read:

* ``oracle`` (:class:`OraclePrediction`, the paper's setting): the window of the scene's own grid (the blurred
  recorded future, known in advance). Scenes without road data (random artificial scenes, inD windows, scene
  files) always use it: they keep their own obstacle model.
* ``observed`` (:class:`ObservedPrediction`, default on road scenes): built only from the road users' recorded
  states at times ``<= t``. Each road user seen within the last ``max_observation_age`` seconds is propagated
  from its last observed state ``(x, y, theta, v)`` at ``t_obs`` (the observed speed where the recording gives
  one, else the finite difference of its last two positions) and, with ``motion_model = "ctrv"``, its turn rate
  ``omega`` from its last two headings (0 when it has been seen only once):

      constant velocity (``"cv"``):       x(tau) = x + v cos(theta) tau,  y(tau) = y + v sin(theta) tau,
      constant turn rate (``"ctrv"``):    theta(tau) = theta + omega tau,
                                          x(tau) = x + v / omega (sin theta(tau) - sin theta),
                                          y(tau) = y - v / omega (cos theta(tau) - cos theta),

  with ``tau = t_k - t_obs``; with ``motion_model = "lane"`` (the default since stop 40), a car, truck or bus
  moving forward on a lane (within ``lane_max_heading_error`` of its direction) moves along the lanes' centre lines
  instead (:meth:`~.lanes.LaneGraph.follow`): at a fork each branch is a row of its own with an equal share of the
  probability (``RoadUserTracks.weight``, at most ``lane_max_branches`` rows; the occupancy is the mixture's
  expected occupancy), its offset from the centre line and its heading relative to the lane kept (or decaying with
  ``lane_offset_time``); its speed along the path follows the intelligent driver model behind the road user ahead
  on it (``lane_speed = "idm"``, default; :mod:`.car_following`: on a free road the observed acceleration
  (``accel_window``) kept for ``accel_hold`` seconds, then constant speed; braking behind slower or stopped
  vehicles) or is kept (``"constant"``); lane changes are not predicted, and other road users
  keep constant velocity. The position error grows with ``tau``: standard deviations
  ``e_along = hypot(std_rate_along * tau, accel_std_along * tau^2 / 2)`` along and ``e_across`` alike across the
  heading (``[online.prediction]``; defaults 1.0 and 0.3 m/s, the importer's own rates for road users
  that end before the grid, and no acceleration term). The footprints are those of :mod:`.footprints` (split Gaussian
  convolved with the position error, :func:`~.footprints.rasterise_road_users` with ``predicted_for = tau``) on
  the scene's static map (outside the drivable area and static obstacles: occupied). Road users not yet seen at
  ``t`` are absent. Red-light strips keep their recorded phases (signal programmes are known infrastructure) and
  set-based obstacles their sets (they are the file's own prediction, not a recording).

The observed prediction at ``t`` is a function of the observations at times ``<= t`` only
(``tests/online/test_prediction.py`` changes the recording after ``t`` and checks the window is unchanged).
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
import torch

from ..checks import check_choice
from .car_following import IDMConfig, find_leaders, idm_distances
from .footprints import FootprintConfig, RoadUserTracks, rasterise_road_users
from .grid import OccupancyGrid
from .scene import Scene

__all__ = [
    "PredictionConfig",
    "Prediction",
    "OraclePrediction",
    "ObservedPrediction",
    "make_prediction",
    "PREDICTION_KINDS",
]

log = logging.getLogger(__name__)

#: prediction kinds, as named in ``[online.prediction] kind`` and ``--prediction``
PREDICTION_KINDS = ("observed", "oracle")
#: motion models of the observed prediction (``[online.prediction] motion_model``)
MOTION_MODELS = ("cv", "ctrv", "lane")
#: speeds along the lanes of the "lane" model (``[online.prediction] lane_speed``)
LANE_SPEEDS = ("constant", "idm")
#: road-user classes (:data:`~.footprints.ROAD_USER_CLASSES`) that the "lane" model moves along lanes: car, truck
_LANE_CLASSES = (0, 1)
#: the class of pedestrians (never a leader of the car-following model)
_PEDESTRIAN = 2
#: arc-length step [m] of the lane paths the car-following model moves vehicles along
_PATH_STEP = 0.5


@dataclass(frozen=True)
class PredictionConfig:
    """``[online.prediction]``: which occupancy an online planner reads (module docstring)."""

    #: "observed": built only from observations up to the replanning time (road scenes; scenes without road data
    #: keep their own obstacle model); "oracle": the scene's blurred recorded future, known in advance (the paper)
    kind: Literal["observed", "oracle"] = "observed"
    #: motion model of the observed prediction: "cv" constant velocity and heading, "ctrv" constant turn rate,
    #: "lane" along the centre lines of the lanes a vehicle is in (a mixture over the branches it may take, at the
    #: speed of ``lane_speed``; pedestrians, bicycles and vehicles off the lanes: constant velocity). Default "lane"
    #: with ``lane_speed = "idm"`` since stop 40 (measured on the suite: docs/environments.md; "cv" until then)
    motion_model: Literal["cv", "ctrv", "lane"] = "lane"
    #: growth of the along-heading position standard deviation [m per s of prediction time]
    std_rate_along: float = 1.0
    #: growth of the across-heading position standard deviation [m per s of prediction time]
    std_rate_across: float = 0.3
    #: unknown acceleration along / across the heading [m/s^2]: adds ``a tau^2 / 2`` to the position standard
    #: deviations (0: the linear growth alone)
    accel_std_along: float = 0.0
    accel_std_across: float = 0.0
    #: road users not observed for longer than this at the replanning time are dropped (left the sensor range) [s]
    max_observation_age: float = 0.5
    #: turn rates below this are treated as zero in "ctrv" (straight-line limit) [rad/s]
    min_turn_rate: float = 1e-3
    #: "lane": a vehicle follows a lane whose direction at its position is within this of its heading [rad]
    lane_max_heading_error: float = 0.6
    #: "lane": a vehicle outside every lane follows the nearest one within this distance [m]
    lane_search_radius: float = 1.0
    #: "lane": time constant [s] with which the offset from the lane's centre line decays (0: kept)
    lane_offset_time: float = 0.0
    #: "lane": at most this many branches (lanes to follow through forks) per vehicle; past it, the straightest
    #: successor is followed
    lane_max_branches: int = 4
    #: "lane": the speed along the lanes: "constant" (the observed speed), or "idm": the intelligent driver model
    #: behind the road user ahead on the path (:mod:`.car_following`; its parameters in ``[online.prediction.idm]``)
    lane_speed: Literal["constant", "idm"] = "idm"
    idm: IDMConfig = field(default_factory=IDMConfig)
    #: "lane" with "idm": on a free road a vehicle keeps its observed acceleration for this long [s], then its speed
    #: (a vehicle braking to a stop is predicted to stop, one pulling away to speed up); 0: the observed speed is kept
    #: (until stop 41). 1 s with a 1-s window, measured on the suite (docs/environments.md): the 5-s median position
    #: error 2.84 -> 2.64 m and 1.55 -> 1.15 m on its two halves, fitted on the first
    accel_hold: float = 1.0
    #: the observed acceleration is the change of the observed speed over this much of the recent past [s] (or over
    #: what has been observed, when less)
    accel_window: float = 1.0

    def __post_init__(self) -> None:
        check_choice("online.prediction.kind", self.kind, PREDICTION_KINDS)
        check_choice("online.prediction.motion_model", self.motion_model, MOTION_MODELS)
        check_choice("online.prediction.lane_speed", self.lane_speed, LANE_SPEEDS)
        if isinstance(self.lane_max_branches, bool) or not isinstance(self.lane_max_branches, int) \
                or self.lane_max_branches < 1:
            raise ValueError(f"online.prediction.lane_max_branches must be an integer >= 1, got "
                             f"{self.lane_max_branches!r}")
        for name in ("std_rate_along", "std_rate_across", "accel_std_along", "accel_std_across",
                     "max_observation_age", "min_turn_rate", "lane_max_heading_error", "lane_search_radius",
                     "lane_offset_time", "accel_hold", "accel_window"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"online.prediction.{name} must be a finite number >= 0, got {v!r}")


class Prediction(ABC):
    """Occupancy over a horizon as seen at a time ``t`` (module docstring)."""

    #: name recorded in results
    name: str = "prediction"
    #: the windows are views of the scene's grid and read what is derived from it (the body's dilated grid), so the
    #: scene grid's caches serve every window; otherwise each window is a grid of its own
    windows_share_scene_grid: bool = False

    def __init__(self, scene: Scene):
        self.scene = scene

    def n_slices(self, horizon: float) -> int:
        n = horizon / self.scene.grid.dt
        if abs(n - round(n)) > 1e-6 * max(1.0, n) or round(n) < 1:
            raise ValueError(f"horizon {horizon:g} s must be a whole number of grid slices of {self.scene.grid.dt:g} s")
        return int(round(n)) + 1

    @abstractmethod
    def window(self, t: float, horizon: float) -> OccupancyGrid:
        """Occupancy ``(n, NX, NY)`` over ``[t, t + horizon]`` [s, absolute], slice 0 at ``t``."""

    def scene_at(self, t: float, horizon: float, start: tuple[float, float, float, float] | None = None) -> Scene:
        """The scene a planner starting at ``t`` reads: the window grid, ``t_start = t`` and ``start`` (default:
        the scene's)."""
        grid = self.window(t, horizon)
        return replace(self.scene, grid=grid, t_start=grid.t0, start=self.scene.start if start is None else start)


class OraclePrediction(Prediction):
    """The scene's own grid over ``[t, t + H]`` (the blurred recorded future, known in advance; the paper).

    Past the end of the scene's grid the last slice is held (logged once): build the scene long enough for the
    whole run (``density-planner drive`` does)."""

    name = "oracle"
    windows_share_scene_grid = True

    def __init__(self, scene: Scene):
        super().__init__(scene)
        self._warned = False

    def window(self, t: float, horizon: float) -> OccupancyGrid:
        grid = self.scene.grid
        n = self.n_slices(horizon)
        k0 = int(grid.slice_index(t))
        if k0 + n > grid.n_slices and not self._warned:
            log.warning("%s: the oracle window [%g, %g] s leaves the scene's grid (ends %g s); its last slice is "
                        "held", self.scene.name, t, t + horizon, grid.t_end)
            self._warned = True
        return grid.window(k0, n)  # shares the scene grid's derived grids (the body's dilation) with every window


@dataclass(frozen=True)
class _Observation:
    """Last observed states of the road users seen at a time (arrays over users)."""

    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    speed: np.ndarray
    turn_rate: np.ndarray
    t_obs: np.ndarray
    accel: np.ndarray
    length: np.ndarray
    width: np.ndarray
    cls: np.ndarray
    ids: np.ndarray


def _observed_speed(times: np.ndarray, poses: np.ndarray, speeds: np.ndarray | None, k: int) -> float:
    """The speed of a road user observed at sample ``k``: the recorded one where the recording gives it, else the
    signed speed along its heading from the positions at ``k - 1`` and ``k`` (0 for a first sample)."""
    if speeds is not None:
        return float(speeds[k])
    if k < 1:
        return 0.0
    th = poses[k, 2]
    dx, dy = poses[k, 0] - poses[k - 1, 0], poses[k, 1] - poses[k - 1, 1]
    return (dx * math.cos(th) + dy * math.sin(th)) / (times[k] - times[k - 1])


class ObservedPrediction(Prediction):
    """Occupancy predicted from the road users' observations up to ``t`` only (module docstring).

    Needs a road scene (``scene.road``, CommonRoad). The static map (outside the drivable area, static obstacles)
    is rasterised once on the scene's lattice.
    """

    name = "observed"

    def __init__(self, scene: Scene, config: PredictionConfig | None = None,
                 footprint: FootprintConfig | None = None, *, lane_graph: Any = None):
        """``lane_graph``: the lanes of the ``"lane"`` motion model (:class:`~.lanes.LaneGraph`; default: the
        scene's, :func:`~.lanes.scene_lane_graph`)."""
        super().__init__(scene)
        if scene.road is None:
            raise ValueError(f"scene {scene.name!r} has no road data (recorded road users); the observed prediction "
                             "needs them (use the oracle prediction: the scene's own obstacle model)")
        self.config = config or PredictionConfig()
        fp = footprint or _scene_footprint(scene)
        self.footprint = replace(fp, prediction_std_rate_along=self.config.std_rate_along,
                                 prediction_std_rate_across=self.config.std_rate_across,
                                 prediction_accel_std_along=self.config.accel_std_along,
                                 prediction_accel_std_across=self.config.accel_std_across)
        from .commonroad import obstacle_class_id

        road = scene.road
        self._users = []  # recorded road users (trajectory tracks)
        self._fixed = []  # static obstacles, red lights, set-based obstacles: drawn as given
        for tr in road.obstacles:
            if tr.static:
                continue  # in the static map
            if tr.occupancies is not None or tr.kind == "red_light":
                self._fixed.append(tr)
                continue
            rec = ~np.asarray(tr.predicted, dtype=bool)
            speeds = None if tr.speeds is None else tr.speeds[rec]
            self._users.append((tr, tr.times[rec], tr.poses[rec], speeds, obstacle_class_id(tr.kind)))
        self._static: torch.Tensor | None = None
        self._lanes: Any = lane_graph  # the lanes of the "lane" model (read on first use), False where none

    # -- observations -------------------------------------------------------------------------------------
    def observe(self, t: float) -> _Observation:
        """The last observed state of every road user seen in ``[t - max_observation_age, t]`` (recorded states at
        times ``<= t`` only)."""
        tol = 1e-6
        rows = []
        for tr, times, poses, speeds, cls in self._users:
            k = int(np.searchsorted(times, t + tol, side="right")) - 1  # last recorded sample at or before t
            if k < 0 or times[k] < t - self.config.max_observation_age - tol:
                continue
            x, y, th = poses[k]
            v = _observed_speed(times, poses, speeds, k)
            w = acc = 0.0
            if k >= 1:
                w = (math.remainder(th - poses[k - 1, 2], 2 * math.pi)) / (times[k] - times[k - 1])
                # the speed change over the last accel_window seconds (at least one sample back; a speed from
                # positions needs the sample before it)
                j_min = 0 if speeds is not None else 1
                if k - 1 >= j_min:
                    j = int(np.searchsorted(times, times[k] - self.config.accel_window - tol, side="left"))
                    j = min(max(j, j_min), k - 1)
                    acc = (v - _observed_speed(times, poses, speeds, j)) / (times[k] - times[j])
            rows.append((x, y, th, v, w, times[k], acc, tr.length, tr.width, cls, tr.obstacle_id))
        if not rows:
            z = np.zeros(0)
            return _Observation(z, z, z, z, z, z, z, z, z, np.zeros(0, np.int64), np.zeros(0, np.int64))
        a = np.asarray(rows, dtype=np.float64)
        return _Observation(a[:, 0], a[:, 1], a[:, 2], a[:, 3], a[:, 4], a[:, 5], a[:, 6], a[:, 7], a[:, 8],
                            a[:, 9].astype(np.int64), a[:, 10].astype(np.int64))

    def tracks(self, t: float, times: np.ndarray) -> RoadUserTracks:
        """Road users predicted at ``times (T,)`` from the observations at ``t`` (``predicted_for = tau``); with
        ``motion_model = "lane"``, one row per branch of a vehicle's lanes (``weight``: its probability)."""
        obs = self.observe(t)
        tau = np.maximum(np.asarray(times, dtype=np.float64)[None, :] - obs.t_obs[:, None], 0.0)  # (N, T)
        x, y, th = self._kinematic(obs, tau)
        speed = np.broadcast_to(obs.speed[:, None], tau.shape).copy()
        if self.config.motion_model == "lane":
            return self._along_lanes(obs, tau, x, y, th, speed)
        return RoadUserTracks(x, y, th, speed, obs.length, obs.width, obs.cls, obs.ids, tau)

    def _kinematic(self, obs: _Observation, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x, y, heading) (N, T)`` of constant velocity, or constant turn rate (``motion_model = "ctrv"``)."""
        th0, v = obs.heading[:, None], obs.speed[:, None]
        w = obs.turn_rate[:, None]
        if self.config.motion_model == "ctrv":
            turning = np.abs(w) >= self.config.min_turn_rate
            w_safe = np.where(turning, w, 1.0)
            th = th0 + np.where(turning, w, 0.0) * tau
            dx = np.where(turning, v / w_safe * (np.sin(th) - np.sin(th0)), v * np.cos(th0) * tau)
            dy = np.where(turning, -v / w_safe * (np.cos(th) - np.cos(th0)), v * np.sin(th0) * tau)
        else:
            th = np.broadcast_to(th0, tau.shape).copy()
            dx, dy = v * np.cos(th0) * tau, v * np.sin(th0) * tau
        return obs.x[:, None] + dx, obs.y[:, None] + dy, th

    def _along_lanes(self, obs: _Observation, tau: np.ndarray, x: np.ndarray, y: np.ndarray, th: np.ndarray,
                     speed: np.ndarray) -> RoadUserTracks:
        """``motion_model = "lane"``: every vehicle moving forward on a lane, along the lanes' centre lines
        (:meth:`~.lanes.LaneGraph.follow`) at its speed (``lane_speed = "constant"``) or with the car-following
        model behind the road user ahead (``"idm"``, :meth:`_car_following`), its offset from the centre line and
        its heading relative to the lane's kept or decaying with ``lane_offset_time`` (at ``tau = 0``: the observed
        pose); the others keep the constant-velocity rows ``x, y, th``."""
        from .lanes import scene_lane_graph

        cfg = self.config
        if self._lanes is None:
            self._lanes = scene_lane_graph(self.scene) or False
            if self._lanes is False:
                log.warning("%s: no lane graph; the lane prediction falls back to constant velocity",
                            self.scene.name)
        idm = cfg.lane_speed == "idm"
        # (user, path or None, weight): a path holds the points at the distances travelled at constant speed, or,
        # for the car-following model, at every _PATH_STEP metres up to that distance
        rows: list[tuple[int, Any, float]] = []
        for i in range(obs.x.shape[0]):
            paths = []
            if self._lanes and obs.cls[i] in _LANE_CLASSES and obs.speed[i] >= 0:
                reach = obs.speed[i] * tau[i]
                if idm and cfg.accel_hold > 0 and obs.accel[i] > 0:  # speeding up: a longer path
                    reach = reach + obs.accel[i] * np.minimum(tau[i], cfg.accel_hold) * tau[i]
                if idm:
                    reach = _PATH_STEP * np.arange(int(math.ceil(float(reach.max()) / _PATH_STEP)) + 2)
                paths = self._lanes.follow((obs.x[i], obs.y[i]), obs.heading[i], reach,
                                           max_heading_error=cfg.lane_max_heading_error,
                                           search_radius=cfg.lane_search_radius, max_branches=cfg.lane_max_branches)
            if not paths:
                rows.append((i, None, 1.0))
            rows.extend((i, path, path.weight) for path in paths)
        user = np.array([r[0] for r in rows], dtype=np.int64)
        weight = np.array([r[2] for r in rows], dtype=np.float64)
        n_rows = len(rows)
        xs, ys, hs = (np.zeros((n_rows, tau.shape[1])) for _ in range(3))
        row_speed = speed[user].copy()
        if idm:
            dist, row_speed = self._car_following(obs, tau, rows, user, weight)
        keep = np.ones_like(tau) if cfg.lane_offset_time == 0 else np.exp(-tau / cfg.lane_offset_time)
        for r, (i, path, _) in enumerate(rows):
            if path is None:
                xs[r], ys[r], hs[r] = x[i], y[i], th[i]
                continue
            if idm:  # the points at the distances travelled, on the path's chords
                m = path.xy.shape[0]
                pos = np.clip(dist[r] / _PATH_STEP, 0.0, m - 1.0)
                k = np.minimum(np.floor(pos).astype(np.int64), m - 2)
                frac = (pos - k)[:, None]
                xy = path.xy[k] * (1.0 - frac) + path.xy[k + 1] * frac
                head = path.heading[k]
            else:
                xy, head = path.xy, path.heading
            d = path.offset * keep[i]
            # the heading relative to the lane is kept (or decays) as the offset is: at tau = 0, the observed pose
            turn = math.remainder(float(obs.heading[i]) - float(path.heading[0]), 2 * math.pi) * keep[i]
            xs[r], ys[r], hs[r] = xy[:, 0] - d * np.sin(head), xy[:, 1] + d * np.cos(head), head + turn
        return RoadUserTracks(xs, ys, hs, row_speed, obs.length[user], obs.width[user], obs.cls[user],
                              obs.ids[user], tau[user], weight=weight)

    def _car_following(self, obs: _Observation, tau: np.ndarray, rows: list[tuple[int, Any, float]],
                       user: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``lane_speed = "idm"``: ``(distance (R, T), speed (R, T))`` of every row along its path
        (:mod:`.car_following`): each path row's leader is the road user ahead on its path
        (:func:`~.car_following.find_leaders`), represented by that user's most probable row; rows without a path
        (constant velocity) keep their speed and may lead."""
        c = self.config.idm
        n_rows = len(rows)
        m = max([1] + [path.xy.shape[0] for _, path, _ in rows if path is not None])
        dense = np.full((n_rows, m, 2), np.nan)
        for r, (_, path, _) in enumerate(rows):
            if path is not None:
                dense[r, : path.xy.shape[0]] = path.xy
        leader_user, ahead = find_leaders(dense, _PATH_STEP, user, np.stack([obs.x, obs.y], axis=-1), obs.heading,
                                          obs.speed, obs.cls != _PEDESTRIAN, c)
        best_row = np.full(obs.x.shape[0], -1, dtype=np.int64)  # each user's most probable row
        for r in np.argsort(-weight, kind="stable"):
            if best_row[user[r]] < 0:
                best_row[user[r]] = r
        has = leader_user >= 0
        leader_row = np.where(has, best_row[np.maximum(leader_user, 0)], -1)
        gap = np.where(has, ahead - 0.5 * (obs.length[user] + obs.length[np.maximum(leader_user, 0)]), np.inf)
        on_path = np.array([path is not None for _, path, _ in rows], dtype=bool)
        hold = self.config.accel_hold
        # standing vehicles stay, unless observed pulling away (to at least min_speed within the hold)
        moving = on_path & (obs.speed[user] + np.maximum(obs.accel[user], 0.0) * hold >= c.min_speed)
        return idm_distances(tau[user], obs.speed[user], moving, leader_row, gap, c, accel=obs.accel[user],
                             accel_hold=hold)

    # -- rendering ----------------------------------------------------------------------------------------
    def static(self) -> torch.Tensor:
        """``(NX, NY)`` static occupancy (outside the drivable area, static obstacles), computed once."""
        if self._static is None:
            from .commonroad import CommonRoadSceneConfig, static_map

            grid, road = self.scene.grid, self.scene.road
            assert road is not None  # a road prediction needs the scene's road
            statics = [tr.polygons_at(np.array([road.t_start]))[0] for tr in road.obstacles if tr.static]
            _, nx, ny = grid.shape
            offroad = bool((self.scene.meta.get("config") or {}).get("offroad_occupied", True))  # as imported
            static, _ = static_map(None, grid.origin, grid.cell_size, (nx, ny),
                                   CommonRoadSceneConfig(offroad_occupied=offroad), drivable=road.drivable,
                                   static_polygons=[p for p in statics if p is not None])
            self._static = torch.from_numpy(static)
        return self._static

    def window(self, t: float, horizon: float) -> OccupancyGrid:
        grid = self.scene.grid
        n = self.n_slices(horizon)
        times = float(t) + grid.dt * np.arange(n)
        _, nx, ny = grid.shape
        probs = rasterise_road_users(self.tracks(t, times), origin=grid.origin, cell_size=grid.cell_size,
                                     shape=(n, nx, ny), config=self.footprint, static=self.static())
        if self._fixed:
            import shapely

            from .commonroad import _rasterise_polygons

            polys: list[list[Any]] = [[] for _ in range(n)]
            for tr in self._fixed:
                for k, poly in enumerate(tr.polygons_at(times)):
                    if poly is not None:
                        polys[k].append(poly)
            if any(polys):
                _rasterise_polygons(probs, polys, grid.origin, grid.cell_size, shapely)
        return OccupancyGrid(probs.to(grid.probs.device), grid.origin, grid.cell_size, grid.dt, float(t),
                             in_range=True)  # the rasteriser's values


def _scene_footprint(scene: Scene) -> FootprintConfig:
    """The footprint model the scene was built with (``meta["config"]["footprint"]``), else the default."""
    data = (scene.meta.get("config") or {}).get("footprint")
    if not isinstance(data, dict):
        return FootprintConfig()
    from ..config import from_dict

    try:
        return from_dict(FootprintConfig, data)
    except Exception:  # noqa: BLE001 - an older scene file: the default model
        return FootprintConfig()


def make_prediction(scene: Scene, config: PredictionConfig | None = None) -> Prediction:
    """The prediction of ``config.kind`` for ``scene``; scenes without road data keep their own obstacle model (the
    oracle, logged when ``observed`` was asked for)."""
    config = config or PredictionConfig()
    if config.kind == "oracle":
        return OraclePrediction(scene)
    if scene.road is None:
        log.info("scene %s has no recorded road users: online planning reads its own obstacle model (oracle)",
                 scene.name)
        return OraclePrediction(scene)
    return ObservedPrediction(scene, config)

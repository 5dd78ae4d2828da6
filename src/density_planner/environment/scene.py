"""A planning scene: the occupancy grid plus where the vehicle starts (a pose and a speed), where it should go and
the box it must stay in. A scene knows no vehicle model: the system maps the start pose to its own state
(:meth:`~density_planner.systems.base.System.state_from_pose`).

Every environment source (random artificial scenes, inD recordings, CommonRoad scenarios) returns a
:class:`Scene`; :func:`save_scene` / :func:`load_scene` store one as a single ``.npz`` (grid arrays + JSON
header), so a later run can plan on exactly the same world.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from density_planner.errors import DataError
from density_planner.io.atomic import atomic_save_npz

from .grid import OccupancyGrid
from .road import RoadScene

__all__ = [
    "Scene",
    "validate_scene",
    "save_scene",
    "load_scene",
    "scene_summary",
    "START_OCCUPIED_THRESHOLD",
    "SCENE_FORMAT_VERSION",
]

#: version of the scene ``.npz`` layout (2: the start is a pose and a speed, 4 numbers; version-1 files stored the
#: kinematic car's 5-entry state with a zero bias and are still read)
SCENE_FORMAT_VERSION = 2

#: :func:`validate_scene` rejects a start whose P_occ at t = 0 exceeds this. It catches starts inside static
#: obstacles or outside the drivable area (P_occ = 1) and on top of another road user; it is deliberately
#: looser than the generators' own start rule (P_occ <= 0.1 around the start), because a recorded ego vehicle
#: in dense traffic legitimately starts inside the wide Gaussian footprints of its neighbours (e.g. P_occ =
#: 0.6-0.7 in both shipped CommonRoad scenarios).
START_OCCUPIED_THRESHOLD = 0.9

@dataclass(frozen=True, eq=False)
class Scene:
    """A world to plan in.

    Attributes:
        grid: occupancy probabilities over (time, x, y).
        start: where the vehicle starts: ``(x [m], y [m], heading [rad], speed [m/s])``, the heading counter-
            clockwise from the x axis; any system maps it to its state (``system.state_from_pose(*start)``).
        goal: goal position ``(x, y)`` [m].
        planning_box: ``(xmin, xmax, ymin, ymax)`` [m] the positions must stay in (the bounds cost J_B).
        name: short identifier, e.g. ``"random-7"``, ``"ind-rec07-t120.0"``.
        meta: JSON-serialisable description of the source (obstacles, road users, file names, configuration).
        t_start: ABSOLUTE time [s] at which the plan starts, on the grid's clock (default: the grid's ``t0``); the
            planners read the occupancy at ``t_start + k * plan_dt`` (``grid.slices_for``).
        road: exact road geometry (drivable area, true obstacle shapes over time, goal region with its time
            interval) for road scenes (CommonRoad); ``None`` for random and inD scenes. ``goal`` is then the
            goal region's representative point. Saved with the scene (``road_json`` entry of the ``.npz``).
    """

    grid: OccupancyGrid
    start: tuple[float, float, float, float]
    goal: tuple[float, float]
    planning_box: tuple[float, float, float, float]
    name: str = "scene"
    meta: dict[str, Any] = field(default_factory=dict)
    t_start: float | None = None
    road: RoadScene | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.grid, OccupancyGrid):
            raise ValueError(f"Scene.grid must be an OccupancyGrid, got {type(self.grid).__name__}")
        t_start = self.grid.t0 if self.t_start is None else self.t_start
        if isinstance(t_start, bool) or not isinstance(t_start, (int, float)) or not math.isfinite(t_start):
            raise ValueError(f"Scene.t_start must be a finite number [s], got {t_start!r}")
        if not self.grid.t0 - 1e-6 * self.grid.dt <= t_start <= self.grid.t_end + 1e-6 * self.grid.dt:
            raise ValueError(
                f"Scene.t_start = {t_start:g} s lies outside the occupancy grid's time span [{self.grid.t0:g}, "
                f"{self.grid.t_end:g}] s"
            )
        object.__setattr__(self, "t_start", float(t_start))
        object.__setattr__(self, "start", _floats("Scene.start", self.start, 4))
        object.__setattr__(self, "goal", _floats("Scene.goal", self.goal, 2))
        box = _floats("Scene.planning_box", self.planning_box, 4)
        if not (box[0] < box[1] and box[2] < box[3]):
            raise ValueError(f"Scene.planning_box must be (xmin, xmax, ymin, ymax) with min < max, got {box}")
        object.__setattr__(self, "planning_box", box)
        if not isinstance(self.meta, dict):
            raise ValueError(f"Scene.meta must be a dict, got {type(self.meta).__name__}")
        if self.road is not None and not isinstance(self.road, RoadScene):
            raise ValueError(f"Scene.road must be a RoadScene or None, got {type(self.road).__name__}")

    def to_json_dict(self) -> dict[str, Any]:
        """The scene without its grid, as plain JSON data (the ``scene.json`` written by the CLI)."""
        T, NX, NY = self.grid.shape
        return {
            "name": self.name,
            "start": list(self.start),
            "goal": list(self.goal),
            "planning_box": list(self.planning_box),
            "t_start": self.t_start,
            "grid": {
                "shape": [T, NX, NY],
                "origin": list(self.grid.origin),
                "cell_size": self.grid.cell_size,
                "dt": self.grid.dt,
                "t0": self.grid.t0,
                "bounds": list(self.grid.bounds),
            },
            "meta": self.meta,
        }


def _floats(name: str, value: Any, n: int) -> tuple[float, ...]:
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().tolist()
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be {n} numbers, got {value!r}") from None
    if len(out) != n:
        raise ValueError(f"{name} must have {n} entries, got {len(out)}")
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"{name} must be finite, got {out}")
    return out


def validate_scene(scene: Scene, *, start_threshold: float = START_OCCUPIED_THRESHOLD) -> Scene:
    """Check that ``scene`` can be planned in; returns it unchanged or raises :class:`ValueError` saying why.

    Rejected: NaN/infinite or out-of-range occupancy (e.g. after an in-place edit), a start or goal outside
    the map, a planning box that does not overlap the map, a start whose P_occ at t = 0 exceeds
    ``start_threshold``
    (default :data:`START_OCCUPIED_THRESHOLD` = 0.9), a negative start speed.
    """
    grid = scene.grid
    # one pass (torch.isfinite on a road scene's 100M-cell grid takes seconds), remembered while the grid is not
    # changed in place: NaN propagates into min and max, an infinite value lies outside [0, 1]
    lo, hi = grid.value_range()
    if math.isnan(lo) or math.isnan(hi):
        raise ValueError(f"scene {scene.name!r}: occupancy grid contains NaN values")
    if lo < 0 or hi > 1:
        raise ValueError(f"scene {scene.name!r}: occupancy probabilities outside [0, 1] (found {lo:g} to {hi:g}; "
                         "an infinite value counts as outside)")
    xmin, xmax, ymin, ymax = grid.bounds

    def inside(x: float, y: float) -> bool:
        return xmin <= x <= xmax and ymin <= y <= ymax

    bounds_text = f"x in [{xmin:g}, {xmax:g}], y in [{ymin:g}, {ymax:g}] m"
    if not inside(*scene.goal):
        raise ValueError(f"scene {scene.name!r}: goal {scene.goal} lies outside the map ({bounds_text})")
    sx, sy = scene.start[0], scene.start[1]
    if not inside(sx, sy):
        raise ValueError(
            f"scene {scene.name!r}: start position ({sx:g}, {sy:g}) lies outside the map ({bounds_text})"
        )
    if scene.start[3] < 0:
        raise ValueError(f"scene {scene.name!r}: start speed must be >= 0, got {scene.start[3]}")
    bx0, bx1, by0, by1 = scene.planning_box
    if bx1 < xmin or bx0 > xmax or by1 < ymin or by0 > ymax:
        raise ValueError(f"scene {scene.name!r}: planning box {scene.planning_box} does not overlap the map")
    k0 = grid.slice_index(grid.t0 if scene.t_start is None else scene.t_start).to(grid.device)
    p0 = float(grid.lookup(torch.tensor([sx, sy], dtype=torch.float64, device=grid.device), k0))
    if p0 > start_threshold:
        raise ValueError(
            f"scene {scene.name!r}: start ({sx:g}, {sy:g}) is in an occupied cell at t={scene.t_start:g} s "
            f"(P_occ = {p0:.3f} > {start_threshold})"
        )
    return scene


def scene_summary(scene: Scene) -> str:
    """One line describing the scene (used by the CLI)."""
    T, NX, NY = scene.grid.shape
    xmin, xmax, ymin, ymax = scene.grid.bounds
    s, g = scene.start, scene.goal
    return (
        f"{scene.name}: {NX}x{NY} cells of {scene.grid.cell_size:g} m (x [{xmin:g}, {xmax:g}], y "
        f"[{ymin:g}, {ymax:g}]), "
        f"{T} slices of {scene.grid.dt:g} s; start ({s[0]:.2f}, {s[1]:.2f}, {s[2]:.2f} rad, {s[3]:.2f} m/s), "
        f"goal ({g[0]:.2f}, {g[1]:.2f})"
    )


def save_scene(scene: Scene, path: str | Path) -> Path:
    """Write ``scene`` (grid + start, goal, box, name, meta) to one compressed ``.npz`` atomically."""
    header = {
        "scene_format_version": SCENE_FORMAT_VERSION,
        "name": scene.name,
        "start": list(scene.start),
        "goal": list(scene.goal),
        "planning_box": list(scene.planning_box),
        "t_start": scene.t_start,
        "meta": scene.meta,
    }
    try:
        text = json.dumps(header, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"scene {scene.name!r}: meta is not JSON-serialisable ({exc})") from exc
    extra = {}
    if scene.road is not None:
        extra["road_json"] = np.asarray(json.dumps(scene.road.to_json_dict(), allow_nan=False))
    return atomic_save_npz(path, **scene.grid.to_arrays(), scene_json=np.asarray(text), **extra)


def load_scene(path: str | Path) -> Scene:
    """Read a scene written by :func:`save_scene`; raises :class:`DataError` naming the file when it is not
    one."""
    from density_planner.io.npz import read_npz

    path = Path(path)
    if not path.is_file():
        raise DataError(f"scene file not found: {path}")
    z = read_npz(path, what="scene")  # declared sizes checked before loading; truncated files refused
    if "scene_json" not in z:
        raise DataError(f"{path}: not a scene file (no 'scene_json' entry; was it written by save_scene?)")
    try:
        header = json.loads(str(z["scene_json"]))
    except ValueError as exc:  # JSONDecodeError
        raise DataError(f"{path}: cannot read scene header ({exc})") from exc
    if not isinstance(header, dict):
        raise DataError(f"{path}: invalid scene header (a JSON object expected, got {type(header).__name__})")
    try:
        road_data = json.loads(str(z["road_json"])) if "road_json" in z else None
    except ValueError as exc:
        raise DataError(f"{path}: cannot read the scene's road data ({exc})") from exc
    grid = OccupancyGrid.from_arrays(z, source=str(path))
    try:
        start = header["start"]
        if header.get("scene_format_version", 1) == 1 and isinstance(start, list) and len(start) == 5:
            if start[4] != 0:
                raise ValueError(f"a version-1 start must have a zero heading bias, got {start[4]!r}")
            start = start[:4]  # version 1 stored the kinematic car's state (x, y, theta, v, bias = 0)
        return Scene(
            grid=grid,
            start=start,
            goal=header["goal"],
            planning_box=header["planning_box"],
            name=str(header.get("name", path.stem)),
            meta=dict(header.get("meta", {})),
            t_start=header.get("t_start"),
            road=None if road_data is None else RoadScene.from_json_dict(road_data),
        )
    except (KeyError, ValueError, TypeError) as exc:
        raise DataError(f"{path}: invalid scene header ({exc})") from exc

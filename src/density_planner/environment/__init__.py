"""Environments: occupancy grids ``P_occ(x, y, t)`` and the scenes built from three sources.

* :func:`random_scene` — random artificial street scenes (the paper's code, ``docs/spec.md`` §8);
* :func:`load_ind_scene` — recorded traffic in the inD CSV format;
* :func:`load_commonroad_scene` — CommonRoad XML scenarios (needs the ``commonroad`` extra).

Each returns a :class:`Scene` (an :class:`OccupancyGrid` plus start, goal and planning box). No module here
imports matplotlib; pictures are drawn by :mod:`density_planner.viz.occupancy`.
"""

from .commonroad import CommonRoadSceneConfig, load_commonroad_scene
from .footprints import ROAD_USER_CLASSES, FootprintConfig, RoadUserTracks, rasterise_road_users
from .grid import OccupancyGrid
from .ind import (
    IndSceneConfig,
    load_ind_scene,
    read_recording_meta,
    read_tracks,
    read_tracks_meta,
)
from .random_scene import BoxObstacle, RandomSceneConfig, random_obstacles, random_scene, rasterise_boxes
from .sampling import StartGoalConfig, sample_start_goal
from .scene import START_OCCUPIED_THRESHOLD, Scene, load_scene, save_scene, validate_scene

__all__ = [
    "OccupancyGrid",
    "Scene",
    "validate_scene",
    "save_scene",
    "load_scene",
    "START_OCCUPIED_THRESHOLD",
    "RandomSceneConfig",
    "BoxObstacle",
    "random_scene",
    "random_obstacles",
    "rasterise_boxes",
    "FootprintConfig",
    "RoadUserTracks",
    "ROAD_USER_CLASSES",
    "rasterise_road_users",
    "StartGoalConfig",
    "sample_start_goal",
    "IndSceneConfig",
    "load_ind_scene",
    "read_tracks",
    "read_tracks_meta",
    "read_recording_meta",
    "CommonRoadSceneConfig",
    "load_commonroad_scene",
]

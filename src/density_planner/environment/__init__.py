"""Environments: occupancy grids and the scenes built from random boxes, inD recordings and CommonRoad files."""

from .grid import OccupancyGrid
from .random_scene import BoxObstacle, RandomSceneConfig, random_obstacles, random_scene
from .scene import Scene, load_scene, save_scene, validate_scene

__all__ = [
    "OccupancyGrid",
    "Scene",
    "validate_scene",
    "save_scene",
    "load_scene",
    "RandomSceneConfig",
    "BoxObstacle",
    "random_scene",
    "random_obstacles",
]

"""A hand-made road for the route, goal-region and road-barrier tests.

Two lanes (3.5 m wide) running +x, each in two 50-m lanelets, then a junction::

    y = 7   +---------- 3 ----------+---------- 4 ----------+
            |  (left lanes)          |                       |
    y = 3.5 +---------- 1 ----------+---------- 2 ----------+---------- 5 ----------+   (straight on)
            |  (right lanes)         |                       |\\
    y = 0   +------------------------+-----------------------+ \\ 6: right turn, centre (100, -10),
            x = 0                    50                     100    then 7 straight down to y = -28

1 -> 2 -> {5, 6}, 6 -> 7, 3 -> 4, with 1 <-> 3 and 2 <-> 4 adjacent in the same direction (lane changes).
"""

from __future__ import annotations

import math

import numpy as np
import shapely
import torch

from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.lanes import Lane, LaneGraph
from density_planner.environment.road import GoalRegion, RoadScene
from density_planner.environment.scene import Scene

W = 3.5


def _straight(x0: float, x1: float, y_right: float, n: int = 11) -> tuple[np.ndarray, np.ndarray]:
    xs = np.linspace(x0, x1, n)
    left = np.stack([xs, np.full(n, y_right + W)], axis=1)
    right = np.stack([xs, np.full(n, y_right)], axis=1)
    return left, right


def _right_turn(n: int = 20) -> tuple[np.ndarray, np.ndarray]:
    phi = np.linspace(math.pi / 2, 0.0, n)
    c = np.array([100.0, -10.0])
    left = c + (10.0 + W) * np.stack([np.cos(phi), np.sin(phi)], axis=1)
    right = c + 10.0 * np.stack([np.cos(phi), np.sin(phi)], axis=1)
    return left, right


def lane_graph() -> LaneGraph:
    l1, r1 = _straight(0, 50, 0.0)
    l2, r2 = _straight(50, 100, 0.0)
    l3, r3 = _straight(0, 50, W)
    l4, r4 = _straight(50, 100, W)
    l5, r5 = _straight(100, 150, 0.0)
    l6, r6 = _right_turn()
    ys = np.linspace(-10.0, -28.0, 7)
    l7 = np.stack([np.full(7, 113.5), ys], axis=1)
    r7 = np.stack([np.full(7, 110.0), ys], axis=1)
    return LaneGraph([
        Lane(1, l1, r1, successors=(2,), left_same=3),
        Lane(2, l2, r2, successors=(5, 6), left_same=4),
        Lane(3, l3, r3, successors=(4,), right_same=1),
        Lane(4, l4, r4, right_same=2),
        Lane(5, l5, r5),
        Lane(6, l6, r6, successors=(7,)),
        Lane(7, l7, r7),
    ])


def drivable(graph: LaneGraph | None = None):
    graph = graph or lane_graph()
    return shapely.union_all([lane.polygon.buffer(1e-3) for lane in graph.lanes.values()])


def road_scene(goal: GoalRegion, *, start=(10.0, 1.75, 0.0, 6.0), n_slices: int = 101,
               graph: LaneGraph | None = None) -> Scene:
    """A :class:`Scene` of the hand-made road (free occupancy; grid 0.25 m over x in [-10, 160], y in [-30, 20])
    with ``scene.road`` set."""
    graph = graph or lane_graph()
    nx, ny = 681, 201
    grid = OccupancyGrid(torch.zeros(n_slices, nx, ny), origin=(-10.0, -30.0), cell_size=0.25, dt=0.1)
    road = RoadScene(drivable(graph), (), goal, 0.1, 0.0, "hand-made")
    gp = goal.representative_point() or (start[0], start[1])
    return Scene(grid, start, gp, (-9.9, 159.9, -29.9, 19.9), name="hand-made-road", road=road)

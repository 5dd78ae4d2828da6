"""Small hand-built scenes for the risk, cost and planner tests."""

from __future__ import annotations

import torch

from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.scene import Scene


def empty_scene(start=(0.0, -20.0, 1.5707963, 3.0), goal=(0.0, 5.0), n_slices=101) -> Scene:
    """Free 24 m x 40 m map (x in [-12, 12], y in [-30, 10]) at 0.1 m."""
    probs = torch.zeros(n_slices, 241, 401)
    grid = OccupancyGrid(probs, origin=(-12.0, -30.0), cell_size=0.1, dt=0.1)
    return Scene(grid, start, goal, (-9.9, 9.9, -29.9, 9.9), name="empty")


def block_scene(p: float = 0.9, half_width: float = 1.5, y_lo: float = -8.0, y_hi: float = -4.0) -> Scene:
    """A single static block on the straight line from start to goal, with a linear ramp of 1 m around it."""
    scene = empty_scene()
    xs = scene.grid.xs.float()
    ys = scene.grid.ys.float()
    dx = (xs.abs() - half_width).clamp_min(0)[:, None]
    dy = torch.maximum(y_lo - ys, ys - y_hi).clamp_min(0)[None, :]
    dist = torch.sqrt(dx**2 + dy**2)
    occ = (p * (1 - dist / 1.0)).clamp(0, 1)
    probs = occ.expand(scene.grid.n_slices, -1, -1).contiguous()
    return Scene(scene.grid.with_probs(probs), scene.start, scene.goal, scene.planning_box, name="block")

"""Small hand-built scenes for the baseline tests (12 m x 20 m at 0.1 m: fast to copy and to search)."""

from __future__ import annotations

import math

import torch

from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.scene import Scene

#: start (0, -8) heading up at 3 m/s; goal (0, 6): 14 m ahead
START = (0.0, -8.0, math.pi / 2, 3.0)
GOAL = (0.0, 6.0)


def small_empty(start=START, goal=GOAL, n_slices: int = 101) -> Scene:
    """Free map x in [-6, 6], y in [-10, 10] m, 0.1-m cells (121 x 201), 101 slices."""
    grid = OccupancyGrid(torch.zeros(n_slices, 121, 201), origin=(-6.0, -10.0), cell_size=0.1, dt=0.1)
    return Scene(grid, start, goal, (-5.9, 5.9, -9.9, 9.9), name="small-empty")


def _with_static(scene: Scene, occ: torch.Tensor, name: str) -> Scene:
    probs = occ.clamp(0, 1).expand(scene.grid.n_slices, -1, -1).contiguous()
    return Scene(scene.grid.with_probs(probs), scene.start, scene.goal, scene.planning_box, name=name)


def wall_scene(y_lo: float = -2.0, y_hi: float = 0.0, ramp: float = 1.0) -> Scene:
    """A wall of certain occupancy (1) across the whole width, y in [y_lo, y_hi], with a linear ramp of ``ramp`` m."""
    scene = small_empty()
    ys = scene.grid.ys.float()
    dist = torch.maximum(y_lo - ys, ys - y_hi).clamp_min(0)
    occ = (1 - dist / ramp).clamp(0, 1)[None, :].expand(121, -1)
    return _with_static(scene, occ, "small-wall")


def block_scene(x_lo: float = -1.0, x_hi: float = 1.5, y_lo: float = -1.5, y_hi: float = 0.5, p: float = 1.0,
                ramp: float = 1.0) -> Scene:
    """One static block across the straight line from start to goal, plateau ``p`` with a ramp of ``ramp`` m."""
    scene = small_empty()
    xs, ys = scene.grid.xs.float(), scene.grid.ys.float()
    dx = torch.maximum(x_lo - xs, xs - x_hi).clamp_min(0)[:, None]
    dy = torch.maximum(y_lo - ys, ys - y_hi).clamp_min(0)[None, :]
    occ = p * (1 - torch.sqrt(dx**2 + dy**2) / ramp)
    return _with_static(scene, occ, "small-block")


def block_clearance(states: torch.Tensor, x_lo: float = -1.0, x_hi: float = 1.5, y_lo: float = -1.5,
                    y_hi: float = 0.5) -> float:
    """Smallest distance [m] of the trajectory's positions to the block rectangle (0 inside)."""
    xy = states[:, :2].double()
    dx = torch.maximum(x_lo - xy[:, 0], xy[:, 0] - x_hi).clamp_min(0)
    dy = torch.maximum(y_lo - xy[:, 1], xy[:, 1] - y_hi).clamp_min(0)
    return float(torch.sqrt(dx**2 + dy**2).min())


def corridor_empty() -> Scene:
    """Free 12 m x 40 m corridor (x in [-6, 6], y in [-30, 10]) with the paper's fixed start (0, -28) at 3 m/s and
    goal (0, 8), 36 m ahead: the distance the ablation baselines' acceptance rules are made for (the goal must
    still be approached in every one-second segment)."""
    grid = OccupancyGrid(torch.zeros(101, 121, 401), origin=(-6.0, -30.0), cell_size=0.1, dt=0.1)
    return Scene(grid, (0.0, -28.0, math.pi / 2, 3.0), (0.0, 8.0), (-5.9, 5.9, -29.9, 9.9), name="corridor")

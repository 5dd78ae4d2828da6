"""The per-cell memo of the desired positions in the collision cost gives exactly the direct values."""

from __future__ import annotations

import torch

from density_planner.cost.composite import CostConfig
from density_planner.cost.terms import CollisionCost, CostInputs, desired_positions
from density_planner.environment import random_scene


def test_memo_matches_direct_computation():
    scene = random_scene(0)
    cfg = CostConfig()
    memo = CollisionCost(scene.grid, beta=cfg.beta, plateau_scales=cfg.plateau_scales)
    direct = CollisionCost(scene.grid, beta=cfg.beta, plateau_scales=cfg.plateau_scales, memo=False)
    g = torch.Generator().manual_seed(0)
    k = torch.arange(101)
    for it in range(3):  # repeated calls reuse cells seen before; a third of the positions lie outside the map
        xy = torch.tensor([0.0, -10.0]) + torch.randn(60, 101, 2, generator=g) * torch.tensor([8.0, 16.0])
        xy = xy + 0.05 * it
        a = memo.desired(xy, k)
        b = desired_positions(scene.grid, xy, k, beta=cfg.beta, plateau_scales=cfg.plateau_scales)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
        x = torch.zeros(60, 101, 5)
        x[..., :2] = xy
        inputs = CostInputs(x=x, weights=torch.full((60, 101), 1 / 60), u_ref=torch.zeros(100, 2), slices=k)
        assert torch.equal(memo(inputs), direct(inputs))
    # float64 positions get their own table
    a = memo.desired(xy.double(), k)
    b = desired_positions(scene.grid, xy.double(), k, beta=cfg.beta, plateau_scales=cfg.plateau_scales)
    assert a[0].dtype == torch.float64 and torch.equal(a[0], b[0])


def test_collision_terms_of_one_grid_share_their_memo():
    """Stage 1, stage 2 and the report each build a collision term: they share one table per setting, filled by
    whichever reads a cell first, and still give the direct values."""
    scene = random_scene(1)
    cfg = CostConfig()
    first = CollisionCost(scene.grid, beta=cfg.beta, plateau_scales=cfg.plateau_scales)
    second = CollisionCost(scene.grid, beta=cfg.beta, plateau_scales=cfg.plateau_scales)
    other_beta = CollisionCost(scene.grid, beta=cfg.beta / 2, plateau_scales=cfg.plateau_scales)
    assert first._memo is second._memo and first._memo is not other_beta._memo
    g = torch.Generator().manual_seed(1)
    k = torch.arange(101)
    xy = torch.tensor([0.0, -10.0]) + torch.randn(40, 101, 2, generator=g) * torch.tensor([8.0, 16.0])
    first.desired(xy, k)  # fills the shared table
    for term, beta in ((second, cfg.beta), (other_beta, cfg.beta / 2)):
        a = term.desired(xy + 0.3, k)
        b = desired_positions(scene.grid, xy + 0.3, k, beta=beta, plateau_scales=cfg.plateau_scales)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_windows_read_their_parents_memo():
    """Replans read windows of the scene's grid: their collision terms share the scene's memo (slice k of a window
    is slice min(k0 + k, T - 1) of the scene, past its end included), give the direct values on the window, for the
    point and the body (whose dilated window is itself a window of the scene's dilated grid), and a second window
    finds the cells the first one filled."""
    from density_planner.risk import CollisionModel
    from density_planner.systems.car import KinematicCar

    scene = random_scene(2)
    cfg = CostConfig()
    g = torch.Generator().manual_seed(2)
    for body in (None, KinematicCar()):
        windows = [scene.grid.window(30, 101), scene.grid.window(35, 101)]  # the second one runs past the end
        terms = [CollisionCost(CollisionModel(w, body), beta=cfg.beta, plateau_scales=cfg.plateau_scales)
                 for w in windows]
        parent = terms[0]._memo.parent
        assert terms[1]._memo.parent is parent and parent.grid.n_slices == scene.grid.n_slices
        k = torch.arange(101)
        xy = torch.tensor([0.0, -10.0]) + torch.randn(30, 101, 2, generator=g) * torch.tensor([8.0, 16.0])
        # the second window 5 slices later sees the same positions at the same times (its slice k is the first
        # window's k + 5), and new ones for its last 5 slices
        later = torch.cat([xy[:, 5:], xy[:, -5:] + 1.0], dim=1)
        known = []
        for term, pos in zip(terms, (xy, later)):
            a = term.desired(pos, k)
            b = desired_positions(term.grid, pos, k, beta=cfg.beta, plateau_scales=cfg.plateau_scales)
            assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
            known.append(int(parent._known.sum()))
        assert known[1] - known[0] < known[0] / 10  # the second window found the first one's cells


def test_a_grid_and_its_collision_memo_are_freed_without_the_cycle_collector():
    """The memo lives in its grid's cache and refers back to the grid weakly: dropping the last reference to the
    grid frees both at once (a cycle would keep a replan's full-size grids alive until the cyclic collector ran)."""
    import gc
    import weakref

    from density_planner.environment.grid import OccupancyGrid

    grid = OccupancyGrid(torch.rand(5, 40, 30), (0.0, 0.0), 0.5, 0.1, 0.0)
    cfg = CostConfig()
    cost = CollisionCost(grid, beta=cfg.beta, plateau_scales=cfg.plateau_scales)
    cost.desired(torch.tensor([[3.0, 4.0]]), torch.tensor([1]))  # fills the table
    body = cost.grid
    refs = [weakref.ref(grid), weakref.ref(body), weakref.ref(cost._memo)]
    gc.disable()
    try:
        del grid, cost, body
        assert all(r() is None for r in refs)
    finally:
        gc.enable()

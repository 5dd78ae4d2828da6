"""Collision probability (paper §IV-B binning)."""

from __future__ import annotations

import torch
from helpers import empty_scene

from density_planner.environment.grid import OccupancyGrid
from density_planner.risk.collision import collision_probability


def _grid(values: torch.Tensor) -> OccupancyGrid:
    return OccupancyGrid(values, origin=(0.0, 0.0), cell_size=1.0, dt=0.1)


def test_single_sample_gives_cell_occupancy():
    probs = torch.zeros(3, 5, 5)
    probs[1, 2, 3] = 0.37
    rep = collision_probability(_grid(probs), torch.tensor([[[0.0, 0.0], [2.1, 2.9], [4.0, 4.0]]]))
    torch.testing.assert_close(rep.per_slice, torch.tensor([0.0, 0.37, 0.0]))
    assert float(rep.max) == float(torch.tensor(0.37)) and abs(float(rep.sum) - 0.37) < 1e-7


def test_uniform_density_over_region_gives_mean_occupancy():
    g = torch.Generator().manual_seed(0)
    probs = torch.rand(1, 10, 10, generator=g)
    # 4 samples in each cell of the block [2, 5] x [3, 7] with equal density
    ii, jj = torch.meshgrid(torch.arange(2, 6), torch.arange(3, 8), indexing="ij")
    centres = torch.stack([ii, jj], -1).reshape(-1, 2).float()
    jitter = torch.tensor([[0.2, 0.2], [-0.2, 0.2], [0.2, -0.2], [-0.2, -0.2]])
    pos = (centres[:, None, :] + jitter[None]).reshape(-1, 1, 2)
    rep = collision_probability(_grid(probs), pos)
    expected = probs[0, 2:6, 3:8].mean()
    torch.testing.assert_close(rep.per_slice[0], expected)


def test_density_averaged_within_cell_not_summed():
    probs = torch.zeros(1, 4, 4)
    probs[0, 1, 1] = 1.0
    # three samples in the occupied cell with density 1, one sample in a free cell with density 1:
    # averaging gives P_ego = 1/2 for both cells (summing would give 3/4)
    pos = torch.tensor([[[1.0, 1.0]], [[1.1, 0.9]], [[0.9, 1.2]], [[3.0, 3.0]]])
    rep = collision_probability(_grid(probs), pos, torch.zeros(4, 1))
    torch.testing.assert_close(rep.per_slice, torch.tensor([0.5]))
    # density weighting: the free sample ten times denser -> 1 / 11
    rep = collision_probability(_grid(probs), pos, torch.log(torch.tensor([[1.0], [1.0], [1.0], [10.0]])))
    torch.testing.assert_close(rep.per_slice, torch.tensor([1 / 11]))


def test_invariant_to_sample_order_and_batched():
    scene = empty_scene()
    g = torch.Generator().manual_seed(1)
    probs = torch.rand(scene.grid.shape, generator=g)
    grid = scene.grid.with_probs(probs)
    pos = torch.randn(3, 50, 101, 2, generator=g) * 3 + torch.tensor([0.0, -10.0])
    lr = torch.randn(3, 50, 101, generator=g)
    rep = collision_probability(grid, pos, lr)
    perm = torch.randperm(50, generator=g)
    rep2 = collision_probability(grid, pos[:, perm], lr[:, perm])
    torch.testing.assert_close(rep.per_slice, rep2.per_slice)
    single = collision_probability(grid, pos[1], lr[1])
    torch.testing.assert_close(rep.per_slice[1], single.per_slice)
    assert rep.per_slice.shape == (3, 101) and ((rep.per_slice >= 0) & (rep.per_slice <= 1)).all()


def test_samples_outside_the_map_collide():
    probs = torch.zeros(1, 4, 4)
    pos = torch.tensor([[[1.0, 1.0]], [[50.0, 50.0]]])
    rep = collision_probability(_grid(probs), pos)
    torch.testing.assert_close(rep.per_slice, torch.tensor([0.5]))

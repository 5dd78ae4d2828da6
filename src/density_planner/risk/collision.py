"""Collision probability of a density-weighted sample cloud on an occupancy grid (paper §IV-B).

For every time slice ``t_k``:

1. each predicted sample position ``x_i(t_k)`` is assigned to its grid cell (nearest cell centre);
2. the densities ``rho_i(t_k)`` of the samples falling into the same cell are averaged (occupancy "logits");
3. these are normalised over the plane to the ego occupancy probability ``P_ego(c, t_k)``;
4. ``P_coll(c, t_k) = P_occ(c, t_k) P_ego(c, t_k)``, summed over the cells: the collision probability at ``t_k``.

Samples outside the map count as colliding (``P_occ = 1``, matching the occupancy lookup's fill value); each of
them forms its own "cell". The binning is not differentiable; the planner minimises the surrogate ``J_C`` instead
(:mod:`density_planner.cost.terms`) and reports this quantity as the *collision probability*.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..checks import check_tensor
from ..environment.grid import OccupancyGrid

__all__ = ["CollisionReport", "collision_probability"]


@dataclass
class CollisionReport:
    """Collision probability per time slice, its maximum and its sum over the horizon.

    Attributes:
        per_slice: ``(*batch, T)`` probability of being in an occupied cell at each planning time.
        max: ``(*batch,)`` maximum over time.
        sum: ``(*batch,)`` sum over time (the discrete integral ``sum_k P_coll(t_k)``; not a probability).
    """

    per_slice: Tensor
    max: Tensor
    sum: Tensor

    def to_dict(self) -> dict:
        return {
            "per_slice": self.per_slice.detach().cpu().tolist(),
            "max": self.max.detach().cpu().tolist(),
            "sum": self.sum.detach().cpu().tolist(),
        }


@torch.no_grad()
def collision_probability(
    grid: OccupancyGrid,
    positions: Tensor,
    log_rho: Tensor | None = None,
    slices: Tensor | None = None,
) -> CollisionReport:
    """Collision probability of sample clouds (paper §IV-B).

    Args:
        grid: occupancy grid.
        positions: ``(*batch, N, T, 2)`` sample positions [m] at the planning times.
        log_rho: ``(*batch, N, T)`` log-densities of the samples (any additive constant per time cancels);
            ``None`` means equal densities.
        slices: ``(T,)`` grid slice of each planning time (default ``0..T-1``; clamped to the last slice).

    Returns:
        :class:`CollisionReport` with ``per_slice (*batch, T)``.
    """
    positions = check_tensor("positions", positions, last_dims=(None, None, 2))
    *batch, n, t, _ = positions.shape
    device = positions.device
    if log_rho is None:
        log_rho = torch.zeros(positions.shape[:-1], dtype=positions.dtype, device=device)
    else:
        log_rho = check_tensor("log_rho", log_rho, dtype=positions.dtype, device=device)
        if log_rho.shape != positions.shape[:-1]:
            raise ValueError(f"log_rho must have shape {tuple(positions.shape[:-1])}, got {tuple(log_rho.shape)}")
    if slices is None:
        slices = torch.arange(t, device=device)
    slices = torch.as_tensor(slices, device=device).long().clamp(0, grid.n_slices - 1)
    if slices.shape != (t,):
        raise ValueError(f"slices must have shape ({t},), got {tuple(slices.shape)}")
    grid = grid.to(device)

    # one group per (batch element, time): move time next to batch, samples last
    pos = positions.movedim(-2, -3).reshape(-1, n, 2)  # (G, N, 2)
    lr = log_rho.movedim(-1, -2).reshape(-1, n)  # (G, N)
    g = pos.shape[0]
    k = slices.repeat(g // t)  # slice of each group (batch-major, time-minor)
    rel = torch.exp(lr - lr.max(dim=-1, keepdim=True).values)  # densities up to a per-group factor

    idx, inside = grid.cell_index(pos)
    _, nx, ny = grid.shape
    n_cells = nx * ny
    cell = idx[..., 0] * ny + idx[..., 1]  # (G, N)
    # outside samples get a private key each so they are never averaged together
    key_in_group = torch.where(inside, cell, n_cells + torch.arange(n, device=device).expand(g, n))
    key = torch.arange(g, device=device)[:, None] * (n_cells + n) + key_in_group
    uniq, inverse = torch.unique(key.reshape(-1), return_inverse=True)
    sums = torch.zeros(uniq.numel(), dtype=rel.dtype, device=device).index_add_(0, inverse, rel.reshape(-1))
    counts = torch.zeros(uniq.numel(), dtype=rel.dtype, device=device).index_add_(
        0, inverse, torch.ones_like(rel).reshape(-1)
    )
    mean_rho = sums / counts  # averaged density per occupied cell
    group = torch.div(uniq, n_cells + n, rounding_mode="floor")
    local = uniq - group * (n_cells + n)
    is_cell = local < n_cells
    p_occ = torch.ones_like(mean_rho)
    flat = grid.probs.reshape(grid.n_slices, -1)
    p_occ[is_cell] = flat[k[group[is_cell]], local[is_cell]].to(mean_rho.dtype)
    norm = torch.zeros(g, dtype=rel.dtype, device=device).index_add_(0, group, mean_rho)
    p_coll = torch.zeros(g, dtype=rel.dtype, device=device).index_add_(0, group, mean_rho * p_occ) / norm
    per_slice = p_coll.reshape(*batch, t)
    return CollisionReport(per_slice=per_slice, max=per_slice.amax(-1), sum=per_slice.sum(-1))

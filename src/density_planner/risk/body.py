"""The vehicle's body on the occupancy grid: a cover of discs and the disc-dilated occupancy grid.

The body of a state is the system's :class:`~density_planner.systems.base.Footprint`, a ``length x width``
rectangle centred on the position and turned by the heading. Collision reads it through a **cover of discs**:
``m`` discs of radius ``r`` whose centres lie on the long axis at ``s_j = -L/2 + (j + 1/2) L/m``::

    r = sqrt((L / (2m))^2 + (W / 2)^2)

Their union contains the rectangle (each disc circumscribes one of ``m`` equal slices of it). The excess area of
the union over the rectangle is :meth:`DiscCover.area_excess`; for the car's 4.5 m x 1.8 m it is 34 % with 3 discs,
28 % with 4 (the default, ``m = ceil(L / W) + 1``), 26 % with 5; it cannot go below ~25 % for this aspect ratio
(the discs bulge out across the long sides by at most ``r - W/2``: 0.16 m with 4 discs). A system without heading
uses one disc of diameter ``max(L, W)`` (a disc footprint, exact); a point is one disc of radius 0 (the paper).

The occupancy seen by one disc is read from the **disc-dilated grid** ``D_r``, computed once per scene and radius
(:func:`body_grid`, cached on the grid):

    ``D_r[k, c] = max P_occ[k, c']`` over the cells ``c'`` whose square lies within distance ``r`` of the square
    of ``c``,

so that for *every* disc centre inside cell ``c`` (the nearest cell of the centre), ``D_r[k, c]`` is at least the
occupancy of every cell the disc touches: conservative, and never more than one cell wider than the disc (the
snapping to the nearest cell that the paper's point lookup makes too). ``r = 0`` is the point: ``D_0 = P_occ``. Cells
beyond the map's border are
not part of the map and read 0 in the dilation; a disc centre outside the map counts as occupied (``P = 1``, as a
point outside the map). The occupancy of the body is the maximum over its discs.

The dilated grid holds the occupancy rounded *up* to a multiple of 1/255 (conservative by less than 0.004; 0 and
1 stay exact), so that the max-filter runs on bytes. The dilation is separable into row runs: a sparse table of
windowed maxima along x (``log2`` levels) and one
maximum per row of the disc, i.e. ``O(T NX NY (log r + r / h))`` operations with no Python loop over cells.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ..environment.grid import OccupancyGrid
from ..systems.base import Footprint

__all__ = ["DiscCover", "dilate", "body_grid", "disc_kernel_rows"]

#: quantisation levels of the dilated grid (values rounded up to multiples of 1 / _LEVELS)
_LEVELS = 255


@dataclass(frozen=True)
class DiscCover:
    """Discs covering a footprint: centres at ``offsets`` [m] along the heading from the position, radius [m]."""

    offsets: tuple[float, ...]
    radius: float
    #: the footprint covered
    footprint: Footprint

    @staticmethod
    def of(footprint: Footprint, *, has_heading: bool, n_discs: int = 0) -> DiscCover:
        """Cover of ``footprint``; ``n_discs = 0`` chooses ``ceil(L / W) + 1`` for a rectangle."""
        if n_discs < 0:
            raise ValueError(f"n_discs must be >= 0 (0 = automatic), got {n_discs}")
        length, width = float(footprint.length), float(footprint.width)
        if footprint.is_point:
            return DiscCover((0.0,), 0.0, footprint)
        if not has_heading or length == width == 0:
            return DiscCover((0.0,), 0.5 * max(length, width) if not has_heading else 0.0, footprint)
        if width == 0:  # a segment: discs of half the slice length
            m = n_discs or 1
            return DiscCover(tuple(-length / 2 + (j + 0.5) * length / m for j in range(m)), length / (2 * m),
                             footprint)
        m = n_discs or (math.ceil(length / width) + 1)
        r = math.hypot(length / (2 * m), width / 2)
        return DiscCover(tuple(-length / 2 + (j + 0.5) * length / m for j in range(m)), r, footprint)

    @property
    def n(self) -> int:
        return len(self.offsets)

    def area_excess(self) -> float:
        """Relative excess area ``|union of discs| / |rectangle| - 1`` (computed with shapely; 0 for a point)."""
        length, width = self.footprint.length, self.footprint.width
        if self.radius == 0 or length * width == 0:
            return 0.0
        from shapely import box, points, union_all

        discs = points([(s, 0.0) for s in self.offsets]).tolist()
        union = union_all([d.buffer(self.radius, quad_segs=256) for d in discs])
        if len(self.offsets) == 1 and length == width:  # disc footprint of a system without heading
            return float(union.area / (math.pi * (length / 2) ** 2) - 1)
        return float(union.area / box(-length / 2, -width / 2, length / 2, width / 2).area - 1)

    def centres(self, positions: Tensor, headings: Tensor | None) -> Tensor:
        """Disc centres ``(..., m, 2)`` [m] of positions ``(..., 2)`` and headings ``(...)`` (differentiable)."""
        if self.n == 1 and self.offsets[0] == 0.0:
            return positions.unsqueeze(-2)
        if headings is None:
            raise ValueError("a footprint with several discs needs a heading")
        s = torch.tensor(self.offsets, dtype=positions.dtype, device=positions.device)
        direction = torch.stack([torch.cos(headings), torch.sin(headings)], dim=-1)  # (..., 2)
        return positions.unsqueeze(-2) + s[:, None] * direction.unsqueeze(-2)


def disc_kernel_rows(radius_cells: float) -> dict[int, int]:
    """Half-width ``a(dj)`` of each row ``dj`` of the dilation kernel: cell offsets ``(di, dj)`` whose square lies
    within ``radius_cells`` of the centre cell's square, i.e. ``max(|di|-1, 0)^2 + max(|dj|-1, 0)^2 <= rho^2``.
    ``rho = 0`` is the single centre cell."""
    rho = float(radius_cells)
    if rho <= 0:
        return {0: 0}
    rows: dict[int, int] = {}
    jmax = int(math.floor(rho)) + 1
    for dj in range(-jmax, jmax + 1):
        dy = max(abs(dj) - 1, 0)
        if dy > rho:
            continue
        rows[dj] = int(math.floor(math.sqrt(max(rho * rho - dy * dy, 0.0)))) + 1
    return rows


def dilate(probs: Tensor, radius_cells: float) -> Tensor:
    """Max-dilation of ``probs (T, NX, NY)`` by the disc kernel of :func:`disc_kernel_rows` (zero beyond the
    border). Returns a new tensor of the same shape and dtype."""
    rows = disc_kernel_rows(radius_cells)
    if rows == {0: 0}:
        return probs.clone()
    T, NX, NY = probs.shape
    J = max(abs(j) for j in rows)
    A = max(rows.values())
    x = probs.permute(1, 0, 2).contiguous()  # (NX, T, NY): windows along the outermost axis are contiguous blocks
    x = F.pad(x, (J, J, 0, 0, A, A))  # (NX + 2A, T, NY + 2J), zero padded
    levels = [x]
    p = 1
    while 2 * p <= 2 * A + 1:  # levels[l][i] = max(x[i : i + 2^l])
        levels.append(torch.maximum(levels[-1][:-p], levels[-1][p:]))
        p *= 2
    windows: dict[int, Tensor] = {}
    for a in sorted(set(rows.values())):
        w = 2 * a + 1
        lev = int(math.floor(math.log2(w)))
        q = 1 << lev
        s = A - a
        table = levels[lev]
        windows[a] = torch.maximum(table[s:s + NX], table[s + w - q:s + w - q + NX])  # (NX, T, NY + 2J)
    out = None
    for dj, a in rows.items():
        v = windows[a][:, :, J + dj:J + dj + NY]
        out = v.clone() if out is None else torch.maximum(out, v, out=out)
    assert out is not None
    return out.permute(1, 0, 2).contiguous()


def body_grid(grid: OccupancyGrid, radius: float) -> OccupancyGrid:
    """The disc-dilated grid ``D_radius`` of ``grid`` (module docstring), cached on ``grid``; ``grid`` itself for
    ``radius = 0``."""
    if radius < 0 or not math.isfinite(radius):
        raise ValueError(f"radius must be a finite number >= 0 [m], got {radius}")
    rho = radius / grid.cell_size
    if disc_kernel_rows(rho) == {0: 0}:
        return grid
    key = ("body_grid", round(rho, 9))
    cached = grid._cache.get(key)
    if cached is not None and cached.device == grid.device:
        return cached
    with torch.no_grad():
        # quantised up to multiples of 1/255 (conservative by < 0.004): the max-filter runs on uint8, ~10x faster
        # than on float32 (~0.05 s for a 101 x 241 x 401 grid on one thread)
        # (in place on one temporary: the grids are large, 50M cells for a 13-s urban scene)
        q = torch.mul(grid.probs, _LEVELS).sub_(1e-4).ceil_().clamp_(0, _LEVELS).to(torch.uint8)
        out = grid.with_probs(dilate(q, rho).to(grid.probs.dtype).div_(_LEVELS))
    grid._cache[key] = out
    return out

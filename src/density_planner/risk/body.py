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
Road users cover about 1 % of a road scene's cells (the off-road cells are the road barrier's, not collision's), so
:func:`body_grid` dilates tiles (:func:`dilate_sparse`): the grid is cut into ``32 x 32``-cell tiles per slice, and
only the tiles with an occupied cell within the disc's reach are dilated (each with its halo, batched over the
tiles), the others stay 0. The result equals :func:`dilate` exactly; on road scenes it is 3-11x faster
(``benchmarks/bench_body_grid.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from ..environment.grid import OccupancyGrid, read_cells
from ..memory import lazy_zeros
from ..systems.base import Footprint

__all__ = ["DiscCover", "dilate", "dilate_sparse", "body_grid", "masked_grid", "disc_kernel_rows", "quantise_up",
           "dequantise", "LazyDilatedGrid"]

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
        # per coordinate (..., m), stacked last: broadcasting over a trailing axis of 2 is 2.5x slower
        cx = positions[..., 0:1] + s * torch.cos(headings).unsqueeze(-1)
        cy = positions[..., 1:2] + s * torch.sin(headings).unsqueeze(-1)
        return torch.stack([cx, cy], dim=-1)


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


def dilate_sparse(probs: Tensor, radius_cells: float, *, tile: int = 32, levels: int | None = None,
                  max_chunk: int = 1 << 22, ignore: Tensor | None = None) -> Tensor:
    """:func:`dilate` of ``probs (T, NX, NY)`` (values >= 0) computed on the tiles that can be non-zero only (module
    docstring). ``ignore (NX, NY)`` (bool): cells read as 0 in every slice (a road scene's off-road cells, which the
    road barrier prices, not collision), without forming the masked grid: equal to ``dilate_sparse(probs *
    ~ignore, ...)``.

    The grid is cut into ``tile x tile``-cell tiles per slice; a tile of the output can be non-zero only if an
    occupied cell lies within the kernel's reach ``h`` (cells) of it, so only those tiles are dilated: each with a
    halo of ``h`` cells read from its neighbours (zero beyond the border), batched over the tiles in chunks of at
    most ``max_chunk`` cells. ``levels``: the values are rounded *up* to multiples of ``1 / levels`` and dilated
    as bytes (``levels <= 255``; floating ``probs`` in [0, 1]), the result returned in ``probs``' dtype. Equal to
    ``dilate`` (of the rounded values) cell for cell.
    """
    if tile < 1:
        raise ValueError(f"tile must be >= 1 cell, got {tile}")
    if levels is not None and not 1 <= levels <= 255:
        raise ValueError(f"levels must lie in [1, 255] (values dilated as bytes), got {levels}")
    if probs.ndim != 3:
        raise ValueError(f"probs must have shape (T, NX, NY), got {tuple(probs.shape)}")
    h, tile = _reach_and_tile(radius_cells, tile)
    probs = probs.contiguous()
    keep = None
    if ignore is not None:
        if ignore.shape != probs.shape[1:] or ignore.dtype != torch.bool:
            raise ValueError(f"ignore must be a bool tensor of shape {tuple(probs.shape[1:])}, got "
                             f"{ignore.dtype} {tuple(ignore.shape)}")
        keep = (~ignore).to(device=probs.device, dtype=probs.dtype).contiguous()
    out = torch.zeros_like(probs)
    idx = _active_tiles(probs, tile, h, keep)  # (N, 3): slice, tile row, tile column
    _dilate_tiles(probs, keep, idx, tile, h, radius_cells, levels, max_chunk, out)
    return out


def _dilate_tiles(probs: Tensor, keep: Tensor | None, idx: Tensor, tile: int, h: int, radius_cells: float,
                  levels: int | None, max_chunk: int, out: Tensor) -> None:
    """Dilate the tiles ``idx (N, 3)`` (slice, tile row, tile column) of ``probs`` (times ``keep``) into ``out``:
    each with its halo of ``h`` cells, batched in chunks of at most ``max_chunk`` cells. ``out`` holds
    ``probs``' dtype, or the level counts (``uint8``) when ``levels`` is given and ``out`` is ``uint8``."""
    size = tile + 2 * h
    per_chunk = max(1, max_chunk // (size * size))
    for c0 in range(0, idx.shape[0], per_chunk):
        t, bx, by = idx[c0:c0 + per_chunk].unbind(-1)
        patch = _read_patches(probs, t, bx * tile - h, by * tile - h, size)
        if keep is not None:
            patch *= _read_patches(keep.unsqueeze(0), torch.zeros_like(t), bx * tile - h, by * tile - h, size)
        if levels is not None:
            patch = quantise_up(patch, levels, out=patch)
        d = dilate(patch, radius_cells)[:, h:h + tile, h:h + tile]
        if levels is not None and out.dtype != torch.uint8:
            d = dequantise(d, levels, probs.dtype)
        _write_tiles(out, t, bx, by, d)


def quantise_up(probs: Tensor, levels: int, *, out: Tensor | None = None) -> Tensor:
    """``probs`` in [0, 1] rounded *up* to multiples of ``1 / levels`` (a tolerance of 1e-4 level keeps exact
    multiples), as ``uint8`` level counts; ``out``: a float tensor of ``probs``' shape to compute in (may be
    ``probs`` itself), else a new one."""
    work = torch.mul(probs, levels) if out is None else torch.mul(probs, levels, out=out)
    return work.sub_(1e-4).ceil_().clamp_(0, levels).to(torch.uint8)


def dequantise(counts: Tensor, levels: int, dtype: torch.dtype) -> Tensor:
    """Level counts of :func:`quantise_up` back to probabilities in ``dtype``."""
    return counts.to(dtype).div_(levels)


def _reach_and_tile(radius_cells: float, tile: int) -> tuple[int, int]:
    """The kernel's reach ``h`` [cells] (its largest row or column offset) and the tile size :func:`dilate_sparse`
    uses: ``tile``, widened to ``h`` (a halo never spans more than the neighbouring tiles)."""
    rows = disc_kernel_rows(radius_cells)
    h = max(max(abs(j) for j in rows), max(rows.values()))
    return h, max(tile, h, 1)


def _tile_maxima(probs: Tensor, tile: int) -> Tensor:
    """``(T, nbx, nby)`` maxima of ``probs (T, NX, NY)`` over its ``tile x tile`` tiles (the last row and column of
    tiles cut at the border); amax reductions along the contiguous axis: no full-size temporary."""
    T, NX, NY = probs.shape
    nbx, nby = -(-NX // tile), -(-NY // tile)
    # per tile column: maxima over tile-wide runs of each row (the last, partial run separately)
    full = NY // tile
    cols = [probs.unfold(2, tile, tile).amax(-1)] if full else []
    if NY % tile:
        cols.append(probs[:, :, full * tile:].amax(-1, keepdim=True))
    runs = torch.cat(cols, dim=-1) if len(cols) > 1 else cols[0]  # (T, NX, nby)
    runs = F.pad(runs, (0, 0, 0, nbx * tile - NX))
    return runs.view(T, nbx, tile, nby).amax(2)


def _active_tiles(probs: Tensor, tile: int, h: int, keep: Tensor | None = None) -> Tensor:
    """``(N, 3)`` indices (slice, tile row, tile column) of the output tiles within ``h`` cells of a non-zero cell
    of ``probs >= 0`` (times ``keep (NX, NY)`` where given). With ``keep``, tiles wholly kept read ``probs`` alone,
    tiles wholly dropped are empty, and only the tiles ``keep`` cuts are re-read with it (a road's edge: few)."""
    T = probs.shape[0]
    occupied = _tile_maxima(probs, tile) > 0  # (T, nbx, nby)
    if keep is not None:
        kmax = _tile_maxima(keep.unsqueeze(0), tile)[0] > 0
        kmin = -_tile_maxima(-keep.unsqueeze(0), tile)[0] > 0  # (tiles cut by the map's border count as cut)
        occupied &= kmax
        cut = (kmax & ~kmin).nonzero()  # (C, 2)
        per_chunk = max(1, (1 << 22) // (tile * tile))
        pairs = torch.cartesian_prod(torch.arange(T, device=probs.device), torch.arange(cut.shape[0],
                                                                                        device=probs.device))
        for c0 in range(0, pairs.shape[0], per_chunk):
            t, c = pairs[c0:c0 + per_chunk].unbind(-1)
            bx, by = cut[c].unbind(-1)
            patch = _read_patches(probs, t, bx * tile, by * tile, tile)
            patch *= _read_patches(keep.unsqueeze(0), torch.zeros_like(t), bx * tile, by * tile, tile)
            occupied[t, bx, by] = patch.flatten(1).amax(1) > 0
    k = -(-h // tile)  # tiles within reach
    active = F.max_pool2d(occupied.to(torch.float32).unsqueeze(1), 2 * k + 1, 1, k).squeeze(1) > 0
    return active.nonzero()


def _read_patches(probs: Tensor, t: Tensor, x0: Tensor, y0: Tensor, size: int) -> Tensor:
    """``(n, size, size)`` blocks ``probs[t, x0:x0 + size, y0:y0 + size]`` (zero beyond the border): blocks inside
    the grid through a strided view, the others through clamped linear indices."""
    T, NX, NY = probs.shape
    out = torch.empty(t.shape[0], size, size, dtype=probs.dtype, device=probs.device)
    inside = (x0 >= 0) & (x0 + size <= NX) & (y0 >= 0) & (y0 + size <= NY)
    if bool(inside.any()):
        # windows at every cell: (T, NX - size + 1, NY - size + 1, size, size), a view of probs
        view = probs.as_strided((T, NX - size + 1, NY - size + 1, size, size), (NX * NY, NY, 1, NY, 1))
        out[inside] = view[t[inside], x0[inside], y0[inside]]
    edge = ~inside
    if bool(edge.any()):
        r = torch.arange(size, device=probs.device)
        ix, iy = x0[edge, None] + r, y0[edge, None] + r
        valid = ((ix >= 0) & (ix < NX))[:, :, None] & ((iy >= 0) & (iy < NY))[:, None, :]
        lin = (t[edge, None, None] * NX + ix.clamp(0, NX - 1)[:, :, None]) * NY + iy.clamp(0, NY - 1)[:, None, :]
        out[edge] = probs.reshape(-1)[lin] * valid
    return out


def _write_tiles(out: Tensor, t: Tensor, bx: Tensor, by: Tensor, values: Tensor) -> None:
    """``out[t, tile bx, tile by] = values (n, tile, tile)``, cut at the grid's border."""
    T, NX, NY = out.shape
    tile = values.shape[-1]
    x0, y0 = bx * tile, by * tile
    whole = (x0 + tile <= NX) & (y0 + tile <= NY)
    if bool(whole.any()):
        view = out.as_strided((T, NX - tile + 1, NY - tile + 1, tile, tile), (NX * NY, NY, 1, NY, 1))
        view[t[whole], x0[whole], y0[whole]] = values[whole]
    cut = ~whole
    if bool(cut.any()):
        r = torch.arange(tile, device=out.device)
        ox, oy = x0[cut, None] + r, y0[cut, None] + r
        keep = (ox < NX)[:, :, None] & (oy < NY)[:, None, :]
        lin = (t[cut, None, None] * NX + ox[:, :, None]) * NY + oy[:, None, :]
        out.view(-1)[lin[keep]] = values[cut][keep]


def masked_grid(grid: OccupancyGrid, ignore: Tensor) -> OccupancyGrid:
    """``grid`` with the cells of ``ignore (NX, NY)`` (bool) at 0 in every slice, cached on ``grid`` (one per mask)."""
    key = ("masked", id(ignore))
    cached = grid._cache.get(key)
    if cached is None or cached.device != grid.device:
        cached = _rows_of_parent(grid, lambda base: masked_grid(base, ignore))
        if cached is None:
            keep = (~ignore).to(device=grid.device, dtype=grid.probs.dtype)
            cached = grid.with_probs(grid.probs * keep)
        grid._cache[key] = cached
    return cached


def _rows_of_parent(grid: OccupancyGrid, derive) -> OccupancyGrid | None:
    """When ``grid`` is :meth:`~density_planner.environment.grid.OccupancyGrid.window` of a grid on the same device,
    the window's rows of ``derive(parent)`` (a grid derived slice by slice, cached on the parent: derived once for
    every window); else ``None``."""
    rec = grid._cache.get(grid.WINDOW_OF)
    if rec is None or rec[0].device != grid.device:
        return None
    base, k0, n = rec
    derived = derive(base)
    if isinstance(derived, LazyDilatedGrid):  # read through the parent: only the cells read are dilated
        out: OccupancyGrid = _LazyWindowRows(derived, k0, n, grid.t0)
    else:
        out = grid.with_probs(grid.window_rows(derived.probs, k0, n))
    out._cache[grid.WINDOW_OF] = (derived, k0, n)  # itself a window of the derived parent (memos read through it)
    return out


def body_grid(grid: OccupancyGrid, radius: float, *, ignore: Tensor | None = None) -> OccupancyGrid:
    """The disc-dilated grid ``D_radius`` of ``grid`` (module docstring), cached on ``grid``; ``grid`` itself for
    ``radius = 0``. ``ignore (NX, NY)`` (bool): cells that count as free (a road scene's off-road cells; the masked
    grid is not formed for ``radius > 0``, :func:`dilate_sparse`; :func:`masked_grid` for ``radius = 0``). Cached per
    ``ignore`` tensor (by identity: pass the same mask object, as :func:`~density_planner.environment.commonroad.
    offroad_mask` does)."""
    if radius < 0 or not math.isfinite(radius):
        raise ValueError(f"radius must be a finite number >= 0 [m], got {radius}")
    rho = radius / grid.cell_size
    if disc_kernel_rows(rho) == {0: 0}:
        return grid if ignore is None else masked_grid(grid, ignore)
    key = ("body_grid", round(rho, 9), None if ignore is None else id(ignore))
    cached = grid._cache.get(key)
    if cached is not None and cached.device == grid.device:
        return cached
    out = _rows_of_parent(grid, lambda base: body_grid(base, radius, ignore=ignore))
    if out is not None:
        grid._cache[key] = out
        return out
    # quantised up to multiples of 1/255 (conservative by < 0.004): the max-filter runs on uint8, ~10x faster than
    # on float32; only the tiles within reach of an occupied cell are dilated (the grids are large, 50M cells for a
    # 13-s urban scene, and ~1 % occupied), and each only when a cell of it is first read (LazyDilatedGrid)
    mask = None if ignore is None else ignore.to(grid.device)
    out = LazyDilatedGrid(grid, rho, ignore=mask)
    grid._cache[key] = out
    return out


class _ReadThroughGrid(OccupancyGrid):
    """A grid whose values are derived (``probs`` a read-only property of the subclass) and read cell by cell:
    :meth:`to` returns it unchanged where nothing changes, so that reading does not derive the whole grid."""

    _value_dtype: torch.dtype

    def _set(self, **state) -> None:
        """Set attributes (a frozen dataclass underneath; its ``__init__`` and validation pass are not run)."""
        for name, value in state.items():
            object.__setattr__(self, name, value)

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> OccupancyGrid:
        """``self`` where nothing changes (nothing is derived); else a full copy (:meth:`OccupancyGrid.to`)."""
        if (device is None or torch.device(device) == self.device) and (dtype is None or dtype == self._value_dtype):
            return self
        return super().to(device, dtype)


class LazyDilatedGrid(_ReadThroughGrid):
    """The grid :func:`dilate_sparse` makes of ``source`` (levels of 1/255), dilated tile by tile as it is read.

    A planner reads the body's grid only near its samples and candidates: a corridor of the map (1-3 % of its
    tiles on suite scenes). Here a tile is dilated the first time :meth:`cell_values` (the read of
    :meth:`~OccupancyGrid.lookup`, the collision cost and the collision probability) asks for one of its cells.
    Any other read of :attr:`probs` (the MPC's interpolants, windows, figures, saving) first dilates every
    remaining tile within reach of an occupied cell (the others are 0) and sees the whole grid. The values equal
    :func:`dilate_sparse`'s cell for cell (the same tiles, halos and quantisation); they are kept as level counts
    (bytes), a quarter of the memory of the float grid. Measured on recorded traffic: docs/planner.md
    ("Speed")."""

    _source: Tensor
    _keep: Tensor | None
    _rho: float
    _tile: int
    _h: int
    _max_chunk: int
    _nbx: int
    _nby: int
    _todo: Tensor
    _counts: Tensor
    _dense: Tensor | None

    def __init__(self, source: OccupancyGrid, radius_cells: float, *, ignore: Tensor | None = None,
                 tile: int = 32, max_chunk: int = 1 << 22):
        probs = source.probs.contiguous()
        if probs.dtype not in (torch.float32, torch.float64):
            raise ValueError(f"a dilated grid needs float32 or float64 probabilities, got {probs.dtype}")
        h, tile = _reach_and_tile(radius_cells, tile)
        keep = None if ignore is None else (~ignore).to(device=probs.device, dtype=probs.dtype).contiguous()
        T, nx, ny = probs.shape
        nbx, nby = -(-nx // tile), -(-ny // tile)
        # tiles not dilated yet (flat over slice, tile row, tile column). No pass over the whole grid to find the
        # tiles within reach of an occupied cell (it took longer than dilating what a plan reads): a tile read is
        # dilated, occupied or not (those far from any road user come out 0)
        todo = torch.ones(T * nbx * nby, dtype=torch.bool, device=probs.device)
        # the geometry of ``source`` (the values are source's, dilated: no validation pass)
        self._set(origin=source.origin, cell_size=source.cell_size, dt=source.dt, t0=source.t0, _cache={},
                  _source=probs, _value_dtype=probs.dtype, _keep=keep, _rho=float(radius_cells), _tile=tile, _h=h,
                  _max_chunk=max_chunk, _nbx=nbx, _nby=nby, _todo=todo,
                  _counts=lazy_zeros((T, nx, ny), torch.uint8, probs.device), _dense=None)

    # the tensor properties read the counts' shape and device without dilating anything
    @property
    def probs(self) -> Tensor:
        """The whole dilated grid (every remaining tile is dilated first), in the source's dtype."""
        if self._dense is None:  # the remaining tiles within reach of an occupied cell (the others are 0)
            with torch.no_grad():
                active = _active_tiles(self._source, self._tile, self._h, self._keep)
            ids = (active[:, 0] * self._nbx + active[:, 1]) * self._nby + active[:, 2]
            self._dilate(ids[self._todo.index_select(0, ids)])
            self._todo.zero_()
            # the counts' memory back (a quarter of the dense grid's); their shape and device stay readable
            self._set(_dense=dequantise(self._counts, _LEVELS, self._source.dtype),
                      _counts=torch.zeros(1, 1, 1, dtype=torch.uint8, device=self._counts.device).expand(
                          self._counts.shape))
        assert self._dense is not None
        return self._dense

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self._counts.shape)  # type: ignore[return-value]

    @property
    def device(self) -> torch.device:
        return self._counts.device

    @property
    def remaining_tiles(self) -> int:
        """Tiles not dilated yet (occupied or not; 0 once the whole grid is formed)."""
        return int(self._todo.sum())

    def cell_values(self, k: Tensor, i: Tensor, j: Tensor) -> Tensor:
        """As :meth:`OccupancyGrid.cell_values`, after dilating the tiles of the cells not dilated yet."""
        if self._dense is not None:
            return super().cell_values(k, i, j)
        tile = self._tile
        ids = ((k * self._nbx + torch.div(i, tile, rounding_mode="floor")) * self._nby
               + torch.div(j, tile, rounding_mode="floor")).reshape(-1)
        need = self._todo.index_select(0, ids)
        if bool(need.any()):  # the tiles to do, each once, in order: a mask over the tiles (torch.unique sorts)
            hit = torch.zeros_like(self._todo)
            hit[ids.masked_select(need)] = True
            self._dilate(hit.nonzero().squeeze(1))
        return dequantise(read_cells(self._counts, k, i, j), _LEVELS, self._source.dtype)

    def _dilate(self, ids: Tensor) -> None:
        """Dilate the tiles of flat indices ``ids`` (all still to do) into the counts."""
        if ids.numel() == 0:
            return
        per_slice = self._nbx * self._nby
        idx = torch.stack([ids // per_slice, (ids // self._nby) % self._nbx, ids % self._nby], dim=-1)
        with torch.no_grad():
            _dilate_tiles(self._source, self._keep, idx, self._tile, self._h, self._rho, _LEVELS, self._max_chunk,
                          self._counts)
        self._todo[ids] = False


class _LazyWindowRows(_ReadThroughGrid):
    """Rows ``k0 .. k0 + n - 1`` of a :class:`LazyDilatedGrid` (the last one held past its end), slice 0 at ``t0``:
    :meth:`cell_values` reads the parent's cells, so a replan's window dilates only the tiles it reads (an oracle
    window of ``drive``); :attr:`probs` is the parent's whole grid's rows."""

    _parent: LazyDilatedGrid
    _k0: int
    _n: int
    _rows: Tensor | None

    def __init__(self, parent: LazyDilatedGrid, k0: int, n: int, t0: float):
        self._set(origin=parent.origin, cell_size=parent.cell_size, dt=parent.dt, t0=float(t0), _cache={},
                  _parent=parent, _value_dtype=parent._value_dtype, _k0=int(k0), _n=int(n), _rows=None)

    @property
    def probs(self) -> Tensor:
        if self._rows is None:
            self._set(_rows=OccupancyGrid.window_rows(self._parent.probs, self._k0, self._n))
        assert self._rows is not None
        return self._rows

    @property
    def shape(self) -> tuple[int, int, int]:
        _, nx, ny = self._parent.shape
        return (self._n, nx, ny)

    @property
    def device(self) -> torch.device:
        return self._parent.device

    def cell_values(self, k: Tensor, i: Tensor, j: Tensor) -> Tensor:
        return self._parent.cell_values((k + self._k0).clamp(max=self._parent.n_slices - 1), i, j)

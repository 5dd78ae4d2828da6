"""Signed distance field of the drivable area: how far a point is from the road's edge, negative on the road.

:meth:`RoadSDF.from_geometry` computes it once per scene from the exact drivable geometry (shapely):

1. the cell centres of a lattice over the region of interest are classified on / off the road (shapely 2
   ``contains_xy``, vectorised);
2. ``scipy.ndimage.distance_transform_edt`` both ways gives, per cell, the distance to the nearest cell of the
   other kind; ``sdf = +(d_out - h/2)`` off the road and ``-(d_in - h/2)`` on it (``h`` the cell size, the
   boundary lying between cell centres);
3. within ``exact_band`` cells of the edge the values are replaced by the exact distance to the drivable area's
   boundary (shapely ``distance``), so the zero level set is the true edge, not a staircase.

:meth:`RoadSDF.__call__` looks it up with bilinear interpolation, differentiable w.r.t. the positions (torch).
Outside the lattice the field continues as ``sdf(nearest lattice point) + distance to the lattice``, so the
gradient points back to the map everywhere: off the road there is no plateau.
"""

from __future__ import annotations

import logging
import math
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..parallel import PendingCalls

__all__ = ["RoadSDF", "road_sdf_for_scene", "start_road_sdf", "cancel_road_sdf", "requesting_road_sdf", "map_ready"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class RoadSDF:
    """A signed distance field on a regular lattice.

    Attributes:
        values: ``(NX, NY)`` signed distance [m] at the lattice points, negative on the road.
        origin: ``(x, y)`` [m] of lattice point ``(0, 0)``; point ``(i, j)`` is at ``origin + (i, j) * cell_size``.
        cell_size: lattice spacing [m].
    """

    values: Tensor
    origin: tuple[float, float]
    cell_size: float

    def __post_init__(self) -> None:
        if self.values.ndim != 2 or min(self.values.shape) < 2:
            raise ValueError(f"RoadSDF.values must be (NX >= 2, NY >= 2), got {tuple(self.values.shape)}")
        if not (self.cell_size > 0 and math.isfinite(self.cell_size)):
            raise ValueError(f"RoadSDF.cell_size must be > 0, got {self.cell_size}")

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.values.shape)  # type: ignore[return-value]

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` [m] of the lattice."""
        nx, ny = self.shape
        x0, y0 = self.origin
        return x0, x0 + (nx - 1) * self.cell_size, y0, y0 + (ny - 1) * self.cell_size

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> RoadSDF:
        values = self.values.to(device=device, dtype=dtype)
        return self if values is self.values else RoadSDF(values, self.origin, self.cell_size)

    def __call__(self, xy: Tensor, offset: float = 0.0) -> Tensor:
        """Signed distance [m] at ``xy (..., 2)`` plus ``offset`` (bilinear; differentiable w.r.t. ``xy``).

        The lattice lookup is one :func:`torch.nn.functional.grid_sample` (bilinear, ``align_corners=True``: the
        corner texels are the lattice points, ``padding_mode="border"``: clamped to the lattice), whose fused
        forward and backward kernels replace four index gathers and their scatter-add backward; the values are
        the same bilinear interpolation (``tests/environment/test_road_sdf.py``). ``offset`` is added to the
        lattice (exact: the bilinear weights sum to one), which saves a pass over large batches. The distance
        to the lattice is only computed when a point lies outside it.
        """
        scale, shift = self.normaliser(xy)
        return self.at_normalised(torch.addcmul(shift, xy, scale), offset)

    def normaliser(self, like: Tensor) -> tuple[Tensor, Tensor]:
        """``(scale (2,), shift (2,))`` with ``g = xy * scale + shift`` the normalised lattice coordinates
        (``-1`` at the first lattice point, ``+1`` at the last; ``(x, y)`` order), on ``like``'s device / dtype."""
        x0, x1, y0, y1 = self.extent
        scale = like.new_tensor([2.0 / (x1 - x0), 2.0 / (y1 - y0)])
        shift = like.new_tensor([-(x1 + x0) / (x1 - x0), -(y1 + y0) / (y1 - y0)])
        return scale, shift

    def at_normalised(self, grid: Tensor, offset: float = 0.0, *, inside: bool = False) -> Tensor:
        """Signed distance [m] plus ``offset`` at normalised coordinates ``grid (..., 2)`` (:meth:`normaliser`);
        ``inside=True`` promises that every point lies on the lattice (skips the test for the distance to it)."""
        img = self._lattice(grid, offset)
        inner = torch.nn.functional.grid_sample(img, grid.reshape(1, 1, -1, 2), mode="bilinear",
                                                padding_mode="border", align_corners=True).reshape(grid.shape[:-1])
        if not inside and grid.numel() and bool(grid.detach().abs().amax() > 1.0):
            scale, _ = self.normaliser(grid)
            d = (grid - grid.clamp(-1.0, 1.0)) / scale  # [m] to the lattice, zero inside
            outside = d.pow(2).sum(-1).clamp_min(1e-24).sqrt()
            inner = inner + torch.where((d == 0).all(-1), torch.zeros_like(outside), outside)
        return inner

    def _lattice(self, like: Tensor, offset: float = 0.0) -> Tensor:
        """``values + offset`` as a ``(1, 1, NY, NX)`` image (x along the width, as ``grid_sample`` reads it) on
        ``like``'s device and dtype, cached per (device, dtype, offset)."""
        key = (like.device, like.dtype, float(offset))
        cache = self.__dict__.setdefault("_images", {})
        img = cache.get(key)
        if img is None:
            v = self.values.to(device=like.device, dtype=like.dtype)
            img = (v.T + float(offset)).reshape(1, 1, self.shape[1], self.shape[0]).contiguous()
            cache[key] = img
        return img

    # ---------------------------------------------------------------------------------------------- builder
    @classmethod
    def from_geometry(
        cls,
        drivable: Any,
        bounds: tuple[float, float, float, float],
        *,
        cell_size: float = 0.2,
        max_cells: int = 4_000_000,
        exact_band: int = 3,
        dtype: torch.dtype = torch.float32,
    ) -> RoadSDF:
        """The SDF of the shapely geometry ``drivable`` over ``bounds = (xmin, xmax, ymin, ymax)`` [m].

        ``cell_size`` [m] grows automatically (logged) when the lattice would exceed ``max_cells`` points.
        """
        sdf, origin, h = _lattice_values(drivable, bounds, cell_size, max_cells, exact_band)
        return cls(torch.as_tensor(sdf, dtype=dtype), origin, h)

    @staticmethod
    def _exact(drivable: Any, x: np.ndarray, y: np.ndarray, inside: np.ndarray) -> np.ndarray:
        import shapely

        d = np.asarray(shapely.distance(drivable.boundary, shapely.points(x, y)), dtype=np.float64)
        return np.where(inside, -d, d)


def _lattice_shape(bounds: tuple[float, float, float, float], cell_size: float, max_cells: int
                   ) -> tuple[float, int, int]:
    """``(cell size, NX, NY)`` of the field's lattice over ``bounds``: ``cell_size``, coarser where the lattice
    would hold more than ``max_cells`` points."""
    xmin, xmax, ymin, ymax = (float(b) for b in bounds)
    h = float(cell_size)
    cells = (math.floor((xmax - xmin) / h) + 2) * (math.floor((ymax - ymin) / h) + 2)
    if cells > max_cells:
        h = h * math.sqrt(cells / max_cells) * 1.01
    return h, math.floor((xmax - xmin) / h) + 2, math.floor((ymax - ymin) / h) + 2


def _lattice_values(drivable: Any, bounds: tuple[float, float, float, float], cell_size: float, max_cells: int,
                    exact_band: int) -> tuple[np.ndarray, tuple[float, float], float]:
    """``(values (NX, NY), (xmin, ymin), cell size)`` of :meth:`RoadSDF.from_geometry` (numpy: no torch)."""
    from scipy import ndimage

    from .road import lattice_in

    xmin, xmax, ymin, ymax = (float(b) for b in bounds)
    if not (xmax > xmin and ymax > ymin) or not all(math.isfinite(b) for b in bounds):
        raise ValueError(f"RoadSDF bounds must be finite (xmin < xmax, ymin < ymax), got {bounds}")
    if drivable is None or drivable.is_empty:
        raise ValueError("RoadSDF needs a non-empty drivable area")
    h, nx, ny = _lattice_shape(bounds, cell_size, max_cells)
    if h != float(cell_size):
        log.info("road SDF: cell size %.3g m -> %.3g m to stay within %d lattice points", cell_size, h, max_cells)
    inside = lattice_in(drivable, (xmin, ymin), h, (nx, ny), strict=True)  # shapely.contains_xy of every point
    if inside.all() or not inside.any():
        # the edge lies outside the lattice: exact distances everywhere
        gx, gy = np.meshgrid(xmin + h * np.arange(nx), ymin + h * np.arange(ny), indexing="ij")
        sdf = RoadSDF._exact(drivable, gx.ravel(), gy.ravel(), inside.ravel()).reshape(nx, ny)
    else:
        d_out = ndimage.distance_transform_edt(~inside) * h  # off-road cells: distance to the road
        d_in = ndimage.distance_transform_edt(inside) * h
        sdf = np.where(inside, -(d_in - 0.5 * h), d_out - 0.5 * h)
        if exact_band > 0:
            band = np.abs(sdf) <= exact_band * h
            ii, jj = np.nonzero(band)
            sdf[ii, jj] = RoadSDF._exact(drivable, xmin + h * ii, ymin + h * jj, inside[ii, jj])
    return sdf, (xmin, ymin), h


_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # road -> {key: RoadSDF}
#: fields being computed in forked processes, per drivable area (the one object every scene of a road shares),
#: under ``(key, bounds)`` (:func:`_scene_key_bounds`)
_PENDING = PendingCalls()
#: the field :func:`requesting_road_sdf` asks of the road scenes built meanwhile: ``(cell_size, max_cells, margin)``
_REQUEST: tuple[float, int, float] | None = None
#: the drivable areas whose fields :func:`map_ready` started inside the current :func:`requesting_road_sdf` block
_STARTED: list[weakref.ref] = []


def _grid_bounds(origin: tuple[float, float], h: float, nx: int, ny: int, margin: float
                 ) -> tuple[float, float, float, float]:
    x0, y0 = float(origin[0]), float(origin[1])
    return (x0 - margin, x0 + (nx - 1) * h + margin, y0 - margin, y0 + (ny - 1) * h + margin)


def _field_key(cell_size: float, max_cells: int, margin: float) -> tuple[float, int, float]:
    """The settings a field depends on beside its bounds: the key of ``_CACHE`` and, with the bounds, of
    ``_PENDING`` (the same tuple whoever starts or reads the field)."""
    return float(cell_size), int(max_cells), float(margin)


def _scene_key_bounds(scene: Any, cell_size: float, max_cells: int, margin: float
                      ) -> tuple[Any, tuple, tuple[float, float, float, float]] | None:
    """``(drivable, cache key, bounds)`` of :func:`road_sdf_for_scene`'s field; ``None`` without a road."""
    drivable = getattr(getattr(scene, "road", None), "drivable", None)
    if drivable is None:
        return None
    grid = scene.grid
    _, nx, ny = grid.shape
    bounds = _grid_bounds(grid.origin, float(grid.cell_size), nx, ny, float(margin))
    return drivable, _field_key(cell_size, max_cells, margin), bounds


@contextmanager
def requesting_road_sdf(*, cell_size: float = 0.2, max_cells: int = 4_000_000, margin: float = 10.0
                        ) -> Iterator[None]:
    """While a road scene is built inside this block, its distance field (:func:`road_sdf_for_scene`'s, same
    arguments) is computed in a forked process from the moment its importer knows the drivable area and the grid's
    extent (:func:`map_ready`), i.e. while the road users are rasterised: for a caller with an idle core that will
    read the field (the ``plan`` command, whose scene build then overlaps the field's 0.4-0.9 s; started after the
    build, :func:`start_road_sdf`, the planner waited for it). :func:`road_sdf_for_scene` takes it, as one
    :func:`start_road_sdf` started; :func:`cancel_road_sdf` ends it; a block left by an error ends it too."""
    global _REQUEST
    before, started = _REQUEST, len(_STARTED)
    _REQUEST = _field_key(cell_size, max_cells, margin)
    try:
        yield
    except BaseException:
        for ref in _STARTED[started:]:
            area = ref()
            if area is not None:
                _PENDING.cancel(area)
        raise
    finally:
        _REQUEST = before
        del _STARTED[started:]


#: niceness of the field's process started during a scene's build (:func:`map_ready`) where its lattice holds no
#: more points than a slice of the grid: it then finishes within the build even at low priority, and yields the
#: second core to the build's own threads (``raster_threads``) meanwhile
_BUILD_NICE = 10


def map_ready(drivable: Any, origin: tuple[float, float], cell_size: float, nx: int, ny: int) -> bool:
    """Called by a road scene's importer once its drivable area and its grid's geometry (centre of cell (0, 0),
    cell size, cells per axis) are fixed: starts the field :func:`requesting_road_sdf` asks for, if it does;
    returns whether a process was started."""
    if _REQUEST is None or drivable is None or drivable.is_empty:
        return False
    sdf_cell, max_cells, margin = _REQUEST
    bounds = _grid_bounds(origin, float(cell_size), int(nx), int(ny), margin)
    # the field's work grows with its lattice, the build's with the grid: a lattice larger than a slice of the grid
    # (a large map on coarse cells) keeps its priority, the planner would wait for it
    _, lx, ly = _lattice_shape(bounds, sdf_cell, max_cells)
    nice = _BUILD_NICE if lx * ly <= int(nx) * int(ny) else 0
    if not _PENDING.start(drivable, (_REQUEST, bounds), _float32_lattice, drivable, bounds, sdf_cell, max_cells,
                          nice=nice):
        return False
    _STARTED.append(weakref.ref(drivable))
    return True


def road_sdf_for_scene(scene: Any, *, cell_size: float = 0.2, max_cells: int = 4_000_000, margin: float = 10.0
                       ) -> RoadSDF | None:
    """The :class:`RoadSDF` of ``scene.road.drivable`` over the occupancy grid's extent grown by ``margin`` [m],
    computed once per road scene (cached; taken from the process of :func:`start_road_sdf` or
    :func:`requesting_road_sdf` where one computes it); ``None`` for scenes without a road (random, inD)."""
    found = _scene_key_bounds(scene, cell_size, max_cells, margin)
    if found is None:
        return None
    drivable, key, bounds = found
    per_road = _CACHE.setdefault(scene.road, {})
    if key not in per_road:
        pending = _PENDING.take(drivable, (key, bounds))
        sdf = None
        if pending is not None:
            try:
                values, origin, h = pending.result()
                sdf = RoadSDF(torch.as_tensor(values), origin, h)
            except RuntimeError as exc:  # computed here instead (the same field)
                log.debug("road SDF: %s; computing it here", exc)
        per_road[key] = sdf or RoadSDF.from_geometry(drivable, bounds, cell_size=cell_size, max_cells=max_cells)
    return per_road[key]


def start_road_sdf(scene: Any, *, cell_size: float = 0.2, max_cells: int = 4_000_000, margin: float = 10.0) -> bool:
    """Start computing :func:`road_sdf_for_scene`'s field (same arguments) in a forked process
    (:class:`~density_planner.parallel.ForkedCall`), for a caller with an idle core: the first
    :func:`road_sdf_for_scene` then takes it from there (0.3-0.9 s otherwise, scipy's import included). Returns
    whether a process was started (not without a road, without ``fork``, or when the field is cached or already
    being computed)."""
    found = _scene_key_bounds(scene, cell_size, max_cells, margin)
    if found is None:
        return False
    drivable, key, bounds = found
    if key in _CACHE.get(scene.road, {}):
        return False
    return _PENDING.start(drivable, (key, bounds), _float32_lattice, drivable, bounds, cell_size, max_cells)


def cancel_road_sdf(scene: Any) -> None:
    """End the processes :func:`start_road_sdf` or :func:`requesting_road_sdf` started for ``scene``'s road whose
    fields were not taken (a planner that did not read them, an error): nothing is left running."""
    drivable = getattr(getattr(scene, "road", None), "drivable", None)
    if drivable is not None:
        _PENDING.cancel(drivable)


def _float32_lattice(drivable: Any, bounds: tuple[float, float, float, float], cell_size: float, max_cells: int
                     ) -> tuple[np.ndarray, tuple[float, float], float]:
    """:func:`_lattice_values` with the values as float32 (:meth:`RoadSDF.from_geometry`'s default dtype; half the
    bytes through the pipe)."""
    sdf, origin, h = _lattice_values(drivable, bounds, cell_size, max_cells, exact_band=3)
    return sdf.astype(np.float32), origin, h

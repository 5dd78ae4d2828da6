"""The lane graph of a road map: lanelets with their centre lines, successors and same-direction neighbours.

A :class:`LaneGraph` is the part of a CommonRoad ``LaneletNetwork`` that route search needs (and nothing else), so
that routes can be planned on hand-made maps in tests and on any map a user builds, without commonroad-io:

* :class:`Lane`: one lanelet, its left / centre / right polylines [m], its length, its successors and its
  adjacent lanelets *in the same driving direction* (the lane changes a vehicle may make);
* :meth:`LaneGraph.from_lanelet_network` reads a commonroad-io ``LaneletNetwork`` (any object with the same
  attributes works: ``lanelets``, ``lanelet_id``, ``left_vertices``, ``center_vertices``, ``right_vertices``,
  ``successor``, ``adj_left``, ``adj_left_same_direction``, ``adj_right``, ``adj_right_same_direction``,
  ``lanelet_type``), keeping only lanelets a car may drive on (sidewalks, crosswalks, bicycle lanes and
  borders are left out, as in the drivable area);
* :func:`lane_graph_from_file` reads it from a CommonRoad XML file once per file (cached by path and
  modification time), which is how planners find the lanes of a scene loaded from a file
  (``scene.meta["file"]``).

Queries are vectorised with shapely 2 (``contains_xy``, ``line_locate_point``).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["Lane", "LaneGraph", "LanePath", "lane_graph_from_file", "scene_lane_graph", "remember_lane_graph",
           "NON_DRIVABLE_LANELET_TYPES"]

log = logging.getLogger(__name__)

#: CommonRoad lanelet types (``LaneletType`` values) a car does not drive on
NON_DRIVABLE_LANELET_TYPES = frozenset({"sidewalk", "crosswalk", "bicycleLane", "border", "restricted"})


def _shapely() -> Any:
    import shapely

    return shapely


def _polyline(name: str, value: Any) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] < 2 or not np.isfinite(arr).all():
        raise ValueError(f"{name} must be a finite (K >= 2, 2) polyline, got shape {arr.shape}")
    return arr


@dataclass(frozen=True, eq=False)
class Lane:
    """One lanelet.

    Attributes:
        lane_id: the lanelet id.
        left, center, right: ``(K, 2)`` polylines [m] in driving direction (``center`` defaults to the mean of
            ``left`` and ``right`` when they have equal length).
        successors: ids of the lanelets that continue this one.
        left_same, right_same: id of the adjacent lanelet to the left / right that runs in the same direction
            (a lane change), or ``None``.
    """

    lane_id: int
    left: np.ndarray
    right: np.ndarray
    center: np.ndarray | None = None
    successors: tuple[int, ...] = ()
    left_same: int | None = None
    right_same: int | None = None

    def __post_init__(self) -> None:
        left = _polyline(f"lane {self.lane_id} left", self.left)
        right = _polyline(f"lane {self.lane_id} right", self.right)
        if self.center is None:
            if left.shape != right.shape:
                raise ValueError(f"lane {self.lane_id}: give center when left and right differ in length")
            center = 0.5 * (left + right)
        else:
            center = _polyline(f"lane {self.lane_id} center", self.center)
        for name, arr in (("left", left), ("right", right), ("center", center)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "lane_id", int(self.lane_id))
        object.__setattr__(self, "successors", tuple(int(s) for s in self.successors))
        for name in ("left_same", "right_same"):
            v = getattr(self, name)
            object.__setattr__(self, name, None if v is None else int(v))

    @functools.cached_property
    def polygon(self) -> Any:
        """The lanelet's area (shapely polygon: left bound, then the reversed right bound)."""
        shapely = _shapely()
        poly = shapely.Polygon(np.vstack([self.left, self.right[::-1]]))
        return poly if poly.is_valid else poly.buffer(0)

    @functools.cached_property
    def centerline(self) -> Any:
        """The centre line as a shapely ``LineString``."""
        assert self.center is not None  # set by __post_init__
        return _shapely().LineString(self.center)

    @property
    def length(self) -> float:
        """Length of the centre line [m]."""
        assert self.center is not None  # set by __post_init__
        return float(np.linalg.norm(np.diff(self.center, axis=0), axis=1).sum())

    def heading_at(self, s: np.ndarray) -> np.ndarray:
        """Heading [rad] of the centre line at arc lengths ``s`` [m] (of the segment containing each)."""
        assert self.center is not None  # set by __post_init__
        seg = np.diff(self.center, axis=0)
        cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
        idx = np.clip(np.searchsorted(cum, np.asarray(s, dtype=np.float64), side="right") - 1, 0, len(seg) - 1)
        return np.arctan2(seg[idx, 1], seg[idx, 0])


@dataclass(frozen=True)
class LanePath:
    """Where a vehicle that follows lanes is after given distances along them (:meth:`LaneGraph.follow`).

    Attributes:
        xy: ``(T, 2)`` points on the centre lines [m] at the distances; past the end of the last lane (no
            successor), on the straight line that continues its last segment.
        heading: ``(T,)`` direction of the centre line there [rad].
        weight: probability of this branch (the branches of one start sum to 1).
        offset: signed distance of the start point from the first lane's centre line [m], positive to the left.
        lanes: the ids of the lanes followed, in order.
    """

    xy: np.ndarray
    heading: np.ndarray
    weight: float
    offset: float
    lanes: tuple[int, ...]


class LaneGraph:
    """Lanes keyed by id, with the successor / lane-change structure (see the module docstring)."""

    def __init__(self, lanes: list[Lane] | tuple[Lane, ...]):
        ids = [lane.lane_id for lane in lanes]
        if len(set(ids)) != len(ids):
            raise ValueError(f"duplicate lane ids {sorted(i for i in set(ids) if ids.count(i) > 1)}")
        if not ids:
            raise ValueError("a LaneGraph needs at least one lane")
        known = set(ids)
        # references to lanes that are not kept (e.g. sidewalks) are dropped
        self.lanes: dict[int, Lane] = {
            lane.lane_id: dataclasses.replace(
                lane,
                successors=tuple(s for s in lane.successors if s in known),
                left_same=lane.left_same if lane.left_same in known else None,
                right_same=lane.right_same if lane.right_same in known else None,
            )
            for lane in lanes
        }

    def __len__(self) -> int:
        return len(self.lanes)

    def __getitem__(self, lane_id: int) -> Lane:
        return self.lanes[int(lane_id)]

    @property
    def ids(self) -> list[int]:
        return list(self.lanes)

    # ------------------------------------------------------------------ queries
    def lanes_at(self, xy: tuple[float, float], heading: float | None = None, *, max_heading_error: float = 1.0,
                 search_radius: float = 5.0) -> list[int]:
        """Ids of the lanes containing the point ``xy`` whose direction at that point is within
        ``max_heading_error`` [rad] of ``heading`` (any direction when ``heading`` is None). Where no lane
        contains the point, the nearest lanes within ``search_radius`` [m] (same heading test) are returned,
        nearest first."""
        shapely = _shapely()
        ids = self.ids
        polys = np.asarray([self.lanes[i].polygon for i in ids], dtype=object)
        point = shapely.Point(float(xy[0]), float(xy[1]))
        dist = np.asarray(shapely.distance(polys, point), dtype=np.float64)
        order = np.argsort(dist, kind="stable")
        inside = [ids[k] for k in order if dist[k] <= 1e-9]
        near = [ids[k] for k in order if dist[k] <= search_radius]
        out = []
        for cand in (inside, near):
            for lane_id in cand:
                if heading is None or abs(_wrap(self._heading_near(lane_id, xy) - heading)) <= max_heading_error:
                    out.append(lane_id)
            if out:
                return out
        return out

    def _heading_near(self, lane_id: int, xy: tuple[float, float]) -> float:
        lane = self.lanes[lane_id]
        s = float(lane.centerline.project(_shapely().Point(float(xy[0]), float(xy[1]))))
        return float(lane.heading_at(np.array([s]))[0])

    def follow(self, xy: tuple[float, float], heading: float, distances: np.ndarray, *,
               max_heading_error: float = 0.6, search_radius: float = 1.0, max_branches: int = 4) -> list[LanePath]:
        """The paths of a vehicle at ``xy`` heading ``heading`` [rad] that follows the lanes' centre lines, at the
        arc ``distances (T,)`` [m] from its projection on them (``[]`` where no lane matches: :meth:`lanes_at`).

        It starts on every lane that contains ``xy`` in its direction (overlapping lanes of an intersection), else
        on the nearest within ``search_radius``, with equal weights; at a fork each branch takes an equal share of
        its weight, as long as there are at most ``max_branches`` paths (past that, only the straightest successor
        is followed). Lane changes are not predicted."""
        shapely = _shapely()
        point = shapely.Point(float(xy[0]), float(xy[1]))
        cand = self.lanes_at(xy, heading, max_heading_error=max_heading_error, search_radius=search_radius)
        if not cand:
            return []
        inside = [i for i in cand if self.lanes[i].polygon.intersects(point)]
        starts = inside[:max_branches] if inside else cand[:1]
        distances = np.asarray(distances, dtype=np.float64)
        need = float(distances.max()) if distances.size else 0.0
        paths: list[tuple[tuple[int, ...], float, float]] = []  # (lanes, weight, s0)
        for lane_id in starts:
            s0 = float(self.lanes[lane_id].centerline.project(point))
            active: list[tuple[tuple[int, ...], float, float]] = [
                ((lane_id,), 1.0 / len(starts), self.lanes[lane_id].length - s0)]
            while active:
                ids, w, covered = active.pop()
                succ = self.lanes[ids[-1]].successors
                if covered >= need or not succ:
                    paths.append((ids, w, s0))
                    continue
                if len(paths) + len(active) + len(succ) > max_branches:
                    succ = (min(succ, key=lambda k: abs(_wrap(float(np.diff(self.lanes[k].heading_at(
                        np.array([0.0, self.lanes[k].length]))).item())))),)
                for k in succ:
                    active.append((ids + (k,), w / len(succ), covered + self.lanes[k].length))
        out = []
        for ids, w, s0 in paths:
            centres = [self.lanes[k].center for k in ids]
            poly: list[np.ndarray] = []
            for c in centres:
                assert c is not None  # set by Lane.__post_init__
                poly.append(c[1:] if poly and np.hypot(*(c[0] - poly[-1][-1])) < 1e-6 else c)
            pts = np.vstack(poly)
            seg = np.diff(pts, axis=0)
            seg_len = np.hypot(seg[:, 0], seg[:, 1])
            keep = seg_len > 1e-9
            pts = np.vstack([pts[:1], pts[1:][keep]])
            seg, seg_len = seg[keep], seg_len[keep]
            cum = np.concatenate([[0.0], np.cumsum(seg_len)])
            s = s0 + distances
            idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
            head = np.arctan2(seg[idx, 1], seg[idx, 0])
            beyond = np.maximum(s - cum[-1], 0.0)
            px = np.interp(s, cum, pts[:, 0]) + beyond * np.cos(head)
            py = np.interp(s, cum, pts[:, 1]) + beyond * np.sin(head)
            k0 = min(int(np.searchsorted(cum, s0, side="right")) - 1, len(seg) - 1)
            h0 = math.atan2(seg[max(k0, 0), 1], seg[max(k0, 0), 0])
            base = np.array([np.interp(s0, cum, pts[:, 0]), np.interp(s0, cum, pts[:, 1])])
            offset = -math.sin(h0) * (float(xy[0]) - base[0]) + math.cos(h0) * (float(xy[1]) - base[1])
            out.append(LanePath(np.stack([px, py], axis=-1), head, float(w), float(offset), ids))
        return out

    def lanes_touching(self, shapes: Any) -> list[int]:
        """Ids of the lanes whose area intersects ``shapes`` (a shapely geometry) with positive area, or that
        contain it where it has no area (points, lines)."""
        shapely = _shapely()
        ids = self.ids
        polys = np.asarray([self.lanes[i].polygon for i in ids], dtype=object)
        hit = np.asarray(shapely.intersects(polys, shapes), dtype=bool)
        if getattr(shapes, "area", 0.0) > 0:
            area = np.asarray(shapely.area(shapely.intersection(polys[hit], shapes)), dtype=np.float64)
            keep = np.zeros(len(ids), dtype=bool)
            keep[np.flatnonzero(hit)] = area > 1e-6
            hit = keep
        return [ids[k] for k in np.flatnonzero(hit)]

    def to_networkx(self, *, lane_change_cost: float = 0.0) -> Any:
        """Directed graph: edge ``a -> b`` for every successor (``kind="successor"``, ``weight`` = length of
        ``a``) and every same-direction lane change (``kind="change"``, ``weight = lane_change_cost``)."""
        import networkx as nx

        g = nx.DiGraph()
        for lane in self.lanes.values():
            g.add_node(lane.lane_id)
        for lane in self.lanes.values():
            for s in lane.successors:
                g.add_edge(lane.lane_id, s, kind="successor", weight=lane.length)
            for n in (lane.left_same, lane.right_same):
                if n is not None and not g.has_edge(lane.lane_id, n):
                    g.add_edge(lane.lane_id, n, kind="change", weight=float(lane_change_cost))
        return g

    def translated(self, dx: float, dy: float) -> LaneGraph:
        """The same lanes moved by ``(dx, dy)`` [m] (e.g. into a scene's local frame: ``-meta["frame_offset"]``)."""
        d = np.array([dx, dy], dtype=np.float64)
        return LaneGraph([dataclasses.replace(lane, left=lane.left + d, right=lane.right + d,
                                              center=None if lane.center is None else lane.center + d)
                          for lane in self.lanes.values()])

    # ----------------------------------------------------------------- builders
    @classmethod
    def from_lanelet_network(cls, network: Any, *, exclude_types: frozenset[str] = NON_DRIVABLE_LANELET_TYPES
                             ) -> LaneGraph:
        """The drivable lanes of a commonroad-io ``LaneletNetwork`` (or an object with the same attributes)."""
        lanes = []
        for ll in getattr(network, "lanelets", ()):
            types = {getattr(t, "value", str(t)) for t in (getattr(ll, "lanelet_type", None) or ())}
            if types and types <= exclude_types:
                continue
            try:
                lane = Lane(
                    lane_id=ll.lanelet_id,
                    left=ll.left_vertices,
                    right=ll.right_vertices,
                    center=getattr(ll, "center_vertices", None),
                    successors=tuple(getattr(ll, "successor", None) or ()),
                    left_same=ll.adj_left if getattr(ll, "adj_left_same_direction", False) else None,
                    right_same=ll.adj_right if getattr(ll, "adj_right_same_direction", False) else None,
                )
            except ValueError as exc:
                log.warning("lanelet %s left out of the lane graph: %s", getattr(ll, "lanelet_id", "?"), exc)
                continue
            lanes.append(lane)
        if not lanes:
            raise ValueError("the lanelet network has no drivable lanelets")
        return cls(lanes)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


#: lane graphs by (resolved path, modification time); a handful of files at most
_GRAPHS: dict[tuple[str, int], LaneGraph] = {}
_MAX_GRAPHS = 8


def _key(path: str | Path) -> tuple[str, int]:
    p = Path(path).resolve()
    return str(p), p.stat().st_mtime_ns


def _store(key: tuple[str, int], graph: LaneGraph) -> LaneGraph:
    if len(_GRAPHS) >= _MAX_GRAPHS:
        _GRAPHS.pop(next(iter(_GRAPHS)))
    _GRAPHS[key] = graph
    return graph


def remember_lane_graph(path: str | Path, network: Any) -> None:
    """Keep the lane graph of the ``LaneletNetwork`` just read from ``path`` (called by the CommonRoad importer, so
    that planners do not read the file a second time). Never raises: a network without drivable lanes is skipped."""
    try:
        key = _key(path)
        if key not in _GRAPHS:
            _store(key, LaneGraph.from_lanelet_network(network))
    except (OSError, ValueError) as exc:
        log.info("no lane graph kept for %s: %s", path, exc)


def lane_graph_from_file(path: str | Path) -> LaneGraph:
    """The :class:`LaneGraph` of a CommonRoad XML file (read once per file and modification time; free when the
    importer already read it, see :func:`remember_lane_graph`)."""
    key = _key(path)
    if key not in _GRAPHS:
        from .commonroad import read_commonroad

        scenario, _ = read_commonroad(key[0])
        _store(key, LaneGraph.from_lanelet_network(scenario.lanelet_network))
    return _GRAPHS[key]


#: lane graphs moved into a scene's local frame, by the file's graph (one offset per file)
_TRANSLATED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def scene_lane_graph(scene: Any) -> LaneGraph | None:
    """The lane graph of a scene: ``scene.lane_graph`` where set, else read from the CommonRoad file named in
    ``scene.meta["file"]`` (cached) and moved into the scene's frame (``meta["frame_offset"]``: the importer
    translates scenarios with large, e.g. UTM, coordinates); ``None`` for scenes without one (random, inD)."""
    graph = getattr(scene, "lane_graph", None)
    if graph is not None:
        return graph
    meta = getattr(scene, "meta", {}) or {}
    path = meta.get("file")
    if meta.get("source") != "commonroad" or not path:
        return None
    try:
        graph = lane_graph_from_file(path)
        ox, oy = (float(v) for v in (meta.get("frame_offset") or (0.0, 0.0)))
        if ox or oy:
            key = ("translated", ox, oy)
            cached = _TRANSLATED.get(graph)
            if cached is None or cached[0] != key:
                cached = (key, graph.translated(-ox, -oy))
                _TRANSLATED[graph] = cached
            return cached[1]
        return graph
    except (OSError, ValueError) as exc:
        log.warning("no lane graph for %s (%s): no lane-based route seeds or predictions", getattr(scene, "name", "?"),
                    exc)
        return None

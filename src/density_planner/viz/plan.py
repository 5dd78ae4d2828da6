"""Figures of plans: the scene with the planned reference and the density-weighted sample cloud, an animation
over time, and the cost curves of the optimisation."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from matplotlib.ticker import FuncFormatter, NullLocator

from ..environment.scene import Scene
from ..io.atomic import _atomic
from .occupancy import _decorate, _extent, show_occupancy
from .style import DENSITY_CMAP, agg_canvas, frame_map, plt, save_figure

__all__ = ["plot_plan", "animate_plan", "plot_costs", "plot_plans"]

#: tick labels of log axes as plain numbers
_PLAIN_NUMBER = FuncFormatter(lambda value, _pos: f"{value:g}")

#: background outside the map (no occupancy data there)
_OUTSIDE_MAP = "#d9e2ec"

_PLANNER_COLOURS = ("tab:orange", "tab:blue", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan",
                    "tab:red", "tab:green", "black")


def _rel_density(log_rho_k: np.ndarray) -> np.ndarray:
    return np.exp(log_rho_k - log_rho_k.max())


def _cloud(ax, x: np.ndarray, log_rho: np.ndarray, k: int, size: float = 4.0):
    rel = _rel_density(log_rho[:, k])
    order = np.argsort(rel)
    return ax.scatter(x[order, k, 0], x[order, k, 1], c=rel[order], s=size, cmap=DENSITY_CMAP, vmin=0, vmax=1,
                      linewidths=0, zorder=3)


def _geometry_patches(geom) -> list[np.ndarray]:
    """Exterior rings ``(M, 2)`` of the polygons in a shapely geometry (polygon, multi-polygon, collection)."""
    if geom is None or geom.is_empty:
        return []
    if hasattr(geom, "geoms"):
        return [r for g in geom.geoms for r in _geometry_patches(g)]
    if hasattr(geom, "exterior"):
        return [np.asarray(geom.exterior.coords)]
    return []


def _draw_goal(ax, scene: Scene, *, label: bool = True) -> None:
    """The goal region's shapes (hatched) where the scene has road data, and the goal point."""
    road = getattr(scene, "road", None)
    shapes = road.goal.shapes if road is not None else None
    first = True
    for ring in _geometry_patches(shapes):
        ax.fill(ring[:, 0], ring[:, 1], facecolor=(0.84, 0.15, 0.16, 0.12), edgecolor="tab:red", lw=0.9,
                hatch="///", zorder=2, label="goal region" if (label and first) else None)
        first = False
    ax.plot(*scene.goal, "*", color="tab:red", ms=11, mec="white", zorder=6,
            label=("goal" if shapes is None else None) if label else None)


def _draw_obstacle_paths(ax, scene: Scene, t_abs: np.ndarray) -> None:
    """Centre paths of the recorded road users over the plan's times (thin) and their true shapes at the
    start (outlined)."""
    from matplotlib.collections import LineCollection

    road = getattr(scene, "road", None)
    if road is None:
        return
    paths, outlines = [], []
    for track in road.obstacles:
        if track.static:
            continue
        poses = track.poses_at(t_abs)
        ok = np.isfinite(poses[:, 0])
        if ok.sum() < 2:
            continue
        paths.append(poses[ok, :2])
        outlines += _geometry_patches(track.polygons_at(t_abs[:1])[0])
    # one artist per kind (a line per road user cost ~1 ms each to make and draw)
    if paths:
        ax.add_collection(LineCollection(paths, colors="tab:blue", linewidths=0.6, alpha=0.6, zorder=2,
                                         label="road users' paths"), autolim=False)
    if outlines:
        ax.add_collection(LineCollection(outlines, colors="tab:blue", linewidths=0.8, zorder=2), autolim=False)


def _window(points: np.ndarray, bounds: tuple[float, float, float, float], margin: float,
            max_aspect: float = 3.0) -> tuple[float, float, float, float]:
    """Bounding box of ``points (N, 2)`` plus ``margin``, widened to an aspect ratio <= ``max_aspect``, clipped to
    ``bounds``."""
    pts = points[np.isfinite(points).all(axis=1)]
    x0, y0 = pts.min(axis=0) - margin
    x1, y1 = pts.max(axis=0) + margin
    w, h = x1 - x0, y1 - y0
    if w > max_aspect * h:
        pad = (w / max_aspect - h) / 2
        y0, y1 = y0 - pad, y1 + pad
    elif h > max_aspect * w:
        pad = (h / max_aspect - w) / 2
        x0, x1 = x0 - pad, x1 + pad
    bx0, bx1, by0, by1 = bounds
    return (max(x0, bx0), min(x1, bx1), max(y0, by0), min(y1, by1))


#: [m] how far around the plan (trajectory, cloud, start, goal point) the overview shows the goal region
GOAL_REGION_REACH = 30.0


def _region_of_interest(scene: Scene, states: np.ndarray,
                        samples_x: np.ndarray | None) -> tuple[float, float, float, float]:
    """What the overview shows: the trajectory, the sample cloud (1-99 % quantiles), start, goal point and the goal
    region within ``GOAL_REGION_REACH`` of them (a goal lanelet can run on for kilometres past a 100-m plan), with a
    margin, inside the map."""
    pts = [states[:, :2], np.asarray([scene.start[:2], scene.goal])]
    if samples_x is not None:
        flat = samples_x[..., :2].reshape(-1, 2)
        pts.append(np.nanquantile(flat, [0.01, 0.99], axis=0))
    road = getattr(scene, "road", None)
    if road is not None and road.goal.shapes is not None:
        import shapely

        core = np.concatenate(pts)
        core = core[np.isfinite(core).all(axis=1)]
        (cx0, cy0), (cx1, cy1) = core.min(axis=0) - GOAL_REGION_REACH, core.max(axis=0) + GOAL_REGION_REACH
        near = road.goal.shapes.intersection(shapely.box(cx0, cy0, cx1, cy1))
        if not near.is_empty:
            gx0, gy0, gx1, gy1 = near.bounds
            pts.append(np.array([[gx0, gy0], [gx1, gy1]]))
    return _window(np.concatenate(pts), _extent(scene), margin=12.0)


Corner = Literal["upper left", "upper right", "lower left", "lower right"]


def _emptiest_corner(points: np.ndarray, window: tuple[float, float, float, float]) -> Corner:
    """The legend corner of ``window`` with the fewest ``points`` in its quarter (matplotlib's ``loc="best"``
    tests every artist and costs a third of the figure's drawing time)."""
    x0, x1, y0, y1 = window
    pts = points[np.isfinite(points).all(axis=1)]
    right = pts[:, 0] > 0.5 * (x0 + x1)
    upper = pts[:, 1] > 0.5 * (y0 + y1)
    counts: dict[Corner, int] = {"upper left": int((upper & ~right).sum()), "upper right": int((upper & right).sum()),
              "lower left": int((~upper & ~right).sum()), "lower right": int((~upper & right).sum())}
    return min(counts, key=counts.__getitem__)


def _verdict_line(verdict, width: int = 150) -> tuple[str, str]:
    """(text, colour) of a verdict for a figure (wrapped to ``width`` characters, at most three lines)."""
    import textwrap

    if verdict is None:
        return "no verdict (no trajectory)", "black"
    if verdict.ok:
        return "verdict: success (goal reached, collision-free, on road, within model)", "tab:green"
    text = "verdict: failed: " + "; ".join(verdict.reasons)
    return "\n".join(textwrap.wrap(text, width)[:3]), "tab:red"


def _mark_failures(ax, states: np.ndarray, verdict, plan_dt: float) -> None:
    if verdict is None:
        return
    for key, marker, label in (("first_collision_time", "X", "first collision"),
                               ("off_road_first_time", "P", "leaves the road")):
        t = verdict.details.get(key)
        if t is None:
            continue
        k = min(int(round(t / plan_dt)), len(states) - 1)
        ax.plot(states[k, 0], states[k, 1], marker, color="tab:red", ms=9, mec="white", zorder=7,
                label=f"{label} (t = {t:.1f} s)")


Rect = tuple[float, float, float, float]


@dataclass(frozen=True)
class _PlanLayout:
    """Where :func:`plot_plan`'s panels go: the figure's size [in] and each panel's rectangle ``(left, bottom,
    width, height)`` in figure fractions, from fixed margins for the tick labels, axis labels and titles.
    matplotlib's constrained layout engine found the same kind of arrangement at ~0.15 s of the figure's ~0.5 s.

    The overview shows the region of interest with equal axes (``aspect``: its width over its height): its box has
    that aspect, with the colour bar beside it. Wide regions (aspect > 2.2) put it on top, over two rows of
    snapshots; others on the left, beside them. Overview and snapshots share the width in proportion to
    ``clip(1.9 aspect, 1.9, 3.6) : 1`` per snapshot column, and a side that cannot use its share (a panel limited by
    the height) leaves the rest to the other. Snapshot panels are square."""

    size: tuple[float, float]
    overview: Rect
    colorbar: Rect | None
    snapshots: list[Rect]
    #: [in] height of the header above the panels (the title, then the verdict's lines)
    header: float

    #: [in] from the figure's top to the title's top and to the verdict's first line, and per line of verdict
    TITLE_TOP, VERDICT_TOP, LINE = 0.1, 0.4, 0.15
    #: [in] left of the overview (tick labels, axis label), below it, right of the figure
    OVER_LEFT, OVER_BOTTOM, RIGHT = 0.7, 0.55, 0.1
    #: [in] gap between the overview and its colour bar, the bar's width, and its tick labels and label
    BAR_GAP, BAR_WIDTH, BAR_LABELS = 0.08, 0.12, 0.55
    #: [in] left of a snapshot (tick labels), right of it, above it (title) and below it (tick labels)
    SNAP_LEFT, SNAP_RIGHT, SNAP_TOP, SNAP_BOTTOM = 0.38, 0.06, 0.3, 0.25

    @classmethod
    def of(cls, aspect: float, n_snap: int, *, header_lines: int = 1, colorbar: bool = True) -> _PlanLayout:
        header = cls.VERDICT_TOP + 0.1 + cls.LINE * header_lines
        bar = cls.BAR_GAP + cls.BAR_WIDTH + cls.BAR_LABELS if colorbar else 0.0
        ncol = max((n_snap + 1) // 2, 1)
        snap_pad_w, snap_pad_h = cls.SNAP_LEFT + cls.SNAP_RIGHT, cls.SNAP_TOP + cls.SNAP_BOTTOM
        extra = 2.5 * max(ncol - 3, 0)  # [in] wider for more than three columns of snapshots
        if aspect > 2.2:  # wide: the overview on top, two rows of snapshots of 3.2 in below it
            over_h = 11.0 / aspect + 0.9
            width, height = 13.0 + extra, header + over_h + 6.4
            box_w = min(width - cls.OVER_LEFT - bar - cls.RIGHT, (over_h - cls.OVER_BOTTOM - 0.05) * aspect)
            box_h = box_w / aspect
            free = width - cls.OVER_LEFT - bar - cls.RIGHT - box_w
            box = (cls.OVER_LEFT + 0.5 * free, 6.4 + cls.OVER_BOTTOM + 0.5 * (over_h - cls.OVER_BOTTOM - 0.05 - box_h),
                   box_w, box_h)
            cells = [(cls.RIGHT + c * (width - 2 * cls.RIGHT) / ncol, 3.2 * (1 - r), (width - 2 * cls.RIGHT) / ncol,
                      3.2) for r in range(2) for c in range(ncol)]
        else:  # the overview on the left, two rows of snapshots beside it
            width, height = 13.0 + max(0.0, aspect - 1.0) * 3.0 + extra, 7.5 + cls.LINE * header_lines
            content = height - header
            row_h = content / 2.0
            side_max = row_h - snap_pad_h  # the snapshots' side where the height limits them
            usable = width - cls.RIGHT
            ratio = float(np.clip(1.9 * aspect, 1.9, 3.6))
            over_cell = max(usable * ratio / (ratio + ncol), usable - ncol * (side_max + snap_pad_w))
            box_h_max = content - cls.OVER_BOTTOM - 0.1
            box_w = min(over_cell - cls.OVER_LEFT - bar, box_h_max * aspect)
            box_h = box_w / aspect
            box = (cls.OVER_LEFT, cls.OVER_BOTTOM + 0.5 * (box_h_max - box_h), box_w, box_h)
            x_snap = cls.OVER_LEFT + box_w + bar
            cell_w = (width - cls.RIGHT - x_snap) / ncol
            cells = [(x_snap + c * cell_w, row_h * (1 - r), cell_w, row_h) for r in range(2) for c in range(ncol)]
        snaps = []
        for cx, cy, cw, ch in cells[:n_snap]:  # a square panel in each cell, centred below its title
            side = max(min(cw - snap_pad_w, ch - snap_pad_h), 0.5)
            snaps.append((cx + cls.SNAP_LEFT + 0.5 * (cw - snap_pad_w - side), cy + ch - cls.SNAP_TOP - side, side,
                          side))

        def frac(r: Rect) -> Rect:
            return (r[0] / width, r[1] / height, r[2] / width, r[3] / height)

        bar_rect = None
        if colorbar:
            bar_rect = frac((box[0] + box[2] + cls.BAR_GAP, box[1] + 0.25 * box[3], cls.BAR_WIDTH, 0.5 * box[3]))
        return cls((width, height), frac(box), bar_rect, [frac(r) for r in snaps], header)


def warm_up(scene: Scene | None = None) -> None:
    """Load what the first figure of a process would (fonts, layout and text machinery: ~0.2-0.3 s) by laying out
    and rendering a small figure, e.g. in a process that waits for a plan to draw. With ``scene``, also draw and
    save (to temporary files, deleted) :func:`plot_plan`'s figure of a vehicle standing at the scene's start with
    a small sample cloud, and a :func:`plot_costs` figure: what the first plan figure of a scene pays once more (its
    occupancy crops, the road users' paths, the colour bar, the PNG writer; ~0.1-0.2 s) and the first cost figure
    (log axes, legends; ~0.1 s) are then paid before the plan arrives."""
    fig, ax = plt.subplots(figsize=(2.0, 1.5), dpi=30, layout="constrained")
    ax.plot([0.0, 1.0], [0.0, 1.0], "o-")
    ax.set_title("t = 0.0 s", fontsize=8)
    ax.set_xlabel("x [m]")
    fig.suptitle("warm-up", fontsize=10)
    agg_canvas(fig).draw()
    plt.close(fig)
    if scene is None:
        return
    import tempfile

    states = np.repeat(np.asarray(scene.start, dtype=np.float64)[None], 2, axis=0)
    cloud = np.repeat(states[None], 4, axis=0) + np.linspace(-1.0, 1.0, 4)[:, None, None]
    with tempfile.TemporaryDirectory(prefix="density-planner-warm-up-") as tmp:
        plot_plan(scene, states, Path(tmp) / "plan.png", samples_x=cloud, samples_log_rho=np.zeros(cloud.shape[:2]),
                  title="warm-up", body=None)
        series = {"total": [10.0, 1.0, 0.1], "goal": [1.0, 0.01, 1e-4]}
        plot_costs({"stage1": series, "stage2": series}, Path(tmp) / "costs.png", title="warm-up")


def plot_plan(
    scene: Scene,
    states: np.ndarray,
    path: str | Path,
    *,
    samples_x: np.ndarray | None = None,
    samples_log_rho: np.ndarray | None = None,
    title: str | None = None,
    snapshot_times: Sequence[float] | None = None,
    plan_dt: float = 0.1,
    label: str = "reference",
    verdict=None,
    body: np.ndarray | None = None,
) -> Path:
    """The plan over the scene (overview) and six occupancy snapshots with the sample cloud around the vehicle.

    The overview shows the region that matters (trajectory, sample cloud, start, goal region, plus a margin) over
    the occupancy at the start, with the swept occupancy of the horizon faintly (so the road stays visible in dense
    traffic), the recorded road users' paths and the goal region where the scene has road data, and the verdict
    (its failures marked on the trajectory). Snapshots are square windows of one size that follow the vehicle.

    Args:
        states: ``(T, nx)`` planned states on the planning grid (a reference, or an executed trajectory that may
            stop early: later snapshots then show where it stopped).
        label: legend label of ``states``.
        samples_x: ``(N, T, nx)`` predicted sample trajectories; samples_log_rho: ``(N, T)``.
        snapshot_times: times [s] of the snapshots (default: six, evenly over the trajectory).
        verdict: the plan's :class:`~density_planner.evaluation.verdict.Verdict` (drawn when given).
        body: ``(T, 4, 2)`` corners of the vehicle's footprint along ``states``
            (:meth:`~density_planner.risk.collision.CollisionModel.outline`), drawn in the snapshots.
    """
    grid = scene.grid
    T = states.shape[0]
    if snapshot_times is None:
        snapshot_times = list(np.round(np.linspace(0.0, (T - 1) * plan_dt, 6) / plan_dt) * plan_dt)
    snapshot_times = list(snapshot_times)
    n_snap = len(snapshot_times)
    has_cloud = samples_x is not None and samples_log_rho is not None
    roi = _region_of_interest(scene, states, samples_x if has_cloud else None)
    x0, x1, y0, y1 = roi
    aspect = (x1 - x0) / max(y1 - y0, 1e-9)
    text, colour = _verdict_line(verdict, width=170)
    layout = _PlanLayout.of(aspect, n_snap, header_lines=text.count("\n") + 1, colorbar=has_cloud)
    fig = plt.figure(figsize=layout.size)
    fig.text(0.1 / layout.size[0], 1.0 - layout.VERDICT_TOP / layout.size[1], text, color=colour, fontsize=8.5,
             va="top", ha="left")  # the verdict, coloured, over the whole width
    ax = fig.add_axes(layout.overview)
    # occupancy cropped to what each panel shows and strided for display (large maps draw fast)
    t0 = grid.t0 if scene.t_start is None else float(scene.t_start)  # on the grid's clock
    k0 = int(grid.slice_index(t0, clamp=True))
    (i0, i1, j0, j1), extent, st = _crop(grid, roi, 700)
    show_occupancy(ax, grid.probs[k0, i0:i1:st, j0:j1:st], extent, alpha=0.9)
    swept = grid.probs[k0:, i0:i1:st, j0:j1:st].amax(dim=0)
    show_occupancy(ax, swept, extent, alpha=0.3)  # swept occupancy, faint
    t_abs = (getattr(scene.road, "t_start", 0.0) if getattr(scene, "road", None) is not None else 0.0) + (
        plan_dt * np.arange(T))
    _draw_obstacle_paths(ax, scene, t_abs)
    _draw_goal(ax, scene)
    sc = None
    if samples_x is not None and samples_log_rho is not None:
        for k in range(0, T, 10):
            sc = _cloud(ax, samples_x, samples_log_rho, k, size=2.0)
    ax.plot(states[:, 0], states[:, 1], "-", color="tab:orange", lw=1.8, label=label, zorder=5)
    sx, sy = scene.start[:2]
    ax.plot(sx, sy, "o", color="tab:green", ms=7, mec="white", zorder=6, label=f"start ({scene.start[3]:.1f} m/s)")
    _mark_failures(ax, states, verdict, plan_dt)
    frame_map(ax, x0, x1, y0, y1)
    ax.set_facecolor(_OUTSIDE_MAP)
    ax.legend(loc=_emptiest_corner(states[:, :2], roi), fontsize=7, framealpha=0.8)
    fig.suptitle(title or f"{scene.name}: plan", fontsize=10, y=1.0 - layout.TITLE_TOP / layout.size[1], va="top")
    if sc is not None and layout.colorbar is not None:
        bar = fig.colorbar(sc, cax=fig.add_axes(layout.colorbar))
        bar.set_label(r"$\rho/\max\rho$ (per time)", fontsize=8)
        bar.ax.tick_params(labelsize=7)

    # snapshots: one window size for all, following the vehicle (and its sample cloud)
    ks = [min(int(round(ts / plan_dt)), T - 1) for ts in snapshot_times]
    half = 12.0
    for k in ks:
        if samples_x is not None and has_cloud and k < samples_x.shape[1]:
            dev = np.nanquantile(np.abs(samples_x[:, k, :2] - states[k, :2]), 0.98, axis=0)
            half = max(half, float(dev.max()) + 4.0)
    half = min(half, 0.5 * max(x1 - x0, y1 - y0))
    for j, (ts, k) in enumerate(zip(snapshot_times, ks)):
        a = fig.add_axes(layout.snapshots[j])
        k_time = int(round(ts / plan_dt))
        cx, cy = states[k, 0], states[k, 1]
        (i0, i1, j0, j1), extent, st = _crop(grid, (cx - half, cx + half, cy - half, cy + half), 300)
        k_slice = int(grid.slice_index(t0 + k_time * plan_dt, clamp=True))  # absolute time on the grid's clock
        show_occupancy(a, grid.probs[k_slice, i0:i1:st, j0:j1:st], extent)
        _draw_goal(a, scene, label=False)
        a.plot(states[: k + 1, 0], states[: k + 1, 1], "-", color="tab:orange", lw=1.0)
        if samples_x is not None and samples_log_rho is not None and k < samples_x.shape[1]:
            _cloud(a, samples_x, samples_log_rho, k, size=2.0)
        a.plot(states[k, 0], states[k, 1], "o", color="tab:orange", ms=3, zorder=6)
        a.set_xlim(cx - half, cx + half)
        a.set_ylim(cy - half, cy + half)
        a.set_aspect("equal")
        a.set_facecolor(_OUTSIDE_MAP)
        if body is not None and k < body.shape[0]:
            a.fill(body[k, :, 0], body[k, :, 1], facecolor="none", edgecolor="tab:orange", lw=1.0, zorder=5)
        a.set_title(f"t = {k_time * plan_dt:.1f} s" + (" (stopped)" if k < k_time else ""), fontsize=8)
        a.tick_params(labelsize=6)
        a.locator_params(nbins=4)
    return _save_laid_out(fig, path)


def _save_laid_out(fig, path: str | Path) -> Path:
    """Save a figure atomically in one draw: no 'tight' bounding-box pass (the layout already fits), and a layout
    engine (constrained layout) is executed once and frozen first (savefig would draw the figure once more to run
    it). Figures with fixed margins (no engine) are saved as they are."""
    path = Path(path)
    fmt = path.suffix.lstrip(".") or "png"
    engine = fig.get_layout_engine()
    if engine is not None:  # lay out once and freeze: savefig would otherwise draw the whole figure twice
        fig.canvas.get_renderer()
        engine.execute(fig)
        fig.set_layout_engine(None)
    _atomic(path, lambda fh: fig.savefig(fh, format=fmt))
    plt.close(fig)
    return path


def plot_plans(scene: Scene, plans: Mapping[str, np.ndarray], path: str | Path, *, title: str | None = None) -> Path:
    """Several planners' nominal trajectories ``name -> (T, >=2)`` over the time-max occupancy of one scene."""
    fig, ax = plt.subplots(figsize=(6, 8))
    show_occupancy(ax, scene.grid.max_over_time(), _extent(scene), alpha=0.85)
    for (name, states), colour in zip(plans.items(), _PLANNER_COLOURS):
        ax.plot(states[:, 0], states[:, 1], "-", color=colour, lw=1.5, label=name, zorder=4)
    _decorate(ax, scene)
    ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
    ax.set_title(title or f"{scene.name}: plans", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def _gif_palette_image():
    """A fixed 256-colour palette for plan GIFs: greys (occupancy), the density colour map, the marker colours.
    Quantising every frame to one fixed palette is fast and keeps colours stable between frames."""
    from matplotlib import colormaps
    from matplotlib.colors import to_rgb
    from PIL import Image

    colours = [(v, v, v) for v in np.linspace(0, 255, 160).round().astype(int)]
    cmap = colormaps[DENSITY_CMAP]
    colours += [tuple(int(round(255 * c)) for c in cmap(x)[:3]) for x in np.linspace(0, 1, 64)]
    for name in ("tab:orange", "tab:red", "tab:green", "tab:blue", _OUTSIDE_MAP, "#f4b183", "#f4a6a6",
                 "#a6d8a6", "#a6c8ec"):
        colours.append(tuple(int(round(255 * c)) for c in to_rgb(name)))
    colours += [(255, 255, 255)] * (256 - len(colours))
    pal = Image.new("P", (1, 1))
    pal.putpalette([c for rgb in colours[:256] for c in rgb])
    return pal


def _crop(grid, window: tuple[float, float, float, float],
          max_cells: int) -> tuple[tuple[int, int, int, int], tuple[float, float, float, float], int]:
    """Index ranges of the cells inside ``window`` and a display stride so that the longest side has at most
    ``max_cells`` cells: ``(slices (i0, i1, j0, j1), extent, stride)``."""
    x0, x1, y0, y1 = window
    (ox, oy), c = grid.origin, grid.cell_size
    _, NX, NY = grid.shape
    i0, i1 = int(np.clip(np.floor((x0 - ox) / c), 0, NX - 1)), int(np.clip(np.ceil((x1 - ox) / c) + 1, 1, NX))
    j0, j1 = int(np.clip(np.floor((y0 - oy) / c), 0, NY - 1)), int(np.clip(np.ceil((y1 - oy) / c) + 1, 1, NY))
    stride = max(1, int(np.ceil(max(i1 - i0, j1 - j0) / max_cells)))
    extent = (ox + (i0 - 0.5) * c, ox + (i1 - 0.5) * c, oy + (j0 - 0.5) * c, oy + (j1 - 0.5) * c)
    return (i0, i1, j0, j1), extent, stride


def animate_plan(
    scene: Scene,
    states: np.ndarray,
    path: str | Path,
    *,
    samples_x: np.ndarray | None = None,
    samples_log_rho: np.ndarray | None = None,
    every: int | None = None,
    plan_dt: float = 0.1,
    speed: float = 2.0,
    max_frames: int = 50,
    max_cells: int = 320,
) -> Path:
    """GIF of the occupancy slices with the density cloud and the reference so far (one frame per ``every``
    planning steps; default: 2, more on long horizons so that there are at most ``max_frames + 1`` frames), over the
    region that matters (trajectory, cloud, start, goal region; as in :func:`plot_plan`), played at ``speed`` times
    real time (2: a 10-s plan in 5 s).

    Fast: the figure is drawn once and only its data change per frame (the scene's name is drawn once, the clock
    per frame), the occupancy is cropped to the region and strided to at most ``max_cells`` cells per side for
    display, colour-mapped once, and copied into each frame's pixels through a fixed pixel -> cell map (what
    ``imshow``'s nearest-cell display draws, without resampling it per frame), and every frame is quantised to one
    fixed palette.
    """
    from PIL import Image

    grid = scene.grid
    T = states.shape[0]
    if every is None:
        every = max(2, math.ceil((T - 1) / max(int(max_frames), 1)))
    if not (isinstance(every, int) and every >= 1 and speed > 0):
        raise ValueError(f"animate_plan: every must be an integer >= 1 and speed > 0, got {every!r}, {speed!r}")
    has_cloud = samples_x is not None and samples_log_rho is not None
    window = _region_of_interest(scene, states, samples_x if has_cloud else None)
    (i0, i1, j0, j1), extent, stride = _crop(grid, window, max_cells)
    ks = list(range(0, T, every))
    t0 = grid.t0 if scene.t_start is None else float(scene.t_start)  # on the grid's clock
    frame_times = torch.as_tensor(t0 + plan_dt * np.asarray(ks, dtype=np.float64))
    frame_slice = grid.slice_index(frame_times, clamp=True).tolist()
    slices = sorted(set(frame_slice))
    sub = grid.probs[slices, i0:i1:stride, j0:j1:stride].detach().cpu().float().numpy()
    where = {s: n for n, s in enumerate(slices)}
    w, h = window[1] - window[0], window[3] - window[2]
    aspect = w / max(h, 1e-9)
    size = (6.4, float(np.clip(6.4 / aspect, 2.4, 6.4)) + 0.9) if aspect >= 1 else (
        float(np.clip(5.6 * aspect, 2.6, 5.6)) + 1.2, 5.6)
    fig = plt.figure(figsize=size, dpi=90)
    # fixed margins [in] for the tick labels, axis labels and titles (no layout engine: ~0.05 s less), the box of
    # the window's aspect centred in the rest
    left, right, bottom, top = 0.6, 0.1, 0.45, 0.25
    box_w = min(size[0] - left - right, (size[1] - bottom - top) * aspect)
    box_h = box_w / aspect
    ax = fig.add_axes(((left + 0.5 * (size[0] - left - right - box_w)) / size[0],
                       (bottom + 0.5 * (size[1] - bottom - top - box_h)) / size[1], box_w / size[0], box_h / size[1]))
    ax.set_facecolor(_OUTSIDE_MAP)
    # colour-mapped once for all frames (what imshow's Greys on [0, 1] gives), one 32-bit RGBA word per cell, rows
    # from the bottom (y up): (S, h, w)
    from matplotlib import colormaps

    sub = colormaps["Greys"](np.clip(sub, 0.0, 1.0), bytes=True).transpose(0, 2, 1, 3)
    cells = np.ascontiguousarray(sub).view(np.uint32)[..., 0]
    before = set(ax.get_children())
    _draw_goal(ax, scene, label=False)
    ax.plot(states[:, 0], states[:, 1], ":", color="tab:orange", lw=0.9)
    (done,) = ax.plot([], [], "-", color="tab:orange", lw=1.8)
    (now,) = ax.plot([], [], "o", color="tab:orange", ms=4, zorder=6)
    cloud = None
    if samples_x is not None and samples_log_rho is not None:
        cloud = ax.scatter(samples_x[:, 0, 0], samples_x[:, 0, 1], c=np.zeros(samples_x.shape[0]), s=4.0,
                           cmap=DENSITY_CMAP, vmin=0, vmax=1, linewidths=0, zorder=4)
    # in the order they were added within one zorder (as a full draw would stack them): deterministic frames
    overlays = sorted((a for a in ax.get_children() if a not in before), key=lambda a: a.get_zorder())
    ax.set_xlim(window[0], window[1])
    ax.set_ylim(window[2], window[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.tick_params(labelsize=7)
    # the scene's name and the clock over the figure's width (a tall map's narrow axes cannot hold both)
    y_text = 1.0 - 0.05 / size[1]
    fig.text(0.1 / size[0], y_text, scene.name, fontsize=9, ha="left", va="top")
    title = fig.text(1.0 - 0.1 / size[0], y_text, "t = 00.0 s", fontsize=9, ha="right", va="top")  # per frame
    # blitting: axes, ticks and labels are drawn (and laid out) once; each frame redraws only what changes
    moving = [*overlays, title]
    for a in moving:
        a.set_animated(True)
    canvas = agg_canvas(fig)
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)
    pixels = np.asarray(canvas.buffer_rgba())  # (H, W, 4), the canvas's own pixels (written below)
    rows, cols, at = _cell_map(ax, extent, cells.shape[1:], pixels.shape[0])
    words = pixels.view(np.uint32)[..., 0]
    palette = _gif_palette_image()
    frames = []
    for k, k_slice in zip(ks, frame_slice):
        canvas.restore_region(background)
        if at is not None:  # the occupancy under the overlays (all its cells opaque)
            words[at] = cells[where[k_slice]].take(rows, axis=0).take(cols, axis=1)
        done.set_data(states[: k + 1, 0], states[: k + 1, 1])
        now.set_data(states[k : k + 1, 0], states[k : k + 1, 1])
        if cloud is not None and samples_x is not None and samples_log_rho is not None and k < samples_x.shape[1]:
            rel = _rel_density(samples_log_rho[:, k])
            order = np.argsort(rel)
            cloud.set_offsets(samples_x[order, k, :2])
            cloud.set_array(rel[order])
        title.set_text(f"t = {k * plan_dt:4.1f} s")
        for a in moving:
            (ax if a is not title else fig).draw_artist(a)
        rgb = Image.frombuffer("RGBA", (pixels.shape[1], pixels.shape[0]), pixels, "raw", "RGBA", 0, 1).convert("RGB")
        frames.append(rgb.quantize(palette=palette, dither=Image.Dither.NONE))
    plt.close(fig)

    def write(fh):
        frames[0].save(fh, format="GIF", save_all=True, append_images=frames[1:],
                       duration=int(round(1000 * every * plan_dt / speed)), loop=0)

    path = Path(path)
    _atomic(path, write)
    return path


def _cell_map(ax, extent: tuple[float, float, float, float], shape: tuple[int, int], height: int
              ) -> tuple[np.ndarray, np.ndarray, tuple[slice, slice] | None]:
    """The pixels of ``ax`` (on a canvas ``height`` pixels high, rows from the top) that show an image of
    ``shape = (h, w)`` cells over ``extent`` (rows from the bottom, as ``imshow(origin="lower")``) and the cell
    each shows, that of its centre (nearest-cell display): ``(rows (n,), cols (m,), (row slice, column slice))``,
    cell ``(rows[a], cols[b])`` at pixel ``(slice rows[a], slice cols[b])``; ``None`` for the slices where the image
    lies outside the axes. Pixels whose centre is outside the axes box or the extent are left alone."""
    h, w = shape
    x0p, y0p, x1p, y1p = ax.bbox.extents  # display pixels, y up
    inv = ax.transData.inverted()
    cx = np.arange(math.floor(x0p), math.ceil(x1p)) + 0.5  # pixel centres, display coordinates
    cy = np.arange(math.floor(y0p), math.ceil(y1p)) + 0.5
    cx, cy = cx[(cx >= x0p) & (cx <= x1p)], cy[(cy >= y0p) & (cy <= y1p)]
    xd = inv.transform(np.column_stack([cx, np.full_like(cx, cy[0] if cy.size else 0.0)]))[:, 0]
    yd = inv.transform(np.column_stack([np.full_like(cy, cx[0] if cx.size else 0.0), cy]))[:, 1]
    col = np.floor((xd - extent[0]) / (extent[1] - extent[0]) * w).astype(np.int64)
    row = np.floor((yd - extent[2]) / (extent[3] - extent[2]) * h).astype(np.int64)
    okx, oky = (col >= 0) & (col < w), (row >= 0) & (row < h)
    if not okx.any() or not oky.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64), None
    px = (cx[okx] - 0.5).astype(np.int64)  # canvas columns
    py = (height - 1 - (cy[oky] - 0.5)).astype(np.int64)  # canvas rows (from the top): decreasing with y
    # the columns grow with x and the rows fall with y: each selection is one contiguous run
    cols, rows = col[okx], row[oky][::-1]
    at = (slice(int(py.min()), int(py.max()) + 1), slice(int(px.min()), int(px.max()) + 1))
    return rows, cols, at


def plot_costs(cost_history: Mapping[str, Mapping[str, Sequence[float]]], path: str | Path, *,
               weights: Mapping[str, float] | None = None, title: str | None = None) -> Path:
    """Cost curves per term and stage (one panel per stage, log scale, unweighted terms and weighted total)."""
    stages = [s for s in cost_history if cost_history[s].get("total")]
    n = max(len(stages), 1)
    fig, axes = plt.subplots(1, n, figsize=(5.2 * n, 3.8), squeeze=False)
    # fixed margins (the panels' labels have known sizes): one draw when saved; a layout engine draws twice
    fig.subplots_adjust(left=0.55 / (5.2 * n), right=1 - 0.06 / n, bottom=0.13, top=0.87, wspace=0.16)
    for ax, stage in zip(axes[0], stages):
        hist = cost_history[stage]
        for name, series in hist.items():
            values = np.asarray(series, dtype=float)
            if values.size < 2:
                continue
            style = {"lw": 2.0, "color": "black"} if name == "total" else {"lw": 1.2}
            base = name.removeprefix("reference_")  # stage 2's terms of the reference itself
            label = "total (weighted)" if name == "total" else f"J_{base[0].upper()} ({name.replace('_', ' ')})"
            if weights and name in weights:
                label += f", alpha={weights[name]:g}"
            shown = np.where(values > 0, values, np.nan)  # zero (or switched-off) terms leave gaps on a log axis
            if np.isnan(shown).all():
                label += ": 0 throughout"
            ax.plot(np.arange(values.size), shown, label=label, **style)
        ax.set_yscale("log")
        # no minor ticks on the log axis: over many decades they are ~70 tick texts per axis, each laid out per draw
        ax.yaxis.set_minor_locator(NullLocator())
        ax.yaxis.set_major_formatter(_PLAIN_NUMBER)  # "0.01", "100", "1e-05": no mathtext to lay out (~0.03 s)
        ax.set_xlabel("iteration")
        ax.set_title(stage, fontsize=9)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.suptitle((title or "cost per iteration") + " (terms unweighted; gaps: term zero or not yet switched on)",
                 fontsize=10)
    return _save_laid_out(fig, path)

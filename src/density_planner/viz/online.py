"""Figures of an online run (``density-planner drive``): the executed path, the plan being tracked and the predicted
occupancy at several replanning times (``run.png``), and an animation over every replan (``run.gif``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..environment.scene import Scene
from ..io.atomic import _atomic
from .occupancy import show_occupancy
from .plan import _OUTSIDE_MAP, _draw_goal, _geometry_patches, _region_of_interest, _save_laid_out, _verdict_line
from .style import agg_canvas, frame_map, plt

__all__ = ["plot_run", "animate_run"]


def _true_shapes(ax, scene: Scene, t: float) -> None:
    """The recorded road users' true shapes at ``t`` (ground truth, outlined)."""
    road = getattr(scene, "road", None)
    if road is None:
        return
    for poly in road.obstacle_polygons(np.array([t]))[:, 0]:
        for ring in _geometry_patches(poly):
            ax.plot(ring[:, 0], ring[:, 1], "-", color="tab:blue", lw=0.9, zorder=4)


def _panel(ax, scene: Scene, result: Any, snap: dict, *, full_path: bool = True, title: bool = True) -> None:
    """One replanning time: predicted occupancy (now, and swept over the next seconds, faint), the true shapes,
    the plan being tracked (dashed), the executed path so far (solid) and ahead (dotted)."""
    t = snap["t"]
    ax.set_facecolor(_OUTSIDE_MAP)
    show_occupancy(ax, snap["swept"], snap["extent"], alpha=0.35)
    show_occupancy(ax, snap["occupancy"], snap["extent"], alpha=0.85)
    _draw_goal(ax, scene, label=False)
    _true_shapes(ax, scene, t)
    k = int(np.searchsorted(result.times, t + 1e-9))
    xs = result.states
    if full_path:
        ax.plot(xs[:, 0], xs[:, 1], ":", color="tab:orange", lw=0.9, zorder=5)
    ax.plot(xs[:k, 0], xs[:k, 1], "-", color="tab:orange", lw=1.8, zorder=6)
    ax.plot(snap["plan"][:, 0], snap["plan"][:, 1], "--", color="tab:green", lw=1.2, zorder=5)
    ax.plot(*snap["position"], "o", color="tab:orange", ms=4, mec="white", zorder=7)
    x0, x1, y0, y1 = snap["extent"]
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)
    if title:
        rec = next((r for r in result.replans if abs(r.t - t) < 1e-6), None)
        extra = ""
        if rec is not None:
            extra = f", {rec.status}" + (f", fallback {rec.fallback}" if rec.fallback else "") + (
                ", rescued" if rec.rescue == "used" else "")
        ax.set_title(f"t = {t - result.times[0]:.1f} s{extra}", fontsize=8)


def plot_run(scene: Scene, result: Any, path: str | Path, *, n_panels: int = 4) -> Path:
    """``run.png``: overview (executed path over the scene, fallbacks and rescues marked, verdict) and ``n_panels``
    replanning times (predicted occupancy, true shapes, the plan tracked from then, the path so far)."""
    xs = result.states
    roi = _region_of_interest(scene, xs, None)
    x0, x1, y0, y1 = roi
    aspect = (x1 - x0) / max(y1 - y0, 1e-9)
    fig = plt.figure(figsize=(14.0, 7.6), layout="constrained")
    outer = fig.add_gridspec(2, 1, height_ratios=[0.06, 1])
    header = fig.add_subplot(outer[0])
    header.axis("off")
    text, colour = _verdict_line(result.verdict, width=170)
    header.text(0.0, 0.5, text, color=colour, fontsize=8.5, va="center", ha="left", transform=header.transAxes)
    ncol = max((n_panels + 1) // 2, 1)
    gs = outer[1].subgridspec(2, 1 + ncol, width_ratios=[float(np.clip(1.7 * aspect, 1.7, 3.6))] + [1] * ncol)
    ax = fig.add_subplot(gs[:, 0])
    grid = scene.grid
    from .plan import _crop

    (i0, i1, j0, j1), extent, st = _crop(grid, roi, 700)
    k0 = int(grid.slice_index(grid.t0 if scene.t_start is None else scene.t_start, clamp=True))
    show_occupancy(ax, grid.probs[k0, i0:i1:st, j0:j1:st], extent, alpha=0.9)
    ax.set_facecolor(_OUTSIDE_MAP)
    road = getattr(scene, "road", None)
    if road is not None:
        first = True
        for track in road.obstacles:
            if track.static:
                continue
            poses = track.poses_at(result.times)
            ok = np.isfinite(poses[:, 0])
            if ok.sum() >= 2:
                ax.plot(poses[ok, 0], poses[ok, 1], "-", color="tab:blue", lw=0.6, alpha=0.6, zorder=2,
                        label="road users (true paths)" if first else None)
                first = False
    _draw_goal(ax, scene)
    snaps = result.snapshots
    for s in snaps[:: max(1, len(snaps) // 12)]:
        ax.plot(s["plan"][:, 0], s["plan"][:, 1], "--", color="tab:green", lw=0.6, alpha=0.6, zorder=4)
    ax.plot([], [], "--", color="tab:green", lw=0.8, label="plans at replanning times")
    ax.plot(xs[:, 0], xs[:, 1], "-", color="tab:orange", lw=2.0, label="executed", zorder=6)
    ax.plot(xs[0, 0], xs[0, 1], "o", color="tab:green", ms=7, mec="white", zorder=7, label="start (true)")
    rescued = False
    for r in result.replans:
        k = min(int(np.searchsorted(result.times, r.t - 1e-9)), len(xs) - 1)
        if r.fallback:
            mk = "x" if r.fallback == "brake" else "s"
            ax.plot(xs[k, 0], xs[k, 1], mk, color="tab:red", ms=6, mfc="none", zorder=8)
        if r.rescue == "used":
            ax.plot(xs[k, 0], xs[k, 1], "D", color="tab:purple", ms=6, mfc="none", zorder=8)
            rescued = True
    ax.plot([], [], "s", color="tab:red", mfc="none", label="fallback: previous reference")
    ax.plot([], [], "x", color="tab:red", label="fallback: braking")
    if rescued:
        ax.plot([], [], "D", color="tab:purple", mfc="none", label="rescue replan used")
    frame_map(ax, x0, x1, y0, y1)
    ax.legend(loc="best", fontsize=7, framealpha=0.8)
    walls = [r.wall_time for r in result.replans if r.status != "initial"]
    fig.suptitle(f"{scene.name}: online ({result.prediction} prediction), {len(walls)} replans, median "
                 f"{np.median(walls) if walls else float('nan'):.2f} s", fontsize=10)
    if snaps:
        idx = np.unique(np.round(np.linspace(0, len(snaps) - 1, n_panels)).astype(int))
        # the first replan that changed course (a rescue used, a fallback) is shown: it replaces the nearest panel
        events = [r.t for r in result.replans if r.status != "initial"
                  and (r.fallback or r.rescue == "used")]
        if events and len(idx) > 1:
            i_ev = int(np.argmin([abs(sn["t"] - events[0]) for sn in snaps]))
            if i_ev not in idx:
                near = int(np.argmin(np.abs(idx[1:] - i_ev))) + 1  # never the first panel (the start)
                idx[near] = i_ev
                idx = np.unique(idx)
        for j, i in enumerate(idx):
            a = fig.add_subplot(gs[j // ncol, 1 + j % ncol])
            _panel(a, scene, result, snaps[i])
    return _save_laid_out(fig, path)


def animate_run(scene: Scene, result: Any, path: str | Path, *, fps: int = 4) -> Path:
    """``run.gif``: one frame per replan (the panel of :func:`plot_run`)."""
    from PIL import Image

    frames = []
    fig, ax = plt.subplots(figsize=(5.6, 5.6), dpi=80, layout="constrained")
    for snap in result.snapshots:
        ax.clear()
        _panel(ax, scene, result, snap, full_path=False)
        ax.set_title(f"{scene.name}  " + ax.get_title(), fontsize=8)
        canvas = agg_canvas(fig)
        canvas.draw()
        rgb = np.asarray(canvas.buffer_rgba())[..., :3]
        frames.append(Image.fromarray(rgb).quantize(colors=128, dither=Image.Dither.NONE))
    plt.close(fig)
    if not frames:
        raise ValueError("the run has no snapshots to animate (drive(..., keep_snapshots=True))")

    def write(fh):
        frames[0].save(fh, format="GIF", save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0)

    path = Path(path)
    _atomic(path, write)
    return path

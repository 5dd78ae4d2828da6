"""Figures of scenes: the time-max occupancy map with start and goal, and a GIF of the slices over time."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from density_planner.environment.scene import Scene
from density_planner.io.atomic import _atomic

from .style import OCCUPANCY_CMAP, agg_canvas, plt, save_figure

__all__ = ["plot_occupancy", "animate_occupancy", "show_occupancy"]

#: longest side [cells] of the image drawn per GIF frame (larger grids are strided for display only)
_GIF_MAX_CELLS = 400


def _gif_palette():
    """A fixed 256-colour palette: 240 greys plus the marker colours (an adaptive palette drops small
    markers)."""
    from matplotlib.colors import to_rgb
    from PIL import Image

    colours = [(v, v, v) for v in np.linspace(0, 255, 240).round().astype(int)]
    for name in (
        "tab:green",
        "tab:red",
        "tab:blue",
        "tab:orange",
        "tab:purple",
        "#a6d8a6",
        "#f4a6a6",
        "#a6c8ec",
    ):
        colours.append(tuple(int(round(255 * c)) for c in to_rgb(name)))
    colours += [(0, 0, 0)] * (256 - len(colours))
    pal = Image.new("P", (1, 1))
    pal.putpalette([c for rgb in colours for c in rgb])
    return pal


def _extent(scene: Scene) -> tuple[float, float, float, float]:
    xmin, xmax, ymin, ymax = scene.grid.bounds
    h = scene.grid.cell_size / 2
    return (xmin - h, xmax + h, ymin - h, ymax + h)


def show_occupancy(ax, probs, extent: tuple[float, float, float, float], **kwargs):
    """Draw occupancy probabilities ``probs (X, Y)`` (array or tensor, index order x, y) on ``ax`` over
    ``extent = (xmin, xmax, ymin, ymax)`` with the package's occupancy colours; returns the image."""
    if hasattr(probs, "detach"):
        probs = probs.detach().cpu().float().numpy()
    return ax.imshow(np.asarray(probs).T, origin="lower", extent=extent, cmap=OCCUPANCY_CMAP, vmin=0.0, vmax=1.0,
                     interpolation="nearest", **kwargs)


def _figsize(scene: Scene, width: float = 6.0) -> tuple[float, float]:
    xmin, xmax, ymin, ymax = scene.grid.bounds
    aspect = (ymax - ymin) / max(xmax - xmin, 1e-9)
    height = float(np.clip(width * aspect, 3.0, 7.5))
    return (width if aspect <= 1.5 else max(height / aspect + 1.6, 4.0), height)


def _outline(geom) -> tuple[np.ndarray, np.ndarray]:
    """x, y of all boundary rings of a shapely geometry, separated by NaN (one ``plot`` call)."""
    import shapely

    parts = shapely.get_parts(shapely.get_parts(shapely.boundary(geom)))
    chunks = []
    for line in parts:
        xy = shapely.get_coordinates(line)
        chunks.extend([xy, np.full((1, 2), np.nan)])
    xy = np.concatenate(chunks) if chunks else np.empty((0, 2))
    return xy[:, 0], xy[:, 1]


def _decorate(ax, scene: Scene) -> None:
    sx, sy, th, v = scene.start[:4]
    gx, gy = scene.goal
    bx0, bx1, by0, by1 = scene.planning_box
    ax.plot(
        [bx0, bx1, bx1, bx0, bx0],
        [by0, by0, by1, by1, by0],
        ls="--",
        lw=0.8,
        color="tab:blue",
        label="planning box",
    )
    span = max(scene.grid.bounds[1] - scene.grid.bounds[0], scene.grid.bounds[3] - scene.grid.bounds[2])
    arrow = 0.06 * span
    ax.annotate(
        "",
        xy=(sx + arrow * math.cos(th), sy + arrow * math.sin(th)),
        xytext=(sx, sy),
        arrowprops={"arrowstyle": "->", "color": "tab:green", "lw": 1.5},
    )
    road = getattr(scene, "road", None)
    if road is not None:  # exact geometry of road scenes: road edges and the goal region (no autoscaling)
        if road.drivable is not None:
            ax.plot(*_outline(road.drivable), color="tab:cyan", lw=0.6, label="road edge")
        goal = road.goal
        if goal.shapes is not None:
            t0, t1 = goal.time_interval
            ax.plot(*_outline(goal.shapes), color="tab:red", lw=1.2, label=f"goal region ({t0:g}-{t1:g} s)",
                    zorder=4)
    ax.plot(sx, sy, "o", color="tab:green", ms=7, mec="white", label=f"start ({v:.1f} m/s)")
    ax.plot(gx, gy, "*", color="tab:red", ms=12, mec="white", label="goal", zorder=3)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ext = _extent(scene)
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])


def plot_occupancy(scene: Scene, path: str | Path, *, title: str | None = None) -> Path:
    """Occupancy of ``scene`` at t0 (left) and its maximum over all slices (right), with start (and heading),
    goal and planning box; saved atomically to ``path`` (format from the suffix)."""
    grid = scene.grid
    T = grid.n_slices
    panels = [
        (grid.slice(0), f"t = {grid.t0:g} s", r"$P_{occ}$"),
        (
            grid.max_over_time(),
            f"max over {T} slices ({grid.t0:g}-{grid.t0 + (T - 1) * grid.dt:g} s)",
            r"$\max_t\, P_{occ}$",
        ),
    ]
    w, h = _figsize(scene)
    fig, axes = plt.subplots(1, 2, figsize=(2 * w, h))
    for ax, (data, label, bar) in zip(axes, panels, strict=True):
        im = show_occupancy(ax, data, _extent(scene))
        _decorate(ax, scene)
        ax.set_title(label)
        fig.colorbar(im, ax=ax, label=bar, shrink=0.8)
    axes[1].legend(loc="upper right", fontsize=7, framealpha=0.8)
    fig.suptitle(title or scene.name)
    fig.tight_layout()
    return save_figure(fig, path)


def animate_occupancy(
    scene: Scene,
    path: str | Path,
    *,
    every: int = 2,
    frame_ms: int = 100,
    title: str | None = None,
) -> Path:
    """GIF of every ``every``-th slice of ``scene`` (start and goal marked), written atomically with Pillow.

    Grids larger than 400 cells along a side are strided for display (the file stays small, about 1-3 MB).
    """
    from PIL import Image

    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    grid = scene.grid
    probs = grid.probs.detach().cpu().float().numpy()
    stride = max(1, math.ceil(max(probs.shape[1:]) / _GIF_MAX_CELLS))
    shown = probs[:, ::stride, ::stride]
    fig, ax = plt.subplots(figsize=_figsize(scene, width=5.0), dpi=80)
    im = show_occupancy(ax, shown[0], _extent(scene))
    _decorate(ax, scene)
    fig.colorbar(im, ax=ax, label=r"$P_{occ}$", shrink=0.8)
    label = title or scene.name
    text = ax.set_title(label)
    fig.tight_layout()
    palette = _gif_palette()
    frames = []
    times = grid.times.numpy()
    for k in range(0, grid.n_slices, every):
        im.set_data(shown[k].T)
        text.set_text(f"{label}: t = {times[k]:.1f} s")
        canvas = agg_canvas(fig)
        canvas.draw()
        rgba = np.asarray(canvas.buffer_rgba())
        frames.append(
            Image.fromarray(rgba[..., :3].copy()).quantize(palette=palette, dither=Image.Dither.NONE)
        )
    plt.close(fig)
    if not frames:  # pragma: no cover - n_slices >= 1 always gives a frame
        raise ValueError("no frames to animate")
    return _atomic(
        Path(path),
        lambda fh: frames[0].save(
            fh,
            format="GIF",
            save_all=True,
            append_images=frames[1:],
            duration=frame_ms,
            loop=0,
            optimize=False,
        ),
    )

"""Figures of plans: the scene with the planned reference and the density-weighted sample cloud, an animation
over time, and the cost curves of the optimisation."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..environment.scene import Scene
from ..io.atomic import _atomic
from .occupancy import _decorate, _extent, show_occupancy
from .style import DENSITY_CMAP, plt, save_figure

__all__ = ["plot_plan", "animate_plan", "plot_costs", "plot_plans"]

_PLANNER_COLOURS = ("tab:orange", "tab:blue", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan",
                    "tab:red", "tab:green", "black")


def _rel_density(log_rho_k: np.ndarray) -> np.ndarray:
    return np.exp(log_rho_k - log_rho_k.max())


def _cloud(ax, x: np.ndarray, log_rho: np.ndarray, k: int, size: float = 4.0):
    rel = _rel_density(log_rho[:, k])
    order = np.argsort(rel)
    return ax.scatter(x[order, k, 0], x[order, k, 1], c=rel[order], s=size, cmap=DENSITY_CMAP, vmin=0, vmax=1,
                      linewidths=0, zorder=3)


def plot_plan(
    scene: Scene,
    states: np.ndarray,
    path: str | Path,
    *,
    samples_x: np.ndarray | None = None,
    samples_log_rho: np.ndarray | None = None,
    title: str | None = None,
    snapshot_times: Sequence[float] = (0.0, 2.5, 5.0, 7.5, 10.0),
    plan_dt: float = 0.1,
    label: str = "reference",
) -> Path:
    """Plan over the time-max occupancy (left) and occupancy snapshots with the sample cloud (right).

    Args:
        states: ``(T, nx)`` planned states on the planning grid (a reference, or an executed trajectory that may
            stop early: later snapshots then show where it stopped).
        label: legend label of ``states``.
        samples_x: ``(N, T, nx)`` predicted sample trajectories; samples_log_rho: ``(N, T)``.
    """
    grid = scene.grid
    n_snap = len(snapshot_times)
    ncol = (n_snap + 1) // 2
    x0, x1, y0, y1 = _extent(scene)
    aspect = (x1 - x0) / max(y1 - y0, 1e-9)
    if aspect > 1.3:  # wide map (e.g. a recorded intersection): overview on top, snapshots in two rows below
        width = 13.0
        row = width / ncol / aspect + 0.6
        fig = plt.figure(figsize=(width, width / aspect + 0.9 + 2 * row))
        gs = fig.add_gridspec(3, ncol, height_ratios=[width / aspect + 0.9, row, row])
        ax = fig.add_subplot(gs[0, :])

        def snapshot_cell(j: int):
            return gs[1 + j // ncol, j % ncol]
    else:  # tall or square map: overview on the left, snapshots in two rows on the right
        fig = plt.figure(figsize=(4.2 + 2.3 * ncol, 7.2))
        gs = fig.add_gridspec(2, 1 + ncol, width_ratios=[1.8] + [1] * ncol)
        ax = fig.add_subplot(gs[:, 0])

        def snapshot_cell(j: int):
            return gs[j // ncol, 1 + j % ncol]
    show_occupancy(ax, grid.max_over_time(), _extent(scene), alpha=0.85)
    sc = None
    if samples_x is not None and samples_log_rho is not None:
        for k in range(0, states.shape[0], 10):
            sc = _cloud(ax, samples_x, samples_log_rho, k, size=2.0)
    ax.plot(states[:, 0], states[:, 1], "-", color="tab:orange", lw=1.6, label=label, zorder=4)
    _decorate(ax, scene)
    ax.legend(loc="upper right", fontsize=7, framealpha=0.85)
    ax.set_title(title or f"{scene.name}: plan", fontsize=9)
    if sc is not None:
        fig.colorbar(sc, ax=ax, label=r"$\rho/\max\rho$ (per time)", shrink=0.6, pad=0.02)

    for j, ts in enumerate(snapshot_times):
        k_time = int(round(ts / plan_dt))
        if scene.t_start + k_time * plan_dt > grid.t_end + 1e-9:
            continue
        k = min(k_time, states.shape[0] - 1)  # an executed trajectory that stopped early stays where it stopped
        a = fig.add_subplot(snapshot_cell(j))
        show_occupancy(a, grid.slice(int(grid.slice_index(scene.t_start + k_time * plan_dt, clamp=True))),
                       _extent(scene))
        a.plot(states[: k + 1, 0], states[: k + 1, 1], "-", color="tab:orange", lw=1.0)
        if samples_x is not None and samples_log_rho is not None and k < samples_x.shape[1]:
            _cloud(a, samples_x, samples_log_rho, k, size=2.0)
        a.plot(*scene.goal, "*", color="tab:red", ms=8)
        a.plot(states[k, 0], states[k, 1], "o", color="tab:orange", ms=3)
        a.set_title(f"t = {k_time * plan_dt:.1f} s" + (" (stopped)" if k < k_time else ""), fontsize=8)
        a.tick_params(labelsize=6)
        a.set_aspect("equal")
    fig.tight_layout()
    return save_figure(fig, path)


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


def animate_plan(
    scene: Scene,
    states: np.ndarray,
    path: str | Path,
    *,
    samples_x: np.ndarray | None = None,
    samples_log_rho: np.ndarray | None = None,
    every: int = 2,
    plan_dt: float = 0.1,
    fps: int = 10,
) -> Path:
    """GIF of the occupancy slices with the density cloud and the reference so far (one frame per ``every``
    planning steps)."""
    from PIL import Image

    grid = scene.grid
    frames = []
    fig, ax = plt.subplots(figsize=(4.6, 6.2), dpi=72)
    for k in range(0, states.shape[0], every):
        ax.clear()
        show_occupancy(ax, grid.slice(int(grid.slice_index(scene.t_start + k * plan_dt, clamp=True))),
                       _extent(scene))
        ax.plot(states[:, 0], states[:, 1], ":", color="tab:orange", lw=0.8)
        ax.plot(states[: k + 1, 0], states[: k + 1, 1], "-", color="tab:orange", lw=1.5)
        if samples_x is not None and samples_log_rho is not None:
            _cloud(ax, samples_x, samples_log_rho, k, size=3.0)
        ax.plot(*scene.goal, "*", color="tab:red", ms=10)
        ax.set_title(f"{scene.name}  t = {k * plan_dt:4.1f} s", fontsize=9)
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_aspect("equal")
        fig.canvas.draw()
        rgba = np.asarray(fig.canvas.buffer_rgba())
        frames.append(Image.fromarray(rgba[..., :3]).quantize(colors=128, method=Image.Quantize.MEDIANCUT))
    plt.close(fig)

    def write(fh):
        frames[0].save(fh, format="GIF", save_all=True, append_images=frames[1:], duration=int(1000 / fps), loop=0,
                       optimize=True)

    path = Path(path)
    _atomic(path, write)
    return path


def plot_costs(cost_history: Mapping[str, Mapping[str, Sequence[float]]], path: str | Path, *,
               weights: Mapping[str, float] | None = None, title: str | None = None) -> Path:
    """Cost curves per term and stage (one panel per stage, log scale, unweighted terms and weighted total)."""
    stages = [s for s in cost_history if cost_history[s].get("total")]
    fig, axes = plt.subplots(1, max(len(stages), 1), figsize=(5.2 * max(len(stages), 1), 3.8), squeeze=False)
    for ax, stage in zip(axes[0], stages):
        hist = cost_history[stage]
        for name, values in hist.items():
            values = np.asarray(values, dtype=float)
            if values.size < 2:
                continue
            style = {"lw": 2.0, "color": "black"} if name == "total" else {"lw": 1.2}
            label = "total (weighted)" if name == "total" else f"J_{name[0].upper()} ({name})"
            if weights and name in weights:
                label += f", alpha={weights[name]:g}"
            shown = np.where(values > 0, values, np.nan)  # zero (or switched-off) terms leave gaps on a log axis
            if np.isnan(shown).all():
                label += ": 0 throughout"
            ax.plot(np.arange(values.size), shown, label=label, **style)
        ax.set_yscale("log")
        ax.set_xlabel("iteration")
        ax.set_title(stage, fontsize=9)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.suptitle((title or "cost per iteration") + " (terms unweighted; gaps: term zero or not yet switched on)",
                 fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)

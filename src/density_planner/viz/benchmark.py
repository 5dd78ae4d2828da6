"""Figures of a benchmark, drawn from its summary rows and records only (like the paper's Figs. of §V).

* one bar chart per metric and setting (failure rate, CRI, GCI, ICI, offline time, online time per step) and one
  overview with all six panels;
* per environment, the executed trajectories of every method over the time-max occupancy map.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .occupancy import show_occupancy
from .style import plt, save_figure

__all__ = ["BAR_METRICS", "planner_colour", "plot_metric_bars", "plot_summary", "plot_env_trajectories",
           "write_figures"]

#: metric -> (title, axis label, scale, log axis)
BAR_METRICS: dict[str, tuple[str, str, float, bool]] = {
    "failure_rate": ("Failure rate", "failure rate [%]", 100.0, False),
    "cri": ("Collision risk increase (CRI)", "CRI (J_C)", 1.0, False),
    "gci": ("Goal cost increase (GCI)", "GCI [m²]", 1.0, False),
    "ici": ("Input cost increase (ICI)", "ICI", 1.0, False),
    "offline_time": ("Offline planning time", "time [s]", 1.0, True),
    "online_time": ("Online time per 0.1-s step", "time [ms]", 1e3, True),
}

#: colours of planners whose registration names none (picked from the name)
_EXTRA_COLOURS = ("tab:pink", "tab:gray", "gold", "navy")


def planner_colour(planner: str) -> str:
    """The planner's colour in figures: its registration's, else one of :data:`_EXTRA_COLOURS` picked from the
    name."""
    from ..planners.registry import planner_info

    colour = planner_info(planner, default=True).colour
    return colour or _EXTRA_COLOURS[sum(map(ord, planner)) % len(_EXTRA_COLOURS)]


def _short(v: float) -> str:
    """Compact bar label: 160, 12, 3.4, 0.91, 0.0039."""
    a = abs(v)
    if a == 0:
        return "0"
    if a >= 1e5 or a < 1e-3:
        return f"{v:.0e}"
    if a >= 10:
        return f"{v:.0f}"
    return f"{v:.2g}"


def _bars(ax, rows: Sequence[Mapping[str, Any]], metric: str, *, annotate: bool = True) -> None:
    title, label, scale, log = BAR_METRICS[metric]
    names = [r["method"] for r in rows]
    values = [r.get(metric) for r in rows]
    vals = np.array([np.nan if v is None else float(v) * scale for v in values], dtype=float)
    x = np.arange(len(rows))
    finite = np.isfinite(vals)
    positive = vals[finite & (vals > 0)]
    floor = positive.min() / 3 if positive.size else 1e-3
    heights = np.where(finite, np.maximum(vals, floor), np.nan) if log else vals
    for i, r in enumerate(rows):
        biased = r.get("variant") == "biased"
        h = heights[i]
        drawn = np.isfinite(h) and not (log and vals[i] <= 0)
        ax.bar(x[i], h if drawn else 0, color=planner_colour(r["planner"]), alpha=0.55 if biased else 0.95,
               hatch="//" if biased else None, edgecolor="black", linewidth=0.5)
        if annotate:
            text = "n/a" if not finite[i] else (f"{vals[i]:.0f}" if metric == "failure_rate" else _short(vals[i]))
            y = h if drawn else (floor if log else 0)
            ax.annotate(text, (x[i], y), textcoords="offset points", xytext=(0, 2), ha="center", va="bottom",
                        fontsize=6.5)
    if log and positive.size:
        ax.set_yscale("log")
        ax.set_ylim(floor / 1.5, positive.max() * 4)
    elif log:
        ax.set_ylim(0, 1)
    elif metric == "failure_rate":
        ax.set_ylim(0, 110)
    else:
        top = np.nanmax(vals) if finite.any() else 1.0
        ax.set_ylim(0, (top if top > 0 else 1.0) * 1.18)
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=45 if len(rows) > 6 else 0, ha="right" if len(rows) > 6 else "center")
    ax.set_ylabel(label)
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)


def plot_metric_bars(rows: Sequence[Mapping[str, Any]], metric: str, path: str | Path, *,
                     title: str | None = None) -> Path:
    """Bar chart of one summary metric (``failure_rate``, ``cri``, ``gci``, ``ici``, ``offline_time``,
    ``online_time``) per method; biased-measurement variants hatched."""
    if metric not in BAR_METRICS:
        raise ValueError(f"unknown metric {metric!r}; valid choices: {', '.join(BAR_METRICS)}")
    fig, ax = plt.subplots(figsize=(max(3.2, 0.45 * len(rows) + 1.5), 3.0))
    _bars(ax, rows, metric)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_summary(rows: Sequence[Mapping[str, Any]], path: str | Path, *, title: str | None = None) -> Path:
    """All six paper metrics of one setting in a 2 x 3 panel."""
    width = max(3.2, 0.42 * len(rows) + 1.4)
    fig, axes = plt.subplots(2, 3, figsize=(3 * width, 6.4))
    for ax, metric in zip(axes.ravel(), BAR_METRICS):
        _bars(ax, rows, metric)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_env_trajectories(
    scene_map: Mapping[str, Any] | None,
    trajectories: Mapping[str, tuple[str, bool, np.ndarray]],
    path: str | Path,
    *,
    references: Mapping[str, np.ndarray] | None = None,
    start: Sequence[float] | None = None,
    goal: Sequence[float] | None = None,
    title: str | None = None,
) -> Path:
    """Executed trajectories ``label -> (planner, biased, states (T, >=2))`` of one environment over its time-max
    occupancy (``scene_map`` from the records; plain axes without it), references dashed."""
    fig, ax = plt.subplots(figsize=(6.2, 7.0))
    if scene_map is not None:
        occ = np.asarray(scene_map["occupancy_u8"], dtype=float) / 255.0
        ox, oy = (float(v) for v in scene_map["origin"])
        h = float(scene_map["cell_size"])
        nx, ny = occ.shape
        extent = (ox - h / 2, ox + (nx - 0.5) * h, oy - h / 2, oy + (ny - 0.5) * h)
        show_occupancy(ax, occ, extent, alpha=0.85)
        bx0, bx1, by0, by1 = (float(v) for v in scene_map["planning_box"])
        ax.plot([bx0, bx1, bx1, bx0, bx0], [by0, by0, by1, by1, by0], ls="--", lw=0.7, color="tab:blue", alpha=0.6)
        start = start if start is not None else scene_map["start"]
        goal = goal if goal is not None else scene_map["goal"]
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
    for label, ref in (references or {}).items():
        ax.plot(ref[:, 0], ref[:, 1], ls=":", lw=1.0, color="black", alpha=0.7, label=label, zorder=3)
    for label, (planner, biased, states) in trajectories.items():
        ax.plot(states[:, 0], states[:, 1], ls="--" if biased else "-", lw=1.4, color=planner_colour(planner),
                label=label, zorder=4)
        ax.plot(states[-1, 0], states[-1, 1], "o", ms=3, color=planner_colour(planner), zorder=5)
    if start is not None:
        ax.plot(float(start[0]), float(start[1]), "o", color="tab:green", ms=7, mec="white", label="start", zorder=6)
    if goal is not None:
        ax.plot(float(goal[0]), float(goal[1]), "*", color="tab:red", ms=13, mec="white", label="goal", zorder=6)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal")
    ax.legend(loc="best", fontsize=6.5, framealpha=0.85, ncol=2)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def write_figures(out: str | Path, rows: Sequence[Mapping[str, Any]], records: Sequence[Mapping[str, Any]], *,
                  plot_envs: int = 3) -> list[Path]:
    """All figures of a benchmark directory into ``DIR/figures``: per setting the six bar charts and the overview,
    and the trajectories of the first ``plot_envs`` environments."""
    from ..evaluation.records import load_scene_map
    from ..evaluation.report import method_label

    out = Path(out)
    fig_dir = out / "figures"
    paths = []
    settings: list[str] = []
    for r in rows:
        if r["setting"] not in settings:
            settings.append(r["setting"])
    for setting in settings:
        srows = [r for r in rows if r["setting"] == setting]
        for metric in BAR_METRICS:
            paths.append(plot_metric_bars(srows, metric, fig_dir / f"{setting}_{metric}.png",
                                          title=f"{setting}: {BAR_METRICS[metric][0]}"))
        n_envs = len({r["env"] for r in records if r["setting"] == setting})
        paths.append(plot_summary(srows, fig_dir / f"{setting}_summary.png",
                                  title=f"{setting} ({n_envs} environments)"))
        envs: list[str] = []
        for r in records:
            if r["setting"] == setting and r["env"] not in envs:
                envs.append(r["env"])
        for env in envs[: max(plot_envs, 0)]:
            trajs: dict[str, tuple[str, bool, np.ndarray]] = {}
            refs: dict[str, np.ndarray] = {}
            for r in records:
                if r["setting"] != setting or r["env"] != env:
                    continue
                label = method_label(r["planner"], r["variant"])
                if r.get("failed"):
                    label += " ✗"
                if r.get("trajectory"):
                    trajs[label] = (r["planner"], r["variant"] == "biased", np.asarray(r["trajectory"], dtype=float))
                ref_label = f"{method_label(r['planner'], 'unbiased')} reference"
                if r.get("reference") and ref_label not in refs:
                    refs[ref_label] = np.asarray(r["reference"], dtype=float)
            if not trajs:
                continue
            smap = load_scene_map(out, setting, env)
            # the ablation scores the planned references from the mean start, the other settings closed loops
            what = "planned references" if setting == "ablation" else "executed trajectories"
            paths.append(plot_env_trajectories(smap, trajs, fig_dir / f"plans_{setting}_{env}.png", references=refs,
                                               title=f"{setting} / {env}: {what} (✗ = failed)"))
    return paths

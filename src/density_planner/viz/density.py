"""Figures of propagated densities: sample clouds coloured by density over the reference."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .style import DENSITY_CMAP, plt, save_figure

__all__ = ["plot_density_snapshots", "plot_density_errors", "plot_density_heatmaps", "binned_density"]


def _relative_density(log_rho_k: np.ndarray) -> np.ndarray:
    return np.exp(log_rho_k - log_rho_k.max())


def plot_density_snapshots(
    t: np.ndarray,
    x: np.ndarray,
    log_rho: np.ndarray,
    x_ref: np.ndarray,
    path: str | Path,
    *,
    times: Sequence[float] = (0.0, 2.0, 4.0, 6.0, 8.0, 10.0),
    title: str | None = None,
) -> Path:
    """Overview of the sample clouds along the reference, zoomed snapshots, and error/density growth over time.

    Colours are the density relative to its maximum at the same time, ``rho / max rho``.

    Args:
        t: ``(T,)`` times; x: ``(N, T, nx)`` states; log_rho: ``(N, T)``; x_ref: ``(T, nx)`` reference states.
    """
    t = np.asarray(t)
    idx = [int(np.argmin(np.abs(t - s))) for s in times if s <= t[-1] + 1e-9][:6]
    fig = plt.figure(figsize=(13, 8.5))
    gs = fig.add_gridspec(3, 4, height_ratios=[1, 1, 0.8], width_ratios=[1.25, 1, 1, 1])
    ax = fig.add_subplot(gs[0:2, 0])
    ax.plot(x_ref[:, 0], x_ref[:, 1], "k-", lw=1.0, label="reference", zorder=1)
    sc = None
    for k in idx:
        rel = _relative_density(log_rho[:, k])
        order = np.argsort(rel)
        sc = ax.scatter(x[order, k, 0], x[order, k, 1], c=rel[order], s=3, cmap=DENSITY_CMAP, vmin=0, vmax=1,
                        zorder=2)
    ax.plot(x_ref[0, 0], x_ref[0, 1], "o", color="tab:green", ms=6, label="reference start", zorder=3)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("$p_x$ [m]")
    ax.set_ylabel("$p_y$ [m]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title or "closed-loop samples coloured by density")

    for j, k in enumerate(idx):
        a = fig.add_subplot(gs[j // 3, 1 + j % 3])
        rel = _relative_density(log_rho[:, k])
        order = np.argsort(rel)
        a.scatter(x[order, k, 0], x[order, k, 1], c=rel[order], s=6, cmap=DENSITY_CMAP, vmin=0, vmax=1)
        a.plot(x_ref[k, 0], x_ref[k, 1], "r+", ms=10, mew=1.5, label="reference")
        lo = np.percentile(x[:, k, :2], 1, axis=0)
        hi = np.percentile(x[:, k, :2], 99, axis=0)
        c = 0.5 * (lo + hi)
        half = max(0.5 * float(np.max(hi - lo)) * 1.15, 0.05)
        a.set_xlim(c[0] - half, c[0] + half)
        a.set_ylim(c[1] - half, c[1] + half)
        a.set_aspect("equal")
        a.set_title(f"t = {t[k]:.1f} s", fontsize=9)
        a.tick_params(labelsize=7)
        if j == 0:
            a.legend(loc="upper left", fontsize=7)
    if sc is not None:
        fig.colorbar(sc, ax=fig.axes[1:], label=r"$\rho / \max\rho$ (per time)", shrink=0.6)

    ax2 = fig.add_subplot(gs[2, :])
    err = np.linalg.norm(x[:, :, :2] - x_ref[None, :, :2], axis=-1)
    ax2.fill_between(t, np.percentile(err, 5, axis=0), np.percentile(err, 95, axis=0), alpha=0.3,
                     label="5-95 % position error")
    ax2.plot(t, np.median(err, axis=0), label="median position error")
    ax2.set_xlabel("t [s]")
    ax2.set_ylabel("tracking error [m]")
    ax3 = ax2.twinx()
    ax3.plot(t, np.median(log_rho - log_rho[:, :1], axis=0), "C3--", label=r"median $\log\rho(t) - \log\rho_0$")
    ax3.set_ylabel(r"$\log\rho(t) - \log\rho_0$", color="C3")
    h2, l2 = ax2.get_legend_handles_labels()
    h3, l3 = ax3.get_legend_handles_labels()
    ax2.legend(h2 + h3, l2 + l3, loc="center right", fontsize=8)
    ax2.set_title("tracking error and density growth (contraction concentrates the density)")
    return save_figure(fig, path)


def plot_density_errors(summaries: Mapping[str, dict], path: str | Path, *, title: str | None = None) -> Path:
    """Median and 95th percentile of the position and log-density errors over time, one colour per predictor.

    ``summaries[name]`` is :meth:`density_planner.density.validation.DensityComparison.summary`.
    """
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    keys = [("position_error_m", "position error [m]"),
            ("log_density_abs_error", r"$|\Delta \log\rho|$"),
            ("log_density_relative_abs_error", r"$|\Delta \log\rho - \overline{\Delta \log\rho}|$ (mean over samples)")]
    for c, (name, s) in enumerate(summaries.items()):
        t = np.asarray(s["t"])
        for ax, (key, label) in zip(axes, keys):
            pt = s[key]["per_time"]
            ax.plot(t, pt["median"], color=f"C{c}", label=f"{name}: median")
            ax.plot(t, pt["p95"], color=f"C{c}", ls="--", label=f"{name}: 95th percentile")
            ax.set_xlabel("t [s]")
            ax.set_ylabel(label)
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
    axes[0].set_title("position error vs exact Liouville")
    axes[1].set_title("log-density error vs exact Liouville")
    axes[2].set_title("log-density error relative to the other samples")
    axes[0].legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


def binned_density(xy: np.ndarray, log_rho: np.ndarray, edges_x: np.ndarray, edges_y: np.ndarray) -> np.ndarray:
    """The paper's occupancy of the ego vehicle (§IV-B): the densities of the samples falling into each cell are
    averaged, and the cell values are normalised to sum one over the plane. Returns ``(len(edges_x) - 1,
    len(edges_y) - 1)``."""
    w = np.exp(log_rho - np.max(log_rho))
    total, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=(edges_x, edges_y), weights=w)
    count, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=(edges_x, edges_y))
    mean = np.divide(total, count, out=np.zeros_like(total), where=count > 0)
    s = mean.sum()
    return mean / s if s > 0 else mean


def plot_density_heatmaps(
    t: np.ndarray,
    clouds: Mapping[str, tuple[np.ndarray, np.ndarray]],
    x_ref: np.ndarray,
    path: str | Path,
    *,
    times: Sequence[float] = (0.5, 4.0, 10.0),
    bins: int = 40,
    title: str | None = None,
) -> Path:
    """Paper-style figure ("Performance of the density NN"): x-y density maps of one sample cloud per predictor
    (rows) at a few times (columns), same cells and colour scale within a column.

    Args:
        t: ``(T,)`` times; clouds: name -> ``(x (N, T, >=2), log_rho (N, T))``; x_ref: ``(T, >=2)`` reference.
    """
    names = list(clouds)
    idx = [int(np.argmin(np.abs(np.asarray(t) - s))) for s in times]
    fig, axes = plt.subplots(len(names), len(idx), figsize=(4.4 * len(idx), 3.6 * len(names)), squeeze=False,
                             layout="constrained")
    for j, k in enumerate(idx):
        pts = np.concatenate([clouds[n][0][:, k, :2] for n in names])
        lo = np.percentile(pts, 1.0, axis=0)
        hi = np.percentile(pts, 99.0, axis=0)
        c = 0.5 * (lo + hi)
        half = max(0.5 * float(np.max(hi - lo)) * 1.1, 0.05)
        ex = np.linspace(c[0] - half, c[0] + half, bins + 1)
        ey = np.linspace(c[1] - half, c[1] + half, bins + 1)
        maps = [binned_density(clouds[n][0][:, k, :2], clouds[n][1][:, k], ex, ey) for n in names]
        vmax = max(float(m.max()) for m in maps) or 1.0
        for i, (n, m) in enumerate(zip(names, maps)):
            ax = axes[i, j]
            im = ax.imshow(m.T, extent=(ex[0], ex[-1], ey[0], ey[-1]), origin="lower", cmap=DENSITY_CMAP, vmin=0,
                           vmax=vmax, interpolation="nearest")
            ax.plot(x_ref[k, 0], x_ref[k, 1], "r+", ms=10, mew=1.5)
            ax.set_title(f"{n}, t = {t[k]:.1f} s", fontsize=9)
            ax.set_xlabel("$p_x$ [m]")
            ax.set_ylabel("$p_y$ [m]")
            ax.tick_params(labelsize=7)
        fig.colorbar(im, ax=list(axes[:, j]), location="bottom", shrink=0.8, aspect=30, label="$P_{ego}$ per cell")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)

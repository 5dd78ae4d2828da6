"""Figures of propagated densities: sample clouds coloured by density over the reference."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .style import DENSITY_CMAP, plt, save_figure

__all__ = ["plot_density_snapshots"]


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
    """Sample positions at several ``times``, coloured by their density relative to the maximum at that time.

    Args:
        t: ``(T,)`` times; x: ``(N, T, nx)`` states; log_rho: ``(N, T)``; x_ref: ``(T, nx)`` reference states.
    """
    t = np.asarray(t)
    idx = [int(np.argmin(np.abs(t - s))) for s in times if s <= t[-1] + 1e-9]
    fig, axes = plt.subplots(1, 2, figsize=(11, 5), gridspec_kw={"width_ratios": [1.3, 1]})
    ax = axes[0]
    ax.plot(x_ref[:, 0], x_ref[:, 1], "k-", lw=1.2, label="reference", zorder=1)
    sc = None
    for k in idx:
        rel = log_rho[:, k] - log_rho[:, k].max()
        order = np.argsort(rel)
        sc = ax.scatter(
            x[order, k, 0], x[order, k, 1], c=np.exp(rel[order]), s=5, cmap=DENSITY_CMAP, vmin=0, vmax=1, zorder=2
        )
        ax.annotate(f"t={t[k]:.1f}s", (x_ref[k, 0], x_ref[k, 1]), xytext=(6, 6), textcoords="offset points",
                    fontsize=8)
    ax.plot(x_ref[0, 0], x_ref[0, 1], "go", ms=6, label="reference start", zorder=3)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("$p_x$ [m]")
    ax.set_ylabel("$p_y$ [m]")
    ax.legend(loc="best", fontsize=8)
    if sc is not None:
        fig.colorbar(sc, ax=ax, label=r"$\rho / \max\rho$ at each time", shrink=0.8)
    ax.set_title(title or "closed-loop samples coloured by density")

    ax2 = axes[1]
    err = np.linalg.norm(x[:, :, :2] - x_ref[None, :, :2], axis=-1)
    ax2.fill_between(t, np.percentile(err, 5, axis=0), np.percentile(err, 95, axis=0), alpha=0.3,
                     label="5-95 % position error")
    ax2.plot(t, np.median(err, axis=0), label="median position error [m]")
    ax2.set_xlabel("t [s]")
    ax2.set_ylabel("tracking error [m]")
    ax3 = ax2.twinx()
    ax3.plot(t, np.median(log_rho - log_rho[:, :1], axis=0), "C3--", label=r"median $\log\rho(t) - \log\rho_0$")
    ax3.set_ylabel(r"$\log\rho(t) - \log\rho_0$", color="C3")
    lines = ax2.get_legend_handles_labels()
    lines3 = ax3.get_legend_handles_labels()
    ax2.legend(lines[0] + lines3[0], lines[1] + lines3[1], loc="center right", fontsize=8)
    ax2.set_title("tracking error and density growth")
    fig.tight_layout()
    return save_figure(fig, path)

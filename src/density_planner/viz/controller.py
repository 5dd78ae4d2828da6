"""Figures of the controller validation: error decay, tracked trajectories, contraction eigenvalues."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .style import plt, save_figure

__all__ = ["plot_error_decay", "plot_tracked_trajectories", "plot_contraction_eigenvalues"]

_COLOURS = {"c3m": "C0", "analytic": "C1"}


def _colour(name: str, i: int) -> str:
    return _COLOURS.get(name, f"C{i + 2}")


def plot_error_decay(
    t: np.ndarray,
    errors: Mapping[str, Mapping[str, np.ndarray]],
    path: str | Path,
    *,
    title: str | None = None,
) -> Path:
    """Median and 95th percentile of the position error over time, one panel per bias variant.

    Args:
        t: ``(T,)`` times [s].
        errors: ``{controller: {variant: (n, T) position errors [m]}}``.
    """
    variants = list(next(iter(errors.values())).keys())
    fig, axes = plt.subplots(1, len(variants), figsize=(5.2 * len(variants), 4.0), sharey=True, squeeze=False)
    for ax, variant in zip(axes[0], variants):
        for i, (name, per_variant) in enumerate(errors.items()):
            err = per_variant[variant]
            c = _colour(name, i)
            ax.plot(t, np.median(err, axis=0), color=c, lw=1.8, label=f"{name}: median")
            ax.plot(t, np.percentile(err, 95, axis=0), color=c, lw=1.2, ls="--", label=f"{name}: 95th percentile")
            ax.fill_between(t, np.percentile(err, 25, axis=0), np.percentile(err, 75, axis=0), color=c, alpha=0.15,
                            lw=0, label=f"{name}: 25-75 %")
        ax.set_yscale("log")
        ax.set_xlabel("t [s]")
        ax.set_title(f"{variant} measurement ({next(iter(errors.values()))[variant].shape[0]} references)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].set_ylabel("position error |p - p_ref| [m]")
    axes[0, -1].legend(loc="lower left", fontsize=7)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_tracked_trajectories(
    x_ref: np.ndarray,
    trajectories: Mapping[str, np.ndarray],
    path: str | Path,
    *,
    t: np.ndarray | None = None,
    labels: Sequence[str] | None = None,
    title: str | None = None,
) -> Path:
    """A few references and the trajectories that track them: the path in the plane and, below it, the position
    error over time (log scale) of every trajectory.

    Args:
        x_ref: ``(k, T, nx)`` reference states.
        trajectories: ``{name: (k, T, nx)}`` closed-loop states on the same time grid; names ending in "biased"
            (not "unbiased") are drawn dashed.
        t: ``(T,)`` times [s] (default: 0.1 s steps).
        labels: optional panel titles.
    """
    k, n_t = x_ref.shape[0], x_ref.shape[1]
    t = np.arange(n_t) * 0.1 if t is None else np.asarray(t)
    cols = min(k, 3)
    rows = int(np.ceil(k / cols))
    fig = plt.figure(figsize=(4.4 * cols, 5.6 * rows))
    grid = fig.add_gridspec(2 * rows, cols, height_ratios=[3.0, 1.3] * rows, hspace=0.45, wspace=0.3)
    for j in range(k):
        r, c = divmod(j, cols)
        ax = fig.add_subplot(grid[2 * r, c])
        ax_e = fig.add_subplot(grid[2 * r + 1, c])
        ax.plot(x_ref[j, :, 0], x_ref[j, :, 1], "k-", lw=2.2, alpha=0.45, label="reference")
        ax.plot(x_ref[j, 0, 0], x_ref[j, 0, 1], "ko", ms=5, label="reference start")
        for i, (name, x) in enumerate(trajectories.items()):
            colour = _colour(name.split(" ")[0], i)
            ls = "--" if name.endswith("biased") and not name.endswith("unbiased") else "-"
            ax.plot(x[j, :, 0], x[j, :, 1], color=colour, ls=ls, lw=1.1, label=name)
            ax.plot(x[j, 0, 0], x[j, 0, 1], "o", color=colour, ms=3)
            err = np.linalg.norm(x[j, :, :2] - x_ref[j, :, :2], axis=-1)
            ax_e.plot(t, np.maximum(err, 1e-7), color=colour, ls=ls, lw=1.0)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("$p_x$ [m]")
        ax.set_ylabel("$p_y$ [m]")
        if labels is not None:
            ax.set_title(labels[j], fontsize=8)
        ax.grid(True, alpha=0.3)
        ax_e.set_yscale("log")
        ax_e.set_ylim(1e-6, 5.0)
        ax_e.set_xlabel("t [s]")
        ax_e.set_ylabel("error [m]")
        ax_e.grid(True, which="major", alpha=0.3)
        if j == 0:
            ax.legend(loc="best", fontsize=6.5)
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


def plot_contraction_eigenvalues(
    lam: np.ndarray,
    lam_generalised: np.ndarray,
    v: np.ndarray,
    path: str | Path,
    *,
    rate: float,
    title: str | None = None,
) -> Path:
    """Distribution of the largest eigenvalue of the contraction condition on fresh samples.

    Args:
        lam: ``(n,)`` largest eigenvalues of ``C`` (condition holds where negative).
        lam_generalised: ``(n,)`` largest generalised eigenvalues of ``(C, W)`` [1/s].
        v: ``(n,)`` true speeds of the samples [m/s].
        rate: the contraction rate lambda [1/s] the condition was checked with.
    """
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.0))
    ax = axes[0]
    bins = np.linspace(np.percentile(lam, 0.1), max(np.percentile(lam, 99.9), 0.0) + 1e-9, 80)
    ax.hist(np.clip(lam, bins[0], bins[-1]), bins=bins, color="C0", alpha=0.8)
    ax.axvline(0.0, color="k", lw=1)
    ax.set_yscale("log")
    ax.set_xlabel(r"$\lambda_{max}(C)$  (outer bins: beyond the 0.1/99.9th percentiles)")
    ax.set_ylabel("samples")
    ax.set_title(f"holds on {np.mean(lam < 0):.2%} of {lam.size} samples")
    ax = axes[1]
    bins = np.linspace(np.percentile(lam_generalised, 0.1), max(np.percentile(lam_generalised, 99.9), 0.0) + 1e-9, 80)
    ax.hist(np.clip(lam_generalised, bins[0], bins[-1]), bins=bins, color="C2", alpha=0.8)
    ax.axvline(0.0, color="k", lw=1)
    ax.set_yscale("log")
    ax.set_xlabel(r"$\lambda_{max}(C, W)$ [1/s]  (certified rate $= \lambda - \lambda_{max}/2$)")
    ax.set_title(f"generalised eigenvalue, $\\lambda$ = {rate:g}/s")
    ax = axes[2]
    sel = np.random.default_rng(0).permutation(lam.size)[: min(lam.size, 20000)]
    ok = lam_generalised[sel] < 0
    ax.scatter(v[sel][ok], lam_generalised[sel][ok], s=1, color="C2", alpha=0.3, label="holds")
    ax.scatter(v[sel][~ok], lam_generalised[sel][~ok], s=3, color="C3", alpha=0.8, label="violated")
    ax.axhline(0.0, color="k", lw=1)
    ax.set_xlabel("true speed v [m/s]")
    ax.set_ylabel(r"$\lambda_{max}(C, W)$ [1/s]")
    ax.set_title("where the condition fails")
    ax.legend(loc="best", fontsize=7, markerscale=4)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path)

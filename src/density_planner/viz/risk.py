"""Figure of the Monte-Carlo risk check (:mod:`density_planner.evaluation.risk_validation`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..evaluation.calibration import CalibrationResult
from ..evaluation.risk_validation import RiskValidation
from .style import plt, save_figure

__all__ = ["plot_risk_validation", "plot_calibration"]


def plot_risk_validation(v: RiskValidation, path: str | Path, *, title: str = "") -> Path:
    """Two panels: both estimates with +-3 SE bands over time, and ``z(t)`` with the threshold."""
    fig, (a, b) = plt.subplots(2, 1, figsize=(7.5, 6.2), sharex=True, gridspec_kw={"height_ratios": [3, 2]})
    t = v.times
    a.plot(t, v.monte_carlo, color="black", lw=1.6, label=f"Monte Carlo ({v.n_monte_carlo} closed loops)")
    a.fill_between(t, v.monte_carlo - 3 * v.monte_carlo_se, v.monte_carlo + 3 * v.monte_carlo_se, color="black",
                   alpha=0.15, lw=0)
    a.plot(t, v.planner, color="tab:blue", lw=1.4, ls="--", label=f"planner ({v.estimator or 'estimate'})")
    a.fill_between(t, v.planner - 3 * v.planner_se, v.planner + 3 * v.planner_se, color="tab:blue", alpha=0.2, lw=0)
    a.set_ylabel("collision probability")
    a.legend(loc="upper left", fontsize=8)
    a.set_title(title or f"risk check: {'PASS' if v.passed else 'FAIL'} (max |z| = {v.max_abs_z:.2f})", fontsize=10)
    a.grid(alpha=0.3)
    z = np.clip(v.z, -10, 10)
    b.plot(t, z, color="tab:red" if not v.passed else "tab:green", lw=1.2)
    for s in (-v.threshold, v.threshold):
        b.axhline(s, color="gray", ls=":", lw=1)
    b.axhline(0, color="gray", lw=0.6)
    b.set_ylabel("z = diff / combined SE")
    b.set_xlabel("time [s]")
    b.grid(alpha=0.3)
    fig.tight_layout()
    out = save_figure(fig, path)
    plt.close(fig)
    return out


def plot_calibration(c: CalibrationResult, path: str | Path, *, title: str = "") -> Path:
    """Reliability diagram of the occupancy model (:mod:`density_planner.evaluation.calibration`): per bin of the
    predicted road-user occupancy, the mean prediction against the observed true-shape hit frequency (+-2 SE),
    marker area ~ number of (sample, time) pairs; with per-time curves when ``c`` is one plan's."""
    per_time = c.times.size > 0
    fig, axes = plt.subplots(1, 2 if per_time else 1, figsize=(11 if per_time else 5.6, 4.8), squeeze=False)
    a = axes[0, 0]
    bins = c.bins()
    a.plot([0, 1], [0, 1], color="gray", ls=":", lw=1, label="calibrated")
    if bins:
        pred = np.array([b["predicted"] for b in bins])
        obs = np.array([b["observed"] for b in bins])
        se = np.array([b["observed_se"] for b in bins])
        pairs = np.array([b["pairs"] for b in bins], dtype=float)
        size = 20 + 280 * np.sqrt(pairs / pairs.max())
        a.errorbar(pred, obs, yerr=2 * se, fmt="none", ecolor="tab:blue", alpha=0.6, lw=1)
        a.scatter(pred, obs, s=size, color="tab:blue", alpha=0.75, zorder=3, label="bins (area ~ pairs)")
        for j, (p_, o_, n_) in enumerate(zip(pred, obs, pairs)):  # pair counts above the markers, staggered
            a.annotate(f"{int(n_)}", (p_, o_), textcoords="offset points", xytext=(0, 10 + 9 * (j % 2)),
                       ha="center", fontsize=7, color="0.3")
    a.set_xlim(-0.02, 1.02)
    a.set_ylim(-0.02, 1.02)
    a.set_xlabel("predicted road-user occupancy of the body")
    a.set_ylabel("observed hit frequency (true shapes)")
    a.set_title(f"reliability: mean predicted {c.total_predicted:.3f}, observed {c.total_observed:.3f}", fontsize=9)
    a.legend(loc="upper left", fontsize=8)
    a.grid(alpha=0.3)
    if per_time:
        b = axes[0, 1]
        b.plot(c.times, c.predicted, color="tab:blue", lw=1.5, label="predicted (road users' occupancy)")
        b.plot(c.times, c.observed, color="black", lw=1.5, label=f"observed ({c.n} closed loops)")
        se = c.observed_se
        b.fill_between(c.times, c.observed - 2 * se, c.observed + 2 * se, color="black", alpha=0.15, lw=0)
        b.set_xlabel("time [s]")
        b.set_ylabel("probability of hitting a road user")
        b.legend(loc="upper left", fontsize=8)
        b.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out = save_figure(fig, path)
    plt.close(fig)
    return out

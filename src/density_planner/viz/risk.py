"""Figure of the Monte-Carlo risk check (:mod:`density_planner.evaluation.risk_validation`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..evaluation.risk_validation import RiskValidation
from .style import plt, save_figure

__all__ = ["plot_risk_validation"]


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

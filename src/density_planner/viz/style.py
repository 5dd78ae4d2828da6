"""Shared matplotlib set-up for all figures (non-interactive backend, no LaTeX needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

__all__ = ["plt", "save_figure", "DENSITY_CMAP", "OCCUPANCY_CMAP"]

DENSITY_CMAP = "viridis"
OCCUPANCY_CMAP = "Greys"

plt.rcParams.update(
    {
        "figure.dpi": 110,
        "savefig.dpi": 110,
        "axes.grid": False,
        "font.size": 9,
        "axes.titlesize": 10,
        "image.origin": "lower",
    }
)


def save_figure(fig, path: str | Path) -> Path:
    """Save ``fig`` atomically (temporary file + rename) and close it."""
    from ..io.atomic import _atomic

    path = Path(path)
    fmt = path.suffix.lstrip(".") or "png"
    _atomic(path, lambda fh: fig.savefig(fh, format=fmt, bbox_inches="tight"))
    plt.close(fig)
    return path

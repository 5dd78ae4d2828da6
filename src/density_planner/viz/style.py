"""Shared matplotlib set-up for all figures (non-interactive backend, no LaTeX needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402

__all__ = ["plt", "save_figure", "agg_canvas", "DENSITY_CMAP", "OCCUPANCY_CMAP"]

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


def agg_canvas(fig) -> FigureCanvasAgg:
    """The figure's canvas, an Agg canvas (the backend selected above): pixels for GIF frames, blitting."""
    canvas = fig.canvas
    assert isinstance(canvas, FigureCanvasAgg), f"figures are drawn with Agg, got {type(canvas).__name__}"
    return canvas


def frame_map(ax, x0: float, x1: float, y0: float, y1: float) -> None:
    """Frame a map panel: limits ``[x0, x1] x [y0, y1]`` [m], equal aspect, centred, axis labels in metres."""
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal", anchor="C")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.tick_params(labelsize=7)


def save_figure(fig, path: str | Path) -> Path:
    """Save ``fig`` atomically (temporary file + rename) and close it."""
    from ..io.atomic import _atomic

    path = Path(path)
    fmt = path.suffix.lstrip(".") or "png"
    _atomic(path, lambda fh: fig.savefig(fh, format=fmt, bbox_inches="tight"))
    plt.close(fig)
    return path

"""Controller selection by name: ``"c3m"`` (the shipped learned controller), ``"analytic"`` or a weights path."""

from __future__ import annotations

from pathlib import Path

from ..systems.car import CarConfig
from .analytic import CarTrackingController
from .base import TrackingController

__all__ = ["DEFAULT_CONTROLLER", "CONTROLLER_CHOICES", "load_controller"]

#: controller used when none is named (command line and library defaults)
DEFAULT_CONTROLLER = "c3m"
CONTROLLER_CHOICES = ("c3m", "analytic")


def load_controller(spec: str | Path | None = None, car: CarConfig | None = None) -> TrackingController:
    """Controller for the kinematic car.

    Args:
        spec: ``"c3m"`` (the learned contraction controller shipped with the package), ``"analytic"``
            (hand-written feedback), the path of a C3M weights file (``NAME.pt`` with ``NAME.json`` beside it), or
            ``None`` for :data:`DEFAULT_CONTROLLER`.
        car: car configuration (input bounds).

    Raises:
        ValueError: unknown name; :class:`~density_planner.errors.CheckpointError` (a ``ValueError``) for a
            missing, corrupt or mismatched weights file.
    """
    from .c3m import load_c3m_controller

    spec = DEFAULT_CONTROLLER if spec is None else spec
    if isinstance(spec, str) and spec == "analytic":
        return CarTrackingController(car=car)
    if isinstance(spec, str) and spec == "c3m":
        return load_c3m_controller(None, car)
    path = Path(spec)
    if path.suffix in (".pt", ".json") or path.exists() or path.with_suffix(".pt").exists():
        return load_c3m_controller(path, car)
    raise ValueError(
        f"unknown controller {str(spec)!r}; valid choices: {', '.join(CONTROLLER_CHOICES)} or a weights file (.pt)"
    )

"""Controller selection by name: ``"analytic"``, ``"c3m"`` (the shipped learned controller) or a weights path."""

from __future__ import annotations

from pathlib import Path

from ..systems.car import CarConfig
from .analytic import CarTrackingController
from .base import TrackingController

__all__ = ["DEFAULT_CONTROLLER", "CONTROLLER_CHOICES", "load_controller"]

#: controller used when none is named (command line and library defaults)
DEFAULT_CONTROLLER = "analytic"
CONTROLLER_CHOICES = ("analytic",)


def load_controller(spec: str | None = None, car: CarConfig | None = None) -> TrackingController:
    """Controller for the kinematic car.

    Args:
        spec: ``"analytic"`` (hand-written feedback), or ``None`` for :data:`DEFAULT_CONTROLLER`.
        car: car configuration (input bounds).
    """
    spec = spec or DEFAULT_CONTROLLER
    if spec == "analytic":
        return CarTrackingController(car=car)
    path = Path(spec)
    if path.suffix or path.exists():
        raise ValueError(f"controller weights file {spec!r}: learned controllers are not available yet")
    raise ValueError(f"unknown controller {spec!r}; valid choices: {', '.join(CONTROLLER_CHOICES)} or a weights file")

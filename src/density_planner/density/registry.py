"""Density predictor selection by name: ``"exact"`` (Liouville integration) or a learned predictor."""

from __future__ import annotations

from ..control.base import TrackingController
from ..systems.base import System
from .base import DensityPredictor
from .liouville import ExactLiouville, LiouvilleConfig

__all__ = ["DEFAULT_PREDICTOR", "PREDICTOR_CHOICES", "load_predictor"]

#: predictor used by the planner's second stage when none is named
DEFAULT_PREDICTOR = "exact"
PREDICTOR_CHOICES = ("exact",)


def load_predictor(
    spec: str | None,
    system: System,
    controller: TrackingController,
    *,
    liouville: LiouvilleConfig | None = None,
) -> DensityPredictor:
    """Density predictor ``spec`` (``None`` for :data:`DEFAULT_PREDICTOR`) for ``system`` tracked by ``controller``."""
    spec = spec or DEFAULT_PREDICTOR
    if spec == "exact":
        return ExactLiouville(system, controller, liouville)
    raise ValueError(f"unknown density predictor {spec!r}; valid choices: {', '.join(PREDICTOR_CHOICES)}")

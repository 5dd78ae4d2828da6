"""Planner registry: names usable with ``density-planner plan --planner NAME`` and in benchmark sweeps.

A planner is registered with a factory ``factory(context) -> Planner``; the :class:`PlannerContext` carries the
system, the tracking controller, a lazily built density predictor, the run configuration (one section per
planner) and device/progress settings. Adding a planner means writing its class and one ``register_planner``
call in its module.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from ..control.base import TrackingController
from ..density.base import DensityPredictor
from ..systems.base import System
from .base import Planner

__all__ = ["PlannerContext", "register_planner", "make_planner", "planner_names", "planner_help"]


@dataclass
class PlannerContext:
    """What planner factories receive.

    Attributes:
        system: dynamics.
        controller: tracking controller (used by the density planner's predictions and closed-loop runs).
        config: the run configuration (:class:`density_planner.settings.RunConfig`); each planner reads its section.
        predictor_factory: builds the density predictor of the density planner on first use.
        exact_factory: builds the exact Liouville predictor (for the final re-check of learned predictions).
        device, dtype: tensor placement.
        progress: show progress bars.
    """

    system: System
    controller: TrackingController
    config: Any
    predictor_factory: Callable[[], DensityPredictor] | None = None
    exact_factory: Callable[[], DensityPredictor] | None = None
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    dtype: torch.dtype = torch.float32
    progress: bool = False
    _cache: dict[str, Any] = field(default_factory=dict, repr=False)

    def predictor(self) -> DensityPredictor:
        if "predictor" not in self._cache:
            if self.predictor_factory is None:
                raise ValueError("this planner needs a density predictor, but none was configured")
            self._cache["predictor"] = self.predictor_factory()
        return self._cache["predictor"]

    def exact(self) -> DensityPredictor | None:
        if self.exact_factory is None:
            return None
        if "exact" not in self._cache:
            self._cache["exact"] = self.exact_factory()
        return self._cache["exact"]


_REGISTRY: dict[str, tuple[Callable[[PlannerContext], Planner], str]] = {}

#: modules whose import registers planners (optional extras are imported lazily by their factories)
_PLANNER_MODULES = ("density_planner", "mpc", "oracle", "search", "sampling", "online")


def register_planner(name: str, help: str) -> Callable[[Callable[[PlannerContext], Planner]], Callable]:
    """Decorator registering ``factory(context) -> Planner`` under ``name``."""

    def deco(factory: Callable[[PlannerContext], Planner]) -> Callable[[PlannerContext], Planner]:
        if name in _REGISTRY and _REGISTRY[name][0] is not factory:
            raise ValueError(f"planner {name!r} registered twice")
        _REGISTRY[name] = (factory, help)
        return factory

    return deco


def _load_all() -> None:
    for module in _PLANNER_MODULES:
        importlib.import_module(f"{__package__}.{module}")


def planner_names() -> list[str]:
    """Registered planner names."""
    _load_all()
    return list(_REGISTRY)


def planner_help() -> dict[str, str]:
    _load_all()
    return {name: help for name, (_, help) in _REGISTRY.items()}


def make_planner(name: str, context: PlannerContext) -> Planner:
    """The planner ``name`` built from ``context``."""
    _load_all()
    if name not in _REGISTRY:
        raise ValueError(f"unknown planner {name!r}; valid choices: {', '.join(_REGISTRY)}")
    return _REGISTRY[name][0](context)

"""What planner factories receive (:class:`PlannerContext`), and the one function that builds it.

:func:`build_context` is used by every entry point that plans (``plan``, ``drive``, ``validate risk``, the
benchmarks, the benchmark scripts): the run's system (:func:`run_system`: ``[system] name`` in the domain of the
model set chosen for the scene), the tracking controller and the density predictor of the model set, on the
requested device.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from ..control.base import TrackingController
from ..density.base import DensityPredictor
from ..systems.base import System

__all__ = ["PlannerContext", "build_context", "run_model_set", "run_system"]


@dataclass
class PlannerContext:
    """What planner factories receive.

    Attributes:
        system: dynamics.
        controller: tracking controller (used by the density planner's predictions and closed-loop runs).
        config: the run configuration (:class:`density_planner.settings.RunConfig`); each planner reads its section.
        predictor_factory: builds the density predictor of the density planner on first use.
        exact_factory: builds the exact Liouville predictor (for the final re-check of learned predictions); may
            return ``None`` (no re-check, e.g. when the predictor is exact already).
        device, dtype: tensor placement.
        progress: show progress bars.
    """

    system: System
    controller: TrackingController
    config: Any
    predictor_factory: Callable[[], DensityPredictor] | None = None
    exact_factory: Callable[[], DensityPredictor | None] | None = None
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


def run_model_set(run_config: Any, kind: str | None):
    """The :class:`~density_planner.control.registry.ModelSet` of the run's ``[system]`` section
    (:class:`~density_planner.systems.registry.SystemConfig`) for a scene of source ``kind`` (``"random"``,
    ``"commonroad"``, ...): the set ``[system] models`` names, else the one its system registered for the kind."""
    from ..control.registry import model_set_for_scene

    cfg = run_config.system
    return model_set_for_scene(kind, cfg.models, cfg.name)


def run_system(run_config: Any, kind: str | None) -> System:
    """The run's system: ``[system] name`` in the domain of its model set for a scene of ``kind``
    (:func:`run_model_set`)."""
    return run_model_set(run_config, kind).make_system()


def build_context(
    run_config: Any,
    *,
    kind: str | None = None,
    controller: str | None = None,
    density: str | None = None,
    parameterization: Any = None,
    system: System | None = None,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
    progress: bool = False,
    lazy: bool = False,
    exact_check: bool = True,
) -> PlannerContext:
    """The planner context of a run.

    Args:
        run_config: the run configuration (:class:`density_planner.settings.RunConfig`); its ``[system]`` section
            names the system, the model set, the controller and the density predictor.
        kind: the scene source (chooses the model set when ``[system] models`` is ``auto``).
        controller, density: override ``[system] controller`` / ``density`` (``None``: the section's).
        parameterization: the plan's horizon, which a learned predictor must fit (checked when given).
        system: the system, if already built (default :func:`run_system`).
        device, dtype: placement of the controller and the predictor.
        lazy: load the predictor on first use (planners that need none, e.g. MPC, never load it); otherwise now,
            so that a bad predictor name fails before any planning.
        exact_check: give the density planner the exact Liouville predictor for its final re-check of a learned
            prediction.
    """
    from ..control.registry import load_controller
    from ..density.liouville import ExactLiouville
    from ..density.registry import load_predictor

    device = torch.device(device) if device is not None else torch.device("cpu")
    mset = run_model_set(run_config, kind)
    car = system if system is not None else mset.make_system()
    ctrl = load_controller(controller or run_config.system.controller, models=mset).to(device=device, dtype=dtype)
    # auto: the default learned predictor if it was trained for this controller, else exact Liouville
    name = density or run_config.system.density
    name = None if name == "auto" else name
    loaded: list[DensityPredictor] = []

    def predictor() -> DensityPredictor:
        if not loaded:
            p = load_predictor(name, car, ctrl, liouville=run_config.liouville, parameterization=parameterization,
                               models=mset.name)
            loaded.append(p.to(device=device, dtype=dtype) if hasattr(p, "to") else p)
        return loaded[0]

    if not lazy:
        predictor()

    def exact() -> DensityPredictor | None:
        return None if isinstance(predictor(), ExactLiouville) else ExactLiouville(car, ctrl, run_config.liouville)

    return PlannerContext(system=car, controller=ctrl, config=run_config, predictor_factory=predictor,
                          exact_factory=exact if exact_check else None, device=device, dtype=dtype,
                          progress=progress)

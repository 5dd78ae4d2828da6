"""Density predictor selection by name: ``"exact"`` (Liouville integration) or a learned predictor.

Names:

* ``"exact"``: :class:`~density_planner.density.liouville.ExactLiouville` (always available, any controller);
* ``"trajectory"`` / ``"pointwise"``: the shipped learned predictors of the controller's model set
  (``density_planner/weights/density_{arch}.pt`` for the car's ``paper``, ``density_{arch}_road.pt`` for its
  ``road``, ``density_{arch}_ks.pt`` for the kinematic single-track model's ``ks``: ``density_{arch}{suffix}.pt``
  with the set's ``density_suffix``; the sets are registered in :mod:`density_planner.control.registry`; the
  package ships the trajectory head for every set and the pointwise net for the car's);
* ``"learned"``: the default learned predictor (:data:`DEFAULT_LEARNED`, the faster one at equal or better
  accuracy);
* a path ``NAME.pt`` (with ``NAME.json`` beside it) written by ``density-planner train density``.

A learned predictor is only valid for the closed loop it was trained on, so the system must be the one whose states
it reads (its architecture's ``system``) and the controller the one that generated its training data (compared by
:func:`~density_planner.density.network.controller_fingerprint`); a named learned predictor with another system
or controller is an error. With no name (``spec=None``) the planner uses
:data:`DEFAULT_PREDICTOR` when it fits the controller and exact Liouville otherwise (logged).
"""

from __future__ import annotations

import logging
from pathlib import Path

from ..control.base import TrackingController
from ..errors import CheckpointError
from ..systems.base import System
from .base import DensityPredictor
from .liouville import ExactLiouville, LiouvilleConfig

__all__ = ["DEFAULT_PREDICTOR", "DEFAULT_LEARNED", "PREDICTOR_CHOICES", "load_predictor", "load_learned_predictor"]

logger = logging.getLogger(__name__)

#: the learned predictor behind the name "learned": the trajectory head (faster than the pointwise net at equal or
#: better accuracy; see docs/density.md)
DEFAULT_LEARNED = "trajectory"
#: predictor used by the planner's second stage when none is named
DEFAULT_PREDICTOR = "learned"
PREDICTOR_CHOICES = ("exact", "learned", "trajectory", "pointwise")


def load_learned_predictor(spec: str | Path, controller: TrackingController | None = None, *,
                           models: str | None = None, fallback: DensityPredictor | None = None,
                           system: System | None = None):
    """The learned predictor ``spec`` ("learned", "trajectory", "pointwise" or a weights path).

    If ``controller`` is given, it must be the controller the predictor was trained for; if ``system`` is given, its
    state layout must be the one the predictor reads. ``models`` names the model set whose shipped weights the names
    refer to (default: the set of ``controller``'s car domain, else the first set of ``system``'s type, else
    ``"paper"``). References outside the training domain (start speed) raise
    :class:`~density_planner.errors.DomainError`, or, with a ``fallback`` predictor, use it with a logged warning.

    Raises:
        CheckpointError: missing/corrupt/mismatched weights, a system or a controller other than the training one.
    """
    from .network import (
        DensityLayout,
        LearnedDensity,
        controller_fingerprint,
        load_density_model,
        shipped_density_path,
    )

    if models is None:
        models = getattr(getattr(controller, "car", None), "domain", None) or _model_set_of(system) or "paper"
    name = DEFAULT_LEARNED if spec == "learned" else spec
    if name in ("trajectory", "pointwise"):
        path, arch = shipped_density_path(str(name), models), str(name)
        if not path.is_file():
            raise CheckpointError(
                f"the package ships no weights for the {name!r} density predictor of the model set {models!r} "
                f"({path}); train them with `density-planner train density --arch {name}` (see docs/density.md) "
                "or use --density exact"
            )
    else:
        path, arch = Path(name), None
    model, meta = load_density_model(path, arch=arch)
    if system is not None and DensityLayout.of(system) != model.layout:
        raise CheckpointError(
            f"the learned density predictor {str(spec)!r} reads states of the system {model.architecture.system!r}, "
            f"not of this {type(system).__name__} ({', '.join(system.state_names)}); use --density exact or train a "
            "predictor for this system (`density-planner data density --system NAME`, docs/density.md)"
        )
    if controller is not None:
        trained = (meta.get("controller") or {}).get("fingerprint")
        found = controller_fingerprint(controller)
        if trained is not None and trained != found:
            label = (meta.get("controller") or {}).get("spec", "?")
            raise CheckpointError(
                f"the learned density predictor {str(spec)!r} was trained for the controller {label!r} "
                f"(fingerprint {trained}), not for this {type(controller).__name__} (fingerprint {found}); use "
                "--density exact or train a predictor for this controller"
            )
    return LearnedDensity(model, meta=meta, fallback=fallback)


def _model_set_of(system: System | None) -> str | None:
    """The first model set registered for ``system``'s type (``None``: no system, or none registered)."""
    if system is None:
        return None
    from ..control.registry import MODEL_SETS, model_set

    model_set()  # loads the registrations
    return next((name for name, m in MODEL_SETS.items() if type(m.make_system()) is type(system)), None)


def load_predictor(
    spec: str | Path | None,
    system: System,
    controller: TrackingController,
    *,
    liouville: LiouvilleConfig | None = None,
    parameterization=None,
    models: str | None = None,
) -> DensityPredictor:
    """Density predictor ``spec`` for ``system`` tracked by ``controller``.

    ``None`` selects :data:`DEFAULT_PREDICTOR` if it was trained for ``controller`` and, when
    ``parameterization`` (the plan's :class:`~density_planner.control.reference.PiecewiseConstantInputs`) is
    given, for its horizon; else exact Liouville, with a log message (a warning for a horizon mismatch). A learned
    predictor named explicitly for a horizon it was not trained for is an error (never a silent extrapolation).
    See the module docstring for the names. ``models`` names the model set whose shipped weights the names refer to
    (default: the set of the controller's car domain, else ``"paper"``; other systems pass their set).
    """
    if spec is None:
        try:
            # outside the training domain the default falls back to exact Liouville (logged), never extrapolates
            learned = load_learned_predictor(DEFAULT_PREDICTOR, controller, models=models,
                                             fallback=ExactLiouville(system, controller, liouville), system=system)
        except CheckpointError as exc:
            logger.info("default density predictor %r not usable (%s); using exact Liouville",
                           DEFAULT_PREDICTOR, exc)
            return ExactLiouville(system, controller, liouville)
        reason = None if parameterization is None else learned.mismatch(parameterization)
        if reason is not None:
            logger.warning("%s: using exact Liouville instead (slower; name --density exact to silence this)", reason)
            return ExactLiouville(system, controller, liouville)
        return learned
    if spec == "exact":
        return ExactLiouville(system, controller, liouville)
    if spec in PREDICTOR_CHOICES:
        return _fitting(load_learned_predictor(spec, controller, models=models, system=system), parameterization)
    path = Path(spec)
    if path.suffix in (".pt", ".json") or path.exists() or path.with_name(path.name + ".pt").exists():
        return _fitting(load_learned_predictor(path, controller, system=system), parameterization)
    raise ValueError(
        f"unknown density predictor {str(spec)!r}; valid choices: {', '.join(PREDICTOR_CHOICES)} or a weights "
        "file (.pt)"
    )


def _fitting(predictor, parameterization):
    """``predictor``, after checking that it was trained for ``parameterization`` (if given)."""
    if parameterization is not None:
        predictor.check_parameterization(parameterization)
    return predictor

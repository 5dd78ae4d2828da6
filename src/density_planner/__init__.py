"""density-planner: motion planning that minimises collision risk under initial-state uncertainty.

The pipeline, in the order data flows through it::

    systems -> control -> density -> environment -> risk -> cost -> planners -> evaluation -> cli / viz

The names below are the stable public API; everything else is importable from its subpackage.
"""

from importlib import import_module
from typing import TYPE_CHECKING, Any

from .memory import tune_allocator

tune_allocator()  # glibc's malloc thresholds for a planner's alloc/free pattern (DENSITY_PLANNER_TUNE_MALLOC=0: off)

#: public name -> the subpackage that defines it, imported on first use (PEP 562): importing the package (and its
#: command line, before it parses its arguments) does not import torch (~1 s), so the ``plan`` command can start
#: reading its scene file in a second process meanwhile (:mod:`density_planner.prefetch`)
_EXPORTS = {
    **dict.fromkeys(("CarTrackingController", "PiecewiseConstantInputs", "Reference", "TrackingController",
                     "make_reference"), ".control"),
    **dict.fromkeys(("DensityPredictor", "DensityTrajectory", "ExactLiouville", "Gaussian", "GaussianMixture",
                     "LearnedDensity", "LiouvilleConfig", "UniformBox", "WeightedSamples", "load_predictor",
                     "paper_gaussian_mixture", "propagate_density", "simulate_closed_loop"), ".density"),
    **dict.fromkeys(("CarConfig", "KinematicCar", "LinearSystem", "System"), ".systems"),
    **dict.fromkeys(("plan_scene", "drive_scene", "load_run_config"), ".api"),
}

if TYPE_CHECKING:  # what the names are, for type checkers and editors
    from .api import drive_scene, load_run_config, plan_scene
    from .control import (
        CarTrackingController,
        PiecewiseConstantInputs,
        Reference,
        TrackingController,
        make_reference,
    )
    from .density import (
        DensityPredictor,
        DensityTrajectory,
        ExactLiouville,
        Gaussian,
        GaussianMixture,
        LearnedDensity,
        LiouvilleConfig,
        UniformBox,
        WeightedSamples,
        load_predictor,
        paper_gaussian_mixture,
        propagate_density,
        simulate_closed_loop,
    )
    from .systems import CarConfig, KinematicCar, LinearSystem, System


def _installed_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("density-planner")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree without installation
        return "0.0.0+unknown"


def __getattr__(name: str) -> Any:
    """``__version__`` (the installed distribution's, looked up on first access: importlib.metadata takes ~0.05 s
    of every command's start-up otherwise), a public name (``_EXPORTS``) or a subpackage, imported on first
    access."""
    if name == "__version__":
        globals()[name] = _installed_version()
        return globals()[name]
    where = _EXPORTS.get(name)
    if where is not None:
        value = getattr(import_module(where, __name__), name)
        globals()[name] = value
        return value
    try:
        return import_module(f".{name}", __name__)
    except ModuleNotFoundError as exc:
        if exc.name != f"{__name__}.{name}":
            raise
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))


__all__ = [
    "__version__",
    "System",
    "KinematicCar",
    "CarConfig",
    "LinearSystem",
    "TrackingController",
    "CarTrackingController",
    "PiecewiseConstantInputs",
    "Reference",
    "make_reference",
    "DensityPredictor",
    "DensityTrajectory",
    "ExactLiouville",
    "LearnedDensity",
    "load_predictor",
    "LiouvilleConfig",
    "propagate_density",
    "simulate_closed_loop",
    "Gaussian",
    "GaussianMixture",
    "UniformBox",
    "WeightedSamples",
    "paper_gaussian_mixture",
    "plan_scene",
    "drive_scene",
    "load_run_config",
]

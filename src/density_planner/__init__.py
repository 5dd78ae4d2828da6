"""density-planner: motion planning that minimises collision risk under initial-state uncertainty.

The pipeline, in the order data flows through it::

    systems -> control -> density -> environment -> risk -> cost -> planners -> evaluation -> cli / viz

The names below are the stable public API; everything else is importable from its subpackage.
"""

from importlib.metadata import PackageNotFoundError, version

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
from .memory import tune_allocator
from .systems import CarConfig, KinematicCar, LinearSystem, System

tune_allocator()  # glibc's malloc thresholds for a planner's alloc/free pattern (DENSITY_PLANNER_TUNE_MALLOC=0: off)

try:
    __version__ = version("density-planner")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without installation
    __version__ = "0.0.0+unknown"

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
]

"""Density propagation: closed loop, exact Liouville integration, initial distributions, predictors (exact and
learned)."""

from .base import DensityPredictor, DensityTrajectory, sample_weights
from .closed_loop import ClosedLoop
from .data import DensityData, DensityDataConfig, generate_density_data, load_density_data
from .distributions import (
    Gaussian,
    GaussianMixture,
    InitialDistribution,
    UniformBox,
    WeightedSamples,
    paper_gaussian_mixture,
)
from .integrators import EULER, RK4, FixedStepIntegrator, get_integrator
from .liouville import ExactLiouville, LiouvilleConfig, propagate_density, simulate_closed_loop
from .network import (
    DensityLayout,
    DensityNetArchitecture,
    DensityNetwork,
    LearnedDensity,
    load_density_model,
    save_density_model,
)
from .registry import DEFAULT_PREDICTOR, PREDICTOR_CHOICES, load_learned_predictor, load_predictor
from .train import DensityTrainConfig, DensityTrainResult, train_density
from .validation import DensityComparison, compare_with_exact, fresh_references

__all__ = [
    "DensityPredictor",
    "DensityTrajectory",
    "sample_weights",
    "ClosedLoop",
    "InitialDistribution",
    "Gaussian",
    "GaussianMixture",
    "UniformBox",
    "WeightedSamples",
    "paper_gaussian_mixture",
    "FixedStepIntegrator",
    "EULER",
    "RK4",
    "get_integrator",
    "LiouvilleConfig",
    "ExactLiouville",
    "propagate_density",
    "simulate_closed_loop",
    "DensityDataConfig",
    "DensityData",
    "DensityLayout",
    "generate_density_data",
    "load_density_data",
    "DensityNetArchitecture",
    "DensityNetwork",
    "LearnedDensity",
    "save_density_model",
    "load_density_model",
    "DensityTrainConfig",
    "DensityTrainResult",
    "train_density",
    "DensityComparison",
    "compare_with_exact",
    "fresh_references",
    "DEFAULT_PREDICTOR",
    "PREDICTOR_CHOICES",
    "load_predictor",
    "load_learned_predictor",
]

"""Density propagation: closed loop, exact Liouville integration, initial distributions, predictors."""

from .base import DensityPredictor, DensityTrajectory, sample_weights
from .closed_loop import ClosedLoop
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
]

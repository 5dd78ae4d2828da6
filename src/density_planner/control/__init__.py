"""Tracking control: reference trajectories and tracking controllers."""

from .analytic import CarTrackingController, CarTrackingGains, LinearFeedbackController
from .base import TrackingController
from .c3m import (
    C3MArchitecture,
    C3MController,
    C3MModel,
    ContractionMetric,
    load_c3m_controller,
    load_c3m_model,
    save_c3m_model,
    shipped_c3m_path,
)
from .c3m_training import C3MTrainConfig, C3MTrainResult, TrainHistory, contraction_diagnostics, train_c3m
from .contraction import ContractionTerms, car_contraction_terms, condition_holds, contraction_loss
from .reference import PiecewiseConstantInputs, Reference, make_reference
from .registry import CONTROLLER_CHOICES, DEFAULT_CONTROLLER, load_controller
from .sampling import sample_feasible_references, sample_initial_errors, sample_tracking_states

__all__ = [
    "TrackingController",
    "CarTrackingController",
    "CarTrackingGains",
    "LinearFeedbackController",
    "PiecewiseConstantInputs",
    "Reference",
    "make_reference",
    "C3MArchitecture",
    "C3MController",
    "C3MModel",
    "ContractionMetric",
    "load_c3m_controller",
    "load_c3m_model",
    "save_c3m_model",
    "shipped_c3m_path",
    "C3MTrainConfig",
    "C3MTrainResult",
    "TrainHistory",
    "train_c3m",
    "contraction_diagnostics",
    "ContractionTerms",
    "car_contraction_terms",
    "condition_holds",
    "contraction_loss",
    "load_controller",
    "DEFAULT_CONTROLLER",
    "CONTROLLER_CHOICES",
    "sample_feasible_references",
    "sample_initial_errors",
    "sample_tracking_states",
]

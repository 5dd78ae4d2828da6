"""Tracking control: reference trajectories and tracking controllers."""

from .analytic import CarTrackingController, CarTrackingGains, LinearFeedbackController
from .base import TrackingController
from .reference import PiecewiseConstantInputs, Reference, make_reference

__all__ = [
    "TrackingController",
    "CarTrackingController",
    "CarTrackingGains",
    "LinearFeedbackController",
    "PiecewiseConstantInputs",
    "Reference",
    "make_reference",
]

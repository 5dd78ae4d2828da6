"""Evaluation: closed-loop Monte-Carlo checks of controllers and planners."""

from .controller import TrackingEvaluation, evaluate_tracking

__all__ = ["TrackingEvaluation", "evaluate_tracking"]

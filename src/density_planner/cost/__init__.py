"""Cost terms of the planners (goal, input effort, state bounds, collision surrogate) and their weighted sum."""

from .composite import TERM_NAMES, CostBreakdown, CostConfig, CostWeights, WeightedCost, build_cost
from .terms import BoundsCost, CollisionCost, CostInputs, CostTerm, GoalCost, InputCost, desired_positions

__all__ = [
    "CostInputs",
    "CostTerm",
    "GoalCost",
    "InputCost",
    "BoundsCost",
    "CollisionCost",
    "desired_positions",
    "CostWeights",
    "CostConfig",
    "CostBreakdown",
    "WeightedCost",
    "build_cost",
    "TERM_NAMES",
]

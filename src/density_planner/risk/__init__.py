"""Collision risk: the one owner of collision (the body on the occupancy grid) and of its probability.

:class:`CollisionModel` (grid + system + :class:`RiskConfig`) gives the occupancy seen by a state's body, the
body's disc centres for the cost surrogate and the CasADi terms, and the collision probability of a sample cloud
with its standard error (:class:`CollisionReport`).
"""

from .body import DiscCover, body_grid, dilate
from .collision import CollisionModel, CollisionReport, RiskConfig, collision_probability, importance_weights

__all__ = ["CollisionModel", "CollisionReport", "RiskConfig", "collision_probability", "importance_weights",
           "DiscCover", "body_grid", "dilate"]

"""Collision risk: the collision probability of a density-weighted sample cloud on an occupancy grid."""

from .collision import CollisionReport, collision_probability

__all__ = ["CollisionReport", "collision_probability"]

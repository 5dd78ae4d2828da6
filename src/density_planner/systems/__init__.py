"""Dynamical systems: the :class:`System` interface, the kinematic car and a linear test system."""

from .base import ControlAffineSystem, System
from .car import CarConfig, KinematicCar
from .linear import LinearSystem

__all__ = ["System", "ControlAffineSystem", "KinematicCar", "CarConfig", "LinearSystem"]

"""Dynamical systems: the :class:`System` interface, the registry of named systems (``--system``), the kinematic
car and a linear test system."""

from .base import ControlAffineSystem, System
from .car import CarConfig, KinematicCar
from .linear import LinearSystem
from .registry import SystemConfig, make_system, register_system, system_names

__all__ = ["System", "ControlAffineSystem", "KinematicCar", "CarConfig", "LinearSystem", "SystemConfig",
           "make_system", "register_system", "system_names"]

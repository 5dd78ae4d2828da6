"""Exceptions raised by density-planner.

Every error caused by user input is a :class:`ValueError` (or a subclass) whose message names the offending
argument, file or key. The command-line interface turns these into a one-line message and a non-zero exit code.
"""

from __future__ import annotations


class DensityPlannerError(Exception):
    """Base class of the library's own exceptions."""


class ConfigError(DensityPlannerError, ValueError):
    """A configuration file, key or value is invalid (unknown key, wrong type, out of range)."""


class CheckpointError(DensityPlannerError, ValueError):
    """A weights/checkpoint file is missing, corrupt or does not match the expected architecture."""


class DataError(DensityPlannerError, ValueError):
    """An input data file (scenario, recording, data set shard) is missing, malformed or inconsistent."""


class DomainError(DensityPlannerError, ValueError):
    """An input lies outside the domain a learned model was trained on (e.g. a start speed above its range)."""


class ResourceError(DensityPlannerError, ValueError):
    """A request needs more memory (or another resource) than the machine has; the message names the setting."""


class OptionalDependencyError(DensityPlannerError, ImportError):
    """An optional extra (``mpc``, ``commonroad``, ``dask``) is needed but not installed."""

    def __init__(self, package: str, extra: str, purpose: str):
        super().__init__(
            f"{purpose} needs the optional package '{package}'; install it with "
            f"`pip install 'density-planner[{extra}]'` (or `make install EXTRAS={extra}`)"
        )
        self.package = package
        self.extra = extra

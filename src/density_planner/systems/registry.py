"""System registry: the dynamics usable with ``--system NAME`` and the ``[system]`` section of a run.

A system module registers itself once, with :func:`register_system` applied to a builder
``build(domain) -> System`` (a *domain* is a named parameter set of the system: state and input boxes, body,
limits; e.g. the kinematic car's ``"paper"`` and ``"road"`` boxes). Every module of this package is imported on
first use, so adding a system is adding a file here: the pipeline (scenes, risk, cost, planners, evaluation, CLI)
reads a system only through :class:`~density_planner.systems.base.System`. Its controllers and trained weights
are registered by model sets (:mod:`density_planner.control.registry`).

The ``[system]`` section (:class:`SystemConfig`) names the system, its model set, the tracking controller and the
density predictor of a run; the command-line flags ``--system``, ``--models``, ``--controller`` and ``--density``
write into it, so the ``config.toml`` written beside results reproduces the run.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass

from .base import System

__all__ = ["SystemEntry", "SystemConfig", "register_system", "system_entry", "system_names", "make_system",
           "DEFAULT_SYSTEM", "AUTO"]

#: the system of a run when none is named
DEFAULT_SYSTEM = "car"
#: value of a :class:`SystemConfig` field that is chosen from the others (and the scene kind)
AUTO = "auto"


@dataclass(frozen=True)
class SystemEntry:
    """A registered system."""

    #: the name used by ``--system`` and ``[system] name``
    name: str
    #: ``build(domain) -> System``
    build: Callable[[str], System]
    #: the named domains ``build`` accepts; the first is the default
    domains: tuple[str, ...]
    #: one line for help texts
    description: str

    def make(self, domain: str | None = None) -> System:
        """The system in ``domain`` (default: the first registered domain)."""
        domain = self.domains[0] if domain is None else domain
        if domain not in self.domains:
            raise ValueError(f"system {self.name!r} has no domain {domain!r}; valid choices: "
                             f"{', '.join(self.domains)}")
        return self.build(domain)


@dataclass(frozen=True)
class SystemConfig:
    """``[system]``: which dynamics, controller and density predictor a run uses (``auto``: chosen for the scene)."""

    #: registered system (``density-planner plan --help`` lists them): "car" = the paper's kinematic car with
    #: heading bias, "ks" = CommonRoad's kinematic single-track model
    name: str = DEFAULT_SYSTEM
    #: model set (the system's domain with the controller and density weights trained on it); "auto": the set of
    #: the system registered for the scene kind (for the car: "paper" on random scenes, "road" on recorded traffic)
    models: str = AUTO
    #: tracking controller: a name registered for the model set ("c3m", "analytic", ...), a C3M weights file, or
    #: "auto" (the model set's default controller)
    controller: str = AUTO
    #: density predictor: "exact", "learned", "trajectory", "pointwise", a weights file, or "auto" (the default
    #: learned predictor when it was trained for this controller and horizon, else exact Liouville)
    density: str = AUTO

    def __post_init__(self) -> None:
        for name in ("name", "models", "controller", "density"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value:
                raise ValueError(f"[system] {name} must be a non-empty string, got {value!r}")


_REGISTRY: dict[str, SystemEntry] = {}
_LOADED = False


def register_system(name: str, *, domains: tuple[str, ...], description: str
                    ) -> Callable[[Callable[[str], System]], Callable[[str], System]]:
    """Decorator registering ``build(domain) -> System`` as the system ``name`` with its ``domains``."""
    if not domains:
        raise ValueError(f"system {name!r} needs at least one domain")

    def deco(build: Callable[[str], System]) -> Callable[[str], System]:
        old = _REGISTRY.get(name)
        if old is not None and old.build is not build:
            raise ValueError(f"system {name!r} registered twice")
        _REGISTRY[name] = SystemEntry(name, build, tuple(domains), description)
        return build

    return deco


def _load_all() -> None:
    """Import every module of this package once (their ``register_system`` calls fill the registry)."""
    global _LOADED
    if _LOADED:
        return
    package = importlib.import_module(__package__)
    for info in pkgutil.iter_modules(package.__path__):
        if not info.name.startswith("_"):
            importlib.import_module(f"{__package__}.{info.name}")
    _LOADED = True


def system_names() -> list[str]:
    """Registered system names."""
    _load_all()
    return list(_REGISTRY)


def system_entry(name: str) -> SystemEntry:
    """The registration of system ``name``."""
    _load_all()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown system {name!r}; valid choices: {', '.join(_REGISTRY)}") from None


def make_system(name: str = DEFAULT_SYSTEM, domain: str | None = None) -> System:
    """The system ``name`` in ``domain`` (default: its first domain)."""
    return system_entry(name).make(domain)

"""Tracking controllers by name and the named **model sets**: a system's domain with the weights trained on it.

A model set bundles a registered system (:mod:`density_planner.systems.registry`) in one of its domains, the
controllers that track references of that system (:func:`register_controller`), the C3M weights trained on the
domain and (in :mod:`density_planner.density.registry`) the density predictors trained on that closed loop:

* ``"paper"``: the kinematic car in the paper's box (v in [0, 10] m/s, inputs +-3, hard clip); the weights behind
  the paper's benchmark results (``weights/controller_c3m``, ``weights/density_{trajectory,pointwise}``).
* ``"road"``: the kinematic car in road traffic (v in [0, 40] m/s, passenger-car inputs, lateral-acceleration
  limit, smooth saturation); ``weights/controller_c3m_road``, ``weights/density_{trajectory,pointwise}_road``.

Scenes choose the set of the run's system by kind (:attr:`ModelSet.scene_kinds`: for the car, recorded road scenes
use ``road``, the paper's artificial scenes ``paper``); ``--models`` overrides it. Adding a system's model set is
one :func:`register_model_set` call, in the module of its controller.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..systems.base import System
from ..systems.car import CarConfig, KinematicCar, car_domain
from ..systems.registry import DEFAULT_SYSTEM, make_system, system_entry
from .analytic import CarTrackingController
from .base import TrackingController

__all__ = ["DEFAULT_CONTROLLER", "CONTROLLER_CHOICES", "load_controller", "ModelSet", "MODEL_SETS",
           "DEFAULT_MODEL_SET", "model_set", "model_set_for_scene", "register_model_set", "register_controller",
           "controller_names"]

#: controller of the car's model sets when none is named (command line and library defaults)
DEFAULT_CONTROLLER = "c3m"
#: the car's controller names (other systems: :func:`controller_names`)
CONTROLLER_CHOICES = ("c3m", "analytic")


@dataclass(frozen=True)
class ModelSet:
    """A system's domain with the controller weights trained on it (density weights: ``density.registry``)."""

    #: name of the set ("paper", "road", ...), unique over all systems
    name: str
    #: file stem of the C3M weights in ``density_planner/weights`` (``None``: the set has no learned controller)
    controller_weights: str | None
    #: one line for help texts
    description: str
    #: registered system the set is for
    system: str = DEFAULT_SYSTEM
    #: the system's domain (default: the set's name)
    domain: str = ""
    #: controller used when none is named
    default_controller: str = DEFAULT_CONTROLLER
    #: scene kinds ("random", "file", "commonroad", "ind") for which this set is its system's default
    scene_kinds: tuple[str, ...] = ()
    #: suffix of the shipped density weights ``density_{arch}{suffix}.pt`` (default ``_{name}``)
    density_suffix: str | None = None

    def __post_init__(self) -> None:
        if not self.domain:
            object.__setattr__(self, "domain", self.name)
        if self.density_suffix is None:
            object.__setattr__(self, "density_suffix", f"_{self.name}")

    def make_system(self) -> System:
        """The set's system in its domain."""
        return make_system(self.system, self.domain)

    @property
    def car(self) -> CarConfig:
        """The car configuration of the set's domain (car sets only)."""
        if self.system != "car":
            raise ValueError(f"model set {self.name!r} is for the system {self.system!r}, not the car")
        return car_domain(self.domain)

    @property
    def speed_max(self) -> float:
        """Largest speed the set covers [m/s]: starts above it are outside the domain of its models."""
        return self.make_system().speed_max

    def controller_path(self) -> Path:
        from importlib import resources

        if self.controller_weights is None:
            raise ValueError(f"model set {self.name!r} ships no learned controller")
        return Path(str(resources.files("density_planner") / "weights" / f"{self.controller_weights}.pt"))


#: registered model sets by name
MODEL_SETS: dict[str, ModelSet] = {}
#: controller factories ``factory(system, model_set) -> TrackingController`` by (system name, controller name)
_CONTROLLERS: dict[tuple[str, str], Callable[[System, ModelSet], TrackingController]] = {}
_LOADED = False


def register_model_set(mset: ModelSet) -> ModelSet:
    """Register ``mset`` (its name must be new)."""
    old = MODEL_SETS.get(mset.name)
    if old is not None and old != mset:
        raise ValueError(f"model set {mset.name!r} registered twice")
    MODEL_SETS[mset.name] = mset
    return mset


def register_controller(system: str, name: str
                        ) -> Callable[[Callable[[System, ModelSet], TrackingController]], Callable]:
    """Decorator registering ``factory(system, model_set) -> TrackingController`` as controller ``name`` of
    ``system``."""

    def deco(factory: Callable[[System, ModelSet], TrackingController]) -> Callable:
        old = _CONTROLLERS.get((system, name))
        if old is not None and old is not factory:
            raise ValueError(f"controller {name!r} of system {system!r} registered twice")
        _CONTROLLERS[(system, name)] = factory
        return factory

    return deco


def _load_all() -> None:
    """Import every module of this package once (controller modules register their model sets)."""
    global _LOADED
    if _LOADED:
        return
    _LOADED = True
    package = importlib.import_module(__package__)
    for info in pkgutil.iter_modules(package.__path__):
        if not info.name.startswith("_") and info.name != "registry":
            importlib.import_module(f"{__package__}.{info.name}")


def controller_names(system: str = DEFAULT_SYSTEM) -> list[str]:
    """Controller names registered for ``system``."""
    _load_all()
    return [name for (sys_name, name) in _CONTROLLERS if sys_name == system]


def model_set(name: str | None = None) -> ModelSet:
    """The model set ``name`` (``None``: :data:`DEFAULT_MODEL_SET`)."""
    _load_all()
    name = DEFAULT_MODEL_SET if name is None else name
    try:
        return MODEL_SETS[name]
    except KeyError:
        raise ValueError(f"unknown model set {name!r}; valid choices: {', '.join(MODEL_SETS)}") from None


def model_set_for_scene(kind: str | None, override: str | None = None, system: str | None = None) -> ModelSet:
    """The model set of ``system`` (default: the car) for a scene kind (``"random"``, ``"commonroad"``, ...), unless
    ``override`` names one (which must belong to ``system`` when that is given)."""
    _load_all()
    if override is not None and override != "auto":
        mset = model_set(override)
        if system is not None and mset.system != system:
            raise ValueError(f"model set {override!r} is for the system {mset.system!r}, not {system!r}; choose one "
                             f"of {', '.join(n for n, m in MODEL_SETS.items() if m.system == system)}")
        return mset
    system = system or DEFAULT_SYSTEM
    system_entry(system)  # an unknown name fails here, with the valid choices
    sets = [m for m in MODEL_SETS.values() if m.system == system]
    if not sets:
        raise ValueError(f"no model set is registered for the system {system!r}")
    return next((m for m in sets if kind in m.scene_kinds), sets[0])


def load_controller(spec: str | Path | None = None, car: CarConfig | None = None,
                    models: str | ModelSet | None = None) -> TrackingController:
    """A tracking controller of a model set's system.

    Args:
        spec: a controller name registered for the set's system (the car: ``"c3m"``, the learned contraction
            controller of the model set, ``"analytic"``, hand-written feedback with the set's input limits), the
            path of a C3M weights file (``NAME.pt`` with ``NAME.json`` beside it; its domain is read from the JSON),
            or ``None`` / ``"auto"`` for the set's default controller.
        car: car configuration (input bounds, saturation) of a car set; default: the model set's domain.
        models: model set name or :class:`ModelSet` (default :data:`DEFAULT_MODEL_SET`).

    Raises:
        ValueError: unknown name; :class:`~density_planner.errors.CheckpointError` (a ``ValueError``) for a
            missing, corrupt or mismatched weights file.
    """
    from .c3m import load_c3m_controller

    mset = models if isinstance(models, ModelSet) else model_set(models)
    spec = mset.default_controller if spec is None or spec == "auto" else spec
    if isinstance(spec, str) and (mset.system, spec) in _CONTROLLERS:
        system = KinematicCar(car) if car is not None else mset.make_system()
        return _CONTROLLERS[(mset.system, spec)](system, mset)
    path = Path(spec)
    if mset.system == "car" and (path.suffix in (".pt", ".json") or path.exists() or path.with_suffix(".pt").exists()):
        return load_c3m_controller(path, car)
    raise ValueError(
        f"unknown controller {str(spec)!r} for the system {mset.system!r}; valid choices: "
        f"{', '.join(controller_names(mset.system))}" + (" or a C3M weights file (.pt)" if mset.system == "car" else "")
    )


# ------------------------------------------------------------------------------------ the car's model sets
register_model_set(ModelSet(
    "paper", "controller_c3m", "the paper's box: v in [0, 10] m/s, inputs +-3, hard clip (reproduces the paper's "
    "results)", scene_kinds=("random", "file"), density_suffix=""))
register_model_set(ModelSet(
    "road", "controller_c3m_road", "road traffic: v in [0, 40] m/s, passenger-car inputs, lateral-acceleration "
    "limit, smooth saturation", scene_kinds=("commonroad", "ind")))
#: model set used when neither a scene kind nor a name chooses one
DEFAULT_MODEL_SET = "paper"


@register_controller("car", "c3m")
def _car_c3m(system: System, mset: ModelSet) -> TrackingController:
    from ..errors import CheckpointError
    from .c3m import load_c3m_controller

    path = mset.controller_path()
    if not path.is_file():
        raise CheckpointError(
            f"the package ships no C3M weights for the model set {mset.name!r} ({path}); train them (see "
            "docs/controller.md) or choose another model set"
        )
    assert isinstance(system, KinematicCar)
    return load_c3m_controller(path, system.config)


@register_controller("car", "analytic")
def _car_analytic(system: System, mset: ModelSet) -> TrackingController:
    assert isinstance(system, KinematicCar)
    return CarTrackingController(car=system.config)

"""Controller selection by name (``"c3m"``, ``"analytic"`` or a weights path) and the named **model sets**.

A model set bundles a car domain (:data:`density_planner.systems.car.CAR_DOMAINS`), the C3M weights trained on it
and (in :mod:`density_planner.density.registry`) the density predictors trained on that closed loop:

* ``"paper"``: the paper's box (v in [0, 10] m/s, inputs +-3, hard clip); the weights behind the paper's
  benchmark results (``weights/controller_c3m``, ``weights/density_{trajectory,pointwise}``).
* ``"road"``: road traffic (v in [0, 40] m/s, passenger-car inputs, lateral-acceleration limit, smooth
  saturation); ``weights/controller_c3m_road``, ``weights/density_{trajectory,pointwise}_road``.

Scenes choose their set by kind (:data:`SCENE_MODEL_SETS`: recorded road scenes use ``road``, the paper's
artificial scenes ``paper``); ``--models`` overrides it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..systems.car import CarConfig, car_domain
from .analytic import CarTrackingController
from .base import TrackingController

__all__ = ["DEFAULT_CONTROLLER", "CONTROLLER_CHOICES", "load_controller", "ModelSet", "MODEL_SETS",
           "DEFAULT_MODEL_SET", "SCENE_MODEL_SETS", "model_set", "model_set_for_scene"]

#: controller used when none is named (command line and library defaults)
DEFAULT_CONTROLLER = "c3m"
CONTROLLER_CHOICES = ("c3m", "analytic")


@dataclass(frozen=True)
class ModelSet:
    """A car domain with the controller weights trained on it (density weights: ``density.registry``)."""

    #: name of the set ("paper", "road")
    name: str
    #: car domain (boxes, input limits, saturation): a key of ``CAR_DOMAINS``
    domain: str
    #: file stem of the C3M weights in ``density_planner/weights``
    controller_weights: str
    #: one line for help texts
    description: str

    @property
    def car(self) -> CarConfig:
        """The car configuration of the set's domain."""
        return car_domain(self.domain)

    @property
    def speed_max(self) -> float:
        """Largest speed the set covers [m/s]: starts above it are outside the domain of its models."""
        return self.car.speed_max

    def controller_path(self) -> Path:
        from importlib import resources

        return Path(str(resources.files("density_planner") / "weights" / f"{self.controller_weights}.pt"))


#: the model sets shipped with the package
MODEL_SETS: dict[str, ModelSet] = {
    "paper": ModelSet("paper", "paper", "controller_c3m",
                      "the paper's box: v in [0, 10] m/s, inputs +-3, hard clip (reproduces the paper's results)"),
    "road": ModelSet("road", "road", "controller_c3m_road",
                     "road traffic: v in [0, 40] m/s, passenger-car inputs, lateral-acceleration limit, smooth "
                     "saturation"),
}
#: model set used when neither a scene kind nor a name chooses one
DEFAULT_MODEL_SET = "paper"
#: model set by scene kind: recorded road scenes need the road domain, the paper's artificial scenes the paper's
SCENE_MODEL_SETS = {"random": "paper", "file": "paper", "commonroad": "road", "ind": "road"}


def model_set(name: str | None = None) -> ModelSet:
    """The model set ``name`` (``None``: :data:`DEFAULT_MODEL_SET`)."""
    name = DEFAULT_MODEL_SET if name is None else name
    try:
        return MODEL_SETS[name]
    except KeyError:
        raise ValueError(f"unknown model set {name!r}; valid choices: {', '.join(MODEL_SETS)}") from None


def model_set_for_scene(kind: str | None, override: str | None = None) -> ModelSet:
    """The model set for a scene kind (``"random"``, ``"commonroad"``, ...), unless ``override`` names one."""
    if override is not None:
        return model_set(override)
    return model_set(SCENE_MODEL_SETS.get(kind or "", DEFAULT_MODEL_SET))


def load_controller(spec: str | Path | None = None, car: CarConfig | None = None,
                    models: str | ModelSet | None = None) -> TrackingController:
    """Controller for the kinematic car.

    Args:
        spec: ``"c3m"`` (the learned contraction controller of the model set), ``"analytic"`` (hand-written
            feedback, with the set's input limits), the path of a C3M weights file (``NAME.pt`` with ``NAME.json``
            beside it; its domain is read from the JSON), or ``None`` for :data:`DEFAULT_CONTROLLER`.
        car: car configuration (input bounds, saturation); default: the model set's domain.
        models: model set name or :class:`ModelSet` (default :data:`DEFAULT_MODEL_SET`).

    Raises:
        ValueError: unknown name; :class:`~density_planner.errors.CheckpointError` (a ``ValueError``) for a
            missing, corrupt or mismatched weights file.
    """
    from ..errors import CheckpointError
    from .c3m import load_c3m_controller

    spec = DEFAULT_CONTROLLER if spec is None else spec
    mset = models if isinstance(models, ModelSet) else model_set(models)
    if isinstance(spec, str) and spec == "analytic":
        return CarTrackingController(car=car or mset.car)
    if isinstance(spec, str) and spec == "c3m":
        path = mset.controller_path()
        if not path.is_file():
            raise CheckpointError(
                f"the package ships no C3M weights for the model set {mset.name!r} ({path}); train them (see "
                "docs/controller.md) or choose another model set"
            )
        return load_c3m_controller(path, car or mset.car)
    path = Path(spec)
    if path.suffix in (".pt", ".json") or path.exists() or path.with_suffix(".pt").exists():
        return load_c3m_controller(path, car)
    raise ValueError(
        f"unknown controller {str(spec)!r}; valid choices: {', '.join(CONTROLLER_CHOICES)} or a weights file (.pt)"
    )

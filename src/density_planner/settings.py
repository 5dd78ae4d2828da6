"""The run configuration: one typed section per component, as read from ``--config FILE.toml`` and ``--set``.

Only the command line and benchmark scripts build a :class:`RunConfig`; library code receives the section it
needs. Example ``run.toml``::

    [density_planner]
    n_candidates = 50

    [density_planner.cost.weights]
    collision = 0.2

    [liouville]
    integrator = "euler"
    dt = 0.01
"""

from __future__ import annotations

from dataclasses import dataclass, field

from .density.liouville import LiouvilleConfig
from .environment.commonroad import CommonRoadSceneConfig
from .environment.ind import IndSceneConfig
from .environment.random_scene import RandomSceneConfig
from .planners.density_planner import DensityPlannerConfig

__all__ = ["RunConfig"]


@dataclass(frozen=True)
class RunConfig:
    """All configurable parts of a run (TOML sections)."""

    #: [density_planner]: the two-stage density planner, including its cost terms ([density_planner.cost])
    density_planner: DensityPlannerConfig = field(default_factory=DensityPlannerConfig)
    #: [liouville]: numerics of the exact density propagation
    liouville: LiouvilleConfig = field(default_factory=LiouvilleConfig)
    #: [random_scene]: the artificial scene generator
    random_scene: RandomSceneConfig = field(default_factory=RandomSceneConfig)
    #: [ind]: scenes from inD recordings
    ind: IndSceneConfig = field(default_factory=IndSceneConfig)
    #: [commonroad]: scenes from CommonRoad scenarios
    commonroad: CommonRoadSceneConfig = field(default_factory=CommonRoadSceneConfig)

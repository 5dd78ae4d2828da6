"""The run configuration: one typed section per component, as read from ``--config FILE.toml`` and ``--set``.

Only the command line and benchmark scripts build a :class:`RunConfig`; library code receives the section it
needs. Example ``run.toml``::

    [density_planner]
    n_candidates = 50

    [density_planner.cost.weights]
    collision = 0.2

    [planning]
    horizon = 10.0          # [s], a whole number of segments; omit to follow the scene (else 10 s)
    segment_duration = 1.0

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
from .evaluation.config import EvaluationConfig
from .evaluation.online import OnlineConfig
from .evaluation.verdict import VerdictConfig
from .io.commonroad_solution import SolutionConfig
from .planners.density_planner import DensityPlannerConfig
from .planners.mpc import MPCConfig, TubeMPCConfig
from .planners.oracle import OracleConfig
from .planners.problem import PlanningConfig
from .planners.sampling import SamplingConfig
from .planners.search import SearchConfig
from .risk.collision import RiskConfig
from .systems.registry import SystemConfig

__all__ = ["RunConfig"]


@dataclass(frozen=True)
class RunConfig:
    """All configurable parts of a run (TOML sections)."""

    #: [system]: the dynamics, its model set, the tracking controller and the density predictor (--system,
    #: --models, --controller, --density write here)
    system: SystemConfig = field(default_factory=SystemConfig)
    #: [planning]: horizon, segment length and time steps shared by every planner and the evaluation
    planning: PlanningConfig = field(default_factory=PlanningConfig)

    #: [density_planner]: the two-stage density planner, including its cost terms ([density_planner.cost])
    density_planner: DensityPlannerConfig = field(default_factory=DensityPlannerConfig)
    #: [liouville]: numerics of the exact density propagation
    liouville: LiouvilleConfig = field(default_factory=LiouvilleConfig)
    #: [random_scene]: the artificial scene generator
    random_scene: RandomSceneConfig = field(default_factory=RandomSceneConfig)
    #: [mpc]: standard MPC M0 (planner "mpc"); its tube_radius is ignored (always 0)
    mpc: MPCConfig = field(default_factory=MPCConfig)
    #: [tube_mpc]: tube MPC M1-M3 (planners "tube_mpc_0.3", "tube_mpc_0.5", "tube_mpc_1.0" fix their radius;
    #: planner "tube_mpc" uses tube_radius); 10 IPOPT iterations per step as the paper's code
    tube_mpc: TubeMPCConfig = field(default_factory=TubeMPCConfig)
    #: [oracle]: the full-horizon NLP from the true initial state (planner "oracle")
    oracle: OracleConfig = field(default_factory=OracleConfig)
    #: [search]: the search-based optimiser of the ablation (planner "search")
    search: SearchConfig = field(default_factory=SearchConfig)
    #: [sampling]: the sampling-based optimiser of the ablation (planner "sampling")
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    #: [ind]: scenes from inD recordings
    ind: IndSceneConfig = field(default_factory=IndSceneConfig)
    #: [commonroad]: scenes from CommonRoad scenarios
    commonroad: CommonRoadSceneConfig = field(default_factory=CommonRoadSceneConfig)
    #: [evaluation]: closed-loop evaluation and benchmarks (Monte-Carlo samples, failure thresholds, execution)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    #: [verdict]: how every plan is judged (vehicle rectangle, road tolerance; see evaluation/verdict.py)
    verdict: VerdictConfig = field(default_factory=VerdictConfig)
    #: [solution]: the CommonRoad solution file of `plan --env commonroad` (vehicle model and type, cost function)
    solution: SolutionConfig = field(default_factory=SolutionConfig)
    #: [risk]: collision with the vehicle's body and the estimator of its probability
    risk: RiskConfig = field(default_factory=RiskConfig)
    #: [online]: the receding-horizon runner (`density-planner drive`) and its occupancy prediction
    online: OnlineConfig = field(default_factory=OnlineConfig)

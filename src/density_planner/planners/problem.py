"""The planning problem: a scene, the initial-state distribution, the system and the reference parameterisation.

Time axis (the one rule every planner, cost and metric follows): a plan starts at the scene's ABSOLUTE time
``scene.t_start`` (on the occupancy grid's clock; default the grid's ``t0``) and its planning-grid point ``k`` lies
at ``t_start + k * plan_dt``. :meth:`PlanningProblem.slices` turns these times into occupancy slices through
:meth:`~density_planner.environment.grid.OccupancyGrid.slices_for`, which refuses a horizon that leaves the grid.
The horizon and the segment length are configuration (:class:`PlanningConfig`, TOML section ``[planning]``).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..checks import check_seed
from ..control.reference import PiecewiseConstantInputs
from ..density.distributions import InitialDistribution, paper_gaussian_mixture
from ..environment.scene import START_OCCUPIED_THRESHOLD, Scene, validate_scene
from ..risk.collision import CollisionModel, RiskConfig
from ..systems.base import System
from ..systems.registry import make_system

__all__ = ["PlanningProblem", "PlanningConfig", "DEFAULT_HORIZON", "initial_error_box", "initial_law_on_road"]

log = logging.getLogger(__name__)

#: the paper's planning horizon [s] (10 segments of 1 s); the shipped learned density predictors are trained for it
#: (and chain windows of it for longer horizons)
DEFAULT_HORIZON = 10.0


@dataclass(frozen=True)
class PlanningConfig:
    """``[planning]``: the time axis shared by every planner (density planner, search, sampling, MPC, oracle) and
    the evaluation.

    The horizon is ``horizon`` when given (explicit configuration wins); else the scene's suggestion
    ``scene.meta["horizon"]`` [s from the plan's start] (e.g. the end of a CommonRoad goal's time interval),
    rounded up to whole segments and clamped to ``[min_horizon, max_horizon]`` and to the scene's time span; else
    :data:`DEFAULT_HORIZON` (10 s, the paper). A CommonRoad plan thus ends with its goal's time interval, as the
    benchmark's solutions do: what follows is neither planned nor judged (``min_horizon`` = 1 s, one segment).
    The shipped learned density predictors are trained for 10 s of 1-s segments at 0.1 s; a shorter horizon is one
    window whose inputs after the horizon are zero, cut to the horizon (the closed loop is causal; measured as
    accurate as the window's own inputs, docs/density.md), a longer one chains windows of 10 s
    (:meth:`~density_planner.density.network.LearnedDensity.windows`; measured as accurate as the first window).
    ``max_horizon`` is 30 s (the CommonRoad suite's goals end up to 20.4 s after the start; the cap bounds memory
    and time, it is not meant to cut a goal off). For another segment
    length or planning step the planner falls back to exact Liouville (logged warning; minutes per plan instead of
    seconds) or, when a learned predictor is named explicitly, refuses with an error. A goal that starts later than
    ``max_horizon`` cannot be reached.
    """

    #: planning horizon [s], a whole number of segments (None: the scene's suggestion, else 10 s)
    horizon: float | None = None
    #: cap on a horizon suggested by the scene [s] (an explicit ``horizon`` is not capped); above 10 s the
    #: learned predictors chain windows of their 10 s
    max_horizon: float = 30.0
    #: floor of a horizon suggested by the scene [s] (a plan ends with its goal's time interval: one segment at
    #: least)
    min_horizon: float = 1.0
    #: duration of one piecewise-constant segment of the reference inputs [s]
    segment_duration: float = 1.0
    #: step of the planning grid on which costs, risks and metrics are evaluated [s]
    plan_dt: float = 0.1
    #: fine integration step of the reference and of closed-loop simulations [s]
    dt: float = 0.01

    def __post_init__(self) -> None:
        for name in ("max_horizon", "min_horizon", "segment_duration", "plan_dt", "dt"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"planning.{name} must be a finite number > 0, got {v!r}")
        if self.horizon is not None:
            h = self.horizon
            if isinstance(h, bool) or not isinstance(h, (int, float)) or not math.isfinite(h) or h <= 0:
                raise ValueError(f"planning.horizon must be a finite number > 0, got {h!r}")
            self._segments(h, "planning.horizon")
        PiecewiseConstantInputs(1, self.segment_duration, self.dt, self.plan_dt)  # validates the ratios

    def _segments(self, horizon: float, what: str) -> int:
        n = horizon / self.segment_duration
        if abs(n - round(n)) > 1e-6 * max(1.0, n) or round(n) < 1:
            raise ValueError(
                f"{what} ({horizon:g} s) must be a whole number of segments of planning.segment_duration = "
                f"{self.segment_duration:g} s"
            )
        return int(round(n))

    def resolve_horizon(self, scene: Scene | None = None) -> float:
        """The horizon [s] for ``scene`` (see the class docstring)."""
        if self.horizon is not None:
            return float(self.horizon)
        suggested = None if scene is None else scene.meta.get("horizon", getattr(scene, "horizon", None))
        if scene is None or suggested is None or scene.t_start is None:  # (Scene.__post_init__ sets t_start)
            return DEFAULT_HORIZON
        try:
            suggested = float(suggested)
        except (TypeError, ValueError):
            raise ValueError(f"scene {scene.name!r}: meta['horizon'] must be a number [s], got {suggested!r}") from None
        if not math.isfinite(suggested) or suggested <= 0:
            raise ValueError(f"scene {scene.name!r}: suggested horizon must be > 0 s, got {suggested}")
        seg = self.segment_duration
        n = max(1, math.ceil(max(suggested, min(self.min_horizon, self.max_horizon)) / seg - 1e-9))
        n = min(n, max(1, math.floor(self.max_horizon / seg + 1e-9)))
        span = scene.grid.t_end - scene.t_start
        n = min(n, max(1, math.floor(span / seg + 1e-9)))
        horizon = n * seg
        if not math.isclose(horizon, suggested):
            log.info("scene %s suggests a %.3g-s horizon; planning over %.3g s (whole %.3g-s segments, at most "
                     "planning.min_horizon/max_horizon = %.3g/%.3g s and the scene's %.3g s)", scene.name, suggested,
                     horizon, seg, self.min_horizon, self.max_horizon, span)
        return horizon

    def parameterization(self, scene: Scene | None = None) -> PiecewiseConstantInputs:
        """The reference parameterisation over the horizon for ``scene``."""
        horizon = self.resolve_horizon(scene)
        n = self._segments(horizon, "planning horizon")
        return PiecewiseConstantInputs(n, float(self.segment_duration), float(self.dt), float(self.plan_dt))


def initial_law_on_road(scene: Scene, system: System, dist: InitialDistribution) -> InitialDistribution:
    """``dist`` conditioned on the system's body lying inside the scene's drivable area
    (:class:`~density_planner.density.distributions.Conditioned` with
    :class:`~density_planner.environment.road.BodyOnRoad`) when ``scene.meta["initial_on_road"]`` is true and the
    scene has a road; ``dist`` itself otherwise, or (logged) when the law gives the event less than 1 % (a recorded
    start off the road)."""
    road = getattr(scene, "road", None)
    if not scene.meta.get("initial_on_road") or road is None or road.drivable is None:
        return dist
    if system.heading_index is None:
        return dist
    from ..density.distributions import Conditioned
    from ..environment.road import BodyOnRoad

    ix, iy = system.position_indices
    accept = BodyOnRoad(road.drivable, road.vehicle_length, road.vehicle_width, (ix, iy), system.heading_index)
    try:
        return Conditioned(dist, accept, description="body on the road", min_acceptance=0.01)
    except ValueError as exc:
        log.warning("scene %s: initial law not conditioned on the road: %s", scene.name, exc)
        return dist


def initial_error_box(scene: Scene, system: System) -> tuple[float, ...]:
    """Half-widths (``system.nx``) of the initial-error box of a plan on ``scene``: the system's XE0 box
    (``system.initial_error_max``), with the position, heading and speed entries replaced by the scene's measurement
    errors ``scene.meta["initial_error"]`` (``{"position", "heading", "speed"}``) where the scene gives them (e.g.
    CommonRoad scenes, ``commonroad.initial_error``)."""
    box = list(system.initial_error_max)
    given = (scene.meta or {}).get("initial_error") if isinstance(getattr(scene, "meta", None), dict) else None
    if given:
        for i in system.position_indices:
            box[i] = float(given["position"])
        for index, key in ((system.heading_index, "heading"), (system.speed_index, "speed")):
            if index is not None:
                box[index] = float(given[key])
    return tuple(box)


@dataclass
class PlanningProblem:
    """Everything a planner needs.

    Attributes:
        scene: occupancy grid, nominal start, goal position and planning box.
        initial_distribution: law of the true initial state (full state, ``system.nx`` dimensions).
        system: the dynamics (default: the registry's default system, the kinematic car).
        parameterization: reference-input parameterisation (10 segments of 1 s, 0.01-s fine grid, 0.1-s planning
            grid); its horizon must not exceed the scene's time span.
        risk: how collision is read (body) and its probability estimated (section ``[risk]``).
        start_threshold: a start whose P_occ exceeds this is refused (:func:`~density_planner.environment.scene.
            validate_scene`); an online replan (:mod:`density_planner.evaluation.online`) passes ``inf``: a vehicle
            that is already in an occupied cell must still be able to plan its way out.
    """

    scene: Scene
    initial_distribution: InitialDistribution
    system: System = field(default_factory=make_system)
    parameterization: PiecewiseConstantInputs = field(default_factory=PiecewiseConstantInputs)
    risk: RiskConfig = field(default_factory=RiskConfig)
    start_threshold: float = START_OCCUPIED_THRESHOLD
    #: ``(nx,)`` start of the reference when it is not the initial law's mean (None: the mean); an online replan
    #: continues the previous reference from its state at the replanning time while the law is centred on the
    #: measurement (:mod:`density_planner.evaluation.online`)
    reference_origin: Tensor | None = None

    def collision(self, device: torch.device | str | None = None, *, road_edge: str | None = None) -> CollisionModel:
        """The collision model of this problem (scene grid, system, risk settings) on ``device``; ``road_edge``
        overrides ``risk.road_edge`` (the MPC and oracle constraints, which have no road term, pass
        ``"occupied"``; :func:`~density_planner.risk.collision.collision_grid`)."""
        return CollisionModel.for_scene(self.scene, self.system, self.risk, device=device, road_edge=road_edge)

    def __post_init__(self) -> None:
        validate_scene(self.scene, start_threshold=self.start_threshold)
        if not isinstance(self.initial_distribution, InitialDistribution):
            raise ValueError(
                f"initial_distribution must be an InitialDistribution, got {type(self.initial_distribution).__name__}"
            )
        if self.initial_distribution.dim != self.system.nx:
            raise ValueError(
                f"initial_distribution has dimension {self.initial_distribution.dim}, the system state has "
                f"{self.system.nx}"
            )
        self.scene.grid.check_span(self.t_start, self.parameterization.horizon)
        if self.reference_origin is not None:
            origin = torch.as_tensor(self.reference_origin)
            if origin.shape != (self.system.nx,) or not bool(torch.isfinite(origin).all()):
                raise ValueError(f"reference_origin must be a finite state of shape ({self.system.nx},), got shape "
                                 f"{tuple(origin.shape)}")

    @classmethod
    def from_scene(
        cls,
        scene: Scene,
        *,
        seed: int = 0,
        system: System | None = None,
        parameterization: PiecewiseConstantInputs | None = None,
        risk: RiskConfig | None = None,
        planning: PlanningConfig | None = None,
    ) -> PlanningProblem:
        """The paper's default problem: its 5-component Gaussian mixture on the initial-error box
        (:func:`initial_error_box`: the system's XE0 box, with the scene's own position / heading / speed errors where
        it gives them) around the scene start (``system.state_from_pose(*scene.start)``), drawn with ``seed``, and
        conditioned on the body being on the road where the scene asks for it (:func:`initial_law_on_road`). The
        horizon comes from ``parameterization`` if given, else from ``planning`` (default :class:`PlanningConfig`:
        the scene's suggestion or 10 s)."""
        check_seed("seed", seed)
        system = system or make_system()
        start = system.state_from_pose(*scene.start)
        mixture = paper_gaussian_mixture(start, initial_error_box(scene, system),
                                         torch.Generator().manual_seed(seed), bounds=system.state_bounds)
        dist = initial_law_on_road(scene, system, mixture)
        if parameterization is None:
            parameterization = (planning or PlanningConfig()).parameterization(scene)
        return cls(scene, dist, system, parameterization, risk or RiskConfig())

    @property
    def t_start(self) -> float:
        """Absolute time [s] of the plan's start on the occupancy grid's clock (``scene.t_start``)."""
        assert self.scene.t_start is not None  # set by Scene.__post_init__
        return self.scene.t_start

    def slices(self, n: int | None = None, device: torch.device | str = "cpu", *, dt: float | None = None) -> Tensor:
        """Occupancy slices ``(n,)`` of the planning times ``t_start + k * dt`` (default: ``plan_dt`` over the whole
        horizon): the one place planners, costs and metrics get their slices from. Raises :class:`ValueError` when
        the times leave the grid's span."""
        par = self.parameterization
        n = par.n_plan if n is None else int(n)
        return self.scene.grid.slices_for(self.t_start, par.plan_dt if dt is None else dt, n).to(device)

    def reference_start(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Tensor:
        """Start of the reference: ``reference_origin`` when given, else the mean of the initial distribution, with
        the states a plan cannot know at their nominal values (``system.nominal_state``; for the car a zero heading
        bias: the reference is the nominal, unbiased trajectory, the bias only enters the measurement)."""
        base = self.initial_distribution.mean if self.reference_origin is None else torch.as_tensor(
            self.reference_origin, dtype=self.initial_distribution.mean.dtype)
        start = self.system.nominal_state(base.clone())
        return start.to(dtype=dtype, device=device)

    @property
    def goal(self) -> tuple[float, float]:
        return self.scene.goal

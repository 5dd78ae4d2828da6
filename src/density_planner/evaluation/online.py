"""Online (receding-horizon) driving: replan every period from the current measurement with the current prediction.

:func:`drive` runs the true vehicle in closed loop over a scene (``density-planner drive``):

1. The true initial state is drawn from the scene's initial distribution (seeded). The first plan is the full
   two-stage plan from that distribution at the scene start (not timed against the budget), on the occupancy the
   prediction shows at the start (:func:`initial_problem`: with the oracle, the offline plan; with the
   observed-only prediction, what was observed by the start).
2. Every ``period`` seconds (default: one input segment, 1 s) at time ``t``: the vehicle's measurement ``x_hat`` (the
   car's biased heading) becomes the centre of the scene's initial law (the same Gaussian mixture, re-centred: the
   measurement error law of the scene); the prediction layer (:mod:`~density_planner.environment.prediction`) renders
   the occupancy over ``[t, t + H]`` from what was observed up to ``t``; the planner replans over its horizon ``H``
   (10 s with the learned predictors; a measured speed below the learned predictor's training range is raised to its
   lower end, and the predictor never falls back to exact Liouville online) *warm-started* from the previous plan
   shifted by ``t - t_plan`` (:func:`shift_parameters`; a shift by part of a segment refitted to the previous
   path, :func:`refit_shift`): stage 2 only, ``replan_epochs`` iterations on
   ``replan_samples`` samples. Stage 1 (candidates) runs only when the warm start is invalid: no previous plan, or
   the measurement lies farther than ``restart_distance`` from the previous reference at ``t``; or to *rescue* a
   warm replan whose collision probability exceeds ``rescue_p_coll``: a replan from stage 1, the warm start among
   its candidates, competes with it on the same samples and the lower stage-2 objective is tracked (:func:`_rescue`).
3. A replan that overruns its wall-time budget (``time_budget``) is, by ``overrun``: tracked from the first
   planning step after it finished (``"delay"``, default: the controller tracks the previous reference meanwhile
   and no replan starts while one runs), discarded as a failure (``"discard"``) or used at once (``"use"``: the
   compute taken as instantaneous). A replan that fails (exception, no finite cost) or is discarded leaves the
   controller tracking the previous reference, unless that reference is unsafe under the current prediction (its
   nominal path's collision probability exceeds ``unsafe_p_coll``) or has ended; then it tracks the least-risk
   braking manoeuvre (full braking with each steering rate of ``brake_steer``, the one with the smallest nominal
   collision probability) when that is safer than the previous reference (an ended reference is always replaced).
   Every fallback is recorded with its reason.
4. The controller tracks the newest reference (explicit Euler at ``evaluation.dt``, one state, as on the car;
   a braking car stops instead of reversing: :meth:`System.standstill`).
   The run ends when the goal's time interval has ended, or earlier when the vehicle is inside the goal region
   during it (road scenes); scenes without a goal region run for ``duration`` (default: the planning horizon).
5. The executed trajectory is judged against the ground truth (:func:`~density_planner.evaluation.verdict.judge`:
   true shapes of the recorded road users, the road, the goal region in its time interval, the model box).

Because every replan has the full horizon ``H`` and the goal cost of the region *in time*, online driving can meet
goals whose time interval starts after the offline plan's horizon (the offline plan is clamped to 10 s).
"""

from __future__ import annotations

import copy
import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch
from torch import Tensor

from ..checks import check_seed
from ..control.base import TrackingController
from ..control.reference import PiecewiseConstantInputs, Reference, make_reference
from ..environment.prediction import Prediction, PredictionConfig, make_prediction
from ..environment.scene import Scene
from ..planners.base import Planner, PlanResult, PlanStatus
from ..planners.problem import PlanningConfig, PlanningProblem
from ..risk.collision import RiskConfig
from ..systems.base import System
from .config import EvaluationConfig
from .verdict import Verdict, VerdictConfig, judge

if TYPE_CHECKING:
    from ..planners.density_planner import DensityPlanner

__all__ = ["OnlineConfig", "Replan", "DriveResult", "drive", "initial_problem", "shift_parameters", "shifted_plan",
           "holds_speed", "refit_shift", "braking_parameters", "warm_replan", "recentred"]

log = logging.getLogger(__name__)

#: values of ``online.overrun`` (:class:`OnlineConfig`)
OVERRUN_MODES = ("delay", "discard", "use")


@dataclass(frozen=True)
class OnlineConfig:
    """``[online]``: the receding-horizon runner (module docstring)."""

    #: time between replans [s] (a multiple of the planning grid step); 0 (default): one input segment
    #: (``planning.segment_duration``, 1 s), so that every warm start is an exact shift of the previous plan. With
    #: 0.5 s (half a segment) the shifted inputs can only approximate the old path (:func:`refit_shift`): on 14
    #: suite scenarios (docs/history.md, stop 33; the replan step of then, 5x today's) 0.5 s passed 10 (observed
    #: prediction) / 11 (oracle) verdicts and 1 s 13 / 14, the offline plan 14; the half-segment replans left the
    #: road in three turns
    period: float = 0.0
    #: stage-2 iterations of a warm-started replan (at most: fewer with ``replan_patience``)
    replan_epochs: int = 10
    #: a replan stops once its best objective has not fallen (by ``density_planner.patience_tolerance`` relative
    #: plus ``backtrack_slack``) for this many iterations (0: all ``replan_epochs``). A warm start that is still
    #: optimal (a scene as predicted, a measurement on the plan) then costs 3 iterations instead of 10 (issue 17's
    #: speed target, ``benchmarks/bench_replan.py``: docs/planner.md, "Online driving"); a replan that improves
    #: goes on
    replan_patience: int = 2
    #: initial samples of a replan (0: density_planner.n_samples)
    replan_samples: int = 0
    #: Adam learning rate of a replan (0, default: density_planner.lr, 0.01). Until stop 33 five times that (0.05,
    #: with a clip of 0.1), so that 10 steps could move a parameter further; but a warm start is nearly converged,
    #: and from it the larger first steps raised the objective (the path moves metres 10 s ahead) in ~55 % of the
    #: replans, which then returned their warm start unchanged. With the planner's step on 14 + 6 suite scenarios
    #: (docs/history.md, stop 33): 67 % of the replans improved on their warm start (45 %), and 14 / 14 and 2 / 6
    #: online runs passed with the observed-only prediction (13 / 14 and 1 / 6)
    replan_lr: float = 0.0
    #: largest change of a parameter per replan step (0, default: density_planner.update_clip, 0.02)
    replan_update_clip: float = 0.0
    #: wall-time budget of one replan [s] (prediction rendering excluded: the perception stack's work)
    time_budget: float = 0.5
    #: what becomes of a replan that overruns ``time_budget``: "delay" (it takes effect at the first planning step
    #: after it finished, ``ceil(wall / plan_dt)`` steps after its measurement; the controller tracks the previous
    #: reference meanwhile and no replan starts while one runs: one planning thread, as on a vehicle), "discard"
    #: (dropped: the previous reference or the braking fallback), "use" (in effect at its measurement time, as if the
    #: compute took no time: what the method does on a fast enough machine, and the only deterministic choice
    #: whatever the machine's speed)
    overrun: str = "delay"
    #: run length [s] on scenes without a goal time interval; 0 = the planning horizon
    duration: float = 0.0
    #: cap on the run length [s] (road scenes run until the goal's time interval ends)
    max_duration: float = 30.0
    #: stop as soon as the vehicle is in the goal region during its time interval (road scenes)
    stop_at_goal: bool = True
    #: the previous reference is unsafe when its nominal path's collision probability under the current prediction
    #: exceeds this; the least-risk braking manoeuvre then replaces it if its own is lower
    unsafe_p_coll: float = 0.2
    #: the warm start is invalid (stage 1 reruns) when the measurement is farther than this from the previous
    #: reference's position at the replanning time [m]
    restart_distance: float = 3.0
    #: a warm replan continues the previous reference from its state at the replanning time (the law of the true
    #: state is re-centred on the measurement; the controller goes on tracking the same path); false: the new
    #: reference starts at the measurement, and a heading error there turns the whole warm start (3.8 m off the
    #: goal after 7.5 s at 10 m/s and 0.05 rad)
    continue_reference: bool = True
    #: a replan's horizon ends when the goal is to be reached (whole segments, at least one): on road scenes with the
    #: goal's time interval, as the offline plan's does; on other scenes with the first plan's horizon, whose goal
    #: cost is at its end, so that the shifted plan stays a solution (false: every replan plans the full horizon
    #: from its own time and reaches for the goal that much later)
    shrink_horizon: bool = True
    #: steering rates of the braking candidates, as fractions of the largest steering rate
    brake_steer: tuple[float, ...] = (-1.0, -0.5, 0.0, 0.5, 1.0)
    #: evaluate the C3M controller of the car torch-free in the online loop (:class:`~density_planner.control.fast.
    #: NumpyC3M`, equal to the torch controller to 1e-6; false: the torch controller)
    fast_controller: bool = True
    #: Gauss-Newton iterations that refit a warm start shifted by part of a segment to the previous reference's
    #: path (:func:`refit_shift`; 0: the time-averaged inputs alone). With a 0.5-s period and 1-s segments the
    #: averaged inputs drift off the old path (CHN_Sha-12_1: 1.2 m, 2 m^2 of the body off the road in the turn 11 s
    #: ahead), and 10 stage-2 steps did not repair it: every replan added its drift and the run left the road
    refit_iterations: int = 3
    #: a warm replan whose collision probability (its samples, max over time) exceeds this is rescued: a replan
    #: from stage 1 (fresh candidates, the warm start among them) competes with it and the lower stage-2 objective
    #: is tracked (1: never). Ten small stage-2 steps from the warm start cannot brake for a slower vehicle ahead
    #: or choose another lane (docs/planner.md, "Online driving")
    rescue_p_coll: float = 0.5
    #: seed of the true initial state
    seed: int = 0
    #: the occupancy an online planner reads
    prediction: PredictionConfig = field(default_factory=PredictionConfig)

    def __post_init__(self) -> None:
        for name in ("time_budget", "max_duration"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise ValueError(f"online.{name} must be a finite number > 0, got {v!r}")
        if isinstance(self.rescue_p_coll, bool) or not isinstance(self.rescue_p_coll, (int, float)) \
                or not 0 <= self.rescue_p_coll <= 1:
            raise ValueError(f"online.rescue_p_coll must be a probability in [0, 1] (1: no rescue), got "
                             f"{self.rescue_p_coll!r}")
        for name in ("period", "duration", "unsafe_p_coll", "restart_distance", "replan_lr", "replan_update_clip"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"online.{name} must be a finite number >= 0, got {v!r}")
        for name in ("refit_iterations", "replan_patience", "replan_samples"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ValueError(f"online.{name} must be an integer >= 0, got {v!r}")
        for name in ("replan_epochs",):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"online.{name} must be a positive integer, got {v!r}")
        if not self.brake_steer or not all(math.isfinite(s) and -1 <= s <= 1 for s in self.brake_steer):
            raise ValueError(f"online.brake_steer must be fractions in [-1, 1], got {self.brake_steer!r}")
        if self.overrun not in OVERRUN_MODES:
            raise ValueError(f"online.overrun must be one of {', '.join(map(repr, OVERRUN_MODES))}, got "
                             f"{self.overrun!r}")
        check_seed("online.seed", self.seed)

    def replan_settings(self) -> dict[str, Any]:
        """The keyword arguments of :func:`warm_replan` this section sets (steps, samples, step size, patience):
        one place for ``drive``'s replans, their rescues and ``benchmarks/bench_replan.py``."""
        return {"epochs": self.replan_epochs, "samples": self.replan_samples, "lr": self.replan_lr,
                "update_clip": self.replan_update_clip, "patience": self.replan_patience}

    def replan_period(self, segment_duration: float) -> float:
        """The replanning period [s]: ``period``, or one input segment of ``segment_duration`` [s] when 0."""
        return float(self.period or segment_duration)


@dataclass
class Replan:
    """One replanning event (a row of ``run.json``)."""

    #: absolute time [s]
    t: float
    #: "success", "failed", "overrun" or "initial" (the first, offline plan)
    status: str
    #: wall time of the replan [s] (excludes the prediction)
    wall_time: float
    #: wall time of rendering the prediction [s]
    prediction_time: float = 0.0
    #: collision probability (max over time) of the new plan's predicted sample cloud, NaN without one
    p_coll: float = math.nan
    #: the warm start was used (False: stage 1 ran)
    warm_start: bool = True
    #: None, "previous" (kept the previous reference) or "brake" (least-risk braking)
    fallback: str | None = None
    #: why the plan was discarded / why the fallback was needed
    reason: str = ""
    #: nominal collision probability of the kept previous reference under the current prediction (fallbacks)
    previous_p_coll: float = math.nan
    #: absolute time [s] from which the controller tracked this plan: ``t``, later for a delayed overrun
    #: (``online.overrun = "delay"``), NaN for a plan never tracked
    t_effective: float = math.nan
    #: relative decrease of the stage-2 objective from the warm start (first iterate) to the returned plan (best
    #: iterate): 0 when no step improved on the warm start; NaN without a stage-2 history
    cost_reduction: float = math.nan
    #: a rescue (``online.rescue_p_coll``): None (none ran), "used" (its plan replaced the warm replan's) or "kept"
    #: (the warm replan's plan was better)
    rescue: str | None = None
    #: collision probability of the rescue's plan (NaN when none ran)
    rescue_p_coll: float = math.nan

    def to_dict(self) -> dict[str, Any]:
        def num(v: float) -> float | None:
            return None if not math.isfinite(v) else float(v)

        return {"t": self.t, "status": self.status, "wall_time": self.wall_time, "prediction_time":
                self.prediction_time, "p_coll": num(self.p_coll), "warm_start": self.warm_start,
                "fallback": self.fallback, "reason": self.reason, "previous_p_coll": num(self.previous_p_coll),
                "t_effective": num(self.t_effective), "cost_reduction": num(self.cost_reduction),
                "rescue": self.rescue, "rescue_p_coll": num(self.rescue_p_coll)}


@dataclass
class _Active:
    """The reference being tracked: the plan it came from, its start time and its per-step values."""

    reference: Reference
    t0: float
    params: Tensor | None
    x_ref: Tensor  # (K, nx) at the integration steps
    u_ref: Tensor  # (K, nu)
    kind: str  # "plan" or "brake"
    x_ref_np: np.ndarray | None = None  # float64 copies for the torch-free controller
    u_ref_np: np.ndarray | None = None

    def step_at(self, t: float, dt: float) -> int:
        """Index of the integration step (of ``dt`` [s]) of the absolute time ``t`` [s] in ``x_ref`` / ``u_ref``."""
        return int(round((t - self.t0) / dt))


@dataclass
class DriveResult:
    """An online run.

    Attributes:
        times: ``(T,)`` absolute times [s] of the executed states (planning grid).
        states: ``(T, nx)`` executed true states.
        inputs: ``(T - 1, nu)`` applied inputs at those times.
        replans: every replanning event.
        verdict: the executed trajectory judged against the ground truth.
        true_initial_state: ``(nx,)``.
        snapshots: per replan, what the figures draw: ``{"t", "plan" (n, 2) positions of the tracked reference,
            "position" (2,), "occupancy" (X, Y) predicted occupancy at t, "swept" (X, Y) its maximum over the next
            ``snapshot_lookahead`` seconds, "extent" (xmin, xmax, ymin, ymax)}`` (cropped around the vehicle).
        prediction: the prediction's name.
        controller_step_time: median wall time of one controller evaluation (one state) [s].
    """

    times: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    replans: list[Replan]
    verdict: Verdict | None
    true_initial_state: np.ndarray
    snapshots: list[dict[str, Any]]
    prediction: str
    controller_step_time: float
    initial_plan: PlanResult | None = None
    #: ``(T - 1,)`` online computation per planning step [s]: the controller evaluations, plus the replan (and its
    #: prediction) at replanning steps
    step_times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: collision probability of the executed trajectory on the scene's own occupancy (:func:`executed_p_coll`)
    p_coll_executed: float = math.nan

    def summary(self) -> dict[str, Any]:
        walls = np.array([r.wall_time for r in self.replans if r.status != "initial"])
        # the warm-started replans that ran no rescue (issue 17's speed target is theirs; a rescue runs stage 1)
        warm = np.array([r.wall_time for r in self.replans
                         if r.status in ("success", "overrun") and r.warm_start and r.rescue is None])
        preds = np.array([r.prediction_time for r in self.replans if r.status != "initial"])
        fallbacks = [r for r in self.replans if r.fallback]
        pc = np.array([r.p_coll for r in self.replans if math.isfinite(r.p_coll)])
        red = np.array([r.cost_reduction for r in self.replans if math.isfinite(r.cost_reduction)])
        late = sum(1 for r in self.replans if math.isfinite(r.t_effective) and r.t_effective > r.t + 1e-9)
        return {
            "prediction": self.prediction,
            "status": None if self.verdict is None else self.verdict.status,
            "verdict": None if self.verdict is None else self.verdict.to_dict(),
            "duration": float(self.times[-1] - self.times[0]) if len(self.times) else 0.0,
            "n_replans": int(walls.size),
            "replan_wall_time_median": float(np.median(walls)) if walls.size else None,
            "replan_wall_time_p95": float(np.percentile(walls, 95)) if walls.size else None,
            "n_warm_replans": int(warm.size),
            "warm_replan_wall_time_median": float(np.median(warm)) if warm.size else None,
            "warm_replan_wall_time_p95": float(np.percentile(warm, 95)) if warm.size else None,
            # building each replan's occupancy window (the prediction), before the replan itself
            "prediction_time_median": float(np.median(preds)) if preds.size else None,
            "prediction_time_p95": float(np.percentile(preds, 95)) if preds.size else None,
            "n_fallbacks": len(fallbacks),
            # replans tracked after their measurement time (online.overrun = "delay")
            "n_tracked_late": late,
            "fallbacks": {k: sum(r.fallback == k for r in fallbacks) for k in ("previous", "brake")},
            "rescues": {k: sum(r.rescue == k for r in self.replans) for k in ("used", "kept")},
            "p_coll_mean": float(pc.mean()) if pc.size else None,
            "p_coll_executed": float(self.p_coll_executed) if math.isfinite(self.p_coll_executed) else None,
            # share of the replans that improved on their warm start, and their median relative improvement
            "replans_improved": float((red > 0).mean()) if red.size else None,
            "cost_reduction_median": float(np.median(red)) if red.size else None,
            "controller_step_time": self.controller_step_time,
            "step_times": self.step_times.tolist(),
            "true_initial_state": self.true_initial_state.tolist(),
            "replans": [r.to_dict() for r in self.replans],
            "times": self.times.tolist(),
            "states": self.states.tolist(),
            "inputs": self.inputs.tolist(),
        }


# ------------------------------------------------------------------------------------------------ warm start
def shift_parameters(params: Tensor, shift: float, segment_duration: float, tail: Tensor | None = None) -> Tensor:
    """The piecewise-constant inputs ``params (nu, S)`` of a plan, as seen ``shift`` seconds later: new segment
    ``j`` gets the time average of the old inputs over ``[shift + j d, shift + (j + 1) d]`` (``d`` the segment
    duration); the part past the old horizon gets ``tail (nu,)`` (default: the last old input). For a shift of
    whole segments this is the exact shift ``params[:, m:]`` followed by ``m`` columns of the tail."""
    nu, n = params.shape
    d = float(segment_duration)
    # overlap of new segment j = [s + j d, s + (j + 1) d] with old segment i = [i d, (i + 1) d]
    starts = shift + d * torch.arange(n, dtype=torch.float64)
    edges = d * torch.arange(n + 1, dtype=torch.float64)
    lo = torch.maximum(starts[:, None], edges[None, :-1])
    hi = torch.minimum(starts[:, None] + d, edges[None, 1:])
    w = ((hi - lo).clamp_min(0.0) / d).to(params)  # (n_new, n_old)
    past = ((starts + d - torch.maximum(starts, edges[-1:])).clamp_min(0.0) / d).to(params)  # (n_new,)
    tail = params[:, -1] if tail is None else tail.to(params)
    return params @ w.T + tail[:, None] * past[None, :]


def shifted_plan(system: System, params: Tensor, reference: Reference, shift: float, segment_duration: float,
                 n_segments: int, *, hold: bool = False) -> Tensor:
    """A replan's warm start: the plan ``params (nu, S)`` (whose reference is ``reference``) seen ``shift`` seconds
    later (:func:`shift_parameters`), cut to the replan's ``n_segments``. Past the old horizon the car goes straight
    and brakes to a stop within a segment (its hardest braking at most; ``hold``: at constant speed, e.g. when the
    horizon ends with the goal's time and nothing is left to plan); other systems hold their last input.
    ``drive``'s replans and ``benchmarks/bench_replan.py`` use it."""
    iv, ia = system.speed_index, system.acceleration_input
    tail = None
    if iv is not None and ia is not None:
        tail = torch.zeros(system.nu, dtype=torch.float64)
        if not hold:
            a_min = float(system.input_bounds[0][ia])
            tail[ia] = max(a_min, -float(reference.x[-1, iv]) / segment_duration)
    warm = shift_parameters(params.detach().to(torch.float64), shift, segment_duration, tail)[:, :n_segments]
    assert warm.shape[-1] == n_segments, "the horizon never grows from one replan to the next"
    return warm


def holds_speed(config: OnlineConfig, t: float, goal_end: float, horizon: float) -> bool:
    """Whether a replan at ``t`` [s] with ``horizon`` [s] ends with the goal's time ``goal_end``
    (``config.shrink_horizon``): its :func:`shifted_plan` then holds the speed past the old horizon (nothing is
    left to plan there) instead of braking."""
    return bool(config.shrink_horizon) and t < goal_end - 1e-9 and goal_end <= t + horizon + 1e-9


def refit_shift(system: System, parameterization: PiecewiseConstantInputs, start: Tensor, params: Tensor,
                target: Tensor, *, iterations: int = 3, damping: float = 1e-6, step: float = 1e-4) -> Tensor:
    """Refit a shifted warm start ``params (nu, S)`` so that its reference from ``start (nx,)`` follows the positions
    of ``target (n, nx)``, the previous reference's states on the planning grid from the replanning time (``n`` at
    most the parameterisation's planning steps).

    Piecewise-constant inputs shifted by part of a segment have no exact representation on the new segment grid;
    the time average (:func:`shift_parameters`) keeps heading and speed at the new segment boundaries but not the
    path (a steering change inside a new segment moves it sideways by ``~ v dw d^2 / 8``, ~0.4 m per segment at
    11 m/s). Damped Gauss-Newton on the squared position errors, with the Jacobian from one batched roll-out of
    ``1 + nu S`` forward-difference perturbations (``step``) per iteration; inputs are clamped to the system's
    bounds. Returns the best iterate (``params`` itself when no iterate is closer)."""
    from ..control.reference import plan_grid_reference

    p = params.detach().to(torch.float64).clone()
    nu, n_seg = p.shape
    m = nu * n_seg
    start = start.detach().to(torch.float64)
    target = target.detach().to(torch.float64)
    lo, hi = (torch.as_tensor(b, dtype=torch.float64)[:, None] for b in system.input_bounds)
    eye = torch.eye(m, dtype=torch.float64)

    def residual(batch: Tensor) -> Tensor:  # (B, nu, S) -> (B, 2 n)
        x_plan, _ = plan_grid_reference(system, start, batch, parameterization)
        n = min(target.shape[0], x_plan.shape[-2])
        d = system.positions(x_plan[:, :n]) - system.positions(target[:n])
        return d.reshape(batch.shape[0], -1)

    best_p, best_err = p, math.inf
    for _ in range(max(0, int(iterations))):
        batch = p[None].repeat(1 + m, 1, 1)
        batch[1:] += step * eye.reshape(m, nu, n_seg)
        r = residual(batch.clamp(lo, hi))
        err = float(r[0].square().sum())
        if err < best_err:
            best_p, best_err = p, err
        jac = (r[1:] - r[0]) / step  # (m, 2 n)
        delta = torch.linalg.solve(jac @ jac.T + damping * eye, -(jac @ r[0]))
        p = (p + delta.reshape(nu, n_seg)).clamp(lo, hi)
    if iterations > 0 and float(residual(p[None])[0].square().sum()) < best_err:
        best_p = p
    return best_p.to(params)


def recentred(dist: Any, mean: Tensor) -> Any:
    """The initial law ``dist`` moved so that its mean is ``mean`` (a :class:`GaussianMixture`: every component and
    the truncation box shifted by the same offset; the shape of the law, i.e. the measurement error law, is
    unchanged)."""
    from ..density.distributions import Conditioned, GaussianMixture

    if isinstance(dist, Conditioned):  # the road prior holds at the scene's start only
        dist = dist.base
    if not isinstance(dist, GaussianMixture):
        raise ValueError(f"re-centring needs a GaussianMixture initial law, got {type(dist).__name__}")
    delta = mean.to(torch.float64).reshape(-1) - dist.mean.to(torch.float64)
    covs = dist.std**2 if dist.diagonal else dist._chol @ dist._chol.transpose(-1, -2)
    low = None if dist.low is None else dist.low + delta
    high = None if dist.high is None else dist.high + delta
    return GaussianMixture(dist.weights, dist.means + delta, covs, low=low, high=high)


def braking_parameters(system: System, v0: float, segment_duration: float, n_segments: int,
                       steer: tuple[float, ...]) -> Tensor:
    """``(len(steer), nu, S)`` braking manoeuvres from speed ``v0``: the largest deceleration (the system's
    acceleration input) until standstill (the last braking segment only removes the remaining speed), with the
    steering input (the turn-rate input, else the first other input) at ``steer`` times its bound while moving, 0
    once stopped."""
    ia = system.acceleration_input
    if ia is None:
        raise ValueError(f"braking needs a system with an acceleration input; {type(system).__name__} has none")
    steer_i = system.turn_rate_input
    if steer_i is None:
        steer_i = next((i for i in range(system.nu) if i != ia), None)
    lo, hi = (torch.as_tensor(b, dtype=torch.float64) for b in system.input_bounds)
    a_min = float(lo[ia])
    v = max(float(v0), 0.0)
    acc, moving = [], []
    for _ in range(n_segments):
        a = max(a_min, -v / segment_duration) if v > 1e-9 else 0.0
        acc.append(a)
        moving.append(v > 1e-9)
        v = max(v + a * segment_duration, 0.0)
    acc_t = torch.tensor(acc, dtype=torch.float64)
    mov = torch.tensor(moving, dtype=torch.float64)
    out = torch.zeros(len(steer), system.nu, n_segments, dtype=torch.float64)
    for i, s in enumerate(steer):
        if steer_i is not None:
            out[i, steer_i] = (s * float(hi[steer_i]) if s >= 0 else -s * float(lo[steer_i])) * mov
        out[i, ia] = acc_t
    return out


#: offset of the seed of a rescue replan's stage-1 generator from its replan's seed (:func:`warm_replan`)
_STAGE1_SEED_OFFSET = 1_000_003


def best_objective(result: PlanResult) -> float:
    """The lowest finite stage-2 objective of a replan (``inf`` when none): what :func:`warm_replan`'s stage 2
    minimised, comparable between replans of one problem on the same samples."""
    totals = [v for v in (result.cost_history.get("stage2") or {}).get("total", []) if math.isfinite(v)]
    return min(totals) if totals else math.inf


def warm_replan(planner: DensityPlanner, problem: PlanningProblem, warm: Tensor | None, *, epochs: int, samples: int,
                seed: int = 0, lr: float = 0.0, update_clip: float = 0.0, patience: int = 0,
                extra_seeds: Tensor | None = None) -> tuple[PlanResult, bool]:
    """A replan of the density planner: stage 2 (``epochs`` iterations, fewer with ``patience``: see
    ``DensityPlannerConfig.patience``; ``samples`` initial samples) from the warm-start parameters ``warm (nu, S)``;
    stage 1 first when ``warm`` is ``None``, with ``extra_seeds (K, nu, S)`` among its candidates
    (:meth:`DensityPlanner.initialise`; its own generator, so that stage 2 draws the same samples as a warm replan
    with the same ``seed``). Returns the result and whether the warm start was used. The reported collision
    probability is that of the best iterate's sample cloud (no fresh draw: a replan is judged by the next one)."""
    cfg = planner.config
    fast = copy.copy(planner)
    fast.config = replace(cfg, epochs_density=int(epochs), n_samples=int(samples or cfg.n_samples),
                          fresh_evaluation_samples=False, lr=float(lr or cfg.lr),
                          update_clip=float(update_clip or cfg.update_clip), patience=int(patience))
    fast.progress = False
    if getattr(fast.predictor, "fallback", None) is not None:  # online: refuse rather than minutes of exact Liouville
        predictor: Any = copy.copy(fast.predictor)
        predictor.fallback = None
        fast.predictor = predictor
    t0 = time.perf_counter()
    gen = torch.Generator().manual_seed(int(seed))
    timings: dict[str, float] = {}
    used_warm = warm is not None
    if warm is None:
        gen1 = gen if extra_seeds is None else torch.Generator().manual_seed(int(seed) + _STAGE1_SEED_OFFSET)
        warm, _, _ = fast.initialise(problem, gen1, extra_seeds=extra_seeds)
        timings["stage1"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    (best, params, ref, traj), hist, (_x0, _lr0, log_q0), slices = fast.refine(
        problem, warm.to(dtype=fast.dtype, device=fast.device), gen)
    timings["stage2"] = time.perf_counter() - t1
    if params is None:
        timings["total"] = time.perf_counter() - t0
        return PlanResult(planner.name, PlanStatus.FAILED, params=warm, timings=timings,
                          message="stage 2 produced no finite cost"), used_warm
    cost, coll = fast.evaluate(problem, ref, traj, log_q0, slices)
    timings["total"] = time.perf_counter() - t0
    return PlanResult(planner.name, PlanStatus.SUCCESS, params=params, reference=ref.select(0),
                      states=ref.x_plan[0], cost=cost, collision=coll, timings=timings,
                      cost_history={"stage2": hist}, iterations={"stage2": int(hist["iterations"][0])}), used_warm


def _rescue(planner: DensityPlanner, problem: PlanningProblem, warm: Tensor, result: PlanResult, rec: Replan,
            config: OnlineConfig, *, seed: int) -> PlanResult:
    """A warm replan whose collision probability exceeds ``online.rescue_p_coll`` competes with a replan from
    stage 1 (route seeds and random candidates, the warm start and the warm replan's plan among them, then the same
    stage 2 on the same samples): the one with the lower stage-2 objective is returned (``rec.rescue``: "used" or
    "kept"). Ten small stage-2 steps from the warm start cannot brake for a slower vehicle ahead, nor choose
    another lane; stage 1 can."""
    assert result.params is not None  # checked by the caller
    seeds = torch.stack([warm.to(result.params.dtype), result.params.detach()])
    rescue, _ = warm_replan(planner, problem, None, seed=seed, extra_seeds=seeds, **config.replan_settings())
    rec.rescue_p_coll = float(rescue.collision.max) if rescue.collision is not None else math.nan
    if rescue.ok and best_objective(rescue) < best_objective(result):
        rec.rescue = "used"
        log.info("t = %.2f s: rescue replan used (P_coll %.3f instead of %.3f)", rec.t, rec.rescue_p_coll,
                 float(result.collision.max) if result.collision is not None else math.nan)
        return rescue
    rec.rescue = "kept"
    return result


# --------------------------------------------------------------------------------------------------- runner
def _run_length(scene: Scene, config: OnlineConfig, horizon: float) -> float:
    road = scene.road
    if road is not None:
        assert scene.t_start is not None  # set by Scene.__post_init__
        return min(road.goal.time_interval[1] - scene.t_start, config.max_duration)
    return min(config.duration or horizon, config.max_duration)


def _replan_parameterization(par: PiecewiseConstantInputs, goal_end: float | None, t: float,
                             shrink: bool) -> PiecewiseConstantInputs:
    """The parameterisation of a replan at ``t``: ``par``, or with ``shrink`` and a goal that ends at ``goal_end``
    [s, absolute] within ``par``'s horizon, the whole segments that reach the goal's end (at least one): the plan ends
    with the goal's time interval, as the offline plan does (scenes without one: the first plan's end)."""
    if not shrink or goal_end is None:
        return par
    n = max(1, math.ceil((goal_end - t) / par.segment_duration - 1e-9))
    if n >= par.n_segments:
        return par
    return replace(par, n_segments=n)


def _nominal_p_coll(grid: Any, system: System, risk: RiskConfig, t: float, plan_dt: float, states: Tensor,
                    ignore: Tensor | None = None) -> float:
    """Collision probability (max over time) of one nominal trajectory ``states (T, nx)`` on the planning grid from
    absolute time ``t`` in the occupancy ``grid`` (the part inside the grid's span). ``ignore``: ``(NX, NY)`` cells
    read as free, the road's off-road cells under ``risk.road_edge = "barrier"`` (:func:`~density_planner.risk.
    collision.collision_mask` of the scene: the planners' own convention; the windows share the scene's lattice)."""
    from ..risk.collision import CollisionModel

    n = min(states.shape[0], int(math.floor((grid.t_end - t) / plan_dt + 1e-6)) + 1)
    if n < 1:
        return math.nan
    slices = grid.slices_for(t, plan_dt, n).to(states.device)
    mask = None if ignore is None else ignore.to(states.device)
    rep = CollisionModel(grid.to(states.device), system, risk, ignore=mask).probability(states[None, :n], slices)
    return float(rep.max)


def executed_p_coll(scene: Scene, system: System, risk: RiskConfig, states: np.ndarray | Tensor,
                    dt: float) -> float:
    """Collision probability (max over time) of an executed trajectory ``states (T, nx)`` (from the scene start,
    every ``dt`` seconds; the vehicle's body) on the scene's own occupancy grid: on recorded traffic the blurred
    recorded future, whatever the run's planner read. One estimator for every method (offline plans tracked, online
    runs with any prediction), unlike each planner's own figure; NaN where the grid does not cover the start."""
    from ..risk.collision import collision_mask

    assert scene.t_start is not None  # set by Scene.__post_init__
    x = torch.as_tensor(np.asarray(states, dtype=np.float64) if not isinstance(states, Tensor) else states)
    return _nominal_p_coll(scene.grid, system, risk, float(scene.t_start), dt, x.to(scene.grid.probs.dtype),
                           ignore=collision_mask(scene, risk))


def initial_problem(problem: PlanningProblem, prediction: Prediction) -> PlanningProblem:
    """The problem of a drive's first plan: ``problem`` (the scene start, its initial law and horizon) on the
    occupancy ``prediction`` shows at the start, ``[t_start, t_start + H]``. For the oracle that is the scene's own
    grid (``problem`` itself: the offline plan); for a prediction from observations, only what was observed by the
    start, so that no plan of an observed-only run reads the recorded future."""
    if prediction.windows_share_scene_grid:
        return problem
    return replace(problem, scene=prediction.scene_at(problem.t_start, problem.parameterization.horizon,
                                                      start=problem.scene.start))


def drive(
    scene: Scene,
    planner: Planner,
    controller: TrackingController,
    *,
    system: System,
    config: OnlineConfig | None = None,
    planning: PlanningConfig | None = None,
    risk: RiskConfig | None = None,
    evaluation: EvaluationConfig | None = None,
    verdict_config: VerdictConfig | None = None,
    distribution_seed: int = 0,
    prediction: Prediction | None = None,
    true_state: Tensor | None = None,
    initial_plan: PlanResult | None = None,
    keep_snapshots: bool = True,
    snapshot_half_width: float = 45.0,
    snapshot_cells: int = 220,
    snapshot_lookahead: float = 3.0,
    progress: Any = None,
) -> DriveResult:
    """Drive ``scene`` online (module docstring). ``planner`` needs ``initialise`` / ``refine`` / ``evaluate`` (the
    density planner) for warm-started replans; other planners replan with a full ``plan``.

    Args:
        prediction: the occupancy prediction (default: ``make_prediction(scene, config.prediction)``).
        true_state: ``(nx,)`` true initial state (default: drawn from the initial distribution with
            ``config.seed``).
        initial_plan: the first plan from the scene start, when already computed: a plan of
            :func:`initial_problem` ``(problem0, prediction)`` (for the oracle, the offline plan itself).
        progress: callable ``progress(t, replan)`` after each replan (terminal progress lines).
        keep_snapshots: keep the figure data of every replan (``DriveResult.snapshots``), a window of
            ``snapshot_half_width`` [m] around the vehicle at most ``snapshot_cells`` cells wide.
    """
    config = config or OnlineConfig()
    planning = planning or PlanningConfig()
    risk = risk or RiskConfig()
    evaluation = evaluation or EvaluationConfig()
    prediction = prediction or make_prediction(scene, config.prediction)
    problem0 = PlanningProblem.from_scene(scene, seed=distribution_seed, planning=planning, risk=risk, system=system)
    par = problem0.parameterization
    horizon = par.horizon
    plan_dt, dt = par.plan_dt, float(evaluation.dt)
    ratio = plan_dt / dt
    per_plan = int(round(ratio))
    if abs(ratio - per_plan) > 1e-6 or per_plan < 1:
        raise ValueError(f"evaluation.dt ({dt}) must divide planning.plan_dt ({plan_dt})")
    period = config.replan_period(par.segment_duration)
    steps_per_period = period / plan_dt
    if abs(steps_per_period - round(steps_per_period)) > 1e-6 or round(steps_per_period) < 1:
        raise ValueError(f"online.period ({period:g} s) must be a whole number of planning steps of "
                         f"{plan_dt} s")
    period_steps = int(round(steps_per_period))
    length = _run_length(scene, config, horizon)
    assert scene.t_start is not None  # set by Scene.__post_init__
    # where the replans' horizons end (``shrink_horizon``): the goal's time interval, else the first plan's end (its
    # goal cost is at its end: the goal is to be reached then, however long the run)
    goal_end = scene.road.goal.time_interval[1] if scene.road is not None else scene.t_start + horizon
    n_total = max(1, int(math.floor(length / plan_dt + 1e-9)))  # planning steps driven
    dtype = getattr(planner, "dtype", torch.float32)
    device = getattr(planner, "device", torch.device("cpu"))
    law0 = problem0.initial_distribution
    iv = system.speed_index
    hidden = list(system.hidden_states)
    speed_range = getattr(getattr(planner, "predictor", None), "speed_range", None)
    v_floor = float(speed_range[0]) if speed_range is not None else -math.inf
    fast = None
    if config.fast_controller:
        from ..control.c3m import C3MController
        from ..control.fast import NumpyC3M

        if isinstance(controller, C3MController) and NumpyC3M.supports(system):
            fast = NumpyC3M(controller)
    warm_capable = all(hasattr(planner, m) for m in ("initialise", "refine", "evaluate"))

    if true_state is None:
        gen = torch.Generator().manual_seed(config.seed)
        true_state = problem0.initial_distribution.sample(1, gen, dtype=torch.float64)[0]
    x = true_state.to(dtype=dtype, device=device).reshape(-1).clone()
    x_init = x.detach().cpu().numpy().astype(np.float64)

    def activate(ref: Reference, t0: float, params: Tensor | None, kind: str) -> _Active:
        n_steps = int(round(ref.n_steps * ref.dt / dt))
        xr, ur = ref.stage_values(dt, n_steps, (0.0,))
        act = _Active(ref, t0, params, xr[:, 0].to(dtype), ur[:, 0].to(dtype), kind)
        if fast is not None:
            act.x_ref_np = xr[:, 0].detach().cpu().double().numpy()
            act.u_ref_np = ur[:, 0].detach().cpu().double().numpy()
        return act

    # the cells the planners' collision ignores (the road's edge is the road barrier's): the fallbacks read the same
    from ..risk.collision import collision_mask

    off_road = collision_mask(scene, risk)

    def brake(grid: Any, x_now: Tensor, t: float) -> tuple[_Active, float]:
        """The least-risk braking manoeuvre from the measurement ``x_now`` at ``t`` in ``grid``."""
        speed = system.speeds(x_now)
        cand = braking_parameters(system, 0.0 if speed is None else float(speed), par.segment_duration,
                                  par.n_segments, config.brake_steer).to(dtype=dtype, device=device)
        # hidden states (the car's heading bias) are not part of a reference
        start = system.nominal_state(x_now.detach().to(dtype=dtype, device=device).clone())
        refs = make_reference(system, start, cand, par)
        risks = [_nominal_p_coll(grid, system, risk, t, plan_dt, refs.x_plan[i], ignore=off_road)
                 for i in range(cand.shape[0])]
        risks = [r if math.isfinite(r) else math.inf for r in risks]
        best = int(np.argmin(risks))
        return activate(refs.select(best), t, cand[best], "brake"), float(risks[best])

    replans: list[Replan] = []
    snapshots: list[dict[str, Any]] = []

    def snapshot(t: float, grid: Any, pos: np.ndarray) -> None:
        if not keep_snapshots:
            return
        from ..viz.plan import _crop

        half = snapshot_half_width
        (i0, i1, j0, j1), extent, st = _crop(grid, (pos[0] - half, pos[0] + half, pos[1] - half, pos[1] + half),
                                             snapshot_cells)
        n_ahead = max(1, min(grid.n_slices, int(round(snapshot_lookahead / grid.dt)) + 1))
        k0 = int(grid.slice_index(t, clamp=True))
        sub = grid.probs[k0 : k0 + n_ahead, i0:i1:st, j0:j1:st].detach().cpu().float()
        # copies, not views: a view (`.float()` of a float32 CPU grid is the grid itself) kept every replan's whole
        # window grid alive, one grid per replan (drive peaked at 16.1 GB on USA_US101-3_1, 4.8 GB with copies)
        snapshots.append({"t": float(t),
                          "plan": system.positions(active.reference.x_plan).detach().cpu().numpy().astype(float),
                          "position": np.asarray(pos[:2], dtype=float), "occupancy": sub[0].numpy().copy(),
                          "swept": sub.amax(dim=0).numpy().copy(), "extent": tuple(float(e) for e in extent)})
    t_start = scene.t_start
    assert t_start is not None  # set by Scene.__post_init__
    # -- the first plan from the initial distribution, on what the prediction shows at the start: the scene's own
    # occupancy for the oracle, only what was observed by then otherwise (never the recorded future)
    problem_init = initial_problem(problem0, prediction)
    if initial_plan is None:
        t0 = time.perf_counter()
        initial_plan = planner.plan(problem_init)
        wall0 = time.perf_counter() - t0
    else:
        wall0 = float(initial_plan.timings.get("total", math.nan))
    p0 = float(initial_plan.collision.max) if initial_plan.collision is not None else math.nan
    if initial_plan.ok and initial_plan.reference is not None:
        active = activate(initial_plan.reference, t_start, initial_plan.params, "plan")
        replans.append(Replan(t_start, "initial", wall0, p_coll=p0, warm_start=False, t_effective=t_start))
    else:
        active, p_b = brake(problem_init.scene.grid, problem0.reference_start(dtype, device), t_start)
        replans.append(Replan(t_start, "initial", wall0, warm_start=False, fallback="brake",
                              reason=f"the initial plan failed: {initial_plan.message or initial_plan.status.value}",
                              previous_p_coll=p_b))
    snapshot(t_start, prediction.window(t_start, horizon), system.positions(torch.from_numpy(x_init)).numpy())
    if not prediction.windows_share_scene_grid:  # the replans plan on grids of their own: the initial plan's
        scene.grid.drop_caches()  # derived grids would only hold memory (an oracle's windows read them: kept)

    states = [x.detach().cpu().numpy().astype(np.float64)]
    inputs: list[np.ndarray] = []
    ctrl_times: list[float] = []
    step_times: list[float] = []
    road = scene.road
    k = 0
    i_replan = 0
    pending: tuple[PlanResult, Replan, int] | None = None  # a delayed overrun: (result, its record, step it is ready)
    while k < n_total:
        t = t_start + k * plan_dt
        step_extra = 0.0
        if pending is not None and k >= pending[2]:  # the overrunning replan has finished: track it from now
            res_p, rec_p, _ = pending
            assert res_p.reference is not None  # only plans with a reference are delayed
            active = activate(res_p.reference, rec_p.t, res_p.params, "plan")
            rec_p.t_effective = t
            pending = None
        if k > 0 and k % period_steps == 0 and pending is None:  # one planning thread: none starts while one runs
            i_replan += 1
            x_hat = system.measure(x[None])[0]
            if iv is not None:  # plan from the state box (a tracking overshoot below standstill) and from the
                # speeds the learned predictor serves (online, its exact-Liouville fallback would take minutes)
                lo_s, hi_s = system.state_bounds
                x_hat = x_hat.clone()
                x_hat[iv] = x_hat[iv].clamp(max(float(lo_s[iv]), v_floor), float(hi_s[iv]))
            centre = system.pose(x_hat.detach().cpu())
            tp = time.perf_counter()
            rec = Replan(t, "failed", 0.0)
            prob = None
            par_t = _replan_parameterization(par, goal_end, t, config.shrink_horizon)
            grid_t = prediction.window(t, par_t.horizon)
            rec.prediction_time = time.perf_counter() - tp
            warm, origin, refit_target = None, None, None
            offset = active.step_at(t, dt)
            if active.kind == "plan" and active.params is not None and offset < active.x_ref.shape[0]:
                gap = float(torch.linalg.vector_norm(system.positions(active.x_ref[offset])
                                                     - system.positions(x_hat).to(dtype)))
                if gap <= config.restart_distance:
                    # past the old horizon: straight, braking; at the goal's end, when the horizon shrinks to it,
                    # straight at constant speed (nothing left to plan)
                    shift = t - active.t0
                    warm = shifted_plan(system, active.params, active.reference, shift, par.segment_duration,
                                        par_t.n_segments, hold=holds_speed(config, t, goal_end, par_t.horizon))
                    if config.continue_reference:  # the reference goes on from where it is, not from the measurement
                        origin = active.x_ref[offset].detach().to(torch.float64).clone()
                    whole = abs(shift / par.segment_duration - round(shift / par.segment_duration)) < 1e-6
                    if config.refit_iterations and not whole:  # the averaged inputs drift off the old path
                        k_old = int(round(shift / active.reference.parameterization.plan_dt))
                        refit_target = active.reference.x_plan[k_old:]
            try:
                scene_t = replace(prediction.scene, grid=grid_t, t_start=grid_t.t0, start=centre)
                mean = x_hat.detach().to(torch.float64).clone()
                if hidden:  # hidden states (the car's heading bias) keep their law: unknown to the vehicle
                    mean[hidden] = law0.mean[hidden].to(mean)
                prob = PlanningProblem(scene_t, recentred(law0, mean), system, par_t, risk,
                                       start_threshold=math.inf, reference_origin=origin)
            except ValueError as exc:
                rec.reason = f"no planning problem at the measurement: {exc}"
            result, delayed = None, False
            if prob is not None:
                t1 = time.perf_counter()
                try:
                    if warm is not None and refit_target is not None:  # part of the replan's compute (timed)
                        warm = refit_shift(system, par_t, prob.reference_start(torch.float64), warm, refit_target,
                                           iterations=config.refit_iterations)
                    if warm_capable:
                        dp = cast("DensityPlanner", planner)  # it has initialise, refine and evaluate
                        result, rec.warm_start = warm_replan(dp, prob, warm, seed=i_replan,
                                                             **config.replan_settings())
                        if (rec.warm_start and warm is not None and result.ok and result.params is not None
                                and result.collision is not None
                                and float(result.collision.max) > config.rescue_p_coll):
                            result = _rescue(dp, prob, warm, result, rec, config, seed=i_replan)
                    else:
                        result, rec.warm_start = planner.plan(prob), False
                except Exception as exc:  # noqa: BLE001 - a failed replan is a recorded fallback, never a crash
                    result = None
                    rec.reason = f"replan raised {type(exc).__name__}: {exc}"
                rec.wall_time = time.perf_counter() - t1
                if result is not None and not result.ok:
                    rec.reason = f"replan {result.status.value}: {result.message}"
                    result = None
                elif result is not None:
                    rec.p_coll = float(result.collision.max) if result.collision is not None else math.nan
                    totals = [v for v in (result.cost_history.get("stage2") or {}).get("total", []) if math.isfinite(v)]
                    if totals and totals[0] != 0:
                        rec.cost_reduction = (totals[0] - min(totals)) / abs(totals[0])
                    rec.status = "success"
                    if rec.wall_time > config.time_budget:
                        rec.status = "overrun"
                        over = f"replan took {rec.wall_time:.3f} s > online.time_budget = {config.time_budget:g} s"
                        if config.overrun == "discard":
                            rec.reason = over
                            result = None
                        elif config.overrun == "delay" and result.reference is not None:
                            lag = max(1, math.ceil(rec.wall_time / plan_dt - 1e-9))
                            pending = (result, rec, k + lag)
                            delayed = True
                            rec.reason = (f"{over}: tracked from {lag * plan_dt:.1f} s after its measurement "
                                          "(online.overrun = 'delay'), the previous reference meanwhile")
                            log.info("t = %.2f s: %s", t, rec.reason)
            if delayed:
                pass  # tracked once it has finished (above); the previous reference until then
            elif result is not None and result.reference is not None:
                active = activate(result.reference, t, result.params, "plan")
                rec.t_effective = t
            else:
                offset = active.step_at(t, dt)
                ended = offset + period_steps * per_plan > active.x_ref.shape[0]
                p_prev = math.nan
                if not ended:
                    stride = int(round(plan_dt / active.reference.dt))
                    p_prev = _nominal_p_coll(grid_t, system, risk, t, plan_dt, active.reference.x[offset::stride],
                                             ignore=off_road)
                rec.previous_p_coll = p_prev
                if ended or not math.isfinite(p_prev) or p_prev > config.unsafe_p_coll:
                    why = "it has ended" if ended else (
                        f"its nominal P_coll {p_prev:.3f} > online.unsafe_p_coll = {config.unsafe_p_coll:g}"
                        if math.isfinite(p_prev) else "its risk cannot be evaluated")
                    braking, p_b = brake(grid_t, x_hat, t)
                    if ended or not math.isfinite(p_prev) or p_b < p_prev:
                        active = braking
                        rec.fallback = "brake"
                        rec.reason += f"; previous reference unsafe ({why}): least-risk braking (P_coll {p_b:.3f})"
                    else:  # braking is no safer than going on: keep the previous reference
                        rec.fallback = "previous"
                        rec.reason += (f"; previous reference unsafe ({why}) but the least-risk braking is no safer "
                                       f"(P_coll {p_b:.3f}): tracking the previous reference")
                else:
                    rec.fallback = "previous"
                    rec.reason += f"; tracking the previous reference (P_coll {p_prev:.3f})"
                rec.reason = rec.reason.lstrip("; ")
                log.info("t = %.2f s: fallback %s: %s", t, rec.fallback, rec.reason)
            replans.append(rec)
            step_extra = rec.wall_time + rec.prediction_time
            if progress is not None:
                progress(t, rec)
            snapshot(t, grid_t, system.positions(x).detach().cpu().numpy())
            grid_t.drop_caches()  # its derived full-size grids are not needed after this replan
        # -- track the active reference for one planning step (per_plan integration steps, one state)
        offset = active.step_at(t, dt)
        if offset + per_plan > active.x_ref.shape[0]:  # the reference ended (long fallback): brake from here
            x_hat = system.measure(x[None])[0]
            active, p_b = brake(prediction.window(t, horizon), x_hat, t)
            replans.append(Replan(t, "failed", 0.0, fallback="brake", reason="the tracked reference ended",
                                  previous_p_coll=p_b))
            offset = 0
        u_first = None
        if fast is not None:  # torch-free closed loop (control/fast.py)
            assert active.x_ref_np is not None and active.u_ref_np is not None  # set with fast (activate)
            xn, u_np = fast.track(x.detach().cpu().double().numpy(), active.x_ref_np[offset:offset + per_plan],
                                  active.u_ref_np[offset:offset + per_plan], dt, ctrl_times,
                                  standstill=system.standstill_index is not None)
            u_first = torch.from_numpy(u_np)
            x = torch.from_numpy(xn).to(dtype=dtype, device=device)
        else:
            with torch.no_grad():
                for j in range(per_plan):
                    xr, ur = active.x_ref[offset + j][None], active.u_ref[offset + j][None]
                    tc = time.perf_counter()
                    u = controller(system.measure(x[None]), xr, ur)
                    ctrl_times.append(time.perf_counter() - tc)
                    if u_first is None:
                        u_first = u[0]
                    x = system.standstill(x + dt * system.f(x[None], u)[0])
        assert u_first is not None  # per_plan >= 1 steps ran
        inputs.append(u_first.detach().cpu().numpy().astype(np.float64))
        step_times.append(float(sum(ctrl_times[-per_plan:])) + step_extra)
        states.append(x.detach().cpu().numpy().astype(np.float64))
        k += 1
        if road is not None and config.stop_at_goal:
            tk = np.array([t_start + k * plan_dt])
            px, py, heading, speed = system.pose(torch.from_numpy(states[-1]))
            inside = road.goal.contains(np.array([[px, py]]), tk, v=np.array([speed]), theta=np.array([heading]))
            if bool(inside[0]):
                log.info("t = %.2f s: in the goal region during its time interval; stopping", float(tk[0]))
                break
    x_all = np.stack(states)
    u_all = np.stack(inputs) if inputs else np.zeros((0, system.nu))
    times = t_start + plan_dt * np.arange(x_all.shape[0])
    pcs = [r.p_coll for r in replans if math.isfinite(r.p_coll)]
    verdict = judge(scene, x_all, u_all, system=system, dt=plan_dt, p_coll_max=max(pcs) if pcs else math.nan,
                    config=verdict_config, evaluation=evaluation)
    return DriveResult(times, x_all, u_all, replans, verdict, x_init, snapshots, prediction.name,
                       float(np.median(ctrl_times)) if ctrl_times else math.nan, initial_plan,
                       np.asarray(step_times, dtype=float),
                       executed_p_coll(scene, system, risk, x_all, plan_dt))

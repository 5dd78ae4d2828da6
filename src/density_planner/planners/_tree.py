"""Shared core of the ablation baselines (paper §V "Trajectory optimization", ``docs/spec.md`` §11): search over
partial sequences of the reference parameters, every node scored with density predictions.

A *node* is a prefix of ``d`` of the ``S`` one-second segments of the reference parameters (``p[:, :d]``). To score
a batch of nodes, ``n_samples`` initial states are propagated along their references in ONE predictor call, and
the cost terms are evaluated on each node's own horizon ``[0, d s]`` (planning points ``0 .. d * 10``) with the
planner's weights. The references are padded with zero inputs to the full horizon, so that any density predictor
(learned ones included) sees the input it was trained on; with the exact Liouville predictor, which integrates
forward in time, they are only as long as the deepest node of the batch (``horizon = "auto"``): the same values
on ``[0, d s]`` at a fraction of the cost. A child is *accepted* when

* its bounds cost ``J_B`` is zero (every sample inside the planning box),
* its goal cost ``J_G`` (density-weighted squared distance at ``t_d``) is below its parent's,
* its unweighted collision cost ``J_C`` is below ``collision_threshold`` (``coll_thr`` = 4),
* for ``d < S``: the reference heading at ``t_d`` points to within ``max_heading_error`` (pi / 2) of the goal and
  the goal is reachable at ``max_required_speed`` (9 m/s) in the remaining time;

an accepted full-length node (``d = S``) whose reference ends within ``goal_threshold`` (3.8 m) of the goal is a
*solution*. Subclasses decide which nodes to expand (:mod:`.search`, :mod:`.sampling`). The search stops at the
first solution it selects, or with status TIMEOUT after ``time_limit`` seconds (checked before every predictor
call, so it is exceeded by at most one call).
"""

from __future__ import annotations

import logging
import math
import time
from abc import abstractmethod
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from ..checks import check_choice, check_seed
from ..control.reference import Reference, make_reference
from ..cost.composite import CostConfig, WeightedCost, build_cost
from ..cost.terms import CostInputs
from ..density.base import DensityPredictor, DensityTrajectory, sample_weights
from ..density.liouville import ExactLiouville
from ._report import evaluate_samples
from .base import Planner, PlanResult, PlanStatus
from .density_planner import sample_initial_states
from .problem import PlanningProblem

__all__ = ["TreeConfig", "Node", "TreePlanner", "Scores", "REJECTION_REASONS"]

#: acceptance rules, as counted in ``extras["rejections"]``
REJECTION_REASONS = ("bounds", "goal_not_decreasing", "collision", "heading", "too_far")

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TreeConfig:
    """Settings shared by the search- and sampling-based optimisers (``docs/spec.md`` §11)."""

    #: initial samples propagated for every node
    n_samples: int = 500
    #: wall-clock limit [s]; TIMEOUT when no solution was found in time (the paper: five minutes)
    time_limit: float = 300.0
    #: stop after this many predictor calls (None: no limit; for reproducible short runs)
    max_calls: int | None = None
    #: a full-length plan must end within this distance of the goal [m] (goal_thr)
    goal_threshold: float = 3.8
    #: a node's unweighted collision cost J_C must stay below this (coll_thr)
    collision_threshold: float = 4.0
    #: maximum angle between the reference heading and the direction to the goal [rad]
    max_heading_error: float = math.pi / 2
    #: maximum average speed needed to reach the goal in the remaining time [m/s]
    max_required_speed: float = 9.0
    #: "support" (uniform on the support of the initial law, density-weighted) or "distribution"
    sample_proposal: Literal["support", "distribution"] = "support"
    #: sample weights: "mass" (importance weights rho0 / q0, unbiased, default) or "density" (paper)
    weighting: Literal["density", "mass"] = "mass"
    #: seed of the samples and of the random choices
    seed: int = 0
    #: cost weights of the node scores (the planners override the defaults with their own)
    cost: CostConfig = field(default_factory=CostConfig)
    #: add alpha_I J_I to the path cost
    include_input_cost: bool = True
    #: horizon of the predictions: "full" (zero-padded to all segments), "node" (as long as the deepest node of
    #: the batch; only valid for predictors that integrate forward in time), "auto" (node for exact Liouville)
    horizon: Literal["auto", "full", "node"] = "auto"

    def __post_init__(self) -> None:
        if isinstance(self.n_samples, bool) or not isinstance(self.n_samples, int) or self.n_samples < 1:
            raise ValueError(f"n_samples must be a positive integer, got {self.n_samples!r}")
        if self.max_calls is not None and (not isinstance(self.max_calls, int) or self.max_calls < 1):
            raise ValueError(f"max_calls must be a positive integer or None, got {self.max_calls!r}")
        for name in ("time_limit", "goal_threshold", "collision_threshold", "max_heading_error",
                     "max_required_speed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ValueError(f"{name} must be a number > 0, got {v!r}")
        check_choice("sample_proposal", self.sample_proposal, ("support", "distribution"))
        check_choice("weighting", self.weighting, ("density", "mass"))
        check_choice("horizon", self.horizon, ("auto", "full", "node"))
        check_seed("seed", self.seed)


@dataclass
class Node:
    """A partial parameter sequence.

    Attributes:
        params: ``(nu, depth)`` parameters of the first ``depth`` segments.
        goal: unweighted ``J_G`` at the end of its horizon [m^2].
        cost: path cost (weighted terms of the planner).
        terms: unweighted cost terms of its horizon.
        complete: full length and within ``goal_threshold`` of the goal.
    """

    params: Tensor
    goal: float
    cost: float = 0.0
    terms: dict[str, float] = field(default_factory=dict)
    complete: bool = False

    @property
    def depth(self) -> int:
        return int(self.params.shape[-1])


@dataclass
class Scores:
    """Scores of a batch of candidate nodes, each ``(B,)``."""

    accept: Tensor
    complete: Tensor
    goal: Tensor
    cost: Tensor
    terms: dict[str, Tensor]


@dataclass
class _Context:
    """Per-plan state: samples, objective, slices, start and the clock."""

    problem: PlanningProblem
    start: Tensor
    x0: Tensor
    log_rho0: Tensor
    log_q0: Tensor
    objective: WeightedCost
    slices: Tensor
    goal0: float
    t_start: float
    calls: int = 0
    nodes_scored: int = 0
    #: candidates failing each acceptance rule (a candidate may fail several)
    rejections: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REJECTION_REASONS, 0))


class TreePlanner(Planner):
    """Base class: owns the samples, the node scoring, the clock and the result; subclasses implement
    :meth:`_search`."""

    name = "tree"

    def __init__(
        self,
        predictor: DensityPredictor,
        config: TreeConfig,
        *,
        evaluation_cost: CostConfig | None = None,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str = "cpu",
    ):
        """
        Args:
            predictor: density predictor scoring the nodes (exact Liouville or a learned network).
            config: planner settings.
            evaluation_cost: cost configuration of the reported cost (shared with the density planner).
        """
        self.predictor = predictor
        self.config = config
        self.evaluation_cost = evaluation_cost or CostConfig()
        self.dtype = dtype
        self.device = torch.device(device)

    # ------------------------------------------------------------- scoring
    def _full(self, ctx: _Context, params: Tensor, n_seg: int | None = None) -> Tensor:
        """Zero-padded parameters ``(B, nu, n_seg)`` (default: all segments) of prefixes ``(B, nu, d)``."""
        n_seg = n_seg or ctx.problem.parameterization.n_segments
        pad = n_seg - params.shape[-1]
        return torch.nn.functional.pad(params, (0, pad)) if pad > 0 else params

    def _short_horizon(self) -> bool:
        mode = self.config.horizon
        return mode == "node" or (mode == "auto" and isinstance(self.predictor, ExactLiouville))

    @torch.no_grad()
    def _predict(self, ctx: _Context, padded: Tensor) -> tuple[Reference, DensityTrajectory]:
        """Predictions along the references of ``padded (B, nu, n)`` parameters (``n`` segments from t = 0)."""
        problem = ctx.problem
        par = problem.parameterization
        if padded.shape[-1] != par.n_segments:
            par = replace(par, n_segments=int(padded.shape[-1]))
        ref = make_reference(problem.system, ctx.start, padded.to(self.dtype).to(self.device), par)
        B = padded.shape[0]
        n = ctx.x0.shape[0]
        traj = self.predictor.predict(ctx.x0.expand(B, n, -1), ctx.log_rho0.expand(B, n), ref)
        return ref, traj

    def time_left(self, ctx: _Context) -> bool:
        """Whether another predictor call is allowed (time and call limits)."""
        cfg = self.config
        if cfg.max_calls is not None and ctx.calls >= cfg.max_calls:
            return False
        return time.perf_counter() - ctx.t_start < cfg.time_limit

    @torch.no_grad()
    def score(self, ctx: _Context, params: list[Tensor], parent_goal: Tensor) -> Scores:
        """Scores of the candidate prefixes ``params[b] (nu, d_b)`` (one predictor call for all of them)."""
        problem = ctx.problem
        par = problem.parameterization
        S = par.n_segments
        seg = int(round(par.segment_duration / par.plan_dt))
        depths = torch.tensor([p.shape[-1] for p in params])
        n_seg = int(depths.max()) if self._short_horizon() else S
        padded = torch.stack([self._full(ctx, p[None], n_seg)[0] for p in params])
        ref, traj = self._predict(ctx, padded)
        ctx.calls += 1
        ctx.nodes_scored += len(params)
        w = sample_weights(traj.log_rho, traj.log_rho0, mode=self.config.weighting, log_q0=ctx.log_q0)
        B = len(params)
        terms = {name: torch.zeros(B, dtype=torch.float64) for name in ctx.objective.terms}
        end = torch.zeros(B, ref.x.shape[-1], dtype=torch.float64)
        for d in sorted(set(depths.tolist())):
            idx = (depths == d).nonzero().squeeze(-1).to(self.device)
            n_t = d * seg + 1
            inputs = CostInputs(x=traj.x[idx, :, :n_t], weights=w[idx, :, :n_t], u_ref=ref.u_plan[idx, : n_t - 1],
                                slices=ctx.slices[:n_t])
            out = ctx.objective(inputs)
            for name, v in out.terms.items():
                terms[name][idx.cpu()] = v.detach().double().cpu()
            end[idx.cpu()] = ref.x_plan[idx, n_t - 1].double().cpu()
        cfg = self.config
        wts = ctx.objective.weights
        cost = wts["goal"] * terms["goal"] + wts["collision"] * terms["collision"]
        if cfg.include_input_cost:
            cost = cost + wts["input"] * terms["input"]
        goal = torch.tensor(problem.goal, dtype=torch.float64)
        delta = goal - problem.system.positions(end)
        dist = torch.linalg.norm(delta, dim=-1)
        bearing = torch.atan2(delta[:, 1], delta[:, 0])
        heading = problem.system.headings(end)
        heading_err = (torch.zeros_like(bearing) if heading is None
                       else torch.atan2(torch.sin(heading - bearing), torch.cos(heading - bearing)).abs())
        remaining = (S - depths).double() * par.segment_duration
        partial = depths < S
        speed_ok = dist <= cfg.max_required_speed * remaining
        rules = {
            "bounds": terms["bounds"] == 0,
            "goal_not_decreasing": terms["goal"] < parent_goal,
            "collision": terms["collision"] < cfg.collision_threshold,
            "heading": ~partial | (heading_err < cfg.max_heading_error),
            "too_far": ~partial | speed_ok,
        }
        accept = torch.isfinite(cost)
        for name, ok in rules.items():
            accept = accept & ok
            ctx.rejections[name] += int((~ok).sum())
        complete = accept & ~partial & (dist < cfg.goal_threshold)
        return Scores(accept=accept, complete=complete, goal=terms["goal"], cost=cost, terms=terms)

    def make_nodes(self, params: list[Tensor], scores: Scores) -> list[Node]:
        """The accepted candidates as :class:`Node` objects."""
        out = []
        for b in scores.accept.nonzero().squeeze(-1).tolist():
            out.append(Node(params[b], float(scores.goal[b]), float(scores.cost[b]),
                            {k: float(v[b]) for k, v in scores.terms.items()}, bool(scores.complete[b])))
        return out

    # ------------------------------------------------------------- planning
    def _context(self, problem: PlanningProblem, generator: torch.Generator) -> _Context:
        cfg = self.config
        start = problem.reference_start(self.dtype, self.device)
        x0, log_rho0, log_q0 = sample_initial_states(problem, cfg.n_samples, generator, cfg.sample_proposal,
                                                     dtype=self.dtype, device=self.device)
        objective = build_cost(problem.scene, cfg.cost, optimisation=True, device=self.device,
                               system=problem.system, risk=problem.risk)
        w0 = sample_weights(log_rho0[:, None], log_rho0, mode=cfg.weighting, log_q0=log_q0)[:, 0]
        goal = torch.tensor(problem.goal, dtype=self.dtype, device=self.device)
        goal0 = float((w0 * (problem.system.positions(x0) - goal).pow(2).sum(-1)).sum())
        return _Context(problem, start, x0, log_rho0, log_q0, objective, problem.slices(device=self.device),
                        goal0, time.perf_counter())

    @abstractmethod
    def _search(self, ctx: _Context, rng: np.random.Generator) -> tuple[Node | None, Node | None, dict[str, Any]]:
        """Run the search: ``(solution or None, best partial node or None, info for the result's extras)``.

        ``info["history"]`` (optional) is a list of path costs, stored as ``cost_history[name]["total"]``."""

    def plan(self, problem: PlanningProblem) -> PlanResult:
        """Run the search; never raises (the status says what happened). ``extras["rejections"]`` counts the
        candidates failing each acceptance rule."""
        if hasattr(self.predictor, "check_parameterization"):  # a learned predictor only serves its own horizon
            self.predictor.check_parameterization(problem.parameterization)
        t_start = time.perf_counter()
        try:
            gen = torch.Generator().manual_seed(self.config.seed)
            rng = np.random.Generator(np.random.PCG64(self.config.seed))
            ctx = self._context(problem, gen)
            solution, partial, info = self._search(ctx, rng)
            t_search = time.perf_counter() - t_start
            node = solution or partial
            if solution is not None:
                status, message = PlanStatus.SUCCESS, ""
            elif not self.time_left(ctx):
                status = PlanStatus.TIMEOUT
                message = (f"no full-length plan within the limit ({self.config.time_limit:g} s, "
                           f"{ctx.calls} predictor calls)")
            else:
                status, message = PlanStatus.FAILED, "search space exhausted: no acceptable full-length plan"
            if node is None:
                worst = max(ctx.rejections, key=ctx.rejections.__getitem__)
                message += (f"; no candidate was accepted ({ctx.nodes_scored} scored, most often rejected by the "
                            f"'{worst}' rule)")
            if node is not None and solution is None:
                message += f"; reporting the best partial plan ({node.depth} segments, zero inputs after)"
            history = info.pop("history", None)
            info["rejections"] = dict(ctx.rejections)
            result = PlanResult(self.name, status, message=message,
                                cost_history={self.name: {"total": list(history)}} if history else {},
                                timings={"search": t_search},
                                iterations={"predictor_calls": ctx.calls, "nodes_scored": ctx.nodes_scored},
                                extras=info)
            if node is not None:
                self._fill(result, ctx, node)
            result.timings["total"] = time.perf_counter() - t_start
            return result
        except Exception as exc:  # noqa: BLE001 - a benchmark never crashes on one planner
            log.warning("%s failed: %s", self.name, exc)
            return PlanResult(self.name, PlanStatus.ERROR, message=f"{type(exc).__name__}: {exc}",
                              timings={"total": time.perf_counter() - t_start})

    def _fill(self, result: PlanResult, ctx: _Context, node: Node) -> None:
        full = self._full(ctx, node.params[None].to(self.dtype).to(self.device))
        ref, traj = self._predict(ctx, full)
        cost, coll = evaluate_samples(ctx.problem, ref, traj, cost_config=self.evaluation_cost,
                                      weighting=self.config.weighting, log_q0=ctx.log_q0[None])
        result.params = full[0]
        result.reference = ref.select(0)
        result.states = ref.x_plan[0]
        result.samples = DensityTrajectory(traj.t, traj.x[0], traj.log_rho[0], traj.log_rho0[0])
        result.cost = cost
        result.collision = coll
        result.extras.update({"depth": node.depth, "path_cost": node.cost, "node_terms": node.terms,
                              "predictor": getattr(self.predictor, "name", type(self.predictor).__name__)})

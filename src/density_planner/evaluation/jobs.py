"""The worker side of a benchmark sweep: a :class:`Job` runs one planner on one environment for one or more
measurement variants and returns its records (:func:`run_job`; a picklable module-level function for joblib and
Dask workers).

A planner whose registration says it does not plan from the true state (density, search, sampling) plans once
offline and that plan is executed for every variant of the job; MPC and oracle plan from the true state, one job
per variant. How a plan is executed is its registration's
:class:`~density_planner.planners.registry.ExecutionMode` (:mod:`.simulate`). Everything random is seeded from
the environment and the planner name (:func:`~.environments.stable_seed`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import socket
import time
import traceback
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from ..config import to_dict
from ..planners.base import PlanResult
from ..planners.context import run_model_set, run_system
from ..planners.problem import PlanningProblem
from ..planners.registry import ExecutionMode, make_planner, planner_info
from .benchmark_settings import SETTINGS
from .config import EvaluationConfig
from .environments import EnvSpec, build_scene, stable_seed
from .metrics import evaluation_box, failure_flags, monte_carlo_metrics, run_metrics
from .records import RECORD_SCHEMA, scene_map_arrays
from .simulate import execute, monte_carlo
from .verdict import record_verdict, verdict_failure

__all__ = ["Job", "JobResult", "run_job", "job_scene", "base_record", "error_record", "planner_run_config"]


@dataclass(frozen=True)
class Job:
    """One planner on one environment, for one or more variants (shipped to a worker)."""

    setting: str
    env: EnvSpec
    planner: str
    variants: tuple[str, ...]
    run_config: Any
    controller: str | None
    density: str | None
    config_hash: str
    #: also return the environment's map for the figures
    want_map: bool = False
    #: the resolved controller / predictor and their digest (recorded)
    components: str = ""

    @property
    def runs(self) -> int:
        return len(self.variants)


@dataclass
class JobResult:
    """What a job returns: its records and, if asked, the environment's map."""

    records: list[dict[str, Any]]
    scene_map: dict[str, Any] | None = None


# ---------------------------------------------------------------------------------------------- worker side
#: per-process caches: planner contexts (controller and predictor loaded once) and the last scenes built
_CONTEXTS: dict[Any, Any] = {}
_SCENES: dict[Any, Any] = {}


def _context(job: Job, parameterization=None):
    """The planner context of ``job`` (:func:`~density_planner.planners.context.build_context`; the controller and
    the predictor are loaded once per process and reused by the following jobs)."""
    from ..planners.context import build_context

    # the run's system and model set for the scene kind (the car: road on recorded scenes, paper on random ones)
    models = run_model_set(job.run_config, job.env.kind)
    exact_check = job.run_config.evaluation.exact_check
    key = (job.controller, job.density, job.run_config.system, job.run_config.liouville, parameterization,
           models.name, exact_check)
    if key not in _CONTEXTS:
        _CONTEXTS.clear()
        # the predictor is loaded on first use (MPC and oracle jobs never load it); the exact re-check of a learned
        # prediction as evaluation.exact_check says
        _CONTEXTS[key] = build_context(job.run_config, kind=job.env.kind, controller=job.controller,
                                       density=job.density, parameterization=parameterization, lazy=True,
                                       exact_check=exact_check)
    return replace(_CONTEXTS[key], config=job.run_config)


def job_scene(job: Job):
    """The scene of ``job`` (the last two built are kept: the jobs of one environment follow each other)."""
    key = (job.env, json.dumps(to_dict(job.run_config), sort_keys=True, default=str))
    if key not in _SCENES:
        if len(_SCENES) >= 2:
            _SCENES.pop(next(iter(_SCENES)))
        _SCENES[key] = build_scene(job.env, job.run_config)
    return _SCENES[key]


def planner_run_config(run_config: Any, planner: str, variant: str | None, seed: int) -> Any:
    """``run_config`` with the planner's section (its registration's) seeded with ``seed`` and, for MPC, the
    measurement variant set."""
    section = planner_info(planner, default=True).section
    cfg = getattr(run_config, section, None) if section else None
    if section is None or cfg is None or not dataclasses.is_dataclass(cfg) or isinstance(cfg, type):
        return run_config
    names = {f.name for f in dataclasses.fields(cfg)}
    changes: dict[str, Any] = {}
    if "seed" in names:
        changes["seed"] = seed
    if "biased_measurement" in names and variant is not None:
        changes["biased_measurement"] = variant == "biased"
    return replace(run_config, **{section: replace(cfg, **changes)}) if changes else run_config


def _floats(t: torch.Tensor | None) -> list | None:
    return None if t is None else t.detach().cpu().double().tolist()


_PLAN_EXTRAS = ("predictor", "tube_radius", "biased_measurement", "n_failed_steps", "step_status_counts",
                "best_restart", "n_tube_offsets")


def _risk_check(job: Job, problem: PlanningProblem, plan: PlanResult, controller, eval_cfg) -> dict[str, Any]:
    """Monte-Carlo check of the plan's collision probability (risk.validate_samples closed loops)."""
    from .risk_validation import validate_risk

    try:
        check = validate_risk(problem, plan, controller, n=job.run_config.risk.validate_samples,
                              seed=stable_seed("risk-check", job.env.name), config=eval_cfg)
    except ValueError as exc:
        return {"passed": None, "message": str(exc)}
    return check.to_dict()


def _plan_summary(plan: PlanResult | None) -> dict[str, Any] | None:
    if plan is None:
        return None
    return {
        "status": plan.status.value,
        "message": plan.message,
        "params": _floats(plan.params),
        "cost": plan.cost,
        "collision_probability_max": None if plan.collision is None else float(plan.collision.max),
        "collision_probability_se_at_max": None if plan.collision is None or plan.collision.se is None
        else plan.collision.to_dict()["se_at_max"],
        "collision_estimator": None if plan.collision is None else plan.collision.estimator,
        # collision at some time (lower bound; the planner's estimate of the metrics' mc_collision_mean)
        "collision_probability_any": None if plan.collision is None or plan.collision.any_time is None
        else float(plan.collision.any_time),
        "collision_probability_any_se": None if plan.collision is None or plan.collision.any_time_se is None
        else float(plan.collision.any_time_se),
        # its upper (union) bound sum_i w_i min(1, sum_k P_body)
        "collision_probability_any_upper": None if plan.collision is None or plan.collision.any_time_upper is None
        else float(plan.collision.any_time_upper),
        # the learned predictor's own estimate when the exact re-check reported instead (report_exact)
        "collision_probability_any_predictor": _predictor_any(plan),
        "iterations": plan.iterations,
        "extras": {k: v for k, v in plan.extras.items() if k in _PLAN_EXTRAS},
    }


def _predictor_any(plan: PlanResult) -> float | None:
    est = plan.extras.get("predictor_estimate") if isinstance(plan.extras, dict) else None
    value = ((est or {}).get("collision_probability") or {}).get("any_time")
    return None if value is None else float(value)


def base_record(job: Job, variant: str) -> dict[str, Any]:
    return {
        "schema": RECORD_SCHEMA,
        "setting": job.setting,
        "env": job.env.name,
        "env_spec": job.env.as_dict(),
        "planner": job.planner,
        "variant": variant,
        "config_hash": job.config_hash,
        "controller": job.controller,
        "density": job.density,
        "components": job.components,
        "status": "error",
        "failed": True,
        "failure_reason": "no_solution",
        "failure_flags": {"no_solution": True},
        "message": "",
        "metrics": None,
        "error": None,
        "timings": {},
        "run_info": {"host": socket.gethostname(), "pid": os.getpid()},
    }


def error_record(job: Job, variant: str, error: str, where: str = "run") -> dict[str, Any]:
    """A failure record for a run that raised (``error``: the traceback) or whose worker died."""
    rec = base_record(job, variant)
    lines = [s for s in error.strip().splitlines() if s.strip()]
    rec["message"] = f"{where} failed: {lines[-1].strip() if lines else 'unknown error'}"
    rec["error"] = error
    rec["config"] = to_dict(job.run_config)
    return rec


def _true_states(
    problem: PlanningProblem, env: EnvSpec, eval_cfg: EvaluationConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """The run's true initial state ``(nx,)`` and the Monte-Carlo states ``(M_max, nx)``, float64, bias included;
    the same for every planner of the environment."""
    dist = problem.initial_distribution
    x_true = dist.sample(1, torch.Generator().manual_seed(stable_seed("true-state", env.name)),
                         dtype=torch.float64)[0]
    m = max(eval_cfg.mc_samples_tracked, eval_cfg.mc_samples_receding, eval_cfg.mc_samples_open_loop)
    mc = dist.sample(m, torch.Generator().manual_seed(stable_seed("monte-carlo", env.name)),
                     dtype=torch.float64) if m > 0 else torch.zeros(0, dist.dim, dtype=torch.float64)
    return x_true, mc


def _variant_state(system, x: torch.Tensor, variant: str) -> torch.Tensor:
    """The true states of a variant: "biased" keeps the hidden states (the car's heading bias) drawn from the initial
    distribution, the others set them to 0 (``system.nominal_state``)."""
    return x.clone() if variant == "biased" else system.nominal_state(x.clone())


def _mc_count(mode: ExecutionMode, cfg: EvaluationConfig) -> int:
    return {ExecutionMode.TRACK: cfg.mc_samples_tracked, ExecutionMode.RECEDING: cfg.mc_samples_receding,
            ExecutionMode.OPEN_LOOP: cfg.mc_samples_open_loop}[mode]


def _evaluate(job: Job, variant: str, planner, problem: PlanningProblem, scene, ctx, plan: PlanResult | None,
              x_true: torch.Tensor, mc_states: torch.Tensor, seeds: dict[str, int]) -> dict[str, Any]:
    """Execute one variant and score it."""
    eval_cfg: EvaluationConfig = job.run_config.evaluation
    setting = SETTINGS[job.setting]
    t_start = time.perf_counter()
    rec = base_record(job, variant)
    rec["seeds"] = seeds
    mode = planner_info(job.planner, default=True).execution
    rec["execution"] = mode.value if setting.closed_loop else "planned"
    car = problem.system
    box = evaluation_box(scene, *car.state_bounds, eval_cfg.position_bounds)
    cost_cfg = job.run_config.density_planner.cost
    plan_dt = problem.parameterization.plan_dt
    x0 = _variant_state(car, x_true, variant)
    mc0 = _variant_state(car, mc_states[: _mc_count(mode, eval_cfg)], variant)
    rec["true_state"] = _floats(x0)

    if not setting.closed_loop:  # ablation: the planned reference
        assert plan is not None
        solved = plan.ok and plan.reference is not None
        plan_time = float(plan.timings.get("total", math.nan))
        timeout = plan_time > eval_cfg.plan_time_limit
        metrics = None
        if plan.reference is not None:
            ref = plan.reference
            metrics = run_metrics(scene, ref.x_plan, ref.u_plan, ref.u_plan, box=box, cost_config=cost_cfg,
                                  plan_dt=plan_dt, collision=problem.collision())
            runs = monte_carlo(planner, problem, mc0, plan=plan, controller=ctx.controller, config=eval_cfg)
            metrics.update(monte_carlo_metrics(scene, runs, threshold=eval_cfg.collision_threshold, plan_dt=plan_dt,
                                               collision=problem.collision()))
            rec["trajectory"] = _floats(ref.x_plan)
            rec["verdict"] = record_verdict(scene, ref.x_plan, ref.u_plan, plan, car, plan_dt, job.run_config)
        flags, reason = verdict_failure(rec.get("verdict"), solved and not timeout) or failure_flags(
            metrics, solved and not timeout, eval_cfg, cost_thresholds=eval_cfg.ablation_cost_failures)
        rec.update(status="timeout" if timeout else plan.status.value, metrics=metrics, failed=bool(reason),
                   failure_reason=reason, failure_flags=flags, plan=_plan_summary(plan),
                   message=plan.message if not timeout else f"planning took {plan_time:.0f} s > "
                   f"{eval_cfg.plan_time_limit:g} s")
        rec["timings"] = {"offline": plan_time, "online_per_step": 0.0, "plan": plan.timings,
                          "evaluation": time.perf_counter() - t_start}
        return rec

    run = execute(planner, problem, x0, plan=plan, controller=ctx.controller, config=eval_cfg)
    metrics = None
    if run.states.shape[0] >= 2:
        metrics = run_metrics(scene, run.states, run.planned_inputs, run.applied_inputs, box=box,
                              cost_config=cost_cfg, plan_dt=plan_dt, collision=problem.collision())
        t_mc = time.perf_counter()
        runs = monte_carlo(planner, problem, mc0, plan=plan, controller=ctx.controller, config=eval_cfg)
        metrics.update(monte_carlo_metrics(scene, runs, threshold=eval_cfg.collision_threshold, plan_dt=plan_dt,
                                               collision=problem.collision()))
        if mode == ExecutionMode.TRACK and not torch.equal(mc0, mc_states[: mc0.shape[0]]):
            # the variant changed the drawn states (unbiased: no heading bias), so the law the planner's risk is an
            # expectation over is not the one above: the same count of closed loops from the law itself, for the
            # calibration of the reported risk (mc_law_collision_mean / _se)
            law = monte_carlo(planner, problem, mc_states[: mc0.shape[0]], plan=plan, controller=ctx.controller,
                              config=eval_cfg)
            law_m = monte_carlo_metrics(scene, law, threshold=eval_cfg.collision_threshold, plan_dt=plan_dt,
                                        collision=problem.collision())
            metrics.update(mc_law_collision_mean=law_m["mc_collision_mean"],
                           mc_law_collision_se=law_m["mc_collision_se"])
        t_mc = time.perf_counter() - t_mc
        if job.run_config.risk.validate_samples and mode == ExecutionMode.TRACK and variant == job.variants[0]:
            rec["risk_check"] = _risk_check(job, problem, run.plan, ctx.controller, eval_cfg)
        rec["trajectory"] = _floats(run.states)
        rec["applied_inputs"] = _floats(run.applied_inputs)
        rec["verdict"] = record_verdict(scene, run.states, run.applied_inputs, run.plan, car, plan_dt, job.run_config)
        if mode == ExecutionMode.TRACK and run.plan.reference is not None:
            rec["reference"] = _floats(problem.system.positions(run.plan.reference.x_plan))
    else:
        t_mc = 0.0
    # road scenes: the verdict decides (the paper's thresholds read a goal point and a cost scale they lack)
    flags, reason = verdict_failure(rec.get("verdict"), run.ok) or failure_flags(metrics, run.ok, eval_cfg)
    rec.update(status=run.plan.status.value, metrics=metrics, failed=bool(reason), failure_reason=reason,
               failure_flags=flags, message=run.message or run.plan.message, plan=_plan_summary(run.plan))
    steps = run.step_times
    rec["timings"] = {
        "offline": run.offline_time,
        "online_per_step": float(np.mean(steps)) if steps.size else 0.0,
        "online_max_step": float(np.max(steps)) if steps.size else 0.0,
        "online_total": float(np.sum(steps)),
        "plan": run.plan.timings,
        "monte_carlo": t_mc,
        "evaluation": time.perf_counter() - t_start,
    }
    return rec


def run_job(job: Job) -> JobResult:
    """Run one job (in a worker): build the scene, plan, execute every variant, score. Exceptions inside a run
    become failure records with the traceback; the job itself only raises if its worker dies."""
    t_job = time.perf_counter()
    torch.manual_seed(stable_seed("job", job.env.name, job.planner))
    try:
        scene = job_scene(job)
        problem = PlanningProblem.from_scene(scene, seed=job.env.law_seed, planning=job.run_config.planning,
                                             risk=job.run_config.risk, system=run_system(job.run_config, job.env.kind))
        x_true, mc_states = _true_states(problem, job.env, job.run_config.evaluation)
        ctx = _context(job, problem.parameterization)
    except Exception:  # noqa: BLE001 - recorded, the sweep goes on
        tb = traceback.format_exc()
        return JobResult([error_record(job, v, tb, "environment") for v in job.variants])
    scene_map = scene_map_arrays(scene) if job.want_map else None
    seed = stable_seed("planner", job.env.name, job.planner)
    seeds = {"distribution": job.env.law_seed, "true_state": stable_seed("true-state", job.env.name),
             "monte_carlo": stable_seed("monte-carlo", job.env.name), "planner": seed}
    per_variant = planner_info(job.planner, default=True).plans_from_true_state and SETTINGS[job.setting].closed_loop
    planner = plan = None
    if not per_variant:  # plan once offline, execute the plan for every variant
        try:
            ctx.config = planner_run_config(job.run_config, job.planner, None, seed)
            planner = make_planner(job.planner, ctx)
            plan = planner.plan(problem)
        except Exception:  # noqa: BLE001 - a planner exception is a recorded failure of every variant
            tb = traceback.format_exc()
            return JobResult([error_record(job, v, tb, "planning") for v in job.variants], scene_map)
    records = []
    for variant in job.variants:
        try:
            if per_variant:
                ctx.config = planner_run_config(job.run_config, job.planner, variant, seed)
                planner = make_planner(job.planner, ctx)
            rec = _evaluate(job, variant, planner, problem, scene, ctx, plan, x_true, mc_states, seeds)
        except Exception:  # noqa: BLE001 - a planner exception is a recorded failure
            rec = error_record(job, variant, traceback.format_exc())
        rec["config"] = to_dict(job.run_config)
        rec["run_info"].update(finished=time.strftime("%Y-%m-%dT%H:%M:%S"), job_wall=time.perf_counter() - t_job)
        records.append(rec)
    return JobResult(records, scene_map)



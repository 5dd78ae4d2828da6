"""Shared helpers of the evaluation tests (a uniquely named module: importable from tests and worker processes).

Importing it registers two test planners: ``test_crash`` (raises in ``plan``) and ``test_kill`` (its worker process
dies in ``plan``); :func:`run_job_with_test_planners` is a picklable job function that makes them known in every
worker.
"""

from __future__ import annotations

import math
import os

from density_planner.config import update
from density_planner.evaluation.jobs import JobResult, run_job
from density_planner.planners.base import Planner
from density_planner.planners.registry import register_planner
from density_planner.settings import RunConfig

#: the smallest density-planner configuration that still exercises both stages
TINY_DP = {"n_candidates": 4, "epochs_init": 3, "epochs_density": 2, "n_samples": 16}


def tiny_run_config(**sections) -> RunConfig:
    """A run configuration for fast tests: tiny density planner, 8 Monte-Carlo samples, deterministic MPC (no CPU
    time limit, few iterations) and a one-restart oracle."""
    data = {
        "density_planner": dict(TINY_DP),
        "evaluation": {"mc_samples_tracked": 8, "mc_samples_receding": 0},
        "mpc": {"max_cpu_time": math.inf, "max_iter": 5},
        "tube_mpc": {"max_cpu_time": math.inf, "max_iter": 3},
        "oracle": {"restarts": 1, "max_iter": 20},
    }
    for k, v in sections.items():
        data.setdefault(k, {}).update(v)
    return update(RunConfig(), data)


class _CrashPlanner(Planner):
    name = "test_crash"

    def plan(self, problem):
        raise RuntimeError("test_crash planner fails on purpose")


class _KillPlanner(Planner):
    name = "test_kill"

    def plan(self, problem):
        os._exit(3)


@register_planner("test_crash", "test planner that raises")
def _make_crash(ctx):
    return _CrashPlanner()


@register_planner("test_kill", "test planner whose process dies")
def _make_kill(ctx):
    return _KillPlanner()


def run_job_with_test_planners(job) -> JobResult:
    """:func:`run_job` in a process where the test planners are registered (this module is imported on
    unpickling)."""
    return run_job(job)


def record(env: str, planner: str, variant: str = "unbiased", *, failed: bool = False, collision: float = 0.0,
           goal: float = 0.0, inputs: float = 0.0, offline: float = 1.0, online: float = 0.01,
           mc: float | None = None, setting: str = "artificial", status: str = "success",
           reason: str | None = None) -> dict:
    """A hand-made benchmark record."""
    return {
        "setting": setting, "env": env, "planner": planner, "variant": variant, "status": status,
        "failed": failed, "failure_reason": reason if reason is not None else ("goal" if failed else ""),
        "metrics": {"collision_cost": collision, "goal_cost": goal, "input_cost": inputs,
                    "final_distance": goal ** 0.5, "collision_probability_max": 0.1,
                    "mc_collision_frequency": mc, "mc_collision_mean": mc},
        "timings": {"offline": offline, "online_per_step": online},
    }

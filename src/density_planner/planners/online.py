"""The density planner run online (receding horizon), as a planner the benchmarks execute step by step.

``density_online`` (observed-only prediction) and ``density_online_oracle`` (the recorded future, known in
advance) wrap :func:`density_planner.evaluation.online.drive`: like the MPC baselines they run in
:class:`~density_planner.evaluation.simulate.ExecutionMode` ``RECEDING`` (``plan_from(problem, true_state)``
simulates the whole run from the true state and returns the executed trajectory), so ``bench commonroad
--planners density,density_online,density_online_oracle,mpc`` (or ``bench commonroad --mode online``) compares
offline and online density planning and MPC M0 on the same scenarios and true initial states, judged by the same
verdict. Settings: ``[online]`` (the prediction kind is set by the planner's name).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from torch import Tensor

from .base import Planner, PlanResult, PlanStatus
from .density_planner import DensityPlanner
from .problem import PlanningProblem
from .registry import PlannerContext, register_planner

__all__ = ["OnlineDensityPlanner"]


class OnlineDensityPlanner(Planner):
    """Receding-horizon density planning (see the module docstring)."""

    def __init__(self, inner: DensityPlanner, ctx: PlannerContext, prediction: str, name: str):
        self.inner = inner
        self.ctx = ctx
        self.prediction = prediction
        self.name = name

    def plan(self, problem: PlanningProblem) -> PlanResult:
        """The first plan from the initial distribution, as :meth:`plan_from` makes it: on what the prediction shows
        at the start (:func:`~density_planner.evaluation.online.initial_problem`; the oracle's: ``problem``)."""
        from ..environment.prediction import make_prediction
        from ..evaluation.online import initial_problem

        return self.inner.plan(initial_problem(problem, make_prediction(problem.scene, self.online_config.prediction)))

    @property
    def online_config(self):
        """``[online]`` with the prediction kind of this planner's name."""
        online = self.ctx.config.online
        return dataclasses.replace(online, prediction=dataclasses.replace(online.prediction, kind=self.prediction))

    def plan_from(self, problem: PlanningProblem, true_state: Tensor) -> PlanResult:
        """Drive online from ``true_state``; the result's ``states`` are the executed states, its extras hold the
        applied inputs, the online time per planning step and every replan."""
        from ..evaluation.online import drive

        cfg = self.ctx.config
        online = self.online_config
        res = drive(problem.scene, self.inner, self.ctx.controller, system=problem.system, config=online,
                    planning=cfg.planning, risk=problem.risk, evaluation=cfg.evaluation, verdict_config=cfg.verdict,
                    true_state=true_state, keep_snapshots=False)
        summary = res.summary()
        p = [r.p_coll for r in res.replans if math.isfinite(r.p_coll)]
        ok = res.initial_plan is not None and res.initial_plan.ok
        extras = {
            "applied_inputs": res.inputs.tolist(),
            "step_times": res.step_times.tolist(),
            "prediction": res.prediction,
            "replans": summary["replans"],
            "n_fallbacks": summary["n_fallbacks"],
            "p_coll_mean": float(np.mean(p)) if p else None,
            "replan_wall_time_median": summary["replan_wall_time_median"],
            "warm_replan_wall_time_median": summary["warm_replan_wall_time_median"],
        }
        timings = {"total": float(sum(r.wall_time for r in res.replans)),
                   "tube_precompute": float(res.replans[0].wall_time)}  # the first plan is offline work
        return PlanResult(self.name, PlanStatus.SUCCESS if ok else PlanStatus.FAILED,
                          states=torch.as_tensor(res.states, dtype=torch.float32), timings=timings, extras=extras,
                          message="" if ok else "the first plan failed")


def _factory(prediction: str, name: str):
    def make(ctx: PlannerContext) -> OnlineDensityPlanner:
        inner = DensityPlanner(ctx.predictor(), ctx.config.density_planner, dtype=ctx.dtype, device=ctx.device)
        return OnlineDensityPlanner(inner, ctx, prediction, name)

    return make


# the first plan from the initial distribution on the prediction at the start, the replans from the measurement
for _name, _prediction, _help in (
    ("density_online", "observed", "density planner online: replans every online.period from the measurement with "
     "the observed-only prediction ([online])"),
    ("density_online_oracle", "oracle", "density planner online with the oracle prediction (the recorded future, "
     "known in advance)"),
):
    register_planner(_name, _help, section="online", reads=("density_planner",),
                     execution="receding")(_factory(_prediction, _name))

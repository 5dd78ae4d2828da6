"""Wall time and success of a warm-started replan vs a full plan (issue 17's speed target: median <= 0.1 s, p95 <=
0.2 s on one thread with 500 samples and the learned predictor, at the success rate of a full plan).

On random scenes ``0 .. N-1``: a full two-stage plan from the initial distribution (timed, judged by
:func:`~density_planner.evaluation.verdict.judge_plan`), then replans warm-started from the shifted plan at
``t = period, 2 period, ...`` from the planned state (oracle occupancy: the scene's own model), as ``drive`` makes
them (``online.replan_epochs`` at most, ``online.replan_patience``; with ``online.shrink_horizon`` the horizon ends
with the first plan's), each timed and judged the same way on its own window. Prints the median and
p95 wall times, the stage-2 iterations and both success rates.

Usage::

    PYTHONPATH=src python benchmarks/bench_replan.py --scenes 5 --replans 4 --set online.replan_epochs=10
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", type=int, default=5)
    p.add_argument("--replans", type=int, default=4, help="replans per scene")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)

    from density_planner.config import load_config, update
    from density_planner.environment.prediction import OraclePrediction
    from density_planner.environment.random_scene import random_scene
    from density_planner.evaluation.online import (
        _replan_parameterization,
        holds_speed,
        recentred,
        shifted_plan,
        warm_replan,
    )
    from density_planner.evaluation.verdict import judge_plan
    from density_planner.planners.context import build_context
    from density_planner.planners.density_planner import DensityPlanner
    from density_planner.planners.problem import PlanningProblem
    from density_planner.settings import RunConfig

    cfg = load_config(RunConfig, None, args.overrides)
    online = cfg.online
    period = online.replan_period(cfg.planning.segment_duration)
    n_slices = int(round((10.0 + args.replans * period + 10.0) / 0.1)) + 1
    cfg = update(cfg, {"random_scene": {"n_slices": max(cfg.random_scene.n_slices, n_slices)}})
    ctx = build_context(cfg, kind="random", controller="c3m")
    car, pred = ctx.system, ctx.predictor()
    planner = DensityPlanner(pred, cfg.density_planner)
    samples = online.replan_samples or cfg.density_planner.n_samples
    full_t, full_ok, re_t, re_ok, re_warm, re_it = [], [], [], [], [], []
    for seed in range(args.scenes):
        scene = random_scene(seed, cfg.random_scene)
        problem = PlanningProblem.from_scene(scene, seed=seed, system=car, planning=cfg.planning, risk=cfg.risk)
        t0 = time.perf_counter()
        plan = planner.plan(problem)
        full_t.append(time.perf_counter() - t0)
        v = judge_plan(scene, plan, system=car, dt=problem.parameterization.plan_dt)
        full_ok.append(bool(v is not None and v.ok))
        oracle = OraclePrediction(scene)
        prev, t_prev = plan, 0.0
        for i in range(1, args.replans + 1):
            t = i * period
            k = int(round((t - t_prev) / problem.parameterization.plan_dt))
            state = prev.reference.x_plan[k]
            mean = state.to(torch.float64).clone()
            mean[-1] = problem.initial_distribution.mean[-1]
            # a random scene's goal is to be reached at the first plan's end (drive's shrink_horizon)
            par_t = _replan_parameterization(problem.parameterization, problem.parameterization.horizon, t,
                                             online.shrink_horizon)
            sc = oracle.scene_at(t, par_t.horizon, start=car.pose(state))
            prob = PlanningProblem(sc, recentred(problem.initial_distribution, mean), car, par_t, problem.risk)
            # drive's warm start (a random scene's goal time is the first plan's end)
            hold = holds_speed(online, t, problem.parameterization.horizon, par_t.horizon)
            warm = shifted_plan(car, prev.params, prev.reference, t - t_prev,
                                problem.parameterization.segment_duration, par_t.n_segments, hold=hold)
            t1 = time.perf_counter()
            res, used = warm_replan(planner, prob, warm, seed=i, **online.replan_settings())  # as drive does
            re_t.append(time.perf_counter() - t1)
            re_it.append(res.iterations.get("stage2", 0) if res.iterations else 0)
            re_warm.append(used)
            v = judge_plan(sc, res, system=car, dt=problem.parameterization.plan_dt)
            re_ok.append(bool(res.ok and v is not None and v.ok))
            if res.ok:
                prev, t_prev = res, t
        print(f"scene {seed}: full plan {full_t[-1]:.2f} s ({'pass' if full_ok[-1] else 'fail'}), replans "
              f"{', '.join(f'{x:.3f}' for x in re_t[-args.replans:])} s", flush=True)
    re = np.asarray(re_t)
    print(f"\nfull plan: median {np.median(full_t):.2f} s, success {np.mean(full_ok):.0%} "
          f"({sum(full_ok)}/{len(full_ok)})")
    print(f"warm-started replan (<= {online.replan_epochs} epochs, patience {online.replan_patience}, {samples} "
          f"samples, {args.threads} thread(s)): median {np.median(re):.3f} s, p95 {np.percentile(re, 95):.3f} s, "
          f"success {np.mean(re_ok):.0%} ({sum(re_ok)}/{len(re_ok)}), stage-2 iterations median "
          f"{np.median(re_it):g} (max {max(re_it)}); target median <= 0.1 s, p95 <= 0.2 s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Experiment: does planning need the predicted density? Positions-only (importance weights) vs density weights.

With ``weighting = "mass"`` (default) the density planner's cost and risk use the samples' closed-loop positions
and their initial importance weights ``rho0 / q0`` only: a predictor that returned positions alone would give the
same plan. With ``weighting = "density"`` (the paper) the predicted density values weight the samples. For each
random scene both variants plan with the same seed and predictor; each plan is then scored by Monte Carlo
(``--mc`` initial states from the planner's initial law, closed loops simulated exactly): the expected body
occupancy ``max_t P_MC(t)``, its time sum, and the distance of the reference's end to the goal.

    python benchmarks/bench_weighting.py [--seeds 1:6] [--mc 4000] [--density NAME] [--threads 1]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from density_planner.control.registry import load_controller
from density_planner.density.registry import load_predictor
from density_planner.environment import random_scene
from density_planner.evaluation.risk_validation import monte_carlo_risk
from density_planner.planners.density_planner import DensityPlanner, DensityPlannerConfig
from density_planner.planners.problem import PlanningProblem
from density_planner.systems.car import KinematicCar


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", default="1:6", help="random scenes A:B (B exclusive)")
    p.add_argument("--mc", type=int, default=4000)
    p.add_argument("--density", default=None)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    a, b = (int(v) for v in args.seeds.split(":"))
    car = KinematicCar()
    controller = load_controller(None)
    predictor = load_predictor(args.density, car, controller)
    rows = []
    print("| scene | weighting | MC max_t P_coll | MC sum_t P_coll | reported max | goal distance [m] | plan [s] |")
    print("|---|---|---|---|---|---|---|")
    for seed in range(a, b):
        scene = random_scene(seed)
        problem = PlanningProblem.from_scene(scene, seed=seed)
        for weighting in ("mass", "density"):
            planner = DensityPlanner(predictor, DensityPlannerConfig(weighting=weighting, seed=seed))
            t0 = time.perf_counter()
            plan = planner.plan(problem)
            t_plan = time.perf_counter() - t0
            mc, _ = monte_carlo_risk(problem, plan, controller, n=args.mc, seed=1000 + seed)
            goal = torch.tensor(scene.goal, dtype=torch.float64)
            dist = float((car.positions(plan.states[-1]).double() - goal).norm())
            row = (seed, weighting, float(mc.max()), float(mc.sum()), float(plan.collision.max), dist, t_plan)
            rows.append(row)
            print(f"| {seed} | {weighting} | {row[2]:.4f} | {row[3]:.3f} | {row[4]:.4f} | {row[5]:.2f} | {row[6]:.1f} |",  # noqa: E501
                  flush=True)
    for weighting in ("mass", "density"):
        sel = [r for r in rows if r[1] == weighting]
        print(f"mean over {len(sel)} scenes, {weighting}: MC max {statistics.mean(r[2] for r in sel):.4f}, "
              f"MC sum {statistics.mean(r[3] for r in sel):.3f}, goal distance {statistics.mean(r[5] for r in sel):.2f} m")  # noqa: E501


if __name__ == "__main__":
    main()

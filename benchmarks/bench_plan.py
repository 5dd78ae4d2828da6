"""Benchmark: wall time of the density planner's two stages at the paper's settings on a fixed random scene.

Stage 1: 100 candidates x 100 epochs (no density). Stage 2: 100 density epochs x 500 samples with the chosen
density predictor. Prints the median over ``--repeats`` full plans (stage 1 alone is also repeated
``--stage1-repeats`` times, as it is cheap), the final cost and collision probability.

Targets: stage 1 <= 0.5 s (issue 5); whole plan <= 3 s median with the learned predictor (issue 6).
The paper reports ~131 s per plan on a GPU workstation.

    python benchmarks/bench_plan.py [--density exact|learned|NAME] [--controller c3m|analytic] [--seed 0]
                                    [--repeats 3] [--threads 1] [--point | --paper]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from dataclasses import replace

import torch

from density_planner.control.registry import load_controller
from density_planner.density.registry import load_predictor
from density_planner.environment import random_scene
from density_planner.planners.density_planner import DensityPlanner, DensityPlannerConfig
from density_planner.planners.problem import PlanningProblem
from density_planner.risk import RiskConfig
from density_planner.systems.car import KinematicCar


def make_predictor(name: str | None, controller_name: str | None):
    car = KinematicCar()
    return load_predictor(name, car, load_controller(controller_name))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--density", default=None, help="density predictor (default: the package default, the learned "
                   "trajectory head; exact for exact Liouville)")
    p.add_argument("--controller", default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--stage1-repeats", type=int, default=5)
    p.add_argument("--epochs-density", type=int, default=100)
    p.add_argument("--samples", type=int, default=500, help="stage-2 samples (the paper's 500; the default is 200)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1, as the CLI; 0 = torch's default)")
    vehicle = p.add_mutually_exclusive_group()
    vehicle.add_argument("--point", action="store_true",
                         help="a point vehicle (risk.body = false, the paper's) instead of the car's body "
                         "(the default)")
    vehicle.add_argument("--paper", action="store_true",
                         help="the paper's whole setting (`--config paper` with the report on the optimisation "
                         "samples): a point vehicle, the paper's estimator, density weights, no fresh evaluation draw")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    scene = random_scene(args.seed)
    risk = RiskConfig(body=False, estimator="paper") if args.paper else RiskConfig(body=not args.point)
    problem = PlanningProblem.from_scene(scene, seed=args.seed, risk=risk)
    predictor = make_predictor(args.density, args.controller)
    config = DensityPlannerConfig(epochs_density=args.epochs_density, n_samples=args.samples)
    if args.paper:
        config = replace(config, weighting="density", fresh_evaluation_samples=False)
    planner = DensityPlanner(predictor, config)
    load = os.getloadavg()[0]
    print(f"density planner on random scene {args.seed}: {config.n_candidates} candidates x {config.epochs_init} "
          f"epochs, then {config.epochs_density} epochs x {config.n_samples} samples; predictor "
          f"{getattr(predictor, 'name', type(predictor).__name__)}; "
          f"{'paper setting' if args.paper else 'point vehicle' if args.point else 'body'}; "
          f"torch {torch.__version__}, "
          f"{torch.get_num_threads()} threads; load average {load:.2f} on {os.cpu_count()} cores")

    planner.initialise(problem, torch.Generator().manual_seed(0))  # warm-up (lazy imports, allocator)
    s1 = []
    for _ in range(args.stage1_repeats):
        t0 = time.perf_counter()
        planner.initialise(problem, torch.Generator().manual_seed(0))
        s1.append(time.perf_counter() - t0)
    print(f"stage 1 alone: median {statistics.median(s1):.3f} s, min {min(s1):.3f} s over {len(s1)} runs")

    results = []
    for _ in range(args.repeats):
        res = planner.plan(problem)
        results.append(res)
        print(f"  plan: stage 1 {res.timings['stage1']:.3f} s, stage 2 {res.timings['stage2']:.3f} s, total "
              f"{res.timings['total']:.3f} s; final distance "
              f"{float(torch.linalg.norm(res.states[-1, :2] - torch.tensor(scene.goal))):.2f} m, "
              f"P_coll max {float(res.collision.max):.3f}")
    med = {k: statistics.median(r.timings[k] for r in results) for k in ("stage1", "stage2", "total")}
    print(f"median over {len(results)} plans: stage 1 {med['stage1']:.3f} s, stage 2 {med['stage2']:.3f} s, "
          f"total {med['total']:.3f} s")
    if "exact_check" in results[-1].extras:
        print(f"exact re-check: {results[-1].extras['exact_check']}")


if __name__ == "__main__":
    main()

"""Benchmark: time to predict 500 samples x 101 times (10 s) with each density predictor.

For the shipped trajectory head, the shipped pointwise net and exact Liouville (RK4 at 0.1 s), on 2 and 1 CPU
threads: the median over ``--repeats`` of (a) a prediction without gradients and (b) a prediction followed by a
backward pass to the reference parameters (what one iteration of the planner's second stage needs; for exact
Liouville the time of one backward through the integration). The machine load is printed with the results,
since the cores may be shared.

Targets (issue 6): trajectory head <= 0.05 s, pointwise net <= 0.3 s (no gradient, 2 threads). The paper reports
11.6 s for exact Liouville and 0.3 s for its network (GPU workstation).

    python benchmarks/bench_density.py [--samples 500] [--repeats 7] [--threads 2,1] [--skip-exact]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import torch

from density_planner.control.reference import make_reference
from density_planner.control.registry import load_controller
from density_planner.density.distributions import paper_gaussian_mixture
from density_planner.density.registry import load_predictor
from density_planner.systems.car import KinematicCar

START = (0.0, -28.0, 1.5, 3.0, 0.0)
PARAMS = ((0.3, 0.3, 0.0, -0.3, -0.3, 0.0, 0.2, 0.2, 0.0, 0.0), (0.8, 0.5, 0.3, 0.0, 0.0, 0.0, 0.0, -0.3, -0.5, -0.5))


def timed(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--samples", type=int, default=500)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--threads", default="2,1", help="comma-separated thread counts (default 2,1)")
    p.add_argument("--skip-exact", action="store_true", help="leave out exact Liouville (slow)")
    p.add_argument("--controller", default=None)
    args = p.parse_args()

    car = KinematicCar()
    controller = load_controller(args.controller)
    g = torch.Generator().manual_seed(0)
    start = torch.tensor(START, dtype=torch.float64)
    dist = paper_gaussian_mixture(start, car.config.initial_error_max, g)
    x0 = dist.sample(args.samples, g, dtype=torch.float32).unsqueeze(0)
    lr0 = dist.log_prob(x0)
    params = torch.tensor(PARAMS, dtype=torch.float32).unsqueeze(0)
    names = ["trajectory", "pointwise"] + ([] if args.skip_exact else ["exact"])
    predictors = {n: load_predictor(n, car, controller) for n in names}

    print(f"{args.samples} samples x 101 times, float32, torch {torch.__version__}, controller "
          f"{type(controller).__name__}; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"{'predictor':>11} {'threads':>7} {'no grad [s]':>12} {'with grad [s]':>14}")
    for threads in [int(s) for s in args.threads.split(",")]:
        torch.set_num_threads(threads)
        for name, pred in predictors.items():
            reps = max(1, args.repeats // 3) if name == "exact" else args.repeats

            def no_grad(pred=pred):
                with torch.no_grad():
                    ref = make_reference(car, start.float(), params)
                    pred.predict(x0, lr0, ref)

            def with_grad(pred=pred):
                pv = params.clone().requires_grad_(True)
                ref = make_reference(car, start.float(), pv)
                out = pred.predict(x0, lr0, ref)
                (out.x[..., :2].sum() + out.log_rho.sum()).backward()

            t_ng = timed(no_grad, reps)
            t_g = timed(with_grad, reps)
            print(f"{name:>11} {threads:>7} {t_ng:12.4f} {t_g:14.4f}", flush=True)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()

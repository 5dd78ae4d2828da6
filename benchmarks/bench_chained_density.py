"""Benchmark: accuracy of a learned density predictor chained past its 10-s horizon, against exact Liouville.

Random feasible references of the road model set over ``--horizons`` seconds (whole 1-s segments), kept when the
reference speed at every window start lies in the network's training range (else the planner would use its exact
fallback), ``--samples`` initial states per reference from the XE0 box; the shipped trajectory head (chained
windows, ``LearnedDensity.windows``) against exact Liouville (RK4 0.1 s). Prints the position error median / p95 [m]
and the median absolute log-density error every 2 s, and both prediction times (1 torch thread). docs/density.md,
"Horizons longer than 10 s", quotes its output.

    python benchmarks/bench_chained_density.py [--horizons 10,17,20] [--references 12] [--samples 40] [--seed 7]
"""

from __future__ import annotations

import argparse
import time

import torch

from density_planner.control.reference import PiecewiseConstantInputs
from density_planner.control.registry import load_controller, model_set
from density_planner.control.sampling import sample_feasible_references, sample_initial_errors
from density_planner.density.liouville import ExactLiouville
from density_planner.density.registry import load_predictor


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--horizons", default="10,17,20")
    ap.add_argument("--references", type=int, default=12)
    ap.add_argument("--samples", type=int, default=40)
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    torch.set_num_threads(1)
    sets = model_set("road")
    system, ctrl = sets.make_system(), load_controller("c3m", models="road")
    lo, hi = 0.5, float(system.config.reference_start_max[3])
    for horizon in (int(h) for h in args.horizons.split(",")):
        par = PiecewiseConstantInputs(n_segments=horizon)
        gen = torch.Generator().manual_seed(args.seed)
        ref = sample_feasible_references(system, 4 * args.references, gen, parameterization=par)
        pred = load_predictor("trajectory", system, ctrl, parameterization=par, models="road")
        starts = [s * par.steps_per_segment for s in pred.windows(par.n_segments)]
        v = ref.x[:, starts, 3]
        ref = ref.select(((v >= lo) & (v <= hi)).all(-1).nonzero()[: args.references, 0])
        n = ref.x.shape[0]
        xe0 = sample_initial_errors(n * args.samples, gen, box=list(system.initial_error_max))
        x0 = ref.start.unsqueeze(-2) + xe0.reshape(n, args.samples, system.nx)
        lr0 = torch.zeros(x0.shape[:-1])
        t0 = time.perf_counter()
        a = pred.predict(x0, lr0, ref)
        t1 = time.perf_counter()
        b = ExactLiouville(system, ctrl).predict(x0, lr0, ref)
        t2 = time.perf_counter()
        print(f"horizon {horizon} s, windows at {pred.windows(par.n_segments)} segments, {n} references x "
              f"{args.samples} samples; learned {t1 - t0:.4f} s, exact {t2 - t1:.2f} s")
        err = (a.x[..., :2] - b.x[..., :2]).norm(dim=-1)
        lde = (a.log_rho - b.log_rho).abs()
        for k in range(20, a.x.shape[-2], 20):
            e, d = err[..., k].flatten(), lde[..., k].flatten()
            print(f"  t = {k * par.plan_dt:4.1f} s: position error median {e.median():.3f} / p95 "
                  f"{e.quantile(0.95):.3f} m, |log-density error| median {d.median():.2f}")


if __name__ == "__main__":
    main()

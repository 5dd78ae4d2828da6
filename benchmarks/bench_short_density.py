"""Benchmark: accuracy of a learned density predictor over horizons shorter than its 10 s, against exact Liouville.

A plan whose horizon is shorter than the network's (a CommonRoad goal that ends after 3 s) is one window whose
reference inputs after the horizon are zero (``LearnedDensity._padded_window``), cut to the horizon. Random
feasible 10-s references of the road model set (start speed in the training range), ``--samples`` initial states
per reference from the XE0 box; for each horizon ``S`` the reference's first ``S`` segments are predicted padded
and compared with exact Liouville (RK4 0.1 s) over ``S`` s, next to the same network fed the reference's own later
inputs (the 10-s prediction cut to ``S`` s). Prints the position error median / p95 [m] and the median absolute
log-density error over all points after t = 0 (1 torch thread). docs/density.md, "Horizons shorter than 10 s",
quotes its output.

    python benchmarks/bench_short_density.py [--horizons 1,2,4,7] [--references 16] [--samples 40] [--seed 21]
"""

from __future__ import annotations

import argparse

import torch

from density_planner.control.reference import PiecewiseConstantInputs, make_reference
from density_planner.control.registry import load_controller, model_set
from density_planner.control.sampling import sample_feasible_references, sample_initial_errors
from density_planner.density.liouville import ExactLiouville
from density_planner.density.registry import load_predictor


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--horizons", default="1,2,4,7")
    ap.add_argument("--references", type=int, default=16)
    ap.add_argument("--samples", type=int, default=40)
    ap.add_argument("--seed", type=int, default=21)
    args = ap.parse_args()
    torch.set_num_threads(1)
    system, ctrl = model_set("road").make_system(), load_controller("c3m", models="road")
    lo, hi = 0.5, float(system.config.reference_start_max[3])
    gen = torch.Generator().manual_seed(args.seed)
    full = sample_feasible_references(system, 3 * args.references, gen)
    v0 = full.x[:, 0, 3]
    full = full.select(((v0 >= lo) & (v0 <= hi)).nonzero()[: args.references, 0])
    n_ref = full.x.shape[0]
    xe0 = sample_initial_errors(n_ref * args.samples, gen, box=list(system.initial_error_max))
    x0 = full.start.unsqueeze(-2) + xe0.reshape(n_ref, args.samples, system.nx)
    lr0 = torch.zeros(x0.shape[:-1])
    own = load_predictor("trajectory", system, ctrl, models="road").predict(x0, lr0, full)
    print(f"{n_ref} references x {args.samples} samples (road set, shipped trajectory head)")
    print("| horizon | padded: position error median / p95 [m] | own later inputs | abs. log-density error median "
          "padded / own |")
    print("| --- | --- | --- | --- |")
    for s in (int(h) for h in args.horizons.split(",")):
        par = PiecewiseConstantInputs(n_segments=s)
        ref = make_reference(system, full.start, full.params[..., :s], par)
        pred = load_predictor("trajectory", system, ctrl, parameterization=par, models="road")
        a, b = pred.predict(x0, lr0, ref), ExactLiouville(system, ctrl).predict(x0, lr0, ref)
        n = par.n_plan
        e = (a.x[..., 1:, :2] - b.x[..., 1:, :2]).norm(dim=-1).flatten()
        e_own = (own.x[..., 1:n, :2] - b.x[..., 1:, :2]).norm(dim=-1).flatten()
        d = (a.log_rho[..., 1:] - b.log_rho[..., 1:]).abs().flatten()
        d_own = (own.log_rho[..., 1:n] - b.log_rho[..., 1:]).abs().flatten()
        print(f"| {s} s | {e.median():.2f} / {e.quantile(0.95):.2f} | {e_own.median():.2f} / "
              f"{e_own.quantile(0.95):.2f} | {d.median():.2f} / {d_own.median():.2f} |")


if __name__ == "__main__":
    main()

"""Benchmark: exact Liouville density for 500 samples x 10 s with the car (float32, CPU threads as available).

Part 1 (speed): for each integration scheme (a fixed step), the median wall time over repeats on one reference, the
peak resident memory of a fresh process that runs only that propagation, and its error against a fine solution (RK4 at
0.005 s in float64).

Then the default scheme in inference mode with and without the log-density (the states alone are what the density
planner's exact re-check integrates by default, ``density_planner.exact_log_density = false``).

Part 2 (accuracy, issue 14): the errors on ``--accuracy-references`` random feasible references spread over the
model set's whole domain (initial errors uniform in XE0, heading bias included), against a converged float64
solution (RK4 at 0.005 s; its own difference to 0.01 s is printed): max / 99th percentile / median absolute
log-density error over samples and times [nats], max position error [m], for fixed steps and for the default
(the system's scheme, ``LiouvilleConfig().scheme(system)``: RK4 at 0.1 s, or for the road domain the error-controlled
"rk43"; its largest error per band of the references' top speed is printed too). Target for the default: max <= 0.1
nats.

Targets (issue 2): <= 3 s for Euler at dt = 0.01 s, <= 1.5 s for the default integrator at equal or better
accuracy, peak memory <= 500 MB.

    python benchmarks/bench_liouville.py [--models paper|road] [--controller c3m|analytic] [--samples 500]
        [--repeats 5] [--threads 1] [--accuracy-references 100] [--accuracy-samples 20] [--accuracy-seed 0]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

import torch

from density_planner.control.reference import make_reference
from density_planner.control.registry import load_controller, model_set
from density_planner.density.distributions import paper_gaussian_mixture
from density_planner.density.liouville import LiouvilleConfig, propagate_density, simulate_closed_loop
from density_planner.systems.car import KinematicCar

SCHEMES = [("euler", 0.01), ("rk4", 0.1), ("rk43", 0.1), ("dopri5", 0.1), ("rk4", 0.05), ("euler", 0.005)]


def setup(n: int, controller_name: str | None, dtype: torch.dtype, models: str | None = None):
    mset = model_set(models)
    car = KinematicCar(mset.car)
    controller = load_controller(controller_name, models=mset).to(dtype)
    g = torch.Generator().manual_seed(0)
    start = torch.tensor([0.0, -28.0, 1.5, 3.0 if mset.speed_max <= 10 else 20.0, 0.0], dtype=torch.float64)
    params = torch.tensor(
        [[0.3, 0.3, 0.0, -0.3, -0.3, 0.0, 0.2, 0.2, 0.0, 0.0], [0.8, 0.5, 0.3, 0.0, 0.0, 0.0, 0.0, -0.3, -0.5, -0.5]],
        dtype=dtype,
    )
    dist = paper_gaussian_mixture(start, car.config.initial_error_max, g)
    x0 = dist.sample(n, g, dtype=dtype)
    reference = make_reference(car, start.to(dtype), params)
    return car, controller, x0, dist.log_prob(x0), reference


def _timed(run, repeats: int) -> tuple[list[float], object]:
    """``run()`` ``repeats`` times: the wall time of each [s] and the last result."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = run()
        times.append(time.perf_counter() - t0)
    return times, out


def run_once(args) -> dict:
    """Child process: one propagation, report time and peak RSS."""
    car, controller, x0, lr0, ref = setup(args.samples, args.controller, torch.float32, args.models)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    cfg = LiouvilleConfig(integrator=args.child_integrator, dt=args.child_dt)
    t0 = time.perf_counter()
    with torch.no_grad():
        propagate_density(car, controller, x0, ref, log_rho0=lr0, config=cfg)
    elapsed = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"time": elapsed, "peak_mb": peak, "base_mb": base}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--controller", default=None)
    p.add_argument("--models", default=None, help="model set: paper (default) or road")
    p.add_argument("--accuracy-references", type=int, default=100,
                   help="random references of the accuracy part (default 100; 0 skips it)")
    p.add_argument("--accuracy-samples", type=int, default=20, help="samples per reference (default 20)")
    p.add_argument("--accuracy-seed", type=int, default=0, help="seed of the accuracy part's references (default 0)")
    p.add_argument("--samples", type=int, default=500)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1; 0 = torch's default)")
    p.add_argument("--child-integrator", default=None, help=argparse.SUPPRESS)
    p.add_argument("--child-dt", type=float, default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.child_integrator:
        print(json.dumps(run_once(args)))
        return

    car, controller, x0, lr0, ref = setup(args.samples, args.controller, torch.float32, args.models)
    ctrl_name = type(controller).__name__
    print(f"exact Liouville, {args.samples} samples x 10 s, float32, controller {ctrl_name}, model set "
          f"{model_set(args.models).name}, torch {torch.__version__}, {torch.get_num_threads()} threads")
    car64, ctrl64, x064, lr064, ref64 = setup(args.samples, args.controller, torch.float64, args.models)
    with torch.no_grad():
        fine = propagate_density(car64, ctrl64, x064, ref64, log_rho0=lr064, config=LiouvilleConfig("rk4", 0.005))
    print(f"{'scheme':>14} {'median s':>9} {'min s':>7} {'peak MB':>8} {'max pos err m':>14} "
          f"{'max |dlogrho|':>14} {'median |dlogrho|':>17}")
    for integrator, dt in SCHEMES:
        cfg = LiouvilleConfig(integrator=integrator, dt=dt)
        with torch.no_grad():
            times, out = _timed(lambda c=cfg: propagate_density(car, controller, x0, ref, log_rho0=lr0, config=c),
                                args.repeats)
        child = subprocess.run(
            [sys.executable, __file__, "--samples", str(args.samples), "--threads", str(args.threads),
             "--child-integrator", integrator,
             "--child-dt", str(dt)] + (["--controller", args.controller] if args.controller else [])
            + (["--models", args.models] if args.models else []),
            capture_output=True, text=True, check=True,
        )
        mem = json.loads(child.stdout.strip().splitlines()[-1])
        pos_err = float((out.x[..., :2].double() - fine.x[..., :2]).norm(dim=-1).max())
        lr_err = (out.log_rho.double() - fine.log_rho).abs()
        print(f"{integrator + ' ' + str(dt):>14} {statistics.median(times):9.3f} {min(times):7.3f} "
              f"{mem['peak_mb']:8.0f} {pos_err:14.2e} {float(lr_err.max()):14.2e} {float(lr_err.median()):17.2e}")
    print("peak MB = peak resident memory of a fresh process running one propagation (includes the torch runtime, "
          f"~{mem['base_mb']:.0f} MB before propagating)")
    # the states alone (ExactLiouville.predict_states: no divergence, so no tangents through the controller), what
    # the density planner's exact re-check integrates by default since stop 50 (density_planner.exact_log_density)
    with torch.inference_mode():
        states, _ = _timed(lambda: simulate_closed_loop(car, controller, x0, ref), args.repeats)
        full, _ = _timed(lambda: propagate_density(car, controller, x0, ref, log_rho0=lr0), args.repeats)
    print(f"default scheme ({LiouvilleConfig().describe(car)}) in inference mode (the exact re-check's "
          f"mode): states only {statistics.median(states):.3f} "
          f"s, with the log-density {statistics.median(full):.3f} s (median of {args.repeats})")
    if args.accuracy_references > 0:
        from density_planner.density.validation import liouville_accuracy

        rep = liouville_accuracy(car, controller, n_references=args.accuracy_references,
                                 samples=args.accuracy_samples, seed=args.accuracy_seed, schemes=SCHEMES[:3])
        r = rep["reference"]
        print(f"\naccuracy on {rep['n_references']} random references x {rep['samples_per_reference']} samples "
              f"(start speeds {rep['start_speed']['min']:.1f}-{rep['start_speed']['max']:.1f} m/s, up to "
              f"{rep['max_speed']:.1f} m/s) against float64 {r['integrator']} {r['dt']} s (which differs from "
              f"{2 * r['dt']:g} s by at most {r['reference_self_error']:.1e} nats)")
        print(f"{'scheme':>14} {'max |dlogrho|':>14} {'p99':>9} {'median':>9} {'max pos err m':>14} {'time s':>7}")
        for name, e in rep["schemes"].items():
            print(f"{name:>14} {e['max_abs_log_density_error']:14.2e} {e['p99_abs_log_density_error']:9.2e} "
                  f"{e['median_abs_log_density_error']:9.2e} {e['max_position_error_m']:14.2e} "
                  f"{e['wall_time_s']:7.2f}")
        bands = rep["schemes"]["default"]["by_top_speed"]
        if bands:
            print("default, max |dlogrho| per band of the references' top speed [m/s]: " + ", ".join(
                f"{band} {e['max_abs_log_density_error']:.3f} ({e['n_references']} refs)" for band, e in bands.items()))


if __name__ == "__main__":
    main()

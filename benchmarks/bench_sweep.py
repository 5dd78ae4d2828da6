"""Benchmark: throughput of a benchmark sweep (runs per minute) for the artificial setting at 1 and 2 workers.

Runs the same small sweep (``--envs`` random scenes, every planner of the artificial setting, both measurement
variants) once per worker count into a fresh temporary directory and prints runs per minute and the scaling
relative to one worker. Small configurations keep it short: density planner 20 candidates x 20 + 20 epochs x 100
samples, MPC limited to ``--mpc-steps`` closed-loop steps, oracle 2 restarts of at most 200 iterations, 20
Monte-Carlo samples. ``--full`` uses the paper's configurations instead (tens of minutes per environment).

Every run writes the same records whatever the worker count (see ``tests/evaluation``), so the comparison
measures only the executor. M0's 0.1-s CPU-time limit per step makes its per-step work shrink on a loaded
machine; the oracle and density planner do fixed work. Expect at most ``min(workers, free cores)`` speed-up.

    python benchmarks/bench_sweep.py [--envs 2] [--workers 1,2] [--planners LIST] [--full] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

from density_planner.config import update
from density_planner.evaluation.benchmark import BenchmarkSpec, run_benchmark
from density_planner.evaluation.benchmark_settings import SETTINGS
from density_planner.evaluation.environments import artificial_envs
from density_planner.settings import RunConfig

SMALL = {
    "density_planner": {"n_candidates": 20, "epochs_init": 20, "epochs_density": 20, "n_samples": 100},
    "oracle": {"restarts": 2, "max_iter": 200},
    "evaluation": {"mc_samples_tracked": 20},
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", type=int, default=2, help="random scenes (default 2)")
    p.add_argument("--workers", default="1,2", help="comma-separated worker counts (default 1,2)")
    p.add_argument("--planners", default=None, help="comma-separated planners (default: the artificial setting's)")
    p.add_argument("--mpc-steps", type=int, default=50, help="closed-loop steps of the MPC runs (default 50 = 5 s)")
    p.add_argument("--full", action="store_true", help="the paper's configurations (slow)")
    p.add_argument("--keep", type=Path, default=None, help="keep the sweep directories under DIR")
    args = p.parse_args()

    cfg = RunConfig()
    if not args.full:
        small = dict(SMALL)
        small["mpc"] = {"n_steps": args.mpc_steps}
        small["tube_mpc"] = {"n_steps": args.mpc_steps}
        cfg = update(cfg, small)
    planners = tuple(args.planners.split(",")) if args.planners else SETTINGS["artificial"].planners
    spec = BenchmarkSpec("artificial", artificial_envs(range(args.envs)), planners, ("unbiased", "biased"), cfg)
    counts = [int(w) for w in args.workers.split(",")]
    print(f"artificial sweep: {args.envs} environments x {len(planners)} planners x 2 variants "
          f"({'paper' if args.full else 'small'} configurations); {os.cpu_count()} CPUs, load "
          f"{os.getloadavg()[0]:.1f}")
    root = Path(tempfile.mkdtemp(prefix="bench-sweep-")) if args.keep is None else args.keep
    rates = {}
    try:
        for w in counts:
            out = root / f"workers-{w}"
            if out.exists():
                shutil.rmtree(out)
            t0 = time.perf_counter()
            rep = run_benchmark(spec, out, workers=w, progress=False)
            wall = time.perf_counter() - t0
            rates[w] = rep.written / wall * 60
            print(f"  workers {w}: {rep.written} runs in {wall:6.1f} s = {rates[w]:5.2f} runs/min "
                  f"({rep.failed_runs} failed, {rep.errors} errors; load {os.getloadavg()[0]:.1f})", flush=True)
        if len(rates) > 1:
            base = rates[counts[0]]
            print("  scaling vs " + f"{counts[0]} worker(s): " + ", ".join(
                f"{w} -> x{rates[w] / base:.2f}" for w in counts[1:]))
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()

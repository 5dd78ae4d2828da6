"""Benchmark: online step times of the MPC baselines, planning time of the oracle, and the density planner's online
step, on fixed random scenes.

* M0 and tube MPC M1-M3: one closed-loop run per scene from the problem's reference start; every step is timed as a
  WHOLE step (occupancy windows, parameter update, IPOPT, warm-start shift; ``MPCStep.step_time``), and the IPOPT
  call alone (``solve_time``). The NLP is built once per planner (its construction and the per-scene tube
  precomputation are reported separately). Printed: median and 90th percentile over all steps of all scenes.
* Paper-style step (``--paper-step``): what the paper's code did every step, emulated with our model: build an
  Opti NLP with ten constant full-map linear interpolants (one per stage), then solve it once.
* Oracle: total planning time (NLP construction + all restarts) per scene.
* Density planner online step: one evaluation of the tracking controller on one state (what DP computes online).

Target (issue 7): M0 whole step <= 0.1 s median. The paper reports that only M0 and M1 run near real time (0.1 s).
On a shared machine, run single-threaded (``--threads 1``, the default): OpenMP threads slow down small torch ops.

    python benchmarks/bench_baselines.py [--seeds 0 1 2] [--threads 1] [--oracle-restarts 10] [--skip-oracle]
                                         [--tube-method auto|offsets|precomputed] [--paper-step]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from density_planner.control.registry import load_controller
from density_planner.environment import random_scene
from density_planner.planners.mpc import TUBE_RADII, MPCConfig, MPCPlanner, TubeMPCConfig
from density_planner.planners.oracle import OracleConfig, OraclePlanner
from density_planner.planners.problem import PlanningProblem


def _pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values), q)) if values else float("nan")


def bench_mpc(label: str, planner: MPCPlanner, problems: list[PlanningProblem]) -> dict:
    steps, solves, fails, n, pre, dist = [], [], 0, 0, [], []
    t_build = 0.0
    for problem in problems:
        res = planner.plan(problem)
        if res.status.value != "success":
            print(f"  {label}: {problem.scene.name}: {res.status.value} {res.message}")
        steps += res.extras.get("step_times", [])
        solves += res.extras.get("solve_times", [])
        fails += res.extras.get("n_failed_steps", 0)
        n += len(res.extras.get("step_times", []))
        t_build = max(t_build, res.timings.get("nlp_build", 0.0))
        pre.append(res.timings.get("tube_precompute", 0.0))
        if res.states is not None:
            dist.append(float(torch.linalg.norm(res.states[-1, :2] - torch.tensor(problem.goal))))
    return {"label": label, "steps": n, "step_median": _pct(steps, 50), "step_p90": _pct(steps, 90),
            "solve_median": _pct(solves, 50), "failed": fails / max(n, 1), "build": t_build,
            "precompute": statistics.median(pre) if pre else 0.0, "final_dist": dist}


def paper_style_step(problem: PlanningProblem, repeats: int = 3) -> float:
    """Median wall time of 'build an Opti NLP with ten full-map constant interpolants, then solve it once'."""
    import casadi as ca

    grid = problem.scene.grid
    xs = [float(v) for v in grid.xs]
    ys = [float(v) for v in grid.ys]
    probs = grid.probs.double().numpy()
    x0 = problem.reference_start(torch.float64)[:4].numpy()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        opti = ca.Opti()
        X = opti.variable(4, 11)
        U = opti.variable(2, 10)
        h = 0.01
        J = 0
        opti.subject_to(X[:, 0] == x0)
        for k in range(10):
            x = X[:, k]
            for _ in range(10):
                x = x + h * ca.vertcat(x[3] * ca.cos(x[2]), x[3] * ca.sin(x[2]), U[0, k], U[1, k])
            opti.subject_to(X[:, k + 1] == x)
            occ = ca.interpolant(f"occ{k}", "linear", [xs, ys], probs[k + 1].ravel(order="F"))
            J = J + 0.1 * occ(X[0:2, k + 1]) ** 2
        J = J + 0.01 * ca.sumsqr(X[0:2, 10] - ca.DM(problem.goal)) + 1e-6 * ca.sumsqr(U)
        opti.subject_to(opti.bounded(-3, U, 3))
        opti.subject_to(opti.bounded(0, X[3, :], 10))
        opti.minimize(J)
        opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes", "max_iter": 300,
                                                     "max_cpu_time": 0.1})
        try:
            opti.solve()
        except RuntimeError:
            pass
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def controller_step(repeats: int = 2000) -> tuple[float, str]:
    """Median time of one tracking-controller evaluation on one state (the density planner's online work)."""
    ctrl = load_controller()
    x = torch.tensor([[0.1, -27.9, 1.55, 3.1, 0.0]])
    xr = torch.tensor([[0.0, -28.0, 1.5, 3.0, 0.0]])
    ur = torch.tensor([[0.1, 0.2]])
    times = []
    with torch.no_grad():
        for _ in range(20):
            ctrl(x, xr, ur)
        for _ in range(repeats):
            t0 = time.perf_counter()
            ctrl(x, xr, ur)
            times.append(time.perf_counter() - t0)
    return statistics.median(times), type(ctrl).__name__


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1; 0 = torch's default)")
    p.add_argument("--oracle-restarts", type=int, default=10)
    p.add_argument("--skip-oracle", action="store_true")
    p.add_argument("--tube-method", default="auto", choices=("auto", "offsets", "precomputed"))
    p.add_argument("--paper-step", action="store_true", help="also time the paper-style rebuild-every-step step")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    problems = [PlanningProblem.from_scene(random_scene(s), seed=s) for s in args.seeds]
    print(f"random scenes {args.seeds}; torch {torch.__version__}, {torch.get_num_threads()} thread(s)")

    rows = [bench_mpc("M0 (mpc)", MPCPlanner(MPCConfig()), problems)]
    for r, label in zip(TUBE_RADII, ("M1", "M2", "M3")):
        cfg = TubeMPCConfig(tube_radius=r, tube_method=args.tube_method)
        rows.append(bench_mpc(f"{label} (tube {r:g} m)", MPCPlanner(cfg), problems))
    print(f"\n{'planner':18s} {'steps':>5s} {'step med':>9s} {'step p90':>9s} {'solve med':>9s} {'failed':>7s} "
          f"{'build':>7s} {'precomp':>7s}  final distance to goal [m]")
    for row in rows:
        print(f"{row['label']:18s} {row['steps']:5d} {row['step_median']:9.4f} {row['step_p90']:9.4f} "
              f"{row['solve_median']:9.4f} {100 * row['failed']:6.1f}% {row['build']:7.2f} {row['precompute']:7.2f}  "
              + " ".join(f"{d:.1f}" for d in row["final_dist"]))
    print("(times in s; 'failed' = steps where IPOPT stopped on its iteration/CPU limit and the last iterate was "
          "applied)")

    if args.paper_step:
        t = statistics.median(paper_style_step(pr) for pr in problems)
        print(f"\npaper-style step (build Opti NLP with 10 full-map interpolants + one solve): median {t:.3f} s")

    if not args.skip_oracle:
        oracle = OraclePlanner(OracleConfig(restarts=args.oracle_restarts))
        times = []
        for pr in problems:
            res = oracle.plan(pr)
            times.append(res.timings["total"])
            conv = sum(1 for r in res.extras.get("restarts", []) if r["success"])
            print(f"oracle {pr.scene.name}: {res.status.value}, {res.timings['total']:.1f} s "
                  f"(build {res.timings.get('nlp_build', 0):.2f} s, {conv}/{args.oracle_restarts} restarts "
                  f"converged), J_MPC {res.extras.get('objective', {}).get('total', float('nan')):.4g}")
        print(f"oracle planning time: median {statistics.median(times):.1f} s over {len(times)} scenes "
              f"({args.oracle_restarts} restarts each)")

    t, name = controller_step()
    print(f"\ndensity planner online step (one evaluation of {name} on one state): median {1e3 * t:.3f} ms")


if __name__ == "__main__":
    main()

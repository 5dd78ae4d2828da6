"""Time and quality of the route-seeded stage-1 candidates on every CommonRoad scenario of a folder.

    python benchmarks/bench_route_seeds.py --scenarios ../shared/data/commonroad-suite --out /tmp/route-seeds

For each file that imports (``load_commonroad_scene`` with default settings; refused files are listed with their
reason): the lane graph read (first read of the file; cached afterwards), the route search + speed profiles + fit
(:func:`density_planner.planners.routes.route_seed_parameters`, one thread), the number of routes and candidates,
the fit's RMS position error, and whether a candidate's *target* and its *fitted roll-out* reach the goal region
inside its time interval with the vehicle's rectangle on the road (the verdict's ``goal_reached`` / ``on_road``
tests of :class:`~density_planner.environment.road.RoadScene` applied to the seeds alone, before any
optimisation). Horizon: the scene's suggestion (end of the goal's interval) in whole seconds, within the grid.
Writes ``OUT/route_seeds.json`` (atomically) and prints medians.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", required=True, type=Path)
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--limit", type=int, default=0, help="first N files only (0: all)")
    args = ap.parse_args(argv)

    import numpy as np
    import torch

    torch.set_num_threads(1)
    from density_planner.control.reference import PiecewiseConstantInputs, plan_grid_reference
    from density_planner.environment.commonroad import load_commonroad_scene
    from density_planner.environment.lanes import scene_lane_graph
    from density_planner.io.atomic import atomic_write_text
    from density_planner.planners.problem import PlanningProblem
    from density_planner.planners.routes import route_seed_parameters

    files = sorted(args.scenarios.glob("*.xml"))
    if args.limit:
        files = files[: args.limit]
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for f in files:
        rec: dict = {"file": f.name}
        try:
            scene = load_commonroad_scene(f)
        except Exception as exc:  # refused or failed import: recorded, not planned
            rec["refused"] = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
            rows.append(rec)
            print(f"{f.name}: refused ({rec['refused'][:100]})", file=sys.stderr)
            continue
        road = scene.road
        span = (scene.grid.n_slices - 1) * scene.grid.dt
        horizon = int(np.clip(math.ceil(scene.meta.get("horizon", 10.0) - 1e-9), 1, min(20, math.floor(span + 1e-9))))
        problem = PlanningProblem.from_scene(scene, parameterization=PiecewiseConstantInputs(n_segments=horizon))
        t0 = time.perf_counter()
        graph = scene_lane_graph(scene)
        t1 = time.perf_counter()
        seeds = route_seed_parameters(problem, lane_graph=graph, v_limits=(0.1, 9.9))
        t2 = time.perf_counter()
        rec.update(horizon=horizon, graph_s=t1 - t0, seeds_s=t2 - t1, v0=scene.start[3])
        if seeds is None:
            rec["seeds"] = None
        else:
            par = problem.parameterization
            x, _ = plan_grid_reference(problem.system, problem.reference_start(), seeds.params, par)
            times = road.t_start + np.arange(par.n_plan) * par.plan_dt

            def ok(states: np.ndarray, road=road, times=times) -> tuple[bool, bool]:
                reach = [bool(road.goal.contains(s[:, :2], times, s[:, 3], s[:, 2]).any()) for s in states]
                onroad = [bool(road.on_road(road.vehicle_polygons(s[:, :3])).all()) for s in states]
                return any(r and o for r, o in zip(reach, onroad)), any(onroad)

            tgt = seeds.targets.double().numpy()
            hd = np.arctan2(np.gradient(tgt[..., 1], axis=1), np.gradient(tgt[..., 0], axis=1))
            tgt_states = np.concatenate([tgt, hd[..., None], seeds.speeds.double().numpy()[..., None]], axis=-1)
            fit = x.detach().double().numpy()
            rec["seeds"] = seeds.info()
            rec["target_success"], rec["target_on_road"] = ok(tgt_states)
            rec["fit_success"], rec["fit_on_road"] = ok(fit)
        rows.append(rec)
        atomic_write_text(args.out / "route_seeds.json", json.dumps(rows, indent=1))
        print(json.dumps(rec), file=sys.stderr)
    done = [r for r in rows if "refused" not in r]
    seeded = [r for r in done if r.get("seeds")]
    if done:
        print(f"{len(files)} files, {len(done)} imported, {len(seeded)} with route seeds")
        print(f"lane graph read: median {statistics.median(r['graph_s'] for r in done):.3f} s")
        print(f"seeds (routes + profiles + fit): median {statistics.median(r['seeds_s'] for r in done):.3f} s, "
              f"max {max(r['seeds_s'] for r in done):.3f} s")
    if seeded:
        print(f"a seed target reaches the goal in time on the road: {sum(r['target_success'] for r in seeded)}"
              f"/{len(seeded)}; a fitted seed does: {sum(r['fit_success'] for r in seeded)}/{len(seeded)}")
    atomic_write_text(args.out / "route_seeds.json", json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Run CommonRoad's reactive planner (commonroad-reactive-planner 2025.1) on one scenario, as a peer.

This script runs INSIDE the peer's own virtual environment (``benchmarks/peers/make_reactive_venv.sh``), never in
density-planner's: it imports only the peer's packages. density-planner calls it through
:mod:`density_planner.evaluation.peers` and judges the returned trajectory with its own verdict.

What it does, with the planner's built-in default configuration (6-s horizon, replanning every 3 planner steps):
route and reference path from the package's own helpers, desired speed from the planning problem (the
package's own rule), then the usual receding-horizon loop: plan, advance the vehicle along the optimal
trajectory by the replanning period, re-plan from there, until the goal is reached, the goal's time interval is
over, or the planner finds no trajectory. The planner's time step is set to the scenario's.

Two version mismatches of the packages pip resolves today are handled (``shared/notes/reactive-planner.md``):
``ReactivePlanner.set_reference_path(path)`` raises, so the coordinate system is built with
``create_coordinate_system``; ``plan()`` returns 3 values. A coordinate conversion that fails (the vehicle ran
past the end of the reference path) ends the run with that reason instead of a traceback.

Execution settings that do not change the plan: no plots, log level ERROR, no multiprocessing (the collision
check's worker pool is the package's own parallelism; 2 cores here).

Output (stdout or ``--out FILE``): JSON with ``status`` ("ok" | "failed"), ``reason``, ``goal_reached`` (the
package's own goal test on the last state), ``dt``, ``initial_time_step``, ``states`` (list of
``[time_step, x, y, orientation, velocity]`` of the vehicle's CENTRE, shifted from the rear axle the planner
uses), ``planning_time_s`` (sum over replans), ``n_replans``, ``vehicle`` (length, width).

    .peers/reactive-venv/bin/python benchmarks/peers/run_reactive.py SCENARIO.xml [--out result.json]
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
import warnings


def _state_row(state, wb_rear: float) -> list[float]:
    x, y = float(state.position[0]), float(state.position[1])
    th = float(state.orientation)
    return [int(state.time_step), x + wb_rear * math.cos(th), y + wb_rear * math.sin(th), th, float(state.velocity)]


def _tolerate_projection_domain(coordinate_system) -> None:
    """Make a failed curvilinear -> Cartesian conversion return None, as the planner expects (commonroad-clcs
    2025.2 raises a CurvilinearProjectionDomain* error instead; the planner then marks that sample infeasible)."""
    convert = coordinate_system.convert_to_cartesian_coords

    def tolerant(s, d):
        try:
            return convert(s, d)
        except Exception as exc:  # noqa: BLE001 - only the projection-domain errors are turned into None
            if "ProjectionDomain" in type(exc).__name__:
                return None
            raise

    coordinate_system.convert_to_cartesian_coords = tolerant


#: a dynamic obstacle whose centre is this close to the planning problem's initial position at the initial time
#: step is the recorded ego vehicle itself (the commonroad-crime convention); density-planner drops it too
EGO_TOLERANCE_M = 1.0


def _drop_recorded_ego(scenario, planning_problem) -> list[int]:
    """Remove the recorded ego vehicle from the obstacles, as density-planner's importer does, so that both
    planners face the same road users (otherwise the peer collides with its own recording at t = 0)."""
    import numpy as np

    init = planning_problem.initial_state
    removed = []
    for obstacle in list(scenario.dynamic_obstacles):
        state = obstacle.state_at_time(init.time_step)
        if state is None or not hasattr(state, "position"):
            continue
        position = np.asarray(getattr(state.position, "center", state.position), dtype=float)
        if position.shape == (2,) and np.hypot(*(position - np.asarray(init.position, dtype=float))) < EGO_TOLERANCE_M:
            scenario.remove_obstacle(obstacle)
            removed.append(int(obstacle.obstacle_id))
    return removed


def run(path: str) -> dict:
    warnings.filterwarnings("ignore")
    logging.disable(logging.CRITICAL)
    from commonroad.common.file_reader import CommonRoadFileReader
    from commonroad_rp.reactive_planner import ReactivePlanner
    from commonroad_rp.utility.config import ReactivePlannerConfiguration
    from commonroad_rp.utility.general import retrieve_desired_velocity_from_pp
    from commonroad_rp.utility.utils_coordinate_system import create_coordinate_system, create_initial_ref_path

    scenario, pp_set = CommonRoadFileReader(path).open()
    planning_problem = next(iter(pp_set.planning_problem_dict.values()))
    removed = _drop_recorded_ego(scenario, planning_problem)
    config = ReactivePlannerConfiguration()
    config.planning.dt = float(scenario.dt)
    config.planning.__post_init__()  # recompute the horizon from dt
    # the shortest sampled manoeuvre may not be shorter than one time step (e.g. 0.5-s scenarios; default 0.4 s)
    config.sampling.t_min = max(float(config.sampling.t_min), float(scenario.dt))
    config.debug.logging_level = "ERROR"
    config.debug.multiproc = False
    config.debug.show_plots = False
    config.debug.save_plots = False
    config.update(scenario=scenario, planning_problem=planning_problem)

    out: dict = {
        "status": "failed",
        "reason": "",
        "goal_reached": False,
        "dt": float(scenario.dt),
        "initial_time_step": int(planning_problem.initial_state.time_step),
        "states": [],
        "planning_time_s": 0.0,
        "n_replans": 0,
        "vehicle": {"length": float(config.vehicle.length), "width": float(config.vehicle.width)},
        "removed_obstacles": removed,
    }
    try:
        ref_path = create_initial_ref_path(scenario.lanelet_network, planning_problem)
        coordinate_system = create_coordinate_system(ref_path)
    except Exception as exc:  # noqa: BLE001 - the peer's own failure, reported as its result
        out["reason"] = f"no reference path: {type(exc).__name__}: {exc}"
        return out

    _tolerate_projection_domain(coordinate_system)
    planner = ReactivePlanner(config)
    wb_rear = float(config.vehicle.wb_rear_axle)
    planner.set_reference_path(coordinate_system=coordinate_system)
    planner.set_desired_velocity(
        desired_velocity=retrieve_desired_velocity_from_pp(planning_problem),
        current_speed=planner.x_0.velocity,
    )
    goal_steps = [getattr(s, "time_step", None) for s in planning_problem.goal.state_list]
    last_step = max((int(ts.end) for ts in goal_steps if ts is not None), default=out["initial_time_step"] + 100)
    out["states"].append(_state_row(planner.x_0, wb_rear))
    every = int(config.planning.replanning_frequency)
    while True:
        if planner.goal_reached():  # a method in 2025.1 (a property in some upstream versions)
            out["status"], out["goal_reached"] = "ok", True
            break
        if planner.x_0.time_step >= last_step:
            out["reason"] = "goal time interval over"
            break
        t0 = time.perf_counter()
        try:
            result = planner.plan()
        except Exception as exc:  # noqa: BLE001 - e.g. the CLCS conversion raising past the reference path's end
            out["reason"] = f"planner raised {type(exc).__name__}: {str(exc)[:200]}"
            break
        finally:
            out["planning_time_s"] += time.perf_counter() - t0
            out["n_replans"] += 1
        if result is None:
            out["reason"] = "no feasible trajectory"
            break
        trajectory, lon, lat = result[0], result[1], result[2]
        states = trajectory.state_list
        k = min(every, len(states) - 1)
        if k < 1:
            out["reason"] = "trajectory too short"
            break
        for s in states[1 : k + 1]:
            out["states"].append(_state_row(s, wb_rear))
        try:
            planner.reset(
                initial_state_cart=states[k],
                initial_state_curv=(lon[k], lat[k]),
                collision_checker=planner.collision_checker,
                coordinate_system=planner.coordinate_system,
            )
        except Exception as exc:  # noqa: BLE001
            out["reason"] = f"re-planning start raised {type(exc).__name__}: {str(exc)[:200]}"
            break
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenario")
    parser.add_argument("--out", default=None, help="write the JSON result here (default: stdout)")
    args = parser.parse_args(argv)
    try:
        result = run(args.scenario)
    except Exception as exc:  # noqa: BLE001 - one line, the caller records it
        result = {"status": "failed", "reason": f"{type(exc).__name__}: {str(exc)[:300]}", "states": []}
    text = json.dumps(result)
    if args.out:
        with open(args.out, "w") as f:
            f.write(text)
    else:
        sys.stdout.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

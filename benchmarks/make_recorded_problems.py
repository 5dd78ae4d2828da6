"""New planning problems posed on recorded traffic: a recorded road user's own drive as the problem.

For every k-th CommonRoad file of a folder, one recorded car (drawn with ``--seed`` and the file's name, among the cars
that move at >= 1 m/s and <= 38 m/s at their first state and stay recorded for at least 4 s) becomes the planning
problem: its first state is the initial state, and the goal is a rectangle (``--goal-length`` or the distance it
covers in one second, whichever is longer, x ``--goal-width``, along its heading) around where it was ``H`` seconds
later (``H`` = min(``--horizon``, its recorded time - 0.5 s)), within ``H +- --goal-slack`` seconds. The scenario's
own planning problems are replaced; the car stays in the file, so the importer drops it as the recorded ego. The
recorded driver solved each problem, so each is feasible; none of them was seen while the planner was developed.

Usage::

    python benchmarks/make_recorded_problems.py --scenarios ../shared/data/commonroad-suite --every 2 \\
        --out results/recorded-problems
    density-planner bench commonroad --scenarios results/recorded-problems --planners density --workers 2 \\
        --threads 1 --out results/bench-recorded

The files are derived from the scenarios they come from (licence of the source); do not ship them.
"""

from __future__ import annotations

import argparse
import sys
import zlib
from pathlib import Path

import numpy as np


def _state(obstacle, step: int):
    """``(x, y, orientation, velocity)`` of a recorded obstacle at time step ``step`` (None if not recorded)."""
    states = [obstacle.initial_state] + list(obstacle.prediction.trajectory.state_list)
    for st in states:
        if int(st.time_step) == step:
            x, y = (float(v) for v in np.asarray(st.position, dtype=float)[:2])
            return x, y, float(st.orientation), float(getattr(st, "velocity", 0.0) or 0.0)
    return None


def _exact(tag: str, value: float) -> str:
    return f"<{tag}><exact>{value:.6f}</exact></{tag}>"


def make_problem(path: Path, out: Path, *, horizon: float, goal_length: float, goal_width: float,
                 goal_slack: float, seed: int = 0) -> str:
    """Write the derived scenario of ``path`` into ``out``; returns a one-line description (or why none)."""
    import xml.etree.ElementTree as ET

    from commonroad.common.file_reader import CommonRoadFileReader

    scenario, _ = CommonRoadFileReader(str(path)).open()
    dt = float(scenario.dt)
    rng = np.random.default_rng([zlib.crc32(path.name.encode()), seed])
    candidates = []
    for obs in scenario.dynamic_obstacles:
        if str(getattr(obs.obstacle_type, "value", obs.obstacle_type)).lower() != "car":
            continue
        traj = getattr(getattr(obs, "prediction", None), "trajectory", None)
        s0 = obs.initial_state
        v0 = float(getattr(s0, "velocity", 0.0) or 0.0)
        if traj is None or not traj.state_list or not 1.0 <= v0 <= 38.0:
            continue
        if (int(traj.state_list[-1].time_step) - int(s0.time_step)) * dt < 4.0:
            continue
        candidates.append(obs)
    if not candidates:
        return f"{path.name}: no recorded car moves for 4 s"
    obs = candidates[int(rng.integers(len(candidates)))]
    t0 = int(obs.initial_state.time_step)
    last = int(obs.prediction.trajectory.state_list[-1].time_step)
    h = min(horizon, (last - t0) * dt - 0.5)
    k_goal = t0 + int(round(h / dt))
    start, goal = _state(obs, t0), _state(obs, k_goal)
    assert start is not None and goal is not None
    length = max(goal_length, goal[3] * 1.0)
    slack = int(round(goal_slack / dt))
    problem = (
        "<planningProblem id=\"1\"><initialState>"
        f"<position><point><x>{start[0]:.6f}</x><y>{start[1]:.6f}</y></point></position>"
        f"{_exact('orientation', start[2])}<time><exact>{t0}</exact></time>{_exact('velocity', start[3])}"
        f"{_exact('yawRate', 0.0)}{_exact('slipAngle', 0.0)}</initialState>"
        f"<goalState><position><rectangle><length>{length:.4f}</length><width>{goal_width:.4f}</width>"
        f"<orientation>{goal[2]:.6f}</orientation><center><x>{goal[0]:.6f}</x><y>{goal[1]:.6f}</y></center>"
        f"</rectangle></position><time><intervalStart>{max(t0 + 1, k_goal - slack)}</intervalStart>"
        f"<intervalEnd>{k_goal + slack}</intervalEnd></time></goalState></planningProblem>"
    )
    tree = ET.parse(path)
    root = tree.getroot()
    for old in root.findall("planningProblem"):
        root.remove(old)
    root.append(ET.fromstring(problem))
    name = f"REC_{path.stem.removesuffix('_T-1')}_o{obs.obstacle_id}_T-1.xml"
    tree.write(out / name, encoding="utf-8", xml_declaration=True)
    return (f"{name}: car {obs.obstacle_id}, start {start[3]:.1f} m/s at step {t0}, goal {h:.1f} s later "
            f"({length:.1f} x {goal_width:.1f} m, +-{goal_slack:.1f} s)")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", required=True, type=Path)
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--every", type=int, default=1, help="every k-th file of the sorted folder")
    p.add_argument("--horizon", type=float, default=8.0, help="goal time after the start [s] (at most)")
    p.add_argument("--goal-length", type=float, default=8.0)
    p.add_argument("--goal-width", type=float, default=3.5)
    p.add_argument("--goal-slack", type=float, default=0.5, help="half-width of the goal's time interval [s]")
    p.add_argument("--seed", type=int, default=0, help="which recorded car of each file (a different draw per seed)")
    args = p.parse_args(argv)
    files = sorted(args.scenarios.glob("*.xml"))[:: max(1, args.every)]
    if not files:
        print(f"no .xml files in {args.scenarios}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    for f in files:
        try:
            print(make_problem(f, args.out, horizon=args.horizon, goal_length=args.goal_length,
                               goal_width=args.goal_width, goal_slack=args.goal_slack, seed=args.seed), flush=True)
        except Exception as exc:  # noqa: BLE001 - a benchmark helper: report and go on
            print(f"{f.name}: skipped ({type(exc).__name__}: {exc})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

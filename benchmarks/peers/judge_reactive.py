"""CommonRoad's reactive planner on a folder of scenarios, judged by density-planner's verdict.

Runs the peer (``benchmarks/peers/run_reactive.py`` in its own environment, see ``make_reactive_venv.sh``) on
every ``*.xml`` of ``--scenarios`` (results cached as JSON under ``--out/runs``, so a re-run resumes), builds the
same scene density-planner plans in (``load_commonroad_scene``: true obstacle shapes, drivable area, goal region
with its time interval) and applies the same :func:`~density_planner.evaluation.verdict.judge` to the peer's
executed trajectory. Writes ``--out/reactive.json`` (one row per scenario) and ``--out/reactive.md`` (the
summary in the columns of ``bench commonroad``) and prints the summary.

The peer plans with its own vehicle (BMW 320i, 4.51 m x 1.61 m) and its own kinematic checks; the verdict judges
it with the scene's vehicle rectangle (4.5 m x 1.8 m), the same as for density-planner's plans. ``within_model``
is judged against the road car's state bounds (speed 0-40 m/s) without inputs. A scenario whose scene cannot be
built (malformed file) is reported as refused with the importer's one-line reason.

    python benchmarks/peers/judge_reactive.py --scenarios ../shared/data/commonroad-suite --out results/peer
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import statistics
import sys
from pathlib import Path

import numpy as np

from density_planner.environment.commonroad import CommonRoadSceneConfig, load_commonroad_scene
from density_planner.evaluation.peers import parse_peer_result, run_reactive_peer
from density_planner.evaluation.verdict import VERDICT_PARTS, judge
from density_planner.io.atomic import atomic_write_json, atomic_write_text


def judging_system():
    """The car whose bounds the verdict's ``within_model`` uses: the road domain where the package has it."""
    from density_planner.planners.context import run_system
    from density_planner.settings import RunConfig

    return run_system(RunConfig(), "commonroad")


def judge_one(xml: Path, runs: Path, system, timeout: float) -> dict:
    cache = runs / f"{xml.stem}.json"
    if cache.is_file():
        peer = parse_peer_result(json.loads(cache.read_text()))
    else:
        peer = run_reactive_peer(xml, timeout=timeout)
        atomic_write_json(cache, {**peer.raw, "wall_time_s": peer.wall_time})
    row = {"scenario": xml.stem, "peer_status": peer.status, "peer_reason": peer.reason,
           "planning_time": peer.planning_time, "n_states": int(len(peer.times))}
    try:
        scene = load_commonroad_scene(xml, CommonRoadSceneConfig(), system=system)
    except Exception as exc:  # noqa: BLE001 - the importer's one-line refusal
        row.update(status="refused", message=str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        return row
    if len(peer.times) < 1:
        row.update(status="failed", verdict=None, message=peer.reason or "no trajectory")
        return row
    offset = np.asarray(scene.meta.get("frame_offset") or (0.0, 0.0), dtype=np.float64)
    t0 = float(scene.road.t_start) if scene.road is not None else float(scene.t_start)
    dt = float(scene.road.dt) if scene.road is not None else float(np.median(np.diff(peer.times)))
    keep = peer.times >= t0 - 1e-9
    xs = peer.states[keep]
    states = np.zeros((len(xs), system.nx))
    names = system.state_names
    states[:, names.index("px")] = xs[:, 0] - offset[0]
    states[:, names.index("py")] = xs[:, 1] - offset[1]
    states[:, names.index("theta")] = xs[:, 2]
    states[:, names.index("v")] = xs[:, 3]
    verdict = judge(scene, states, None, system=system, dt=dt)
    row.update(status=verdict.status, verdict=verdict.to_dict(),
               final_goal_distance=verdict.details.get("final_goal_distance", math.nan))
    return row


def summary(rows: list[dict]) -> dict:
    n = len(rows)
    judged = [r for r in rows if isinstance(r.get("verdict"), dict)]
    out = {"planner": "reactive (commonroad-reactive-planner 2025.1, defaults)", "scenarios": n,
           "refused": sum(r["status"] == "refused" for r in rows),
           "no_trajectory": sum(r["status"] == "failed" and r.get("verdict") is None for r in rows),
           "success": sum(r["status"] == "success" for r in rows),
           "peer_own_goal_test": sum(r["peer_status"] == "ok" for r in rows)}
    for part in VERDICT_PARTS:
        out[f"{part}_rate"] = (sum(bool(r["verdict"].get(part)) for r in judged) / len(judged)) if judged else math.nan
    times = [r["planning_time"] for r in rows if math.isfinite(r.get("planning_time", math.nan))]
    out["planning_time_median"] = statistics.median(times) if times else math.nan
    dists = [r["final_goal_distance"] for r in judged if r.get("final_goal_distance") is not None
             and math.isfinite(r["final_goal_distance"])]
    out["final_goal_distance_median"] = statistics.median(dists) if dists else math.nan
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", required=True, type=Path)
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--timeout", type=float, default=600.0, help="wall-clock limit of one peer run [s]")
    args = parser.parse_args(argv)
    files = sorted(args.scenarios.glob("*.xml"))
    if not files:
        print(f"judge_reactive: no *.xml in {args.scenarios}", file=sys.stderr)
        return 2
    logging.getLogger("commonroad").setLevel(logging.ERROR)
    runs = args.out / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    system = judging_system()
    rows = []
    for i, xml in enumerate(files):
        rows.append(judge_one(xml, runs, system, args.timeout))
        if sys.stderr.isatty():
            print(f"\r{i + 1}/{len(files)} {xml.stem:40s}", end="", file=sys.stderr)
    s = summary(rows)
    atomic_write_json(args.out / "reactive.json", {"summary": s, "rows": rows})
    lines = ["| " + " | ".join(s) + " |", "|" + "---|" * len(s),
             "| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in s.values()) + " |"]
    atomic_write_text(args.out / "reactive.md", "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

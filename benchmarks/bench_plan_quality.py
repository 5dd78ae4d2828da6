"""Benchmark: plan quality and planning time of ``density-planner plan --env commonroad`` on a fixed, varied subset
of suite scenarios, for before/after comparisons of speed work (the verdict must not get worse while the planner
gets faster).

Runs the command once per scenario (fresh process, ``--threads 1``, no GIF) and prints per scenario the verdict
parts (goal_reached, collision_free, on_road, within_model), the collision probability max, the final distance to
the goal region, the stage-1 / stage-2 / planning times, the command's wall time and its CPU time (user + sys:
about what it would take on an idle core), then the count of each verdict part and the median times, with the
load average (wall times on a shared machine measure the other processes too). ``--json FILE`` also writes the
rows, ``--keep DIR`` keeps the output folders (plan.json with the cost histories).

    python benchmarks/bench_plan_quality.py [--scenarios DIR] [--pick A,B,...] [--json FILE] [-- EXTRA...]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SUITE = REPO / ".." / "shared" / "data" / "commonroad-suite"
#: 2 CHN_Sha, 2 DEU_Muc, 1 RUS_Bicycle, 2 USA_Lanker, 1 USA_US101; four of them start at rest (CHN_Sha-6_2,
#: DEU_Muc-9_2, USA_Lanker-2_20, USA_Lanker-2_17), the others at 2.9 to 14 m/s
DEFAULT_PICK = ("CHN_Sha-4_3_T-1", "CHN_Sha-6_2_T-1", "DEU_Muc-9_2_T-1", "DEU_Muc-2_2_T-1", "RUS_Bicycle-7_2_T-1",
                "USA_Lanker-2_20_T-1", "USA_Lanker-1_9_T-1", "USA_US101-3_1_T-1")
PARTS = ("goal_reached", "collision_free", "on_road", "within_model")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenarios", type=Path, default=DEFAULT_SUITE, help="folder of CommonRoad *.xml")
    p.add_argument("--pick", default=",".join(DEFAULT_PICK), help="comma-separated scenario names")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--timeout", type=float, default=900.0, help="seconds per scenario")
    p.add_argument("--json", type=Path, default=None, help="also write the rows to this JSON file")
    p.add_argument("--keep", type=Path, default=None, help="keep each run's output folder under this folder")
    p.add_argument("--exe", default=None, help="density-planner executable (default: beside this Python)")
    p.add_argument("extra", nargs="*", help="more arguments for `plan` (after --)")
    args = p.parse_args()
    exe = args.exe or str(Path(sys.executable).with_name("density-planner"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        if args.keep is not None:
            args.keep.mkdir(parents=True, exist_ok=True)
            tmp = str(args.keep)
        for name in args.pick.split(","):
            f = args.scenarios / f"{name}.xml"
            if not f.exists():
                print(f"{name}: not found in {args.scenarios}")
                continue
            out = Path(tmp) / name
            cmd = [exe, "plan", "--env", "commonroad", "--file", str(f), "--threads", str(args.threads),
                   "--no-progress", "--no-gif", "--out", str(out), *args.extra]
            load = os.getloadavg()[0]
            t0 = time.perf_counter()
            c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            try:
                proc = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout)
                rc = proc.returncode
            except subprocess.TimeoutExpired:
                rc = "timeout"
            wall = time.perf_counter() - t0
            c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)
            row = {"scenario": name, "exit": rc, "wall": wall, "cpu": cpu, "load": load, "extra": args.extra}
            if (out / "plan.json").exists():
                s = json.loads((out / "plan.json").read_text())
                v = s.get("verdict") or {}
                row.update({k: bool(v.get(k)) for k in PARTS})
                row["p_coll_max"] = v.get("p_coll_max")
                row["final_goal_distance"] = (v.get("details") or {}).get("final_goal_distance")
                t = s.get("timings", {})
                row.update({"stage1": t.get("stage1"), "stage2": t.get("stage2"), "planning": t.get("total")})
                row["predictor"] = s.get("density_predictor")
                row["iterations"] = s.get("iterations")
                row["command_timings"] = s.get("command_timings")
            else:
                row["error"] = (proc.stderr.strip().splitlines() or [""])[-1] if rc != "timeout" else "timeout"
            rows.append(row)
            print(_fmt(row), flush=True)
    ok = [r for r in rows if "stage1" in r]
    print("counts: " + ", ".join(f"{k} {sum(r[k] for r in ok)}/{len(rows)}" for k in PARTS))
    for k in ("stage1", "stage2", "planning", "wall", "cpu"):
        vals = [r[k] for r in ok if r.get(k) is not None]
        if vals:
            print(f"median {k}: {statistics.median(vals):.2f} s")
    print(f"load average at the end: {os.getloadavg()[0]:.2f}")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


def _fmt(r: dict) -> str:
    if "stage1" not in r:
        return f"{r['scenario']:22s} exit {r['exit']}: {r.get('error', '')}"
    parts = "".join("Y" if r[k] else "n" for k in PARTS)
    d = r["final_goal_distance"]
    pc = r["p_coll_max"]
    return (f"{r['scenario']:22s} {parts} p_coll_max {pc if pc is None else round(pc, 4)!s:>7s} dist "
            f"{d if d is None else round(d, 2)!s:>6s} m  stage1 {r['stage1']:6.2f} stage2 {r['stage2']:6.2f} "
            f"plan {r['planning']:6.2f} wall {r['wall']:6.1f} cpu {r['cpu']:6.1f} s (load {r['load']:.1f})")


if __name__ == "__main__":
    main()

"""Benchmark: wall time of the whole ``density-planner plan --env commonroad`` command (start-up, scene, plan,
verdict, solution.xml, figures and GIF), as a user runs it, on suite scenarios.

Runs the command ``--repeats`` times on each scenario (fresh processes; the first run of each scenario is also
counted) and prints per scenario the median wall time with the breakdown from ``plan.json``'s
``command_timings`` (start-up = wall time - the in-process total: interpreter, imports, argument parsing; outputs =
the wait for the process that writes solution.xml and the figures, forked before planning; out_plan_png and
out_child_wait: its plan.png and its wait for its GIF process, from ``output_process_timings``),
then the median over all runs, with the CPU time (user + sys of the command and its figure process: the wall time a
command would take on an idle machine with one core for it, roughly), the load average, since wall times on a
shared machine measure the other processes too, and ``machine_reference.py``'s time before and after (the machine's
own speed, which drifts by 5-15 % between days). Target (issue 13): <= 5 s median wall time.

    python benchmarks/bench_plan_command.py [--scenarios DIR] [--n 5] [--repeats 3] [--threads 1] [-- EXTRA...]
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
#: a fixed, varied choice (intersection, urban, highway, bicycle lane scene), used when present
#: (scenarios the models' domain refuses are left out: their command ends in a second)
DEFAULT_PICK = ("DEU_Muc-9_2_T-1", "USA_Lanker-2_17_T-1", "RUS_Bicycle-7_2_T-1", "CHN_Sha-4_3_T-1",
                "USA_Peach-3_4_T-1", "DEU_Ffb-1_6_T-1", "USA_Lanker-1_1_T-1")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenarios", type=Path, default=DEFAULT_SUITE, help="folder of CommonRoad *.xml")
    p.add_argument("--n", type=int, default=5, help="number of scenarios (default 5)")
    p.add_argument("--repeats", type=int, default=3, help="runs per scenario (default 3)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--exe", default=None, help="density-planner executable (default: beside this Python)")
    p.add_argument("extra", nargs="*", help="more arguments for `plan` (after --)")
    args = p.parse_args()
    files = {f.stem: f for f in sorted(args.scenarios.glob("*.xml"))}
    if not files:
        sys.exit(f"no *.xml in {args.scenarios}")
    pick = [files[n] for n in DEFAULT_PICK if n in files] + [f for n, f in files.items() if n not in DEFAULT_PICK]
    exe = args.exe or str(Path(sys.executable).with_name("density-planner"))
    env = dict(os.environ)
    load0 = f"{os.getloadavg()[0]:.1f}"
    ref0 = machine_reference()
    walls, cpus, rows = [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        for f in pick[: args.n]:
            runs = []
            for r in range(args.repeats):
                out = Path(tmp) / f"{f.stem}-{r}"
                cmd = [exe, "plan", "--env", "commonroad", "--file", str(f), "--threads", str(args.threads),
                       "--no-progress", "--out", str(out), *args.extra]
                t0 = time.perf_counter()
                c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
                wall = time.perf_counter() - t0
                c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu = (c1.ru_utime - c0.ru_utime) + (c1.ru_stime - c0.ru_stime)
                if proc.returncode not in (0, 3):  # refused (exit 2) or no plan: not a timing of the whole command
                    print(f"{f.stem}: exit {proc.returncode}: {proc.stderr.strip().splitlines()[-1:]}")
                    break
                data = json.loads((out / "plan.json").read_text())
                timings = data.get("command_timings", {})
                # the output process (solution.xml, figures) works beside planning; its own steps after the plan came
                timings.update({f"out_{k}": v for k, v in data.get("output_process_timings", {}).items()})
                timings["startup"] = wall - timings.get("total", 0.0)
                timings["wall"] = wall
                timings["cpu"] = cpu
                runs.append(timings)
                walls.append(wall)
                cpus.append(cpu)
            if runs:
                med = {k: statistics.median(r.get(k, 0.0) for r in runs) for k in runs[0]}
                rows.append((f.stem, med))
    keys = ("wall", "cpu", "startup", "scene", "setup", "plan", "verdict", "outputs", "out_plan_png",
            "out_child_wait")
    print(f"{'scenario':28s} " + " ".join(f"{k:>9s}" for k in keys))
    for name, med in rows:
        print(f"{name:28s} " + " ".join(f"{med.get(k, 0.0):9.2f}" for k in keys))
    if walls:
        ref1 = machine_reference()
        median = statistics.median(walls)
        refs = [float(r) for r in (ref0, ref1) if r != "?"]
        ratio = f", i.e. {median / statistics.mean(refs):.1f}x their mean" if refs else ""
        print(f"median wall time over {len(walls)} runs: {median:.2f} s (target <= 5 s), median "
              f"CPU time (user + sys, figure process included) {statistics.median(cpus):.2f} s; "
              f"cores {os.cpu_count()}, threads {args.threads}, load average before/after {load0} / "
              f"{os.getloadavg()[0]:.1f}; machine_reference.py before/after {ref0} / {ref1} s{ratio} "
              "(the machine's speed: compare timings of other days and machines through it; the suite's median "
              "command has taken ~8x on an Intel Xeon and an AMD EPYC alike)")


def machine_reference() -> str:
    """``benchmarks/machine_reference.py``'s reference time [s] now, in a fresh process (``"?"`` if it fails)."""
    proc = subprocess.run([sys.executable, str(Path(__file__).with_name("machine_reference.py")), "--json"],
                          capture_output=True, text=True)
    try:
        return f"{json.loads(proc.stdout)['reference']:.3f}"
    except (ValueError, KeyError):
        return "?"


if __name__ == "__main__":
    main()

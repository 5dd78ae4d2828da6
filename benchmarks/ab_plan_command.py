"""Interleaved A/B of the whole ``density-planner plan --env commonroad`` command between two source trees.

Wall times on a shared or virtual machine drift by tens of per cent within an hour, so two codes are compared in
the same minutes: for every scenario the command runs once with each tree's ``src`` first on ``PYTHONPATH`` (e.g.
a ``git worktree`` of the older commit, byte-compiled), in alternating order from one scenario to the next. Prints
per run the wall time, verdict status and P_coll max (which must agree where a change keeps the plans), then per
tree the median wall time and how many runs took at most 5 s (issue 13's target).

    python benchmarks/ab_plan_command.py OLD_TREE NEW_TREE [--scenarios DIR] [--only NAME ...] [-- EXTRA...]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("trees", nargs=2, type=Path, help="two source trees (each holds src/density_planner)")
    p.add_argument("--scenarios", type=Path, default=REPO / ".." / "shared" / "data" / "commonroad-suite")
    p.add_argument("--only", nargs="*", default=None, help="scenario names (file stems) to run; default: all")
    p.add_argument("--exe", default=str(Path(sys.executable).with_name("density-planner")))
    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1:] if "--" in argv else []  # more arguments for `plan`
    args = p.parse_args(argv[: argv.index("--")] if "--" in argv else argv)
    files = sorted(args.scenarios.glob("*.xml"))
    if args.only:
        files = [f for f in files if f.stem in set(args.only)]
    srcs = []
    for tree in args.trees:
        if not (tree / "src" / "density_planner").is_dir():
            sys.exit(f"{tree} holds no src/density_planner")
        srcs.append((tree.name or str(tree), str((tree / "src").resolve())))
    if not files:
        sys.exit(f"no scenario to run in {args.scenarios}")
    walls: dict[str, list[float]] = {name: [] for name, _ in srcs}
    for i, f in enumerate(files):
        for name, src in srcs if i % 2 == 0 else srcs[::-1]:
            with tempfile.TemporaryDirectory() as tmp:
                env = dict(os.environ, PYTHONPATH=src)
                cmd = [args.exe, "plan", "--env", "commonroad", "--file", str(f), "--no-progress", "--out",
                       str(Path(tmp) / "o"), *extra]
                t0 = time.perf_counter()
                proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
                wall = time.perf_counter() - t0
                if proc.returncode not in (0, 3):
                    print(f"{name:12s} {f.stem:28s} exit {proc.returncode}", flush=True)
                    continue
                data = json.loads((Path(tmp) / "o" / "plan.json").read_text())
                p_max = (data.get("collision_probability") or {}).get("max")
                walls[name].append(wall)
                print(f"{name:12s} {f.stem:28s} {wall:7.2f} s  {data.get('status')}  P_coll max {p_max}", flush=True)
    for name, values in walls.items():
        if values:
            print(f"{name}: {len(values)} runs, median {statistics.median(values):.2f} s, "
                  f"{sum(v <= 5.0 for v in values)} within 5 s")
    from bench_plan_command import machine_reference

    print(f"machine_reference.py now: {machine_reference()} s (the machine's speed, for comparing other days)")


if __name__ == "__main__":
    main()

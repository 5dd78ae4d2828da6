"""Interleaved A/B of the whole ``density-planner plan --env commonroad`` command between two source trees.

Wall times on a shared or virtual machine drift by tens of per cent within an hour, so two codes are compared in
the same minutes: for every scenario the command runs once with each tree's ``src`` first on ``PYTHONPATH`` (e.g.
a ``git worktree`` of the older commit), in alternating order from one scenario to the next. Both trees are
byte-compiled first, and both or neither must hold their compiled collision kernels (``_check_trees_alike``). Prints
per run the wall time, verdict status and P_coll max (which must agree where a change keeps the plans), then per
tree the median wall time and how many runs took at most 5 s (issue 13's target).

    python benchmarks/ab_plan_command.py OLD_TREE NEW_TREE [--scenarios DIR] [--only NAME ...] [-- EXTRA...]
"""

from __future__ import annotations

import argparse
import importlib.util
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
    _check_trees_alike([Path(src) for _, src in srcs])
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


def _check_trees_alike(srcs: list[Path]) -> None:
    """Both trees byte-compiled, and each holding the compiled collision kernels of its own source or neither, so
    that neither pays start-up costs the other does not: a copied tree's ``.pyc`` files are stale (the copy's
    sources are newer) and, with ``PYTHONDONTWRITEBYTECODE``, every run compiles every module again (~0.3 s); a
    tree without the ahead-of-time kernels (``cost/_collision_aot_*.so``, a build product that ``git worktree``
    and ``git archive`` do not carry) loads numba's just-in-time code instead (~0.5 s per run)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    for src in srcs:
        subprocess.run([sys.executable, "-m", "compileall", "-q", str(src / "density_planner")], env=env, check=True)
    have = []
    for i, src in enumerate(srcs):  # each tree's own rule for its kernels' module name (it hashes their source)
        cost = src / "density_planner" / "cost"
        spec = importlib.util.spec_from_file_location(f"_ab_aot_{i}", cost / "_aot.py")
        if spec is None or spec.loader is None:
            sys.exit(f"{cost / '_aot.py'} cannot be loaded")
        aot = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(aot)  # stdlib and numpy only at import
        name = aot.module_name()
        have.append(name is not None and any(cost.glob(name + "*")))
    if have[0] != have[1]:
        lacking = srcs[have.index(False)]
        sys.exit(f"{lacking} lacks the compiled collision kernels the other tree has: build them there with "
                 f"PYTHONPATH={lacking} python -m density_planner.cost._aot (or copy the file if the kernels' "
                 "source is the same)")


if __name__ == "__main__":
    main()

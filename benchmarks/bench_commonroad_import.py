"""Import (and optionally plan) every CommonRoad scenario of a folder through the CLI, one file at a time.

    python benchmarks/bench_commonroad_import.py --scenarios ../shared/data/commonroad-suite --out /tmp/cr-import
    python benchmarks/bench_commonroad_import.py --scenarios ... --out ... --plan      # also `plan` (default planner)

For each file: ``density-planner env --kind commonroad --file F --no-gif`` (and ``plan --threads 1 -q``) in a
fresh process; records the outcome (imported / refused with its one-line reason / crashed), the wall time of the
command and the scene build time, the grid (slices x cells, cell size, MiB), the horizon and what the importer
simplified. Writes ``OUT/import.json`` (one record per file, rewritten atomically after each file, resumable) and
``OUT/import.md`` (the table). Outcomes: exit 0 = imported, 2 = refused (bad input or outside the model's domain,
one line), anything else or a traceback = crashed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path


def _run(cmd: list[str], timeout: float) -> tuple[int, float, str]:
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
        rc, text = p.returncode, (p.stderr.strip() + "\n" + p.stdout.strip()).strip()
    except subprocess.TimeoutExpired:
        rc, text = -9, f"timed out after {timeout:g} s"
    return rc, time.perf_counter() - t0, text


def _reason(text: str) -> str:
    lines = [ln for ln in text.splitlines() if ln.strip() and "Warning" not in ln and not ln.startswith("  ")]
    errs = [ln for ln in lines if ln.startswith("density-planner: error:")]
    return (errs[-1] if errs else (lines[-1] if lines else "")).replace("density-planner: error: ", "")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--plan", action="store_true", help="also run `plan` (default planner) on imported files")
    ap.add_argument("--timeout", type=float, default=600.0)
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args(argv)
    exe = [sys.executable, "-m", "density_planner"]
    args.out.mkdir(parents=True, exist_ok=True)
    rec_path = args.out / "import.json"
    records = json.loads(rec_path.read_text()) if rec_path.is_file() else {}
    sets = [x for kv in args.overrides for x in ("--set", kv)]
    files = sorted(args.scenarios.glob("*.xml"))
    for i, f in enumerate(files):
        rec = records.get(f.name, {})
        if "env_rc" not in rec:
            out = args.out / f.stem / "env"
            rc, wall, text = _run([*exe, "env", "--kind", "commonroad", "--file", str(f), "--no-gif", "--out",
                                   str(out), *sets], args.timeout)
            rec = {"file": f.name, "env_rc": rc, "env_wall_s": wall, "reason": _reason(text) if rc else ""}
            rec["outcome"] = "imported" if rc == 0 else ("refused" if rc == 2 and "Traceback" not in text
                                                         else "crashed")
            if rc == 0:
                scene = json.loads((out / "scene.json").read_text())
                meta = scene["meta"]
                rec.update({
                    "build_s": scene.get("build_time_s"),
                    "grid": scene["grid"]["shape"],
                    "cell_size": scene["grid"]["cell_size"],
                    "mib": meta["map"]["memory_bytes"] / 2**20,
                    "horizon": meta["horizon"],
                    "dropped_ego": (meta.get("dropped_ego") or {}).get("id"),
                    "n_obstacles": len(meta.get("dynamic_obstacles", [])),
                    "notes": meta.get("simplifications", []),
                })
        if args.plan and rec["outcome"] == "imported" and "plan_rc" not in rec:
            out = args.out / f.stem / "plan"
            rc, wall, text = _run([*exe, "plan", "--env", "commonroad", "--file", str(f), "--threads", "1", "-q",
                                   "--no-gif", "--out", str(out), *sets], args.timeout)
            rec.update({"plan_rc": rc, "plan_wall_s": wall, "plan_reason": _reason(text) if rc else ""})
            pj = out / "plan.json"
            if pj.is_file():
                summary = json.loads(pj.read_text())
                rec["plan_status"] = summary.get("status")
                rec["plan_time_s"] = (summary.get("timings") or {}).get("total")
        records[f.name] = rec
        tmp = rec_path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(records, indent=1))
        tmp.replace(rec_path)
        print(f"[{i + 1}/{len(files)}] {f.name}: {rec['outcome']} {rec.get('reason', '')[:120]}", flush=True)
    _table(records, args.out / "import.md")
    return 0


def _table(records: dict, path: Path) -> None:
    counts = Counter(r["outcome"] for r in records.values())
    reasons = Counter()
    for r in records.values():
        if r["outcome"] != "imported":
            text = r["reason"]
            key = text.split(": ", 1)[-1]
            for marker in ("start speed", "no planning problem", "ends before the start"):
                if marker in key:
                    key = marker
            reasons[key[:100]] += 1
    lines = [f"{len(records)} files: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())), ""]
    lines += ["| refusal / crash reason | files |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in reasons.most_common()]
    lines += ["", "| file | outcome | env wall [s] | build [s] | grid (T x NX x NY) | cell [m] | MiB | horizon [s] | "
              "ego dropped | plan exit | plan status | plan time [s] |", "|---" * 12 + "|"]
    for name in sorted(records):
        r = records[name]
        grid = "x".join(str(g) for g in r["grid"]) if "grid" in r else ""
        fmt = lambda v, f="{:.2f}": "" if v is None else f.format(v)  # noqa: E731
        lines.append(
            f"| {name} | {r['outcome']}{(': ' + r['reason'][:90]) if r['outcome'] != 'imported' else ''} | "
            f"{fmt(r.get('env_wall_s'), '{:.1f}')} | {fmt(r.get('build_s'))} | {grid} | {fmt(r.get('cell_size'))} | "
            f"{fmt(r.get('mib'), '{:.0f}')} | {fmt(r.get('horizon'), '{:.1f}')} | {r.get('dropped_ego') or ''} | "
            f"{r.get('plan_rc', '')} | {r.get('plan_status') or ''} | {fmt(r.get('plan_time_s'))} |")
    path.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    raise SystemExit(main())

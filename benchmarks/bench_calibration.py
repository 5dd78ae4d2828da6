"""Risk on recorded traffic: the Monte-Carlo check of the reported collision probability and the calibration of
the occupancy model, over a folder of CommonRoad scenarios (issue 12, items 4-5).

For every scenario it runs ``density-planner validate risk --env commonroad --file X`` (the density planner with
its defaults; a Monte-Carlo check with ``--samples`` closed loops; the calibration with ``--calibration-samples``)
into ``OUT/<scenario>/`` (skipped when its ``risk_report.json`` exists: an interrupted run resumes), then writes

* ``OUT/summary.json``: per scenario the risk check (pass, max |z|), the predicted and observed road-user risk
  (max over time, mean over (sample, time) pairs), failures with their one-line reason;
* ``OUT/reliability.png``: the reliability diagram pooled over every calibrated scenario
  (:func:`density_planner.viz.risk.plot_calibration`).

    python benchmarks/bench_calibration.py --scenarios ../shared/data/commonroad-suite --out results/calibration
    python benchmarks/bench_calibration.py --scenarios ../shared/data/commonroad-suite --every 7 --samples 10000 \
        --out results/risk-10000      # 10 scenarios with the validator's default 10 000 closed loops

Scenarios refused as out of the models' domain, or whose planning fails, are listed with their reason.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", required=True, help="folder of CommonRoad .xml scenarios")
    p.add_argument("--out", required=True, help="output folder (resumable)")
    p.add_argument("--samples", type=int, default=2000, help="closed loops of the Monte-Carlo risk check")
    p.add_argument("--calibration-samples", type=int, default=1000, help="closed loops of the calibration")
    p.add_argument("--limit", type=int, default=0, help="first N scenarios only (sorted by name; 0 = all)")
    p.add_argument("--every", type=int, default=1, metavar="K",
                   help="every K-th scenario of the sorted folder (0-based index 0, K, 2K, ...; before --limit)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="configuration override passed to every run")
    args = p.parse_args(argv)

    from density_planner.cli import main as cli
    from density_planner.evaluation.calibration import CalibrationResult
    from density_planner.io.atomic import atomic_write_json
    from density_planner.viz.risk import plot_calibration

    files = sorted(Path(args.scenarios).glob("*.xml"))
    if not files:
        print(f"no .xml scenarios in {args.scenarios}", file=sys.stderr)
        return 2
    if args.every < 1:
        print(f"--every must be >= 1, got {args.every}", file=sys.stderr)
        return 2
    files = files[:: args.every]
    if args.limit:
        files = files[: args.limit]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, pooled = [], []
    for i, f in enumerate(files):
        d = out / f.stem
        report = d / "risk_report.json"
        failure = d / "failure.json"
        if not report.exists() and not failure.exists():
            cmd = ["validate", "risk", "--env", "commonroad", "--file", str(f), "--samples", str(args.samples),
                   "--calibration-samples", str(args.calibration_samples), "-q", "--out", str(d)]
            for o in args.overrides:
                cmd += ["--set", o]
            t0 = time.perf_counter()
            err = io.StringIO()
            with contextlib.redirect_stderr(err):
                try:
                    rc = cli(cmd)
                except SystemExit as e:  # argparse
                    rc = int(e.code or 0)
            if not report.exists():
                d.mkdir(parents=True, exist_ok=True)
                lines = [ln for ln in err.getvalue().splitlines() if ln.strip()]
                atomic_write_json(failure, {"exit_code": rc, "message": lines[-1] if lines else "",
                                            "seconds": time.perf_counter() - t0})
        row: dict = {"scenario": f.stem}
        if report.exists():
            r = json.loads(report.read_text())
            row.update(risk_check_passed=r["passed"], max_abs_z=r["max_abs_z"], p_coll_max=r["planner_max"],
                       p_coll_max_monte_carlo=r["monte_carlo_max"], plan_time_s=r.get("plan_time_s"))
            cal = r.get("calibration")
            if cal:
                c = CalibrationResult.from_dict(cal)
                pooled.append(c)
                row.update(road_user_risk_predicted_max=cal["predicted_max"],
                           road_user_risk_observed_max=cal["observed_max"],
                           road_user_risk_predicted_mean=cal["mean_predicted"],
                           road_user_risk_observed_mean=cal["mean_observed"])
        else:
            row.update(json.loads(failure.read_text()))
        rows.append(row)
        status = ("risk check " + ("PASS" if row.get("risk_check_passed") else "FAIL")) if report.exists() else (
            f"no check (exit {row.get('exit_code')}): {row.get('message', '')[:120]}")
        print(f"[{i + 1}/{len(files)}] {f.stem}: {status}", file=sys.stderr, flush=True)

    checked = [r for r in rows if "risk_check_passed" in r]
    summary = {
        "scenarios": len(rows),
        "checked": len(checked),
        "risk_check_passed": sum(bool(r["risk_check_passed"]) for r in checked),
        "samples": args.samples,
        "calibration_samples": args.calibration_samples,
        "rows": rows,
    }
    if pooled:
        pool = CalibrationResult.pooled(pooled)
        summary["pooled_calibration"] = pool.to_dict()
        plot_calibration(pool, out / "reliability.png",
                         title=f"occupancy model vs true shapes, {len(pooled)} scenarios "
                               f"({args.calibration_samples} closed loops each)")
    atomic_write_json(out / "summary.json", summary)
    print(f"{len(checked)} of {len(rows)} scenarios checked; risk check passed on {summary['risk_check_passed']}; "
          f"wrote {out / 'summary.json'}" + (f", {out / 'reliability.png'}" if pooled else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())

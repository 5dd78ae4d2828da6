"""Tables of a benchmark directory, computed from its records alone: ``summary.csv`` and ``summary.md``.

The figures are drawn by :mod:`density_planner.viz.benchmark` from the same rows; ``density-planner report DIR``
regenerates both.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..io.atomic import atomic_write_text
from .benchmark_settings import SETTINGS, VARIANTS, planner_variants
from .metrics import summarise
from .records import scan_records

__all__ = ["planner_label", "method_label", "summary_rows", "write_tables", "summary_markdown", "CSV_COLUMNS"]

#: columns of ``summary.csv``
CSV_COLUMNS = (
    "setting", "method", "planner", "variant", "runs", "missing", "valid", "failures", "errors", "failure_rate", "cri",
    "gci",
    "ici", "final_distance", "goal_cost", "collision_cost", "input_cost", "collision_probability_max",
    "offline_time", "online_time", "mc_collision_mean", "mc_collision_frequency", "mc_runs", "failure_reasons",
)


def planner_label(planner: str) -> str:
    """The planner's short name in tables and figures: its registration's label (the paper's ``DP``, ``M0``, ``O``,
    ...), or its name when it is not registered."""
    from ..planners.registry import planner_info

    return planner_info(planner, default=True).label


def method_label(planner: str, variant: str) -> str:
    """``DP``, ``DP-b`` (biased measurement), ``M2``, ``O``, ..."""
    base = planner_label(planner)
    return f"{base}-b" if variant == "biased" else base


def _order(s) -> tuple:
    settings = list(SETTINGS)
    setting = SETTINGS.get(s.setting)
    planners = list(setting.planners) if setting else []
    variants = list(VARIANTS)
    return (settings.index(s.setting) if s.setting in settings else len(settings), s.setting,
            planners.index(s.planner) if s.planner in planners else len(planners), s.planner,
            variants.index(s.variant) if s.variant in variants else len(variants), s.variant)


def summary_rows(
    records: Sequence[Mapping[str, Any]], missing: Mapping[tuple[str, str, str], int] | None = None
) -> list[dict[str, Any]]:
    """One row per (setting, planner, variant), in the order of :data:`CSV_COLUMNS`. ``missing`` counts the runs of
    each ``(setting, planner, variant)`` that have no usable record (unreadable file, or not yet run); a method
    whose every record is missing still gets a row."""
    missing = dict(missing or {})
    rows = []
    summaries = summarise(records)
    present = {(s.setting, s.planner, s.variant) for s in summaries}
    for key in sorted(k for k, n in missing.items() if n and k not in present):
        summaries.append(_empty_summary(*key))
    for s in sorted(summaries, key=_order):
        row: dict[str, Any] = s.as_dict()
        row["missing"] = int(missing.get((s.setting, s.planner, s.variant), 0))
        row["method"] = method_label(s.planner, s.variant)
        row["failure_reasons"] = ", ".join(f"{k} {v}" for k, v in sorted(s.failure_reasons.items()))
        rows.append({k: row[k] for k in CSV_COLUMNS})
    return rows


def _empty_summary(setting: str, planner: str, variant: str):
    from .metrics import MethodSummary

    nan = math.nan
    return MethodSummary(setting, planner, variant, 0, 0, 0, 0, nan, nan, nan, nan, nan, nan, nan, nan, nan, nan,
                         nan, nan, nan, 0, {})


def missing_runs(out: str | Path, records: Sequence[Mapping[str, Any]], bad) -> dict[tuple[str, str, str], int]:
    """Runs without a usable record per ``(setting, planner, variant)``: the runs the sweep file
    ``DIR/sweep_<setting>.json`` expects minus the valid records, and at least the unusable record files."""
    import json

    out = Path(out)
    have: dict[tuple[str, str, str], int] = {}
    for r in records:
        k = (str(r["setting"]), str(r["planner"]), str(r["variant"]))
        have[k] = have.get(k, 0) + 1
    missing: dict[tuple[str, str, str], int] = {}
    for b in bad:
        if b.planner is not None:
            k = (b.setting, b.planner, b.variant)
            missing[k] = missing.get(k, 0) + 1
    for path in sorted(out.glob("sweep_*.json")):
        try:
            sweep = json.loads(path.read_text())
            setting, planners, variants = sweep["setting"], sweep["planners"], sweep["variants"]
            n_envs = len(sweep["envs"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
        for planner in planners:
            for variant in planner_variants(planner, variants):
                k = (setting, planner, variant)
                missing[k] = max(missing.get(k, 0), n_envs - have.get(k, 0))
    return {k: v for k, v in missing.items() if v > 0}


def _csv_value(v: Any) -> Any:
    if isinstance(v, float):
        return "" if math.isnan(v) else f"{v:.6g}"
    return v


def _fmt(v: Any, digits: int = 3, scale: float = 1.0, percent: bool = False) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if percent:
        return f"{100 * v:.0f} %"
    v = float(v) * scale
    if v == 0:
        return "0"
    if abs(v) >= 10 ** digits or abs(v) < 10 ** -(digits - 1):
        return f"{v:.{digits - 1}e}"
    return f"{v:.{digits}g}"


def summary_markdown(rows: Sequence[Mapping[str, Any]], records: Sequence[Mapping[str, Any]] = ()) -> str:
    """Markdown tables, one per setting (rows from :func:`summary_rows`)."""
    out = io.StringIO()
    out.write("# Benchmark summary\n\n")
    out.write(
        "Failure: no solution, collision cost J_C > 10, final distance > 4.5 m, or bounds cost J_B > 1e-4 "
        "(ablation: no solution within the time limit); on road scenes (CommonRoad) a verdict other than success "
        "(failed parts: goal, collision, off_road, outside_model). CRI / GCI / ICI: mean excess of the collision "
        "cost J_C, goal cost J_G [m²] and input cost J_I over the best valid method of each environment, over the "
        "method's valid runs. Final distance, P_coll max (occupancy probability met along the executed "
        "trajectory), offline and online times: means over valid runs. MC: Monte-Carlo initial states from the "
        "planner's initial distribution; mean of max_t P_occ and the fraction of samples with max_t P_occ > 0.5, "
        "over all runs that have them.\n\n"
    )
    settings = []
    for r in rows:
        if r["setting"] not in settings:
            settings.append(r["setting"])
    for setting in settings:
        envs = sorted({r["env"] for r in records if r["setting"] == setting})
        desc = SETTINGS[setting].description if setting in SETTINGS else ""
        out.write(f"## {setting}\n\n{desc}" + (f"; {len(envs)} environments" if envs else "") + ".\n\n")
        out.write("| Method | Runs | Failure rate | CRI | GCI [m²] | ICI | Final dist. [m] | Offline [s] | "
                  "Online / step [ms] | P_coll max | MC max P_occ | MC coll. freq. | Failures |\n")
        out.write("|---|---|---|---|---|---|---|---|---|---|---|---|---|\n")
        for r in rows:
            if r["setting"] != setting:
                continue
            runs = f"{r['runs']} ({r['missing']} missing)" if r.get("missing") else f"{r['runs']}"
            out.write(
                f"| {r['method']} | {runs} | {_fmt(r['failure_rate'], percent=True)} | {_fmt(r['cri'])} | "
                f"{_fmt(r['gci'])} | {_fmt(r['ici'])} | {_fmt(r['final_distance'])} | {_fmt(r['offline_time'])} | "
                f"{_fmt(r['online_time'], scale=1e3)} | {_fmt(r['collision_probability_max'])} | "
                f"{_fmt(r['mc_collision_mean'])} | {_fmt(r['mc_collision_frequency'], percent=True)} | "
                f"{r['failure_reasons'] or '–'} |\n"
            )
        out.write("\n")
        checks = [r["risk_check"] for r in records if r.get("setting") == setting
                  and isinstance(r.get("risk_check"), Mapping) and r["risk_check"].get("passed") is not None]
        if checks:
            by_planner: dict[str, list[bool]] = {}
            for r in records:
                c = r.get("risk_check")
                if r.get("setting") == setting and isinstance(c, Mapping) and c.get("passed") is not None:
                    by_planner.setdefault(r["planner"], []).append(bool(c["passed"]))
            parts = [f"{planner_label(k)}: {sum(v)} of {len(v)} ({100 * sum(v) / len(v):.0f} %)"
                     for k, v in by_planner.items()]
            out.write("Risk check (`--validate-risk`: reported collision probability within 3 standard errors of "
                      f"{checks[0].get('n_monte_carlo')} Monte-Carlo closed loops at every time step): "
                      + "; ".join(parts) + " of the plans pass.\n\n")
        lost = [r for r in rows if r["setting"] == setting and r.get("missing")]
        if lost:
            out.write("**Missing runs** (no usable record: unreadable or not a record, or not run yet; the rates "
                      "above are over the runs present): "
                      + ", ".join(f"{r['method']} {r['missing']}" for r in lost) + ".\n\n")
    return out.getvalue()


def write_tables(out: str | Path) -> tuple[list[dict[str, Any]], list[dict[str, Any]], list[Path]]:
    """Write ``DIR/summary.csv`` and ``DIR/summary.md`` from the records under ``DIR``.

    Returns ``(records, rows, paths)``. Raises ``ValueError`` if ``DIR`` has no records."""
    out = Path(out)
    records, bad = scan_records(out)
    if not records:
        extra = f"; {len(bad)} file(s) there are not records (e.g. {bad[0].path.name}: {bad[0].reason})" if bad else ""
        raise ValueError(f"no benchmark records under {out / 'records'} (run `density-planner bench ... --out {out}`)"
                         + extra)
    rows = summary_rows(records, missing_runs(out, records, bad))
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(CSV_COLUMNS), lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: _csv_value(v) for k, v in r.items()})
    paths = [atomic_write_text(out / "summary.csv", buf.getvalue()),
             atomic_write_text(out / "summary.md", summary_markdown(rows, records))]
    return records, rows, paths


"""``bench commonroad``: every CommonRoad scenario of a folder, planned as its author posed it, judged by the verdict.

One environment per ``*.xml`` file of ``--scenarios DIR`` (the scenario's own planning problem, never a sampled
start or goal), every planner of ``--planners`` on each, executed in closed loop from a true initial state drawn
from the planner's initial distribution (the ``unbiased`` variant of the benchmark machinery in
:mod:`.benchmark`: same seeds, same records, same resumption). Each record gets:

* ``verdict``: :func:`~density_planner.evaluation.verdict.judge` of the *executed* trajectory against the
  scenario's ground truth (goal region in its time interval, true obstacle shapes, drivable area, model bounds),
  with the planner's own ``p_coll_max`` next to it;
* ``status``: ``"refused"`` when the scenario could not be turned into a planning problem (out of the models'
  domain, malformed file, ...), with the one-line reason in ``message``; a refused scenario is a record too, so
  the summary counts it.

:func:`commonroad_summary` aggregates the records per planner: success rate by the verdict and by each of its
four parts (over all scenarios, refused ones counting as failures, and over the planned ones), P_coll, the final
distance to the goal region, planning time and the refusals grouped by reason. :func:`write_commonroad_summary`
writes it to ``DIR/summary_commonroad.md`` and ``.csv``.
"""

from __future__ import annotations

import csv
import io
import math
import re
import traceback
from collections import Counter, defaultdict
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..io.atomic import atomic_write_text
from .environments import EnvSpec, stable_seed
from .jobs import Job, JobResult, base_record, error_record, job_scene, run_job
from .records import load_records
from .verdict import VERDICT_PARTS

__all__ = ["commonroad_envs", "run_commonroad_job", "commonroad_summary", "write_commonroad_summary",
           "summary_markdown", "SUMMARY_COLUMNS", "refusal_reason"]

#: setting name of the sweep (a :data:`~density_planner.evaluation.benchmark_settings.SETTINGS` entry)
SETTING = "commonroad"


def commonroad_envs(folder: str | Path) -> tuple[EnvSpec, ...]:
    """One environment per ``*.xml`` of ``folder`` (sorted by name), each with its own planning problem."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"--scenarios {folder} does not exist or is not a directory")
    files = sorted(folder.glob("*.xml"))
    if not files:
        raise ValueError(f"--scenarios {folder} holds no CommonRoad scenarios (*.xml)")
    # the initial law's seed from the file's name: a scenario's record does not depend on the folder's other files
    return tuple(EnvSpec("commonroad", i, 0, f"cr-{f.stem}", file=str(f.resolve()),
                         distribution_seed=stable_seed("distribution", f.stem)) for i, f in enumerate(files))


def refusal_reason(exc: BaseException) -> str:
    """The one-line reason of a refused scenario (the error's first line)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _refused_record(job: Job, variant: str, reason: str) -> dict[str, Any]:
    from ..config import to_dict

    rec = base_record(job, variant)
    rec.update(status="refused", failed=True, failure_reason="refused", message=reason, verdict=None,
               config=to_dict(job.run_config))
    return rec


def run_commonroad_job(job: Job) -> JobResult:
    """:func:`~density_planner.evaluation.jobs.run_job` for one scenario and planner, with the scenario's
    refusal as a record and the verdict of the executed trajectory in every record (a module-level function:
    picklable for joblib and Dask workers)."""
    from ..planners.context import run_system
    from ..planners.problem import PlanningProblem

    try:  # the scene and its planning problem (the run's system); a refusal is a record, not an error
        scene = job_scene(job)
        PlanningProblem.from_scene(scene, seed=job.env.law_seed, planning=job.run_config.planning,
                                   system=run_system(job.run_config, job.env.kind))
    except (ValueError, OSError, ImportError) as exc:
        return JobResult([_refused_record(job, v, refusal_reason(exc)) for v in job.variants])
    except Exception:  # noqa: BLE001 - a bug: recorded with its traceback, the sweep goes on
        tb = traceback.format_exc()
        return JobResult([error_record(job, v, tb, "environment") for v in job.variants])
    result = run_job(job)  # every record holds the verdict of its executed trajectory (benchmark._evaluate)
    for rec in result.records:
        rec.setdefault("verdict", None)
        if isinstance(rec["verdict"], dict) and rec["verdict"].get("status") == "error":
            rec["verdict_error"] = rec["verdict"].get("error")
            rec["verdict"] = None
    return result


# ------------------------------------------------------------------------------------------------- summary
#: columns of ``summary_commonroad.csv``
SUMMARY_COLUMNS = ("planner", "scenarios", "refused", "planned", "errors", "success", "success_rate",
                   "success_rate_planned", *(f"{p}_rate" for p in VERDICT_PARTS), "p_coll_max_mean",
                   "p_coll_max_median", "final_goal_distance_median", "final_goal_distance_mean",
                   "planning_time_median", "planning_time_mean", "p_any_mean", "mc_collision_mean", "calibrated",
                   "calibration_checked")


def _median(values: Sequence[float | None]) -> float:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.median(v)) if v else math.nan


def _mean(values: Sequence[float | None]) -> float:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.mean(v)) if v else math.nan


def _reason_key(message: str) -> str:
    """A refusal reason without the file-specific numbers and names (to group them)."""
    text = re.sub(r"^[^:]*\.xml[^:]*:\s*", "", message)  # leading '<file> (<id>): '
    text = re.sub(r"-?\d+(\.\d+)?(e-?\d+)?", "#", text)
    return text[:140]


def commonroad_summary(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Per planner: counts, verdict success rates (all scenarios; planned ones), part rates, P_coll, final distance
    to the goal region, planning time; refusals grouped by reason (with one example file each)."""
    by_planner: dict[str, list[Mapping[str, Any]]] = defaultdict(list)
    for r in records:
        if r.get("setting") == SETTING:
            by_planner[r["planner"]].append(r)
    rows = []
    refusals: dict[str, Counter] = {}
    examples: dict[str, dict[str, str]] = {}
    for planner, recs in by_planner.items():
        refused = [r for r in recs if r.get("status") == "refused"]
        errors = [r for r in recs if r.get("status") == "error"]
        judged = [r["verdict"] for r in recs if r.get("verdict")]
        planned = len(recs) - len(refused)
        n = len(recs)
        success = sum(v["status"] == "success" for v in judged)
        row: dict[str, Any] = {
            "planner": planner, "scenarios": n, "refused": len(refused), "planned": planned, "errors": len(errors),
            "success": success, "success_rate": success / n if n else math.nan,
            "success_rate_planned": success / planned if planned else math.nan,
        }
        for part in VERDICT_PARTS:
            row[f"{part}_rate"] = sum(bool(v[part]) for v in judged) / planned if planned else math.nan
        p_coll = [v.get("p_coll_max") for v in judged]
        dist = [(v.get("details") or {}).get("final_goal_distance") for v in judged]
        times = [((r.get("timings") or {}).get("offline")) for r in recs if r.get("status") not in ("refused",)]
        times = [t + 0.0 if t is not None else None for t in times]
        row.update(p_coll_max_mean=_mean(p_coll), p_coll_max_median=_median(p_coll),
                   final_goal_distance_median=_median(dist), final_goal_distance_mean=_mean(dist),
                   planning_time_median=_median(times), planning_time_mean=_mean(times))
        row.update(risk_calibration(recs))
        rows.append(row)
        counter: Counter = Counter()
        ex: dict[str, str] = {}
        for r in refused:
            key = _reason_key(str(r.get("message", "")))
            counter[key] += 1
            ex.setdefault(key, f"{r['env']}: {r.get('message', '')}")
        refusals[planner] = counter
        examples[planner] = ex
    failures: dict[str, Counter] = {}
    for planner, recs in by_planner.items():
        c: Counter = Counter()
        for r in recs:
            v = r.get("verdict")
            if v:
                for part in VERDICT_PARTS:
                    if not v[part]:
                        c[part] += 1
        failures[planner] = c
    return {"rows": rows, "refusals": refusals, "refusal_examples": examples, "failed_parts": failures}


def _mc_law(metrics: Mapping[str, Any]) -> tuple[float | None, float | None]:
    """The Monte-Carlo ``E[max_t P_body]`` over the planner's initial law and its standard error:
    ``mc_law_collision_*`` where the variant changed the executed states, else ``mc_collision_*``."""
    key = "mc_law_collision" if metrics.get("mc_law_collision_mean") is not None else "mc_collision"
    return metrics.get(f"{key}_mean"), metrics.get(f"{key}_se")


def risk_calibration(records: Sequence[Mapping[str, Any]], z: float = 3.0) -> dict[str, Any]:
    """The planner's collision-at-some-time estimate against Monte Carlo, over the records that have both: the
    plan's ``P_any`` (``plan.collision_probability_any``, from its own samples and density predictor) and the
    benchmark's Monte-Carlo ``E[max_t P_body]`` of executed closed loops from initial states drawn from the same law
    (:func:`_mc_law`). ``calibrated``: how many agree within ``z`` combined standard errors (at least 0.01, the
    grid's quantisation); ``worst``: the three largest differences ``(env, P_any, MC)``."""
    pairs, learned = [], []
    for r in records:
        plan = r.get("plan") or {}
        q, q_se = _mc_law(r.get("metrics") or {})
        if q is None or not math.isfinite(q):
            continue
        p = plan.get("collision_probability_any")
        if p is not None and math.isfinite(p):
            se = math.hypot(plan.get("collision_probability_any_se") or 0.0, q_se or 0.0)
            pairs.append((str(r.get("env")), float(p), float(q), max(se, 0.01)))
        # the learned predictor's own estimate where the exact re-check reported instead
        p_learned = plan.get("collision_probability_any_predictor")
        if p_learned is not None:
            learned.append((float(p_learned), float(q)))
    worst = sorted(pairs, key=lambda t: -abs(t[1] - t[2]))[:3]
    return {"p_any_mean": _mean([p for _, p, _, _ in pairs]), "mc_collision_mean": _mean([q for _, _, q, _ in pairs]),
            "calibrated": sum(abs(p - q) <= z * se for _, p, q, se in pairs), "calibration_checked": len(pairs),
            "calibration_worst": [(e, round(p, 3), round(q, 3)) for e, p, q, _ in worst],
            "learned_checked": len(learned), "learned_p_any_mean": _mean([p for p, _ in learned]),
            "learned_off_by_0_1": sum(abs(p - q) > 0.1 for p, q in learned)}


def _fmt(v: Any, pct: bool = False) -> str:
    if isinstance(v, float):
        if not math.isfinite(v):
            return "-"
        return f"{100 * v:.0f} %" if pct else f"{v:.3g}"
    return str(v)


def summary_markdown(summary: Mapping[str, Any]) -> str:
    """The summary as Markdown: the table, then the refusals grouped by reason."""
    lines = ["| planner | scenarios | refused | planned (errors) | success (all) | success (planned) | goal reached | "
             "collision-free | on road | within model | P_coll max mean | final dist. to goal [m] median | "
             "planning time [s] median |",
             "|---|" + "---:|" * 12]
    for r in summary["rows"]:
        lines.append(
            f"| {r['planner']} | {r['scenarios']} | {r['refused']} | {r['planned']} ({r['errors']}) | "
            f"{r['success']} ({_fmt(r['success_rate'], True)}) | {_fmt(r['success_rate_planned'], True)} | "
            + " | ".join(_fmt(r[f'{p}_rate'], True) for p in VERDICT_PARTS)
            + f" | {_fmt(r['p_coll_max_mean'])} | {_fmt(r['final_goal_distance_median'])} | "
            f"{_fmt(r['planning_time_median'])} |")
    lines.append("")
    lines.append("Part rates are over the planned scenarios (a run that raised counts as failing every part); "
                 "'success (all)' counts refused scenarios as failures.")
    for r in summary["rows"]:
        if r.get("calibration_checked"):
            worst = "; ".join(f"{e} {p:.2f} vs {q:.2f}" for e, p, q in r["calibration_worst"])
            lines.append(f"Risk calibration ({r['planner']}): collision at some time, the planner's P_any against "
                         f"Monte Carlo over closed loops executed from the same initial law (E[max_t P_body]), means "
                         f"{_fmt(r['p_any_mean'])} "
                         f"vs {_fmt(r['mc_collision_mean'])}; within 3 standard errors (at least 0.01) on "
                         f"{r['calibrated']} of {r['calibration_checked']} scenarios; largest differences: {worst}.")
            if r.get("learned_checked"):
                lines.append(f"The learned predictor's own estimate (reported: the exact re-check, "
                             f"evaluation.exact_check): mean {_fmt(r['learned_p_any_mean'])}, off Monte Carlo by "
                             f"more than 0.1 on {r['learned_off_by_0_1']} of {r['learned_checked']} scenarios.")
    for planner, counter in summary["failed_parts"].items():
        if counter:
            lines.append(f"Failed parts ({planner}, planned scenarios): "
                         + ", ".join(f"{part} {counter[part]}" for part in VERDICT_PARTS) + ".")
    for planner, counter in summary["refusals"].items():
        if not counter:
            continue
        lines += ["", f"Refused scenarios ({planner}), by reason:", ""]
        for key, count in counter.most_common():
            lines.append(f"- {count} x {summary['refusal_examples'][planner][key]}")
    return "\n".join(lines) + "\n"


def write_commonroad_summary(out: str | Path) -> list[Path]:
    """``DIR/summary_commonroad.md`` and ``.csv`` from the records under ``DIR/records/commonroad``."""
    out = Path(out)
    summary = commonroad_summary(load_records(out, SETTING))
    md = out / "summary_commonroad.md"
    atomic_write_text(md, summary_markdown(summary))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_COLUMNS, extrasaction="ignore")
    w.writeheader()
    for r in summary["rows"]:
        w.writerow(r)
    path_csv = out / "summary_commonroad.csv"
    atomic_write_text(path_csv, buf.getvalue())
    return [md, path_csv]

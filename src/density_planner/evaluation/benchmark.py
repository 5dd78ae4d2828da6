"""The paper's benchmarks (§V): sweeps of planners over environments, one JSON record per run, resumable.

Settings (:data:`SETTINGS`):

* ``ablation``: the density planner's gradient optimisation against the search- and sampling-based optimisers
  (``docs/spec.md`` §11) on random artificial scenes. The *planned* references are compared (no closed loop:
  metrics of the reference from the mean start; the Monte-Carlo figures track it from sampled initial states);
  failure = no solution within ``evaluation.plan_time_limit`` (5 min).
* ``artificial``: density planner, MPC M0, tube MPC M1-M3 and the oracle on random artificial scenes, each
  executed from a true initial state drawn from the planner's initial distribution, with the measured heading
  biased (``biased``: the true state's ``theta_bias``) or not (``unbiased``: bias 0). The oracle knows the true
  state and applies its inputs open loop, so the bias does not affect it: it runs once (``unbiased``).
* ``real``: density planner, M0, M2 and the oracle on recorded traffic: inD recordings from ``--data-dir``
  (random 10-s windows and start/goal pairs), or, without it, the two CommonRoad NGSIM scenarios shipped with
  the package, each with several start/goal pairs (seed 0: the scenario's planning problem; others sampled).

The sweep is split along its jobs: the settings (:mod:`.benchmark_settings`), the environments
(:mod:`.environments`), the worker side (:mod:`.jobs`: one planner on one environment), the records on disk
(:mod:`.records`) and, here, the sweep itself (:class:`BenchmarkSpec`, :func:`config_hash`, :func:`run_benchmark`).

Runs (= records) are keyed by (environment, planner, variant) and written to
``DIR/records/<setting>/<env>__<planner>__<variant>.json`` (atomically) as soon as their job finishes; a re-run
with the same ``DIR`` skips every existing record (a killed sweep loses only the runs in flight). A *job* runs
one planner on one environment: planners whose plan does not depend on the true state (density, search,
sampling) plan once offline and execute that plan for every variant in the same job (the paper's DP also planned
once); MPC and oracle plan from the true state, one job per variant (their registrations say which:
:func:`~density_planner.planners.registry.planner_info`).

Everything random is seeded from the environment and the planner name (never from the execution order or the
worker): the scene, the initial distribution (seed = environment index), the true initial state and the
Monte-Carlo states (the same for every planner of an environment: common random numbers), and the planner's own
seed. Serial, joblib and Dask sweeps therefore write identical records, apart from the wall times (``timings``)
and the provenance (``run_info``). Exception: the MPC's IPOPT CPU-time limit (0.1 s per step, as the paper) makes
its iterates depend on the machine's load.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from collections.abc import Iterator
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from ..config import to_dict
from ..io.atomic import atomic_save_npz, atomic_write_json
from ..parallel import run_tasks
from ..planners.registry import planner_info
from .benchmark_settings import SETTINGS, VARIANTS, planner_variants
from .config import EvaluationConfig
from .environments import EnvSpec
from .jobs import Job, JobResult, error_record, run_job
from .records import RECORD_SCHEMA, map_path, read_record, record_path

__all__ = ["BenchmarkSpec", "SweepReport", "make_jobs", "run_benchmark", "config_hash", "component_digest",
           "EXECUTION_SETTINGS"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BenchmarkSpec:
    """What a sweep runs: a setting, its environments, planners and variants, and the run configuration."""

    setting: str
    envs: tuple[EnvSpec, ...]
    planners: tuple[str, ...]
    variants: tuple[str, ...]
    #: the run configuration (:class:`density_planner.settings.RunConfig`) with its ``evaluation`` section
    run_config: Any
    #: tracking controller name or weights file (``None``: the package default)
    controller: str | None = None
    #: density predictor of the density planner (``None``: the package default)
    density: str | None = None
    #: what the controller and predictor names resolved to, with the digest of their weights
    #: (:func:`component_digest`), so that records made with other weights under the same name are never mixed
    components: str = ""

    def __post_init__(self) -> None:
        if self.setting not in SETTINGS:
            raise ValueError(f"unknown setting {self.setting!r}; valid choices: {', '.join(SETTINGS)}")
        if not self.envs:
            raise ValueError("a benchmark needs at least one environment")
        names = [e.name for e in self.envs]
        if len(set(names)) != len(names):
            raise ValueError("environment names must be unique")
        if not self.planners:
            raise ValueError("a benchmark needs at least one planner")
        for v in self.variants:
            if v not in VARIANTS:
                raise ValueError(f"unknown variant {v!r}; valid choices: {', '.join(VARIANTS)}")
        if not self.variants:
            raise ValueError("a benchmark needs at least one variant")

    @property
    def evaluation(self) -> EvaluationConfig:
        return self.run_config.evaluation

    def variants_of(self, planner: str) -> tuple[str, ...]:
        """Variants run for ``planner`` (:func:`~.benchmark_settings.planner_variants`)."""
        return planner_variants(planner, self.variants)


#: run-configuration sections that every record depends on (scenes, scoring, the reported cost)
#: sections every record depends on, besides the scene sections of its setting (``Setting.scene_sections``)
_COMMON_SECTIONS = ("evaluation",)


#: settings of ``[evaluation]`` that change how a sweep runs, never its numbers: left out of the configuration hash
#: (held at their defaults there, so that records made before keep their hashes)
EXECUTION_SETTINGS = ("threads_per_worker",)


def _without_execution_settings(cfg: dict[str, Any]) -> dict[str, Any]:
    evaluation = cfg.get("evaluation")
    if not isinstance(evaluation, dict):
        return cfg
    default = to_dict(EvaluationConfig())
    return {**cfg, "evaluation": {**evaluation, **{k: default[k] for k in EXECUTION_SETTINGS}}}


def _config_payload(spec: BenchmarkSpec, planner: str | None = None) -> dict[str, Any]:
    """What the records of ``planner`` depend on (all planners when ``None``): the scene and evaluation sections
    (without :data:`EXECUTION_SETTINGS`), the reported cost, the ``[system]`` and ``[planning]`` sections when they
    are not the defaults, the sections of the planner's registration and, unless
    it plans from the true state (MPC, oracle), the Liouville numerics, the controller, the predictor and their
    weights. MPC and oracle records therefore stay valid when only the learned components change."""
    cfg = _without_execution_settings(to_dict(spec.run_config))
    payload: dict[str, Any] = {"schema": RECORD_SCHEMA, "setting": spec.setting}
    if planner is None:
        payload.update(run_config=cfg, controller=spec.controller, density=spec.density, components=spec.components)
        return payload
    info = planner_info(planner, default=True)
    setting = SETTINGS.get(spec.setting)
    scene_sections = setting.scene_sections if setting else ("random_scene", "commonroad", "ind")
    payload.update({k: cfg.get(k) for k in (*scene_sections, *_COMMON_SECTIONS)})
    payload["cost"] = (cfg.get("density_planner") or {}).get("cost")
    payload["planner"] = {planner: cfg.get(info.section) if info.section else None}
    if info.reads:
        payload["reads"] = {s: cfg.get(s) for s in info.reads}
    from ..planners.problem import PlanningConfig
    from ..systems.registry import SystemConfig

    # the default time axis and system add nothing: records made before these sections existed keep their hashes
    if cfg.get("planning") not in (None, to_dict(PlanningConfig())):
        payload["planning"] = cfg["planning"]
    system = dict(cfg.get("system") or {})
    if info.plans_from_true_state:  # MPC, oracle: the dynamics and domain matter, not controller and predictor
        system = {k: v for k, v in system.items() if k not in ("controller", "density")}
    default = {k: v for k, v in to_dict(SystemConfig()).items() if k in system}
    if system and system != default:
        payload["system"] = system
    if not info.plans_from_true_state:
        payload.update(liouville=cfg.get("liouville"), controller=spec.controller, density=spec.density,
                       components=spec.components)
    return payload


def component_digest(*components: Any) -> str:
    """Digest of the state (parameters and buffers) of ``components``: torch modules, or objects holding modules as
    attributes (each module counted once); ``""`` when there is none."""
    import torch

    from ..io.checkpoint import hash_state

    h = hashlib.sha256()
    found = False
    seen: set[int] = set()

    def add(module: torch.nn.Module) -> None:
        nonlocal found
        if id(module) in seen:
            return
        seen.add(id(module))
        hash_state(h, module)
        found = found or bool(module.state_dict())

    for c in components:
        if isinstance(c, torch.nn.Module):
            add(c)
        else:
            for v in vars(c).values() if hasattr(c, "__dict__") else ():
                if isinstance(v, torch.nn.Module):
                    add(v)
    return h.hexdigest()[:16] if found else ""


def config_hash(spec: BenchmarkSpec, planner: str | None = None) -> str:
    """Hash of everything that changes the numbers of ``planner``'s records (see :func:`_config_payload`); of the
    whole sweep when ``planner`` is ``None``."""
    text = json.dumps(_config_payload(spec, planner), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def make_jobs(spec: BenchmarkSpec, done: AbstractSet[tuple[str, str, str]] = frozenset(),
              maps_done: AbstractSet[str] = frozenset()) -> list[Job]:
    """Jobs for every run of ``spec`` not in ``done`` (keys ``(env, planner, variant)``); environment-major."""
    hashes = {p: config_hash(spec, p) for p in spec.planners}
    jobs: list[Job] = []
    for env in spec.envs:
        want_map = env.name not in maps_done
        for planner in spec.planners:
            todo = tuple(v for v in spec.variants_of(planner) if (env.name, planner, v) not in done)
            if not todo:
                continue
            groups = [(v,) for v in todo] if planner_info(planner, default=True).plans_from_true_state else [todo]
            for variants in groups:
                jobs.append(Job(spec.setting, env, planner, variants, spec.run_config, spec.controller, spec.density,
                                hashes[planner], want_map=want_map, components=spec.components))
                want_map = False
    return jobs


@dataclass
class SweepReport:
    """What :func:`run_benchmark` did."""

    total: int
    skipped: int
    written: int
    failed_runs: int
    errors: int
    wall_time: float
    records_dir: Path
    messages: list[str] = field(default_factory=list)


def _existing(out: Path, spec: BenchmarkSpec, retry_errors: bool, redo_stale: bool) -> tuple[set, set]:
    hashes = {p: config_hash(spec, p) for p in spec.planners}
    done: set[tuple[str, str, str]] = set()
    stale = []
    d = Path(out) / "records" / spec.setting
    for p in sorted(d.glob("*.json")) if d.is_dir() else []:
        r = read_record(p)
        if r is None or r.get("planner") not in hashes:
            continue
        if r.get("config_hash") != hashes[r["planner"]]:
            stale.append(p.name)
            continue
        if retry_errors and r.get("status") == "error":
            continue
        done.add((r["env"], r["planner"], r["variant"]))
    if stale and not redo_stale:
        raise ValueError(
            f"--out {out} holds {len(stale)} {spec.setting} record(s) made with a different configuration (e.g. "
            f"{stale[0]}); use another --out, the same --config/--set/--controller/--density as before, or "
            "--redo-stale to recompute them")
    if stale:
        log.warning("recomputing %d record(s) made with a different configuration", len(stale))
    maps = {p.stem for p in (d / "maps").glob("*.npz")} if (d / "maps").is_dir() else set()
    return done, maps


def run_benchmark(
    spec: BenchmarkSpec,
    out: str | Path,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = False,
    retry_errors: bool = False,
    redo_stale: bool = False,
    run_info: dict[str, Any] | None = None,
    job_fn: Any = None,
    threads_per_worker: int | None | Literal["config"] = "config",
) -> SweepReport:
    """Run every missing record of ``spec`` into ``out`` (serial, joblib ``workers`` or a Dask ``scheduler``).

    Records are written by this process as jobs finish; a job whose worker died (or that could not be run at all)
    becomes failure records with the error. Existing records are kept unless they are errors and ``retry_errors``,
    or were made with another configuration (:func:`config_hash`): then the sweep refuses to start, or recomputes
    them with ``redo_stale``. ``threads_per_worker`` overrides ``evaluation.threads_per_worker`` (``None``: torch's
    default). ``job_fn`` replaces :func:`run_job` (a picklable module-level function
    ``job -> JobResult``; for tests and instrumentation). Returns counts and the wall time.
    """
    out = Path(out)
    t0 = time.perf_counter()
    done, maps_done = _existing(out, spec, retry_errors, redo_stale)
    jobs = make_jobs(spec, done, maps_done)
    total = sum(len(spec.variants_of(p)) for p in spec.planners) * len(spec.envs)
    pending = sum(j.runs for j in jobs)
    info = dict(run_info or {})
    sweep = {"setting": spec.setting, "config_hash": config_hash(spec), "envs": [e.as_dict() for e in spec.envs],
             "planners": list(spec.planners), "variants": list(spec.variants), "controller": spec.controller,
             "density": spec.density, "config": to_dict(spec.run_config), "workers": workers, "scheduler": scheduler,
             "run_info": info, "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "runs_total": total,
             "runs_pending": pending}
    sweep_path = out / f"sweep_{spec.setting}.json"
    # written once the first job has come back (an unreachable scheduler leaves nothing behind) and at the end
    from tqdm.auto import tqdm

    threads = spec.evaluation.threads_per_worker if threads_per_worker == "config" else threads_per_worker
    written = failed = errors = 0
    started = False
    bar = tqdm(total=pending, desc=f"bench {spec.setting}", unit="run", disable=not progress)
    try:
        outcomes: Iterator = run_tasks(job_fn or run_job, jobs, workers=workers, scheduler=scheduler,
                                       threads_per_worker=threads, progress=False)
        for outcome in outcomes:
            if not started:
                atomic_write_json(sweep_path, sweep)
                started = True
            job = jobs[outcome.index]
            if outcome.ok:
                result: JobResult = outcome.value
                records = result.records
                if result.scene_map is not None:
                    atomic_save_npz(map_path(out, spec.setting, job.env.name), **result.scene_map)
            else:
                records = [error_record(job, v, outcome.error or "unknown error", "worker") for v in job.variants]
            for r in records:
                r["run_info"].update(info)
                atomic_write_json(record_path(out, spec.setting, r["env"], r["planner"], r["variant"]), r)
                written += 1
                failed += bool(r.get("failed"))
                errors += r.get("status") == "error"
            bar.update(len(records))
            bar.set_postfix(failed=failed, errors=errors)
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    sweep.update(finished=time.strftime("%Y-%m-%dT%H:%M:%S"), wall_time_s=wall, runs_written=written,
                 runs_failed=failed, runs_error=errors)
    atomic_write_json(sweep_path, sweep)
    return SweepReport(total=total, skipped=total - pending, written=written, failed_runs=failed, errors=errors,
                       wall_time=wall, records_dir=out / "records" / spec.setting)

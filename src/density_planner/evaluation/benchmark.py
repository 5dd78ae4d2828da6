"""The paper's benchmarks (§V): sweeps of planners over environments, one JSON record per run, resumable.

Settings (:data:`SETTINGS`):

* ``ablation``: the density planner's gradient optimisation against the search- and sampling-based optimisers
  (``original.md`` §11) on random artificial scenes. The *planned* references are compared (no closed loop:
  metrics of the reference from the mean start; the Monte-Carlo figures track it from sampled initial states);
  failure = no solution within ``evaluation.plan_time_limit`` (5 min).
* ``artificial``: density planner, MPC M0, tube MPC M1-M3 and the oracle on random artificial scenes, each
  executed from a true initial state drawn from the planner's initial distribution, with the measured heading
  biased (``biased``: the true state's ``theta_bias``) or not (``unbiased``: bias 0). The oracle knows the true
  state and applies its inputs open loop, so the bias does not affect it: it runs once (``unbiased``).
* ``real``: density planner, M0, M2 and the oracle on recorded traffic: inD recordings from ``--data-dir``
  (random 10-s windows and start/goal pairs), or, without it, the two CommonRoad NGSIM scenarios shipped with
  the package, each with several start/goal pairs (seed 0: the scenario's planning problem; others sampled).

Runs (= records) are keyed by (environment, planner, variant) and written to
``DIR/records/<setting>/<env>__<planner>__<variant>.json`` (atomically) as soon as their job finishes; a re-run
with the same ``DIR`` skips every existing record (a killed sweep loses only the runs in flight). A *job* runs
one planner on one environment: planners whose plan does not depend on the true state (density, search,
sampling) plan once offline and execute that plan for every variant in the same job (the paper's DP also planned
once); MPC and oracle plan from the true state, one job per variant.

Everything random is seeded from the environment and the planner name (never from the execution order or the
worker): the scene, the initial distribution (seed = environment index), the true initial state and the
Monte-Carlo states (the same for every planner of an environment: common random numbers), and the planner's own
seed. Serial, joblib and Dask sweeps therefore write identical records, apart from the wall times (``timings``)
and the provenance (``run_info``). Exception: the MPC's IPOPT CPU-time limit (0.1 s per step, as the paper) makes
its iterates depend on the machine's load.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import socket
import time
import traceback
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from ..config import to_dict
from ..io.atomic import atomic_save_npz, atomic_write_json
from ..parallel import run_tasks
from ..planners.base import PlanResult
from ..planners.problem import PlanningProblem
from ..systems.car import BIAS
from .config import EvaluationConfig
from .metrics import evaluation_box, failure_flags, monte_carlo_metrics, run_metrics
from .simulate import ExecutionMode, execute, execution_mode, monte_carlo
from .verdict import record_verdict

__all__ = [
    "Setting",
    "SETTINGS",
    "EnvSpec",
    "BenchmarkSpec",
    "Job",
    "JobResult",
    "SweepReport",
    "artificial_envs",
    "real_envs",
    "shipped_commonroad_dir",
    "make_jobs",
    "run_job",
    "run_benchmark",
    "record_path",
    "load_records",
    "scan_records",
    "record_problem",
    "BadRecord",
    "load_scene_map",
    "identity_view",
    "stable_seed",
    "config_hash",
    "RECORD_SCHEMA",
]

log = logging.getLogger(__name__)

#: version of the record layout
RECORD_SCHEMA = 1

#: planners that plan from the true state (one job per variant); all others plan once per environment
_PLANS_FROM_TRUE_STATE = ("mpc", "tube_mpc", "oracle")


@dataclass(frozen=True)
class Setting:
    """A benchmark setting of the paper."""

    name: str
    #: planners compared (registry names)
    planners: tuple[str, ...]
    #: measurement variants of every run
    variants: tuple[str, ...]
    #: number of environments when ``--envs`` is not given
    default_envs: int
    #: execute the plans in closed loop (False: the ablation compares the planned references)
    closed_loop: bool
    #: planners that run only the first variant (the oracle: it knows the true state, the bias cannot matter)
    single_variant: tuple[str, ...] = ()
    description: str = ""


SETTINGS: dict[str, Setting] = {
    "ablation": Setting(
        "ablation", ("density", "search", "sampling"), ("nominal",), 10, False,
        description="gradient vs search vs sampling optimisation of the reference (planned references)",
    ),
    "artificial": Setting(
        "artificial", ("density", "mpc", "tube_mpc_0.3", "tube_mpc_0.5", "tube_mpc_1.0", "oracle"),
        ("unbiased", "biased"), 50, True, single_variant=("oracle",),
        description="all planners on random artificial scenes, perfect and biased heading measurement",
    ),
    "real": Setting(
        "real", ("density", "mpc", "tube_mpc_0.5", "oracle"), ("unbiased", "biased"), 30, True,
        single_variant=("oracle",),
        description="density planner, M0, M2 and oracle on recorded traffic (inD, or the shipped CommonRoad scenes)",
    ),
    "commonroad": Setting(
        "commonroad", ("density", "mpc"), ("unbiased",), 0, True,
        description="every CommonRoad scenario of --scenarios DIR as its author posed it, judged by the verdict "
        "(evaluation/commonroad_bench.py)",
    ),
}

_VARIANTS = ("nominal", "unbiased", "biased")


def stable_seed(*parts: Any) -> int:
    """A seed in ``[0, 2^31)`` from ``parts`` (SHA-256 of their text; independent of the Python process)."""
    text = "/".join(str(p) for p in parts)
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little") % (2**31)


# -------------------------------------------------------------------------------------------------- environments
@dataclass(frozen=True)
class EnvSpec:
    """How to build one benchmark environment (JSON-serialisable, cheap to ship to workers).

    Attributes:
        kind: ``"random"`` (artificial scene number ``seed``), ``"commonroad"`` (``file``; ``seed`` 0 = the
            scenario's planning problem, else a sampled start/goal pair) or ``"ind"`` (``data_dir``,
            ``recording``, window starting at ``start_time`` [s], start/goal sampler seed ``seed``).
        index: the environment's number in the sweep (seed of the initial distribution).
        name: unique name (file names of the records).
    """

    kind: Literal["random", "commonroad", "ind"]
    index: int
    seed: int
    name: str
    file: str | None = None
    data_dir: str | None = None
    recording: int | None = None
    start_time: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


def artificial_envs(indices: Sequence[int]) -> tuple[EnvSpec, ...]:
    """Random artificial scenes with the given numbers (``random_scene(i)``)."""
    return tuple(EnvSpec("random", int(i), int(i), f"random-{int(i)}") for i in indices)


#: prefix of the shipped CommonRoad scenarios in :attr:`EnvSpec.file` (resolved on the worker)
_SHIPPED = "<shipped>"


#: the shipped CommonRoad scenarios `bench real` uses without --data-dir
SHIPPED_REAL_SCENARIOS = ("USA_Peach-4_8_T-1.xml", "USA_US101-4_1_T-1.xml")


def shipped_commonroad_dir() -> Path:
    """Folder of the CommonRoad scenarios shipped with the package (NGSIM, BSD-3 licence file beside them)."""
    from importlib.resources import files

    return Path(str(files("density_planner") / "data" / "commonroad"))


def _ind_recordings(data_dir: Path) -> list[int]:
    recs = []
    for p in sorted(data_dir.glob("*_tracks.csv")):
        stem = p.name[: -len("_tracks.csv")]
        if stem.isdigit():
            recs.append(int(stem))
    return recs


def _ind_duration(data_dir: Path, recording: int) -> float | None:
    from ..environment.ind import ind_paths, read_recording_meta

    try:
        meta = read_recording_meta(ind_paths(data_dir, recording)["recording_meta"])
    except ValueError:
        return None
    d = meta.get("duration")
    return float(d) if isinstance(d, float) and math.isfinite(d) else None


def real_envs(
    indices: Sequence[int], data_dir: str | Path | None = None, *, window: float = 10.0
) -> tuple[EnvSpec, ...]:
    """Recorded-traffic environments.

    With ``data_dir``: inD recordings there (``NN_tracks.csv`` ...) or CommonRoad scenarios (``*.xml``). inD: the
    environment ``i`` uses recording ``i mod R``, a seeded random ``window``-second period of it and start/goal
    seed ``i``. CommonRoad: scenario ``i mod F`` with start/goal seed ``i div F`` (0: its planning problem).
    Without ``data_dir`` the shipped CommonRoad scenarios are used.
    """
    folder = Path(data_dir) if data_dir is not None else shipped_commonroad_dir()
    if not folder.is_dir():
        raise ValueError(f"--data-dir {folder} is not a directory")
    recordings = _ind_recordings(folder)
    if recordings:
        out = []
        for i in indices:
            rec = recordings[int(i) % len(recordings)]
            duration = _ind_duration(folder, rec)
            rng = np.random.default_rng(stable_seed("ind-window", rec, i))
            start = float(np.round(rng.uniform(0.0, duration - window), 1)) if duration and duration > window else (
                (int(i) // len(recordings)) * window)
            out.append(EnvSpec("ind", int(i), int(i), f"ind-rec{rec:02d}-t{start:g}-s{int(i)}", data_dir=str(folder),
                               recording=rec, start_time=start))
        return tuple(out)
    files = sorted(folder.glob("*.xml"))
    if data_dir is None:  # the package ships more scenarios (tests, examples); `bench real` uses the two NGSIM ones
        files = [f for f in files if f.name in SHIPPED_REAL_SCENARIOS]
    if not files:
        raise ValueError(f"--data-dir {folder} holds neither inD recordings (NN_tracks.csv) nor CommonRoad "
                         "scenarios (*.xml)")
    out = []
    for i in indices:
        f = files[int(i) % len(files)]
        k = int(i) // len(files)
        name = f"{_SHIPPED}/{f.name}" if data_dir is None else str(f)
        out.append(EnvSpec("commonroad", int(i), k, f"cr-{f.stem}-s{k}", file=name))
    return tuple(out)


def build_scene(env: EnvSpec, run_config: Any):
    """The :class:`~density_planner.environment.scene.Scene` of ``env`` built with ``run_config``'s sections."""
    from ..config import update

    if env.kind == "random":
        from ..environment.random_scene import random_scene

        scene = random_scene(env.seed, run_config.random_scene)
    elif env.kind == "commonroad":
        from ..environment.commonroad import load_commonroad_scene

        logging.getLogger("commonroad").setLevel(logging.ERROR)
        cfg = run_config.commonroad
        file = str(env.file)
        if file.startswith(_SHIPPED + "/"):
            file = str(shipped_commonroad_dir() / file[len(_SHIPPED) + 1 :])
        if env.seed > 0:  # a start and goal sampled on the road instead of the planning problem
            cfg = update(cfg, {"sample_start_goal": True, "seed": env.seed})
        from ..control.registry import model_set_for_scene
        from ..systems.car import KinematicCar

        scene = load_commonroad_scene(file, cfg, system=KinematicCar(model_set_for_scene(env.kind).car))
    elif env.kind == "ind":
        from ..environment.ind import load_ind_scene

        cfg = update(run_config.ind, {"seed": env.seed, "start_time": env.start_time or 0.0})
        scene = load_ind_scene(env.data_dir, env.recording, cfg)
    else:
        raise ValueError(f"unknown environment kind {env.kind!r}; valid choices: random, commonroad, ind")
    if scene.name != env.name:
        scene = dataclasses.replace(scene, name=env.name)
    return scene


# ------------------------------------------------------------------------------------------------------ the sweep
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
            if v not in _VARIANTS:
                raise ValueError(f"unknown variant {v!r}; valid choices: {', '.join(_VARIANTS)}")
        if not self.variants:
            raise ValueError("a benchmark needs at least one variant")

    @property
    def evaluation(self) -> EvaluationConfig:
        return self.run_config.evaluation

    def variants_of(self, planner: str) -> tuple[str, ...]:
        """Variants run for ``planner`` (single-variant planners: only the first)."""
        if planner in SETTINGS[self.setting].single_variant:
            return self.variants[:1]
        return self.variants


#: run-configuration sections that every record depends on (scenes, scoring, the reported cost)
_COMMON_SECTIONS = ("random_scene", "commonroad", "ind", "evaluation")


def _section_of(planner: str) -> str:
    return _SECTIONS.get(planner) or ("tube_mpc" if planner.startswith("tube_mpc") else planner)


def _config_payload(spec: BenchmarkSpec, planner: str | None = None) -> dict[str, Any]:
    """What the records of ``planner`` depend on (all planners when ``None``): the scene and evaluation sections,
    the reported cost, the planner's own section and, for planners that track a reference with the controller
    (density, search, sampling), the Liouville numerics, the controller, the predictor and their weights. MPC and
    oracle records therefore stay valid when only the learned components change."""
    cfg = to_dict(spec.run_config)
    payload: dict[str, Any] = {"schema": RECORD_SCHEMA, "setting": spec.setting}
    if planner is None:
        payload.update(run_config=cfg, controller=spec.controller, density=spec.density, components=spec.components)
        return payload
    payload.update({k: cfg.get(k) for k in _COMMON_SECTIONS})
    payload["cost"] = (cfg.get("density_planner") or {}).get("cost")
    payload["planner"] = {planner: cfg.get(_section_of(planner))}
    from ..planners.problem import PlanningConfig

    if cfg.get("planning") not in (None, to_dict(PlanningConfig())):  # default time axis: hashes of older records
        payload["planning"] = cfg["planning"]
    if not _plans_from_true_state(planner):
        payload.update(liouville=cfg.get("liouville"), controller=spec.controller, density=spec.density,
                       components=spec.components)
    return payload


def component_digest(*components: Any) -> str:
    """Digest of the state (parameters and buffers) of ``components``: torch modules, or objects holding modules as
    attributes (each module counted once); ``""`` when there is none."""
    h = hashlib.sha256()
    found = False
    seen: set[int] = set()

    def add(module: torch.nn.Module) -> None:
        nonlocal found
        if id(module) in seen:
            return
        seen.add(id(module))
        for name, t in sorted(module.state_dict().items()):
            h.update(name.encode())
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
            found = True

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


@dataclass(frozen=True)
class Job:
    """One planner on one environment, for one or more variants (shipped to a worker)."""

    setting: str
    env: EnvSpec
    planner: str
    variants: tuple[str, ...]
    run_config: Any
    controller: str | None
    density: str | None
    config_hash: str
    #: also return the environment's map for the figures
    want_map: bool = False
    #: the resolved controller / predictor and their digest (recorded)
    components: str = ""

    @property
    def runs(self) -> int:
        return len(self.variants)


@dataclass
class JobResult:
    """What a job returns: its records and, if asked, the environment's map."""

    records: list[dict[str, Any]]
    scene_map: dict[str, Any] | None = None


def _plans_from_true_state(planner: str) -> bool:
    return any(planner == p or planner.startswith(p + "_") for p in _PLANS_FROM_TRUE_STATE)


def record_path(out: str | Path, setting: str, env: str, planner: str, variant: str) -> Path:
    """``DIR/records/<setting>/<env>__<planner>__<variant>.json``."""
    return Path(out) / "records" / setting / f"{env}__{planner}__{variant}.json"


def _map_path(out: str | Path, setting: str, env: str) -> Path:
    return Path(out) / "records" / setting / "maps" / f"{env}.npz"


def make_jobs(spec: BenchmarkSpec, done: set[tuple[str, str, str]] = frozenset(),
              maps_done: set[str] = frozenset()) -> list[Job]:
    """Jobs for every run of ``spec`` not in ``done`` (keys ``(env, planner, variant)``); environment-major."""
    hashes = {p: config_hash(spec, p) for p in spec.planners}
    jobs: list[Job] = []
    for env in spec.envs:
        want_map = env.name not in maps_done
        for planner in spec.planners:
            todo = tuple(v for v in spec.variants_of(planner) if (env.name, planner, v) not in done)
            if not todo:
                continue
            groups = [(v,) for v in todo] if _plans_from_true_state(planner) else [todo]
            for variants in groups:
                jobs.append(Job(spec.setting, env, planner, variants, spec.run_config, spec.controller, spec.density,
                                hashes[planner], want_map=want_map, components=spec.components))
                want_map = False
    return jobs


# ---------------------------------------------------------------------------------------------- worker side
#: per-process caches: planner contexts (controller and predictor loaded once) and the last scenes built
_CONTEXTS: dict[Any, Any] = {}
_SCENES: dict[Any, Any] = {}


def _context(job: Job, parameterization=None):
    from ..control.registry import load_controller, model_set_for_scene
    from ..density.registry import load_predictor
    from ..planners.registry import PlannerContext
    from ..systems.car import KinematicCar

    models = model_set_for_scene(job.env.kind)  # recorded road scenes: the road set; the paper's scenes: paper
    key = (job.controller, job.density, job.run_config.liouville, parameterization, models.name)
    if key not in _CONTEXTS:
        car = KinematicCar(models.car)
        controller = load_controller(job.controller, models=models)
        predictor: list[Any] = []

        def factory():
            if not predictor:
                predictor.append(load_predictor(job.density, car, controller, liouville=job.run_config.liouville,
                                                parameterization=parameterization))
            return predictor[0]

        _CONTEXTS.clear()
        _CONTEXTS[key] = (car, controller, factory)
    car, controller, factory = _CONTEXTS[key]
    return PlannerContext(system=car, controller=controller, config=job.run_config, predictor_factory=factory,
                          exact_factory=None)


def _scene(job: Job):
    key = (job.env, json.dumps(to_dict(job.run_config), sort_keys=True, default=str))
    if key not in _SCENES:
        if len(_SCENES) >= 2:
            _SCENES.pop(next(iter(_SCENES)))
        _SCENES[key] = build_scene(job.env, job.run_config)
    return _SCENES[key]


_SECTIONS = {"density": "density_planner", "mpc": "mpc", "oracle": "oracle", "search": "search",
             "sampling": "sampling"}


def planner_run_config(run_config: Any, planner: str, variant: str | None, seed: int) -> Any:
    """``run_config`` with the planner's section seeded with ``seed`` and, for MPC, the measurement variant set."""
    section = _section_of(planner)
    cfg = getattr(run_config, section, None)
    if cfg is None or not dataclasses.is_dataclass(cfg):
        return run_config
    names = {f.name for f in dataclasses.fields(cfg)}
    changes: dict[str, Any] = {}
    if "seed" in names:
        changes["seed"] = seed
    if "biased_measurement" in names and variant is not None:
        changes["biased_measurement"] = variant == "biased"
    return replace(run_config, **{section: replace(cfg, **changes)}) if changes else run_config


def scene_map_arrays(scene) -> dict[str, Any]:
    """Compact picture of a scene for the figures: time-max occupancy as uint8 (0-255), geometry, start, goal."""
    occ = scene.grid.max_over_time().detach().cpu().float().numpy()
    return {
        "occupancy_u8": np.round(np.clip(occ, 0, 1) * 255).astype(np.uint8),
        "origin": np.asarray(scene.grid.origin, dtype=np.float64),
        "cell_size": np.float64(scene.grid.cell_size),
        "start": np.asarray(scene.start, dtype=np.float64),
        "goal": np.asarray(scene.goal, dtype=np.float64),
        "planning_box": np.asarray(scene.planning_box, dtype=np.float64),
        "name": np.asarray(scene.name),
    }


def _floats(t: torch.Tensor | None) -> list | None:
    return None if t is None else t.detach().cpu().double().tolist()


_PLAN_EXTRAS = ("predictor", "tube_radius", "biased_measurement", "n_failed_steps", "step_status_counts",
                "best_restart", "n_tube_offsets")


def _risk_check(job: Job, problem: PlanningProblem, plan: PlanResult, controller, eval_cfg) -> dict[str, Any]:
    """Monte-Carlo check of the plan's collision probability (risk.validate_samples closed loops)."""
    from .risk_validation import validate_risk

    try:
        check = validate_risk(problem, plan, controller, n=job.run_config.risk.validate_samples,
                              seed=stable_seed("risk-check", job.env.name), config=eval_cfg)
    except ValueError as exc:
        return {"passed": None, "message": str(exc)}
    return check.to_dict()


def _plan_summary(plan: PlanResult | None) -> dict[str, Any] | None:
    if plan is None:
        return None
    return {
        "status": plan.status.value,
        "message": plan.message,
        "params": _floats(plan.params),
        "cost": plan.cost,
        "collision_probability_max": None if plan.collision is None else float(plan.collision.max),
        "collision_probability_se_at_max": None if plan.collision is None or plan.collision.se is None
        else plan.collision.to_dict()["se_at_max"],
        "collision_estimator": None if plan.collision is None else plan.collision.estimator,
        "iterations": plan.iterations,
        "extras": {k: v for k, v in plan.extras.items() if k in _PLAN_EXTRAS},
    }


def _base_record(job: Job, variant: str) -> dict[str, Any]:
    return {
        "schema": RECORD_SCHEMA,
        "setting": job.setting,
        "env": job.env.name,
        "env_spec": job.env.as_dict(),
        "planner": job.planner,
        "variant": variant,
        "config_hash": job.config_hash,
        "controller": job.controller,
        "density": job.density,
        "components": job.components,
        "status": "error",
        "failed": True,
        "failure_reason": "no_solution",
        "failure_flags": {"no_solution": True},
        "message": "",
        "metrics": None,
        "error": None,
        "timings": {},
        "run_info": {"host": socket.gethostname(), "pid": os.getpid()},
    }


def error_record(job: Job, variant: str, error: str, where: str = "run") -> dict[str, Any]:
    """A failure record for a run that raised (``error``: the traceback) or whose worker died."""
    rec = _base_record(job, variant)
    lines = [s for s in error.strip().splitlines() if s.strip()]
    rec["message"] = f"{where} failed: {lines[-1].strip() if lines else 'unknown error'}"
    rec["error"] = error
    rec["config"] = to_dict(job.run_config)
    return rec


def _true_states(
    problem: PlanningProblem, env: EnvSpec, eval_cfg: EvaluationConfig
) -> tuple[torch.Tensor, torch.Tensor]:
    """The run's true initial state ``(nx,)`` and the Monte-Carlo states ``(M_max, nx)``, float64, bias included;
    the same for every planner of the environment."""
    dist = problem.initial_distribution
    x_true = dist.sample(1, torch.Generator().manual_seed(stable_seed("true-state", env.name)),
                         dtype=torch.float64)[0]
    m = max(eval_cfg.mc_samples_tracked, eval_cfg.mc_samples_receding, eval_cfg.mc_samples_open_loop)
    mc = dist.sample(m, torch.Generator().manual_seed(stable_seed("monte-carlo", env.name)),
                     dtype=torch.float64) if m > 0 else torch.zeros(0, dist.dim, dtype=torch.float64)
    return x_true, mc


def _variant_state(x: torch.Tensor, variant: str) -> torch.Tensor:
    x = x.clone()
    if variant != "biased" and x.shape[-1] > BIAS:
        x[..., BIAS] = 0.0
    return x


def _mc_count(mode: ExecutionMode, cfg: EvaluationConfig) -> int:
    return {ExecutionMode.TRACK: cfg.mc_samples_tracked, ExecutionMode.RECEDING: cfg.mc_samples_receding,
            ExecutionMode.OPEN_LOOP: cfg.mc_samples_open_loop}[mode]


def _evaluate(job: Job, variant: str, planner, problem: PlanningProblem, scene, ctx, plan: PlanResult | None,
              x_true: torch.Tensor, mc_states: torch.Tensor, seeds: dict[str, int]) -> dict[str, Any]:
    """Execute one variant and score it."""
    eval_cfg: EvaluationConfig = job.run_config.evaluation
    setting = SETTINGS[job.setting]
    t_start = time.perf_counter()
    rec = _base_record(job, variant)
    rec["seeds"] = seeds
    mode = execution_mode(planner)
    rec["execution"] = mode.value if setting.closed_loop else "planned"
    car = problem.system
    box = evaluation_box(scene, car.config.state_min, car.config.state_max, eval_cfg.position_bounds)
    cost_cfg = job.run_config.density_planner.cost
    plan_dt = problem.parameterization.plan_dt
    x0 = _variant_state(x_true, variant)
    mc0 = _variant_state(mc_states[: _mc_count(mode, eval_cfg)], variant)
    rec["true_state"] = _floats(x0)

    if not setting.closed_loop:  # ablation: the planned reference
        assert plan is not None
        solved = plan.ok and plan.reference is not None
        plan_time = float(plan.timings.get("total", math.nan))
        timeout = plan_time > eval_cfg.plan_time_limit
        metrics = None
        if plan.reference is not None:
            ref = plan.reference
            metrics = run_metrics(scene, ref.x_plan, ref.u_plan, ref.u_plan, box=box, cost_config=cost_cfg,
                                  plan_dt=plan_dt, collision=problem.collision())
            runs = monte_carlo(planner, problem, mc0, plan=plan, controller=ctx.controller, config=eval_cfg)
            metrics.update(monte_carlo_metrics(scene, runs, threshold=eval_cfg.collision_threshold, plan_dt=plan_dt,
                                               collision=problem.collision()))
            rec["trajectory"] = _floats(ref.x_plan)
            rec["verdict"] = record_verdict(scene, ref.x_plan, ref.u_plan, plan, car, plan_dt, job.run_config)
        flags, reason = failure_flags(metrics, solved and not timeout, eval_cfg,
                                      cost_thresholds=eval_cfg.ablation_cost_failures)
        rec.update(status="timeout" if timeout else plan.status.value, metrics=metrics, failed=bool(reason),
                   failure_reason=reason, failure_flags=flags, plan=_plan_summary(plan),
                   message=plan.message if not timeout else f"planning took {plan_time:.0f} s > "
                   f"{eval_cfg.plan_time_limit:g} s")
        rec["timings"] = {"offline": plan_time, "online_per_step": 0.0, "plan": plan.timings,
                          "evaluation": time.perf_counter() - t_start}
        return rec

    run = execute(planner, problem, x0, plan=plan, controller=ctx.controller, config=eval_cfg)
    metrics = None
    if run.states.shape[0] >= 2:
        metrics = run_metrics(scene, run.states, run.planned_inputs, run.applied_inputs, box=box,
                              cost_config=cost_cfg, plan_dt=plan_dt, collision=problem.collision())
        t_mc = time.perf_counter()
        runs = monte_carlo(planner, problem, mc0, plan=plan, controller=ctx.controller, config=eval_cfg)
        metrics.update(monte_carlo_metrics(scene, runs, threshold=eval_cfg.collision_threshold, plan_dt=plan_dt,
                                               collision=problem.collision()))
        t_mc = time.perf_counter() - t_mc
        if job.run_config.risk.validate_samples and mode == ExecutionMode.TRACK and variant == job.variants[0]:
            rec["risk_check"] = _risk_check(job, problem, run.plan, ctx.controller, eval_cfg)
        rec["trajectory"] = _floats(run.states)
        rec["applied_inputs"] = _floats(run.applied_inputs)
        rec["verdict"] = record_verdict(scene, run.states, run.applied_inputs, run.plan, car, plan_dt, job.run_config)
        if mode == ExecutionMode.TRACK and run.plan.reference is not None:
            rec["reference"] = _floats(problem.system.positions(run.plan.reference.x_plan))
    else:
        t_mc = 0.0
    flags, reason = failure_flags(metrics, run.ok, eval_cfg)
    rec.update(status=run.plan.status.value, metrics=metrics, failed=bool(reason), failure_reason=reason,
               failure_flags=flags, message=run.message or run.plan.message, plan=_plan_summary(run.plan))
    steps = run.step_times
    rec["timings"] = {
        "offline": run.offline_time,
        "online_per_step": float(np.mean(steps)) if steps.size else 0.0,
        "online_max_step": float(np.max(steps)) if steps.size else 0.0,
        "online_total": float(np.sum(steps)),
        "plan": run.plan.timings,
        "monte_carlo": t_mc,
        "evaluation": time.perf_counter() - t_start,
    }
    return rec


def run_job(job: Job) -> JobResult:
    """Run one job (in a worker): build the scene, plan, execute every variant, score. Exceptions inside a run
    become failure records with the traceback; the job itself only raises if its worker dies."""
    from ..planners.registry import make_planner

    t_job = time.perf_counter()
    torch.manual_seed(stable_seed("job", job.env.name, job.planner))
    try:
        scene = _scene(job)
        from ..control.registry import model_set_for_scene
        from ..systems.car import KinematicCar

        problem = PlanningProblem.from_scene(scene, seed=job.env.index, planning=job.run_config.planning,
                                             risk=job.run_config.risk,
                                             system=KinematicCar(model_set_for_scene(job.env.kind).car))
        x_true, mc_states = _true_states(problem, job.env, job.run_config.evaluation)
        ctx = _context(job, problem.parameterization)
    except Exception:  # noqa: BLE001 - recorded, the sweep goes on
        tb = traceback.format_exc()
        return JobResult([error_record(job, v, tb, "environment") for v in job.variants])
    scene_map = scene_map_arrays(scene) if job.want_map else None
    seed = stable_seed("planner", job.env.name, job.planner)
    seeds = {"distribution": job.env.index, "true_state": stable_seed("true-state", job.env.name),
             "monte_carlo": stable_seed("monte-carlo", job.env.name), "planner": seed}
    per_variant = _plans_from_true_state(job.planner) and SETTINGS[job.setting].closed_loop
    planner = plan = None
    if not per_variant:  # plan once offline, execute the plan for every variant
        try:
            ctx.config = planner_run_config(job.run_config, job.planner, None, seed)
            planner = make_planner(job.planner, ctx)
            plan = planner.plan(problem)
        except Exception:  # noqa: BLE001 - a planner exception is a recorded failure of every variant
            tb = traceback.format_exc()
            return JobResult([error_record(job, v, tb, "planning") for v in job.variants], scene_map)
    records = []
    for variant in job.variants:
        try:
            if per_variant:
                ctx.config = planner_run_config(job.run_config, job.planner, variant, seed)
                planner = make_planner(job.planner, ctx)
            rec = _evaluate(job, variant, planner, problem, scene, ctx, plan, x_true, mc_states, seeds)
        except Exception:  # noqa: BLE001 - a planner exception is a recorded failure
            rec = error_record(job, variant, traceback.format_exc())
        rec["config"] = to_dict(job.run_config)
        rec["run_info"].update(finished=time.strftime("%Y-%m-%dT%H:%M:%S"), job_wall=time.perf_counter() - t_job)
        records.append(rec)
    return JobResult(records, scene_map)


# ---------------------------------------------------------------------------------------------- parent side
#: record keys that must be strings, and the number-or-null metrics the summary reads
_RECORD_KEYS = ("setting", "env", "planner", "variant", "status")
_SUMMARY_METRICS = ("final_distance", "goal_cost", "collision_cost", "input_cost", "bounds_cost",
                    "collision_probability_max", "mc_collision_mean", "mc_collision_frequency")


def record_problem(record: Any) -> str | None:
    """Why ``record`` (parsed JSON) is not a benchmark record, or ``None`` when it is one."""
    if not isinstance(record, dict):
        return f"a JSON object expected, got {type(record).__name__}"
    missing = [k for k in _RECORD_KEYS if k not in record]
    if missing:
        return f"missing key(s) {missing}"
    bad = [k for k in _RECORD_KEYS if not isinstance(record[k], str) or not record[k]]
    if bad:
        return f"key(s) {bad} must be non-empty strings"
    for key in ("metrics", "timings", "env_spec"):
        if record.get(key) is not None and not isinstance(record[key], dict):
            return f"{key!r} must be an object or null, got {type(record[key]).__name__}"
    for key in _SUMMARY_METRICS:
        v = (record.get("metrics") or {}).get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            return f"metrics.{key} must be a number or null, got {v!r}"
    for key in ("offline", "online_per_step"):
        v = (record.get("timings") or {}).get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            return f"timings.{key} must be a number or null, got {v!r}"
    if not isinstance(record.get("failed", False), bool):
        return f"'failed' must be true or false, got {record['failed']!r}"
    if not isinstance(record.get("failure_reason") or "", str):
        return f"'failure_reason' must be a string, got {record['failure_reason']!r}"
    return None


def _read_json(path: Path) -> dict[str, Any] | None:
    """The record at ``path``, or ``None`` (with a warning) when it is unreadable or not a record."""
    r, problem = _read_record(path)
    if problem:
        log.warning("ignoring %s: %s", path, problem)
    return r


def _read_record(path: Path) -> tuple[dict[str, Any] | None, str | None]:
    try:
        r = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        return None, f"unreadable JSON ({exc})"
    problem = record_problem(r)
    return (None, f"not a benchmark record ({problem})") if problem else (r, None)


@dataclass(frozen=True)
class BadRecord:
    """A record file that could not be used: its path, why, and the run it stands for (from its name)."""

    path: Path
    reason: str
    setting: str
    env: str | None
    planner: str | None
    variant: str | None


def scan_records(out: str | Path, setting: str | None = None) -> tuple[list[dict[str, Any]], list[BadRecord]]:
    """``(records, bad)``: the valid records under ``DIR/records`` (as :func:`load_records`) and the files that are
    unreadable or not records (truncated, ``42``, missing keys, wrong types)."""
    root = Path(out) / "records"
    if not root.is_dir():
        return [], []
    dirs = [root / setting] if setting else sorted(p for p in root.iterdir() if p.is_dir())
    records, bad = [], []
    for d in dirs:
        for p in sorted(d.glob("*.json")):
            r, problem = _read_record(p)
            if problem:
                parts = p.stem.split("__")
                env, planner, variant = parts if len(parts) == 3 else (None, None, None)
                bad.append(BadRecord(p, problem, d.name, env, planner, variant))
                log.warning("ignoring %s: %s", p, problem)
                continue
            records.append(r)
    return _sorted_records(records), bad


def load_records(out: str | Path, setting: str | None = None) -> list[dict[str, Any]]:
    """All valid records under ``DIR/records`` (one setting, or all), sorted by setting, environment index,
    planner, variant; files that are not records are skipped with a warning (:func:`scan_records` lists them)."""
    return scan_records(out, setting)[0]


def _sorted_records(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    order = {name: i for i, name in enumerate(SETTINGS)}

    def key(r: dict[str, Any]) -> tuple:
        index = (r.get("env_spec") or {}).get("index", 0)
        return (order.get(r["setting"], 99), r["setting"], index if isinstance(index, int) else 0, r["env"],
                r["planner"], r["variant"])

    return sorted(records, key=key)


def load_scene_map(out: str | Path, setting: str, env: str) -> dict[str, Any] | None:
    """The map stored for ``env`` (see :func:`scene_map_arrays`), or ``None``."""
    path = _map_path(out, setting, env)
    if not path.is_file():
        return None
    from ..io.npz import read_npz

    return read_npz(path, what="benchmark map")


def identity_view(record: dict[str, Any]) -> dict[str, Any]:
    """The part of a record that must not depend on how or where it ran (no wall times, no provenance)."""
    return {k: v for k, v in record.items() if k not in ("timings", "run_info")}


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
        r = _read_json(p)
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
                    atomic_save_npz(_map_path(out, spec.setting, job.env.name), **result.scene_map)
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

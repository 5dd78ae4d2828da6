"""Plan a scene in one call, the way ``density-planner plan`` does: the Python face of the command.

::

    from density_planner.api import plan_scene

    outcome = plan_scene("commonroad", file="my_scenario.xml")       # or "random", seed=3; "ind", ...
    print(outcome.status, outcome.verdict.reasons, float(outcome.result.collision.max))
    outcome.write("results/mine")        # plan.json, config.toml, solution.xml (CommonRoad), plan.png, costs.png

    run = drive_scene("commonroad", file="my_scenario.xml")         # online: replans from what was observed
    print(run.status, run.summary()["n_replans"]); run.write("results/mine-online")   # run.json, run.png, ...

The steps are also public, for users who change one of them: :func:`load_run_config` (defaults, a TOML file or a
shipped preset, ``KEY=VALUE`` overrides, the ``[system]`` choices), :func:`build_scene` (a scene source with the
run's system for its domain checks), :func:`set_up` (planning problem, models, planner), :func:`judge` (the
verdict against the scene's ground truth, :func:`density_planner.evaluation.verdict.judge_plan`). The command
line runs these same functions, so a plan made here and one made by ``plan`` with the same arguments are the same.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # torch and the models load on first use: importing this module stays cheap
    import torch

    from .environment.scene import Scene
    from .evaluation.online import DriveResult
    from .evaluation.verdict import Verdict
    from .planners.base import PlanResult
    from .planners.context import PlannerContext
    from .planners.problem import PlanningProblem
    from .settings import RunConfig

__all__ = ["load_run_config", "with_system", "build_scene", "default_distribution_seed", "PlanSetup", "set_up",
           "judge", "PlanOutcome", "plan_scene", "write_plan_solution", "write_plan_figures", "drive_config",
           "check_drivable", "DriveOutcome", "drive_scene", "write_run_figures"]


# ------------------------------------------------------------------------------------------------ configuration
def with_system(run_config: RunConfig, *, system: str | None = None, models: str | None = None,
                controller: str | None = None, density: str | None = None) -> RunConfig:
    """``run_config`` with the given ``[system]`` keys replaced (``None``: keep): the system's name, its model set
    (``paper``, ``road``, ``auto``), the tracking controller and the density predictor, as ``--system``,
    ``--models``, ``--controller`` and ``--density`` do."""
    from .config import update

    changes = {key: value for key, value in (("name", system), ("models", models), ("controller", controller),
                                             ("density", density)) if value is not None}
    return update(run_config, {"system": changes}) if changes else run_config


def load_run_config(config: str | Path | None = None, overrides: Sequence[str] = (), **system: str | None
                    ) -> RunConfig:
    """The run configuration: the documented defaults, then the TOML file ``config`` (or a shipped preset such
    as ``"paper"``), then ``overrides`` (``"section.key=value"`` strings, as ``--set``), then the ``[system]``
    keywords of :func:`with_system`. Unknown keys raise :class:`~density_planner.config.ConfigError` naming the
    valid ones."""
    from .config import load_config
    from .settings import RunConfig

    if isinstance(overrides, str):
        raise TypeError("overrides must be a sequence of 'KEY=VALUE' strings, not one string")
    return with_system(load_config(RunConfig, config, list(overrides)), **system)


def _resolve_run_config(run_config: RunConfig | None, config: str | Path | None, overrides: Sequence[str],
                        **system: str | None) -> RunConfig:
    """``run_config`` with the ``[system]`` keywords, or :func:`load_run_config` of ``config`` and ``overrides``
    (not both)."""
    if run_config is None:
        return load_run_config(config, overrides, **system)
    if config is not None or overrides:
        raise ValueError("give either run_config or config / overrides, not both")
    return with_system(run_config, **system)


# ------------------------------------------------------------------------------------------------ the scene
def build_scene(env: str, run_config: RunConfig | None = None, *, seed: int | None = None,
                file: str | Path | None = None, data_dir: str | Path | None = None, recording: int | None = None,
                start_time: float | None = None, raster_threads: int | None = None,
                where: str | None = None, quiet: bool = True) -> Scene:
    """The scene of source ``env`` (``"random"``, ``"ind"``, ``"commonroad"``, ``"file"`` or a registered one)
    built with ``run_config``'s section for it; the domain checks of recorded scenes (start speed, reachable
    region) use the run's system in the model set of that source. ``raster_threads`` (CPU): threads of the
    occupancy grid's upsampling (the same grid for any number; default: as set, 1). ``where``: how errors name the
    source (default ``--env KIND``); ``quiet``: silence commonroad-io's warnings on legacy elements."""
    from .environment.footprints import using_raster_threads
    from .environment.sources import SceneRequest
    from .environment.sources import build_scene as build_from_source
    from .planners.context import run_system

    if seed is not None:
        from .checks import check_seed

        check_seed("seed", seed)
    run_config = run_config if run_config is not None else load_run_config()
    request = SceneRequest(env, seed=seed, file=file, data_dir=data_dir, recording=recording, start_time=start_time)
    system = run_system(run_config, env)
    with using_raster_threads(raster_threads):
        return build_from_source(request, run_config, system=system, where=where, quiet=quiet)


def default_distribution_seed(distribution_seed: int | None, seed: int | None) -> int:
    """The seed of the initial law's draw: ``distribution_seed`` where given, else the scene's ``seed``, else 0 (as
    ``--distribution-seed`` defaults to ``--seed``)."""
    return distribution_seed if distribution_seed is not None else (seed or 0)


# ------------------------------------------------------------------------------------------------ problem, planner
@dataclass
class PlanSetup:
    """What a plan is made from: the scene, its planning problem, the models (``context``) and the planner."""

    scene: Scene
    problem: PlanningProblem
    context: PlannerContext
    planner: Any
    run_config: RunConfig
    #: the scene's source (chooses the model set when ``[system] models = "auto"``)
    kind: str
    #: seed of the initial distribution's draw (the paper's random Gaussian mixture)
    distribution_seed: int
    #: the planner's registered name
    planner_name: str


def set_up(scene: Scene, run_config: RunConfig, *, kind: str, planner: str = "density",
           distribution_seed: int = 0, device: str | torch.device = "cpu", dtype: torch.dtype | None = None,
           progress: bool = False) -> PlanSetup:
    """The planning problem of ``scene`` (horizon, initial law drawn with ``distribution_seed``, risk), the run's
    system, controller and density predictor (loaded now, so that a bad name fails before planning) and the
    registered planner ``planner``."""
    import torch

    from .checks import check_seed
    from .planners.context import build_context, run_system
    from .planners.problem import PlanningProblem
    from .planners.registry import make_planner

    check_seed("distribution_seed", distribution_seed)
    system = run_system(run_config, kind)
    problem = PlanningProblem.from_scene(scene, seed=distribution_seed, planning=run_config.planning,
                                         risk=run_config.risk, system=system)
    context = build_context(run_config, kind=kind, parameterization=problem.parameterization, system=system,
                            device=device, dtype=dtype or torch.float32, progress=progress)
    return PlanSetup(scene, problem, context, make_planner(planner, context), run_config, kind, distribution_seed,
                     planner)


def judge(setup: PlanSetup, result: PlanResult) -> Verdict | None:
    """The verdict on ``result`` (goal in time, collision with the true shapes, road, model box; ``None`` when no
    plan was made), with the run's ``[verdict]`` and ``[evaluation]`` settings."""
    from .evaluation.verdict import judge_plan

    return judge_plan(setup.scene, result, system=setup.problem.system, dt=setup.problem.parameterization.plan_dt,
                      config=setup.run_config.verdict, evaluation=setup.run_config.evaluation)


# ------------------------------------------------------------------------------------------------ the outcome
@dataclass
class _Outcome:
    """What :class:`PlanOutcome` and :class:`DriveOutcome` share: the set-up, the status of the verdict, and the
    set-up's part of the summary and of the files."""

    setup: PlanSetup

    @property
    def scene(self) -> Scene:
        return self.setup.scene

    @property
    def problem(self) -> PlanningProblem:
        return self.setup.problem

    @property
    def status(self) -> str:
        raise NotImplementedError

    @property
    def ok(self) -> bool:
        return self.status == "success"

    def _setup_summary(self) -> dict[str, Any]:
        """The summary's keys that describe the set-up: the scene, the initial law's seed, the density predictor
        and the whole configuration."""
        from .config import to_dict

        setup = self.setup
        return {
            "scene": setup.scene.to_json_dict(),
            "distribution_seed": setup.distribution_seed,
            "density_predictor": getattr(setup.context.predictor(), "name", setup.run_config.system.density),
            "config": to_dict(setup.run_config),
        }

    def _write_summary(self, out: str | Path, name: str, summary: dict[str, Any]) -> tuple[Path, list[Path]]:
        """``summary`` as the JSON file ``name`` and ``config.toml`` into the folder ``out`` (created), each
        written atomically; returns the folder and the paths written."""
        from .config import dumps_toml
        from .io.atomic import atomic_write_json, atomic_write_text

        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_json(out / name, summary)
        atomic_write_text(out / "config.toml", dumps_toml(self.setup.run_config))
        return out, [out / name, out / "config.toml"]


@dataclass
class PlanOutcome(_Outcome):
    """A plan and its verdict (:func:`plan_scene`)."""

    result: PlanResult
    verdict: Verdict | None

    @property
    def status(self) -> str:
        """``"success"`` when the plan passed every part of its verdict, else ``"failed"``."""
        return "failed" if self.verdict is None else self.verdict.status

    def summary(self) -> dict[str, Any]:
        """The content of ``plan.json`` (without the command line's own keys): the planner's result, the verdict,
        the scene, the models and the whole configuration."""
        from .planners.context import run_model_set

        setup = self.setup
        summary = self.result.summary()
        summary.update({
            "status": self.status,
            "planner_status": self.result.status.value,
            "verdict": None if self.verdict is None else self.verdict.to_dict(),
            "controller": type(setup.context.controller).__name__,
            "models": run_model_set(setup.run_config, setup.kind).name,
            **self._setup_summary(),
        })
        return summary

    def body(self):
        """The vehicle's rectangle along the plan, ``(T, 4, 2)`` corners (``None`` without a plan)."""
        states = self.result.states
        return None if states is None else self.problem.collision().outline(states.detach().cpu()).numpy()

    def write_solution(self, path: str | Path) -> Path:
        """A CommonRoad solution file of the plan (CommonRoad scenes only; ``[solution]``'s vehicle model and
        cost function)."""
        if self.setup.kind != "commonroad":
            raise ValueError(f"a solution file needs a CommonRoad scene, not a {self.setup.kind!r} one")
        if self.result.states is None:
            raise ValueError(f"no plan to write: {self.result.message or self.result.status.value}")
        path = Path(path)
        write_plan_solution(path, self.scene, self.result, self.problem, self.setup.run_config)
        return path

    def write(self, out: str | Path, *, figures: bool = True, gif: bool = False) -> list[Path]:
        """``plan.json``, ``config.toml``, on CommonRoad scenes ``solution.xml``, and with ``figures`` plan.png,
        costs.png (and plan.gif with ``gif``) into the folder ``out`` (created); each file written atomically.
        Returns the paths written."""
        out, written = self._write_summary(out, "plan.json", self.summary())
        if self.result.states is None:
            return written
        if self.setup.kind == "commonroad":
            written.append(self.write_solution(out / "solution.xml"))
        if figures:
            written += [out / name for name in write_plan_figures(out, self.scene, self.result, self.verdict,
                                                                    gif=gif, body=self.body())]
        return written


def plan_scene(env: str = "random", *, seed: int | None = None, file: str | Path | None = None,
               data_dir: str | Path | None = None, recording: int | None = None, start_time: float | None = None,
               planner: str = "density", config: str | Path | None = None, overrides: Sequence[str] = (),
               run_config: RunConfig | None = None, system: str | None = None, models: str | None = None,
               controller: str | None = None, density: str | None = None, distribution_seed: int | None = None,
               device: str | torch.device = "cpu", dtype: torch.dtype | None = None, processes: int = 1,
               progress: bool = False) -> PlanOutcome:
    """Build the scene, plan it with ``planner`` and judge the plan: ``density-planner plan`` without its files.

    Args:
        env, seed, file, data_dir, recording, start_time: the scene (as ``--env`` and its flags).
        planner: a registered planner (``density``, ``mpc``, ``oracle``, ...).
        config, overrides: a TOML file or preset and ``KEY=VALUE`` strings (:func:`load_run_config`); or
            ``run_config`` itself (then neither may be given).
        system, models, controller, density: the ``[system]`` choices (:func:`with_system`).
        distribution_seed: seed of the initial law's draw (default: ``seed``, else 0, as the command).
        processes: CPU processes for the exact re-check of a learned prediction (2: as the command, the same
            figures; needs ``fork``).

    Returns:
        a :class:`PlanOutcome` (``.result``, ``.verdict``, ``.status``, ``.write(out)``).
    """
    from .density.split import using_prediction_processes

    cfg = _resolve_run_config(run_config, config, overrides, system=system, models=models, controller=controller,
                              density=density)
    scene = build_scene(env, cfg, seed=seed, file=file, data_dir=data_dir, recording=recording,
                        start_time=start_time)
    setup = set_up(scene, cfg, kind=env, planner=planner,
                   distribution_seed=default_distribution_seed(distribution_seed, seed),
                   device=device, dtype=dtype, progress=progress)
    with using_prediction_processes(processes if setup.context.device.type == "cpu" and processes > 1 else None):
        result = setup.planner.plan(setup.problem)
    return PlanOutcome(setup, result, judge(setup, result))


# ------------------------------------------------------------------------------------------------ online
def drive_config(run_config: RunConfig, kind: str, *, prediction: str | None = None,
                 period: float | None = None) -> RunConfig:
    """``run_config`` for driving a scene of source ``kind`` online: ``prediction`` (``"observed"`` or
    ``"oracle"``) and ``period`` [s] set in ``[online]`` where given, and a scene long enough for the run plus one
    planning horizon (random scenes: more slices; CommonRoad: the grid covers ``online.max_duration``, and the whole
    run plus a horizon for an oracle read over full horizons)."""
    import math

    from .config import update
    from .planners.problem import DEFAULT_HORIZON

    changes: dict[str, Any] = {}
    if prediction is not None:
        changes["prediction"] = {"kind": prediction}
    if period is not None:
        changes["period"] = period
    if changes:
        run_config = update(run_config, {"online": changes})
    online = run_config.online
    horizon = run_config.planning.horizon or min(run_config.planning.max_horizon, DEFAULT_HORIZON)
    if kind == "random":
        dt = getattr(run_config.random_scene, "dt", 0.1)
        length = min(online.duration or horizon, online.max_duration)
        need = int(math.ceil((length + horizon) / dt - 1e-9)) + 1
        if run_config.random_scene.n_slices < need:
            run_config = update(run_config, {"random_scene": {"n_slices": need}})
    if kind == "commonroad":
        cr = run_config.commonroad
        cfg: dict[str, Any] = {"max_horizon": max(cr.max_horizon, online.max_duration)}
        if online.prediction.kind == "oracle" and not online.shrink_horizon:
            # replans over a full horizon from every time read the oracle up to the run's end plus one horizon (with
            # online.shrink_horizon they end with the goal, which the scene's grid covers: no longer, coarser grid)
            cfg["min_duration"] = max(cr.min_duration, online.max_duration + horizon)
        run_config = update(run_config, {"commonroad": cfg})
    return run_config


def check_drivable(planner: str, where: str = "planner") -> None:
    """Refuse a planner that already runs step by step from the true state (MPC): it has no plan to replan."""
    from .planners.registry import ExecutionMode, planner_info

    if planner_info(planner).execution == ExecutionMode.RECEDING:
        raise ValueError(f"{where} {planner}: this planner already runs step by step (receding horizon) from the "
                         "true state; compare it with `density-planner bench commonroad`")


@dataclass
class DriveOutcome(_Outcome):
    """An online run (:func:`drive_scene`): the set-up and the :class:`~density_planner.evaluation.online.
    DriveResult` (executed states, every replan, the verdict of the executed trajectory)."""

    result: DriveResult

    @property
    def verdict(self) -> Verdict:
        assert self.result.verdict is not None  # drive() judges every run
        return self.result.verdict

    @property
    def status(self) -> str:
        return self.verdict.status

    def summary(self) -> dict[str, Any]:
        """The content of ``run.json`` (without the command line's own keys)."""
        initial = self.result.initial_plan
        summary = self.result.summary()
        summary.update({
            "planner": self.setup.planner_name,
            "initial_plan": None if initial is None else {
                "status": initial.status.value, "timings": initial.timings,
                "collision_probability_max": None if initial.collision is None else float(initial.collision.max)},
            **self._setup_summary(),
        })
        return summary

    def write(self, out: str | Path, *, figures: bool = True, gif: bool = False) -> list[Path]:
        """``run.json``, ``config.toml`` and with ``figures`` run.png (and run.gif with ``gif``) into ``out``."""
        out, written = self._write_summary(out, "run.json", self.summary())
        return written + ([out / n for n in write_run_figures(out, self.scene, self.result, gif=gif)]
                          if figures else [])


def drive_scene(env: str = "random", *, seed: int | None = None, file: str | Path | None = None,
                planner: str = "density", prediction: str | None = None, period: float | None = None,
                config: str | Path | None = None, overrides: Sequence[str] = (), run_config: RunConfig | None = None,
                system: str | None = None, models: str | None = None, controller: str | None = None,
                density: str | None = None, distribution_seed: int | None = None, device: str | torch.device = "cpu",
                dtype: torch.dtype | None = None, progress: Any = None) -> DriveOutcome:
    """Drive a scene online, as ``density-planner drive`` does without its files: the true vehicle drawn from the
    initial law, a replan every ``period`` from the measurement with the ``prediction`` (``"observed"``: built
    only from what was seen so far, the default on recorded traffic; ``"oracle"``: the recorded future), the
    executed trajectory judged against the ground truth. ``progress(t, replan_record)`` is called after each
    replan. The other arguments are :func:`plan_scene`'s."""
    from .evaluation.online import drive

    check_drivable(planner)
    cfg = _resolve_run_config(run_config, config, overrides, system=system, models=models, controller=controller,
                              density=density)
    cfg = drive_config(cfg, env, prediction=prediction, period=period)
    scene = build_scene(env, cfg, seed=seed, file=file)
    setup = set_up(scene, cfg, kind=env, planner=planner,
                   distribution_seed=default_distribution_seed(distribution_seed, seed),
                   device=device, dtype=dtype)
    result = drive(scene, setup.planner, setup.context.controller, system=setup.problem.system, config=cfg.online,
                   planning=cfg.planning, risk=cfg.risk, evaluation=cfg.evaluation, verdict_config=cfg.verdict,
                   distribution_seed=setup.distribution_seed, progress=progress)
    return DriveOutcome(setup, result)


def write_run_figures(out: str | Path, scene: Scene, result: DriveResult, *, gif: bool = True) -> list[str]:
    """run.png (and run.gif) of an online run; returns the names written."""
    from .viz.online import animate_run, plot_run

    out = Path(out)
    plot_run(scene, result, out / "run.png")
    written = ["run.png"]
    if gif:
        animate_run(scene, result, out / "run.gif")
        written.append("run.gif")
    return written


# ------------------------------------------------------------------------------------------------ files
def write_plan_solution(path, scene, result, problem, run_config) -> None:
    """``solution.xml`` of a plan on a CommonRoad scene (vehicle model and cost function of ``[solution]``)."""
    from .evaluation.verdict import plan_inputs
    from .io.commonroad_solution import write_solution

    meta = scene.meta
    scenario_dt = float(meta.get("scenario_dt") or problem.parameterization.plan_dt)
    road = getattr(scene, "road", None)
    t_start = float(road.t_start) if road is not None else float(scene.grid.t0)
    pp = meta.get("planning_problem")
    write_solution(path, result.states, plan_inputs(result), problem.parameterization.plan_dt,
                   scenario_id=str(meta.get("scenario_id") or scene.name),
                   planning_problem_id=int(pp) if pp is not None and int(pp) >= 0 else 0,
                   scenario_dt=scenario_dt, initial_time_step=int(round(t_start / scenario_dt)),
                   config=run_config.solution, state_names=problem.system.state_names, system=problem.system,
                   computation_time=result.timings.get("total"),
                   frame_offset=tuple(meta.get("frame_offset") or (0.0, 0.0)))


def write_plan_figures(out, scene, result, verdict, *, gif: bool = True, clock: Any = None,
                       body=None) -> list[str]:
    """plan.png (with the verdict), plan.gif and costs.png of a plan; returns the names written. ``clock``: an
    object whose ``lap(name)`` is called after each step (the command's timings).

    The GIF and costs.png are drawn by two forked child processes while this one draws plan.png (where ``fork``
    exists; else in turn): the three figures (~0.45, ~0.4 and ~0.2 s on a suite scene) share the cores, and the
    wall time holds about their sum over the cores, not plan.png's time plus whichever figure follows it."""
    import multiprocessing as mp

    from .viz.plan import animate_plan, plot_costs, plot_plan

    def lap(name: str) -> None:
        if clock is not None:
            clock.lap(name)

    out = Path(out)
    states = result.states.detach().cpu().numpy()
    sx = slx = None
    if result.samples is not None:
        sx = result.samples.x.detach().cpu().numpy()
        slx = result.samples.log_rho.detach().cpu().numpy()
    p_max = float(result.collision.max) if result.collision is not None else float("nan")
    title = (f"{scene.name}: {result.planner}, P_coll max {p_max:.3f}, "
             f"{result.timings.get('total', float('nan')):.1f} s")
    label = "reference" if result.reference is not None else "executed (nominal model)"
    written = []
    # figures drawn beside plan.png, each by a forked child: (file name, lap name, draw)
    beside = []
    if gif:
        beside.append(("plan.gif", "gif", lambda: animate_plan(scene, states, out / "plan.gif", samples_x=sx,
                                                               samples_log_rho=slx)))
    if result.cost_history:
        beside.append(("costs.png", "costs_png", lambda: plot_costs(result.cost_history, out / "costs.png",
                                                                    title=f"{result.planner}: cost per iteration")))
    children = []
    if beside and "fork" in mp.get_all_start_methods():
        ctx = mp.get_context("fork")
        for name, _, draw in beside:
            child = ctx.Process(target=_run_quietly, args=(draw,), daemon=True)
            child.start()
            children.append((name, child))
    plot_plan(scene, states, out / "plan.png", samples_x=sx, samples_log_rho=slx, title=title, label=label,
              verdict=verdict, body=body)
    written.append("plan.png")
    lap("plan_png")
    if not children:
        for _, name, draw in beside:
            draw()
            lap(name)
    else:
        for _, child in children:
            child.join()
        lap("child_wait")
        failed = [(name, child.exitcode) for name, child in children if child.exitcode != 0]
        if failed:
            names = " and ".join(f"{out / name} (exit code {code})" for name, code in failed)
            raise RuntimeError(f"drawing {names} failed" + ("; rerun with --no-gif" if gif else ""))
    written += [name for name, _, _ in beside]
    return written


def _run_quietly(draw) -> None:
    """Target of a figure's process: started as every forked helper is (:func:`~density_planner.parallel.enter_child`:
    one torch thread, the inherited heap frozen, Ctrl-C the parent's), then ``draw()``."""
    from .parallel import enter_child

    enter_child(threads=1)
    draw()

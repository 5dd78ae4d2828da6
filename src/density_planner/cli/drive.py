"""``density-planner drive``: drive a scene online (receding horizon: replan every period from the measurement with
the current prediction) and judge the executed trajectory against the ground truth."""

from __future__ import annotations

import argparse
import math

from ._common import (
    add_config,
    add_device,
    add_out,
    add_progress,
    add_system,
    apply_system_args,
    check_out,
    out_dir,
    show_progress,
)
from ._scenes import add_scene_args, scene_from_args


def register(sub: argparse._SubParsersAction, groups: dict) -> None:
    p = sub.add_parser(
        "drive",
        help="drive a scene online: replan every period from the measurement with the current prediction",
        description="Drive the true vehicle (drawn from the initial distribution) through a scene: the first plan "
        "is the offline plan; every online.period seconds the planner replans from the current measurement (the "
        "initial law re-centred on it) with the current occupancy prediction (observed-only on recorded traffic, "
        "or the oracle), warm-started from the shifted previous plan; a replan that overruns online.time_budget is "
        "tracked once it has finished (online.overrun), a failed one falls back to the previous reference or a "
        "least-risk braking manoeuvre. Writes DIR/run.json (per replan: time, wall "
        "time, status, P_coll, fallback; the executed trajectory and its verdict against the ground truth), "
        "DIR/run.png, DIR/run.gif and DIR/config.toml. Exit code 0: the executed trajectory passed its verdict; "
        "3: it failed it; 2: bad input.",
    )
    add_scene_args(p, kinds=("random", "commonroad", "file"))
    p.add_argument("--planner", default="density", metavar="NAME",
                   help="planner (density: warm-started stage-2 replans; other reference planners: full replans)")
    p.add_argument("--distribution-seed", type=int, default=None, metavar="S",
                   help="seed of the initial distribution (default: --seed)")
    p.add_argument("--prediction", default=None, choices=("observed", "oracle"),
                   help="occupancy the replans read: observed (built only from what was seen so far; default) or "
                        "oracle (the recorded future, known in advance: the paper's setting); sets "
                        "online.prediction.kind")
    p.add_argument("--period", type=float, default=None, metavar="S",
                   help="replanning period [s] (online.period; default 0: one input segment, 1 s)")
    add_system(p)
    add_config(p, example="online.replan_epochs=5")
    add_device(p)
    p.add_argument("--no-gif", action="store_true", help="skip run.gif")
    add_progress(p)
    add_out(p)
    p.set_defaults(func=run, fast_exit=True)


def _scene_for_drive(args, run_config):
    """The scene, long enough for the run plus one planning horizon (random scenes: more slices; CommonRoad: the
    grid covers the goal's time interval, and the oracle's windows past it, when asked for)."""
    from ..config import update
    from ..planners.problem import DEFAULT_HORIZON

    online = run_config.online
    horizon = run_config.planning.horizon or min(run_config.planning.max_horizon, DEFAULT_HORIZON)
    if args.kind == "random":
        dt = run_config.random_scene.dt if hasattr(run_config.random_scene, "dt") else 0.1
        length = min(online.duration or horizon, online.max_duration)
        need = int(math.ceil((length + horizon) / dt - 1e-9)) + 1
        if run_config.random_scene.n_slices < need:
            run_config = update(run_config, {"random_scene": {"n_slices": need}})
    if args.kind == "commonroad":
        cr = run_config.commonroad
        cfg = {"max_horizon": max(cr.max_horizon, online.max_duration)}
        if online.prediction.kind == "oracle" and not online.shrink_horizon:
            # replans over a full horizon from every time read the oracle up to the run's end plus one horizon (with
            # online.shrink_horizon they end with the goal, which the scene's grid covers: no longer, coarser grid)
            cfg["min_duration"] = max(cr.min_duration, online.max_duration + horizon)
        run_config = update(run_config, {"commonroad": cfg})
    return scene_from_args(args, run_config, both_cores=True), run_config


def run(args: argparse.Namespace) -> int:
    import time

    from ..checks import check_seed
    from ..config import dumps_toml, load_config, to_dict, update
    from ..evaluation.online import drive
    from ..io.atomic import atomic_write_json, atomic_write_text
    from ..planners.context import run_system
    from ..planners.problem import PlanningProblem
    from ..planners.registry import ExecutionMode, make_planner, planner_info
    from ..settings import RunConfig
    from ._common import context_from_args
    from .plan import versions

    check_out(args.out)
    if args.distribution_seed is not None:
        check_seed("--distribution-seed", args.distribution_seed)
    run_config = apply_system_args(args, load_config(RunConfig, args.config, args.overrides))
    changes = {}
    if args.prediction is not None:
        changes["prediction"] = {"kind": args.prediction}
    if args.period is not None:
        changes["period"] = args.period
    if changes:
        run_config = update(run_config, {"online": changes})
    if planner_info(args.planner).execution == ExecutionMode.RECEDING:
        raise ValueError(f"--planner {args.planner}: this planner already runs step by step (receding horizon) from "
                         "the true state; compare it with `density-planner bench commonroad`")
    t0 = time.perf_counter()
    scene, run_config = _scene_for_drive(args, run_config)
    t_scene = time.perf_counter() - t0
    dist_seed = args.distribution_seed if args.distribution_seed is not None else (args.seed or 0)
    system = run_system(run_config, args.kind)
    problem = PlanningProblem.from_scene(scene, seed=dist_seed, planning=run_config.planning, risk=run_config.risk,
                                         system=system)
    ctx = context_from_args(args, run_config, progress=show_progress(args), parameterization=problem.parameterization,
                            system=system)
    planner = make_planner(args.planner, ctx)
    out = out_dir(args.out)
    atomic_write_text(out / "config.toml", dumps_toml(run_config))
    verbose = show_progress(args)

    def progress(t, rec):
        if verbose:
            fb = f", fallback {rec.fallback}" if rec.fallback else ""
            print(f"  t = {t:5.1f} s: {rec.status} in {rec.wall_time:.2f} s, P_coll {rec.p_coll:.3f}{fb}", flush=True)

    result = drive(scene, planner, ctx.controller, system=system, config=run_config.online,
                   planning=run_config.planning, risk=run_config.risk, evaluation=run_config.evaluation,
                   verdict_config=run_config.verdict, distribution_seed=dist_seed, progress=progress)
    summary = result.summary()
    initial = result.initial_plan
    summary.update({
        "scene": scene.to_json_dict(),
        "scene_build_time_s": t_scene,
        "planner": args.planner,
        "distribution_seed": dist_seed,
        "density_predictor": getattr(ctx.predictor(), "name", run_config.system.density),
        "initial_plan": None if initial is None else {
            "status": initial.status.value, "timings": initial.timings,
            "collision_probability_max": None if initial.collision is None else float(initial.collision.max)},
        "config": to_dict(run_config),
        "versions": versions(),
        "command": "density-planner " + " ".join(getattr(args, "argv", []) or []),
    })
    atomic_write_json(out / "run.json", summary)
    from ..viz.online import animate_run, plot_run

    written = ["run.json", "config.toml"]
    plot_run(scene, result, out / "run.png")
    written.append("run.png")
    if not args.no_gif:
        animate_run(scene, result, out / "run.gif")
        written.append("run.gif")
    v = result.verdict
    assert v is not None  # drive() judges every run
    n_fb = summary["n_fallbacks"]
    med = summary["replan_wall_time_median"]
    late = summary["n_tracked_late"]
    late_text = f", {late} tracked late (online.overrun = delay)" if late else ""
    print(f"{args.planner} online ({result.prediction} prediction) on {scene.name}: {v.summary()}; "
          f"{summary['n_replans']} replans (median {math.nan if med is None else med:.3f} s){late_text}, {n_fb} "
          f"fallbacks; wrote {', '.join(str(out / w) for w in written)}")
    from . import plan_exit_code

    return plan_exit_code(v)


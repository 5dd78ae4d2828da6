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
    resolve_device,
    resolve_dtype,
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


def run(args: argparse.Namespace) -> int:
    """``density-planner drive``: :func:`density_planner.api.drive_config`, the scene, :func:`~density_planner.api.
    set_up` and :func:`~density_planner.evaluation.online.drive`, as :func:`density_planner.api.drive_scene`, then
    the files."""
    import time

    from ..api import (
        DriveOutcome,
        check_drivable,
        default_distribution_seed,
        drive_config,
        set_up,
        write_run_figures,
    )
    from ..checks import check_seed
    from ..config import dumps_toml, load_config
    from ..evaluation.online import drive
    from ..io.atomic import atomic_write_json, atomic_write_text
    from ..settings import RunConfig
    from .plan import versions

    check_out(args.out)
    if args.distribution_seed is not None:
        check_seed("--distribution-seed", args.distribution_seed)
    run_config = apply_system_args(args, load_config(RunConfig, args.config, args.overrides))
    run_config = drive_config(run_config, args.kind, prediction=args.prediction, period=args.period)
    check_drivable(args.planner, "--planner")
    t0 = time.perf_counter()
    scene = scene_from_args(args, run_config, both_cores=True)
    t_scene = time.perf_counter() - t0
    dist_seed = default_distribution_seed(args.distribution_seed, args.seed)
    setup = set_up(scene, run_config, kind=args.kind, planner=args.planner, distribution_seed=dist_seed,
                   device=resolve_device(args.device), dtype=resolve_dtype(args.dtype),
                   progress=show_progress(args))
    out = out_dir(args.out)
    atomic_write_text(out / "config.toml", dumps_toml(run_config))
    verbose = show_progress(args)

    def progress(t, rec):
        if verbose:
            fb = f", fallback {rec.fallback}" if rec.fallback else ""
            print(f"  t = {t:5.1f} s: {rec.status} in {rec.wall_time:.2f} s, P_coll {rec.p_coll:.3f}{fb}", flush=True)

    result = drive(scene, setup.planner, setup.context.controller, system=setup.problem.system,
                   config=run_config.online, planning=run_config.planning, risk=run_config.risk,
                   evaluation=run_config.evaluation, verdict_config=run_config.verdict, distribution_seed=dist_seed,
                   progress=progress)
    outcome = DriveOutcome(setup, result)
    summary = outcome.summary()
    summary.update({
        "scene_build_time_s": t_scene,
        "versions": versions(),
        "command": "density-planner " + " ".join(getattr(args, "argv", []) or []),
    })
    atomic_write_json(out / "run.json", summary)
    written = ["run.json", "config.toml"] + write_run_figures(out, scene, result, gif=not args.no_gif)
    v = outcome.verdict
    n_fb = summary["n_fallbacks"]
    med = summary["replan_wall_time_median"]
    pred = summary["prediction_time_median"]
    late = summary["n_tracked_late"]
    late_text = f", {late} tracked late (online.overrun = delay)" if late else ""
    warm = summary["warm_replan_wall_time_median"]
    n_rescued = sum(summary["rescues"].values())
    warm_text = (f"; {summary['n_warm_replans']} warm without a rescue: median {warm:.3f} s"
                 if warm is not None and summary["n_warm_replans"] < summary["n_replans"] else "")
    rescue_text = f", {n_rescued} rescued" if n_rescued else ""
    print(f"{args.planner} online ({result.prediction} prediction) on {scene.name}: {v.summary()}; "
          f"{summary['n_replans']} replans (median {math.nan if med is None else med:.3f} s{warm_text}, its "
          f"prediction {math.nan if pred is None else pred:.3f} s){rescue_text}{late_text}, {n_fb} "
          f"fallbacks; wrote {', '.join(str(out / w) for w in written)}")
    from . import plan_exit_code

    return plan_exit_code(v)

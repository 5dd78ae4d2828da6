"""``density-planner plan``: plan in a scene and write the plan, its figures and the effective configuration."""

from __future__ import annotations

import argparse
import time

from ._common import (
    add_config,
    add_controller,
    add_device,
    add_out,
    check_out,
    out_dir,
    resolve_device,
    resolve_dtype,
)
from ._scenes import add_scene_args, scene_from_args


def register(sub: argparse._SubParsersAction, groups: dict) -> None:
    from ..planners.registry import planner_help

    helps = "; ".join(f"{k}: {v}" for k, v in planner_help().items())
    p = sub.add_parser(
        "plan",
        help="plan a motion in a scene (the main job)",
        description="Build a scene, plan with the chosen planner and write DIR/plan.json (parameters, costs, "
        "collision probability, timings, configuration, versions), DIR/plan.png, DIR/plan.gif, DIR/costs.png and "
        "DIR/config.toml (the effective configuration; pass it back with --config to reproduce the run).",
    )
    add_scene_args(p)
    p.add_argument("--planner", default="density", metavar="NAME", help=f"planner ({helps})")
    p.add_argument("--density", default=None, metavar="NAME",
                   help="density predictor of the density planner: exact (Liouville) or a learned one")
    p.add_argument("--distribution-seed", type=int, default=None, metavar="S",
                   help="seed of the random initial distribution (default: --seed)")
    add_controller(p)
    p.add_argument("--models", default=None, metavar="SET",
                   help="model set (car domain, controller and density weights): paper or road (default: by scene "
                        "kind, road for recorded road scenes, paper for the paper's random scenes)")
    add_config(p)
    add_device(p)
    p.add_argument("--no-gif", action="store_true", help="skip plan.gif")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    add_out(p)
    p.set_defaults(func=run)


def build_context(args: argparse.Namespace, run_config, progress: bool, parameterization=None):
    """Planner context (system, controller, predictor factories) from the command-line arguments; a learned
    predictor must fit ``parameterization`` (the plan's horizon) when given. The model set (car domain, controller
    and density weights) follows the scene kind unless ``--models`` names one."""
    from ..control.registry import load_controller, model_set_for_scene
    from ..density.liouville import ExactLiouville
    from ..density.registry import load_predictor
    from ..planners.registry import PlannerContext
    from ..systems.car import KinematicCar

    device, dtype = resolve_device(args.device), resolve_dtype(args.dtype)
    models = model_set_for_scene(getattr(args, "kind", None), getattr(args, "models", None))
    car = KinematicCar(models.car)
    controller = load_controller(args.controller, models=models).to(device=device, dtype=dtype)
    # None: the default learned predictor if it was trained for this controller, else exact Liouville
    predictor = load_predictor(args.density, car, controller, liouville=run_config.liouville,
                               parameterization=parameterization)
    if hasattr(predictor, "to"):
        predictor = predictor.to(device=device, dtype=dtype)
    return PlannerContext(
        system=car,
        controller=controller,
        config=run_config,
        predictor_factory=lambda: predictor,
        exact_factory=None if isinstance(predictor, ExactLiouville) else (
            lambda: ExactLiouville(car, controller, run_config.liouville)),
        device=device,
        dtype=dtype,
        progress=progress,
    )


def versions() -> dict[str, str]:
    """Versions of the package and its main dependencies (written next to results)."""
    import platform
    import sys

    import numpy
    import torch

    from .. import __version__

    out = {"density_planner": __version__, "python": sys.version.split()[0], "torch": torch.__version__,
           "numpy": numpy.__version__, "platform": platform.platform()}
    try:
        import casadi

        out["casadi"] = casadi.__version__
    except ImportError:
        pass
    return out


def run(args: argparse.Namespace) -> int:
    from ..checks import check_seed
    from ..config import dumps_toml, load_config, to_dict
    from ..io.atomic import atomic_write_json, atomic_write_text
    from ..planners.problem import PlanningProblem
    from ..planners.registry import make_planner
    from ..settings import RunConfig

    check_out(args.out)
    if args.distribution_seed is not None:
        check_seed("--distribution-seed", args.distribution_seed)
    run_config = load_config(RunConfig, args.config, args.overrides)
    t0 = time.perf_counter()
    scene = scene_from_args(args, run_config)
    t_scene = time.perf_counter() - t0
    dist_seed = args.distribution_seed if args.distribution_seed is not None else (args.seed or 0)
    from ..control.registry import model_set_for_scene
    from ..systems.car import KinematicCar

    system = KinematicCar(model_set_for_scene(args.kind, getattr(args, "models", None)).car)
    problem = PlanningProblem.from_scene(scene, seed=dist_seed, planning=run_config.planning, system=system)
    ctx = build_context(args, run_config, progress=not args.quiet, parameterization=problem.parameterization)
    planner = make_planner(args.planner, ctx)
    out = out_dir(args.out)  # inputs are valid: only now create the output directory
    result = planner.plan(problem)

    atomic_write_text(out / "config.toml", dumps_toml(run_config))
    summary = result.summary()
    summary.update({
        "scene": scene.to_json_dict(),
        "scene_build_time_s": t_scene,
        "distribution_seed": dist_seed,
        "controller": type(ctx.controller).__name__,
        "models": getattr(getattr(ctx.controller, "car", None), "domain", None),
        "density_predictor": getattr(ctx.predictor(), "name", args.density or "default"),
        "config": to_dict(run_config),
        "versions": versions(),
        "command": "density-planner " + " ".join(getattr(args, "argv", []) or []),
    })
    atomic_write_json(out / "plan.json", summary)
    written = ["plan.json", "config.toml"]
    if result.states is not None:
        from ..viz.plan import animate_plan, plot_costs, plot_plan

        states = result.states.detach().cpu().numpy()
        sx = slx = None
        if result.samples is not None:
            sx = result.samples.x.detach().cpu().numpy()
            slx = result.samples.log_rho.detach().cpu().numpy()
        p_max = float(result.collision.max) if result.collision is not None else float("nan")
        title = (f"{scene.name}: {result.planner} ({result.status.value}), P_coll max {p_max:.3f}, "
                 f"{result.timings.get('total', float('nan')):.1f} s")
        label = "reference" if result.reference is not None else "executed (nominal model)"
        plot_plan(scene, states, out / "plan.png", samples_x=sx, samples_log_rho=slx, title=title, label=label)
        written.append("plan.png")
        if not args.no_gif:
            animate_plan(scene, states, out / "plan.gif", samples_x=sx, samples_log_rho=slx)
            written.append("plan.gif")
        if result.cost_history:
            plot_costs(result.cost_history, out / "costs.png", title=f"{result.planner}: cost per iteration")
            written.append("costs.png")
    dist = float("nan")
    if result.states is not None:
        gx, gy = scene.goal
        dist = float(((result.states[-1, 0] - gx) ** 2 + (result.states[-1, 1] - gy) ** 2).sqrt())
    print(f"{result.planner} on {scene.name}: {result.status.value}; final distance to goal {dist:.2f} m; "
          f"collision probability max "
          f"{float(result.collision.max) if result.collision is not None else float('nan'):.3f}; "
          f"planning time {result.timings.get('total', float('nan')):.2f} s; wrote "
          f"{', '.join(str(out / w) for w in written)}")
    if not result.ok:
        print(f"density-planner: planning {result.status.value}: {result.message}", flush=True)
        return 1
    return 0

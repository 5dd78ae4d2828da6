"""``density-planner validate risk``: check a plan's reported collision probability against Monte Carlo."""

from __future__ import annotations

import argparse
import time

from ._common import add_config, add_device, add_out, add_progress, add_system, apply_system_args, out_dir
from ._scenes import add_scene_args, scene_from_args


def register(sub: argparse._SubParsersAction, groups: dict) -> None:
    from . import group

    validate = group(sub, groups, "validate")
    p = validate.add_parser(
        "risk",
        help="check a plan's collision probability against Monte Carlo",
        description="Plan in a scene (a tracked-reference planner: density, search, sampling), draw N initial "
        "states from the planner's initial distribution, simulate their closed loops exactly (batched) and compare "
        "the Monte-Carlo collision probability per time step with the planner's estimate, in units of the "
        "combined standard error. Writes DIR/risk_report.json (passed = every step within --threshold sigma), "
        "DIR/risk.png and DIR/config.toml. Exit code 0 when the check passes, 1 when it fails.",
    )
    add_scene_args(p)
    p.add_argument("--planner", default="density", metavar="NAME",
                   help="planner whose reference is tracked (density, search, sampling; default density)")
    p.add_argument("--distribution-seed", type=int, default=None, metavar="S",
                   help="seed of the random initial distribution (default: --seed)")
    p.add_argument("--samples", type=int, default=10_000, metavar="N",
                   help="Monte-Carlo initial states (default 10000)")
    p.add_argument("--mc-seed", type=int, default=12345, metavar="S", help="seed of the Monte-Carlo states")
    p.add_argument("--threshold", type=float, default=3.0, metavar="SIGMA",
                   help="largest accepted |difference| in combined standard errors (default 3)")
    p.add_argument("--calibration-samples", type=int, default=2_000, metavar="N",
                   help="recorded road scenes (--env commonroad): closed loops of the calibration check of the "
                   "occupancy model, predicted road-user risk against true-shape hits (risk_report.json "
                   "'calibration', calibration.png; default 2000, 0 = off)")
    add_system(p)
    add_config(p)
    add_device(p)
    add_progress(p)
    add_out(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..api import default_distribution_seed
    from ..config import dumps_toml, load_config, to_dict
    from ..evaluation.risk_validation import validate_risk
    from ..io.atomic import atomic_write_json, atomic_write_text
    from ..planners.context import run_system
    from ..planners.problem import PlanningProblem
    from ..planners.registry import ExecutionMode, make_planner, planner_info
    from ..settings import RunConfig
    from ..viz.risk import plot_risk_validation
    from ._common import context_from_args, show_progress
    from .plan import versions

    if args.samples < 2:
        raise ValueError(f"--samples must be at least 2, got {args.samples}")
    if args.calibration_samples != 0 and args.calibration_samples < 2:
        raise ValueError(f"--calibration-samples must be 0 (off) or at least 2, got {args.calibration_samples}")
    out = out_dir(args.out)
    run_config = apply_system_args(args, load_config(RunConfig, args.config, args.overrides))
    scene = scene_from_args(args, run_config)
    dist_seed = default_distribution_seed(args.distribution_seed, args.seed)
    system = run_system(run_config, args.kind)
    problem = PlanningProblem.from_scene(scene, seed=dist_seed, risk=run_config.risk, planning=run_config.planning,
                                         system=system)
    mode = planner_info(args.planner).execution
    if mode != ExecutionMode.TRACK:
        raise ValueError(f"validate risk needs a planner whose reference is tracked (density, search, sampling); "
                         f"{args.planner!r} executes {mode.value}")
    ctx = context_from_args(args, run_config, progress=show_progress(args), system=system)
    planner = make_planner(args.planner, ctx)
    t0 = time.perf_counter()
    plan = planner.plan(problem)
    t_plan = time.perf_counter() - t0
    if plan.reference is None or plan.collision is None:
        raise ValueError(f"{args.planner} returned no plan to check ({plan.status.value}: {plan.message})")
    t0 = time.perf_counter()
    check = validate_risk(problem, plan, ctx.controller, n=args.samples, seed=args.mc_seed,
                          threshold=args.threshold, config=run_config.evaluation)
    t_mc = time.perf_counter() - t0
    report = check.to_dict()
    # the second estimate of the same fresh samples: the learned predictor's own when the plan reports the exact
    # propagation (report_exact), else the exact re-prediction; separates the estimator from the learned
    # predictor's trajectory error
    second_key = "predictor_estimate" if "predictor_estimate" in plan.extras else "exact_check"
    second_label = ("the learned predictor's own estimate" if second_key == "predictor_estimate"
                    else "same samples through exact Liouville")
    exact = (plan.extras.get(second_key) or {}).get("collision_probability")
    if exact and exact.get("se") is not None:
        import math

        import numpy as np

        from ..evaluation.risk_validation import compare_risk

        t = check.z.size
        se = np.asarray(exact["se"][:t], dtype=float)
        ess_min = float(exact.get("ess_min", 0.0)) or 1.0
        se = np.maximum(se, check.monte_carlo_se * math.sqrt(args.samples) / math.sqrt(ess_min))
        ex = compare_risk(np.asarray(exact["per_slice"][:t]), se, check.monte_carlo, check.monte_carlo_se,
                          times=check.times, threshold=args.threshold, n_monte_carlo=args.samples,
                          estimator=exact.get("estimator", ""))
        report[second_key] = {k: v for k, v in ex.to_dict().items() if k in (
            "passed", "max_abs_z", "steps_beyond_threshold", "max_abs_difference", "planner_max")}
        report[second_key]["planner_p"] = exact["per_slice"][:t]
        report[second_key]["label"] = second_label
    calibration = None
    if args.calibration_samples and getattr(scene, "road", None) is not None and args.kind == "commonroad":
        calibration = _calibrate(args, run_config, scene, problem, plan, ctx)
        report["calibration"] = calibration.to_dict()
    report.update({
        "scene": scene.name,
        "planner": plan.planner,
        "plan_status": plan.status.value,
        "density_predictor": getattr(ctx.predictor(), "name", run_config.system.density),
        "reported_by": plan.extras.get("reported_by"),
        "n_samples_planner": int(plan.samples.n_samples) if plan.samples is not None else None,
        "distribution_seed": dist_seed,
        "monte_carlo_seed": args.mc_seed,
        "plan_time_s": t_plan,
        "monte_carlo_time_s": t_mc,
        "params": plan.params.detach().cpu().tolist() if plan.params is not None else None,
        "config": to_dict(run_config),
        "versions": versions(),
        "command": "density-planner " + " ".join(getattr(args, "argv", []) or []),
    })
    atomic_write_text(out / "config.toml", dumps_toml(run_config))
    atomic_write_json(out / "risk_report.json", report)
    title = (f"{scene.name}: {plan.planner} ({report['density_predictor']}, estimator {check.estimator}) vs "
             f"{args.samples} closed loops: {'PASS' if check.passed else 'FAIL'}, max |z| {check.max_abs_z:.2f}")
    plot_risk_validation(check, out / "risk.png", title=title)
    if calibration is not None:
        from ..viz.risk import plot_calibration

        plot_calibration(calibration, out / "calibration.png",
                         title=f"{scene.name}: occupancy model of the road users vs their true shapes "
                         f"({calibration.n} closed loops of the {plan.planner} plan)")
        print(f"calibration on {scene.name}: road-user risk predicted max {calibration.predicted.max():.3f}, "
              f"observed max {calibration.observed.max():.3f} (mean over time {calibration.total_predicted:.4f} vs "
              f"{calibration.total_observed:.4f}); wrote {out / 'calibration.png'}")
    print(f"risk check on {scene.name}: {'PASS' if check.passed else 'FAIL'}; max |z| = {check.max_abs_z:.2f} "
          f"({report['steps_beyond_threshold']} of {report['steps']} steps beyond {args.threshold:g} sigma); "
          f"P_coll max planner {report['planner_max']:.4f}, Monte Carlo {report['monte_carlo_max']:.4f}"
          + (f"; {second_label}: {'PASS' if report[second_key]['passed'] else 'FAIL'}, max "
             f"|z| {report[second_key]['max_abs_z']:.2f}" if second_key in report else "") + "; wrote "
          f"{out / 'risk_report.json'}, {out / 'risk.png'}")
    return 0 if check.passed else 1


def _calibrate(args, run_config, scene, problem, plan, ctx):
    """The calibration check of the occupancy model on a recorded road scene (evaluation/calibration.py): the
    scene is rebuilt with the road users' occupancy only (``commonroad.offroad_occupied = false``)."""
    import dataclasses

    from ..config import update
    from ..evaluation.calibration import calibrate_plan
    from ..risk.collision import CollisionModel

    users_config = dataclasses.replace(run_config, commonroad=update(run_config.commonroad,
                                                                       {"offroad_occupied": False}))
    users_scene = scene_from_args(args, users_config)
    g, h = scene.grid, users_scene.grid
    if g.probs.shape != h.probs.shape or tuple(g.origin) != tuple(h.origin) or g.cell_size != h.cell_size:
        raise RuntimeError("the road users' occupancy was rebuilt on a different lattice; cannot calibrate")
    users = CollisionModel(h, problem.system, problem.risk)
    return calibrate_plan(problem, plan, ctx.controller, users, scene.road, n=args.calibration_samples,
                          seed=args.mc_seed, config=run_config.evaluation)

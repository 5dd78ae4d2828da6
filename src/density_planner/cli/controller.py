"""``density-planner train controller`` and ``density-planner validate controller``."""

from __future__ import annotations

import argparse
import logging
import shlex
import time
from pathlib import Path
from typing import Any

import torch

from . import group
from ._common import add_config, add_out, add_progress, add_threads, out_dir, resolve_device, show_progress

logger = logging.getLogger(__name__)

#: targets (issue 14), checked and written into the reports: the contraction condition on the box where the car moves
#: (v >= 0.5 m/s; at standstill it cannot hold, docs/controller.md) and the tracking error ratio at 10 s
TARGET_FRAC_HOLDS = 0.995
TARGET_MEDIAN_RATIO = 0.10


def register(sub: argparse._SubParsersAction, groups: dict) -> None:
    train = group(sub, groups, "train")
    p = train.add_parser(
        "controller",
        help="train the C3M contraction controller",
        description="Train the learned contraction controller (C3M: metric W(x) and controller trained jointly on "
        "penalties of the contraction conditions), then check it: the contraction condition on 1e5 fresh samples "
        "and closed-loop tracking of 1000 random references (also with the analytic controller). Writes "
        "DIR/controller_c3m.pt + .json (state_dict and metadata with the diagnostics), DIR/checkpoint.pt "
        "(resumable: run the same command again to continue) and DIR/history.json.",
    )
    add_out(p)
    p.add_argument("--epochs", type=int, default=None, help="number of epochs (default from the configuration)")
    add_config(p, example="epochs=100")
    p.add_argument("--device", default=None, help="torch device for training: cpu (default), cuda, cuda:N or auto")
    add_threads(p)
    p.add_argument("--no-resume", action="store_true", help="start afresh even if DIR/checkpoint.pt exists")
    p.add_argument("--export", type=Path, default=None, metavar="FILE.pt",
                   help="also write the final weights to FILE.pt + FILE.json (e.g. the package's shipped weights)")
    add_progress(p)
    p.add_argument("--check-samples", type=int, default=100_000,
                   help="fresh samples for the final contraction check (default 1e5)")
    p.add_argument("--check-references", type=int, default=1000,
                   help="random references for the final tracking check (default 1000)")
    p.set_defaults(func=run_train)

    validate = group(sub, groups, "validate")
    p = validate.add_parser(
        "controller",
        help="check a tracking controller: contraction condition and closed-loop tracking",
        description="(a) fraction of fresh samples where the contraction condition holds and the distribution of "
        "its largest eigenvalue (learned controllers only); (b) position error at t = 0, 1, 5, 10 s when tracking "
        "random feasible references from initial errors in the XE0 box, with and without heading bias, for the "
        "chosen controller and the analytic one; (c) figures. Writes DIR/controller_report.json, "
        "DIR/error_decay.png, DIR/trajectories.png and DIR/eigenvalues.png.",
    )
    p.add_argument("--controller", default=None, metavar="NAME|FILE",
                   help="c3m (shipped weights, default), analytic, or a C3M weights file")
    p.add_argument("--samples", type=int, default=100_000, help="fresh samples for the condition (default 1e5)")
    p.add_argument("--references", type=int, default=1000, help="random references for tracking (default 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the tracking references (default 0)")
    p.add_argument("--models", default=None, metavar="SET",
                   help="model set whose controller 'c3m' / 'analytic' means: paper (default) or road")
    add_threads(p)
    add_out(p)
    p.set_defaults(func=run_validate)


# ------------------------------------------------------------------------------------------------------ helpers
def _command(args: argparse.Namespace) -> str:
    """The command line that reproduces a training run (from the parsed arguments)."""
    parts = ["density-planner", "train", "controller", "--out", str(args.out)]
    if args.epochs is not None:
        parts += ["--epochs", str(args.epochs)]
    if args.config is not None:
        parts += ["--config", str(args.config)]
    for item in args.overrides:
        parts += ["--set", item]
    if args.export is not None:
        parts += ["--export", str(args.export)]
    if args.threads is not None:
        parts += ["--threads", str(args.threads)]
    if args.device is not None:
        parts += ["--device", str(args.device)]
    if args.check_samples != 100_000:
        parts += ["--check-samples", str(args.check_samples)]
    if args.check_references != 1000:
        parts += ["--check-references", str(args.check_references)]
    return shlex.join(parts)


def _targets(contraction: dict[str, Any] | None, tracking: dict[str, Any], name: str) -> dict[str, Any]:
    """Check the issue's targets for controller ``name`` (and compare with the analytic one)."""
    out: dict[str, Any] = {}
    if contraction is not None:
        value = contraction["frac_holds_v_ge_0.5"]
        out["frac_holds_v_ge_0.5"] = {"value": value, "target": f">= {TARGET_FRAC_HOLDS}",
                                      "met": value >= TARGET_FRAC_HOLDS, "all_speeds": contraction["frac_holds"]}
    for variant, s in tracking[name].items():
        ratio = s["median"][-1] / s["median"][0]
        entry = {
            "median_ratio_final_to_initial": ratio,
            "target": f"<= {TARGET_MEDIAN_RATIO}",
            "met": ratio <= TARGET_MEDIAN_RATIO,
            "p95_final_below_p95_initial": s["p95"][-1] <= s["p95"][0],
        }
        if name != "analytic" and "analytic" in tracking:
            a = tracking["analytic"][variant]
            entry["beats_analytic_median_final"] = s["median"][-1] < a["median"][-1]
            entry["beats_analytic_p95_final"] = s["p95"][-1] < a["p95"][-1]
        out[f"tracking_{variant}"] = entry
    return out


def _integration() -> str:
    from ..evaluation.controller import TRACKING_INTEGRATION as c

    return f"{c.integrator} {c.dt:g} s"


def _tracking(controllers: dict, n_references: int, seed: int, car=None):
    from ..evaluation.controller import evaluate_tracking
    from ..systems.car import KinematicCar

    return evaluate_tracking(controllers, n_references=n_references, seed=seed, system=KinematicCar(car))


# ------------------------------------------------------------------------------------------------------- train
def run_train(args: argparse.Namespace) -> int:
    from ..config import load_config, to_dict, update
    from ..control.analytic import CarTrackingController
    from ..control.c3m import SHIPPED_C3M_WEIGHTS, save_c3m_model
    from ..control.c3m_training import C3MTrainConfig, train_c3m

    config = load_config(C3MTrainConfig, args.config, args.overrides)
    if args.epochs is not None:
        if args.epochs < 1:
            raise ValueError(f"--epochs must be >= 1, got {args.epochs}")
        config = update(config, {"epochs": args.epochs})
    if args.device is not None:
        config = update(config, {"device": str(resolve_device(args.device))})
    if args.check_samples < 1 or args.check_references < 1:
        raise ValueError("--check-samples and --check-references must be >= 1")
    out = out_dir(args.out)
    t0 = time.perf_counter()
    result = train_c3m(config, out, progress=show_progress(args), resume=not args.no_resume,
                       diagnostics_samples=args.check_samples)
    train_wall = time.perf_counter() - t0
    car = result.model.car
    tracking = _tracking({"c3m": result.model.controller, "analytic": CarTrackingController(car=car)},
                         args.check_references, 0, car)
    summary = tracking.summary()
    diagnostics = {
        "contraction": result.diagnostics,
        "tracking": summary,
        "tracking_setup": {"n_references": args.check_references, "seed": 0, "initial_error_box": "XE0",
                           "integrator": _integration(), "domain": car.domain},
        "targets": _targets(result.diagnostics, summary, "c3m"),
        "train_wall_time_s": result.wall_time,
        "command_wall_time_s": time.perf_counter() - t0,
        "threads": torch.get_num_threads(),
    }
    command = _command(args)
    paths = [save_c3m_model(out / SHIPPED_C3M_WEIGHTS, result.model, config=to_dict(config),
                            diagnostics=diagnostics, command=command)[0]]
    if args.export is not None:
        paths.append(save_c3m_model(args.export, result.model, config=to_dict(config), diagnostics=diagnostics,
                                    command=command)[0])
    c = result.diagnostics
    t = summary["c3m"]
    print(f"trained in {train_wall / 60:.1f} min; contraction condition holds on {c['frac_holds']:.2%} of "
          f"{c['n_samples']} fresh samples; median position error 0/10 s: "
          f"{t['unbiased']['median'][0]:.3f}/{t['unbiased']['median'][-1]:.3f} m (unbiased), "
          f"{t['biased']['median'][0]:.3f}/{t['biased']['median'][-1]:.3f} m (biased)")
    print("wrote " + ", ".join(str(p) for p in paths) + " (+ .json)")
    return 0


# ---------------------------------------------------------------------------------------------------- validate
def run_validate(args: argparse.Namespace) -> int:
    from ..control.analytic import CarTrackingController
    from ..control.base import TrackingController
    from ..control.c3m import load_c3m_model
    from ..control.c3m_training import contraction_diagnostics
    from ..control.registry import DEFAULT_CONTROLLER, model_set
    from ..io.atomic import atomic_write_json
    from ..viz.controller import plot_contraction_eigenvalues, plot_error_decay, plot_tracked_trajectories

    if args.samples < 1 or args.references < 1:
        raise ValueError("--samples and --references must be >= 1")
    out = out_dir(args.out)
    spec = args.controller or DEFAULT_CONTROLLER
    mset = model_set(args.models)
    report: dict[str, Any] = {"controller": spec, "models": mset.name}
    contraction = None
    samples = None
    car = mset.car
    if spec == "analytic":
        name = "analytic"
        controllers: dict[str, TrackingController] = {"analytic": CarTrackingController(car=car)}
        report["contraction"] = None
        report["contraction_note"] = "the analytic controller has no contraction metric"
    else:
        path = mset.controller_path() if spec == "c3m" else Path(spec)
        model, meta = load_c3m_model(path)
        car = model.car
        name = "c3m"
        rate = float(meta.get("training_config", {}).get("rate", 0.5))
        t0 = time.perf_counter()
        contraction = contraction_diagnostics(model, n=args.samples, rate=rate, return_samples=True)
        samples = contraction.pop("_samples")
        contraction["wall_time_s"] = time.perf_counter() - t0
        report["weights"] = str(path)
        report["weights_command"] = meta.get("command")
        report["contraction"] = contraction
        controllers = {"c3m": model.controller, "analytic": CarTrackingController(car=car)}
    report["domain"] = car.domain
    evaluation = _tracking(controllers, args.references, args.seed, car)
    summary = evaluation.summary()
    report["tracking"] = summary
    report["tracking_setup"] = {"n_references": args.references, "seed": args.seed, "initial_error_box": "XE0",
                                "integrator": _integration(), "wall_time_s": evaluation.wall_time}
    report["targets"] = _targets(contraction, summary, name)
    atomic_write_json(out / "controller_report.json", report)

    plot_error_decay(evaluation.t, evaluation.errors, out / "error_decay.png",
                     title=f"position tracking error from XE0 initial errors ({name} vs analytic)")
    k = min(6, args.references)
    stride = int(round(float(evaluation.t[1] - evaluation.t[0]) / evaluation.reference.dt))
    x_ref = evaluation.reference.x[:k, ::stride].cpu().numpy()
    trajectories = {f"{c} {v}": evaluation.x[c][v][:k] for c in evaluation.x for v in ("unbiased", "biased")}
    bias = [f"ref {i}: bias {float(evaluation.x[name]['biased'][i, 0, 4]):+.3f} rad" for i in range(k)]
    plot_tracked_trajectories(x_ref, trajectories, out / "trajectories.png", t=evaluation.t, labels=bias,
                              title="tracked trajectories (dashed: with heading bias)")
    written = ["controller_report.json", "error_decay.png", "trajectories.png"]
    if samples is not None and contraction is not None:
        plot_contraction_eigenvalues(samples["lambda_max"].numpy(), samples["lambda_max_generalised"].numpy(),
                                     samples["v"].numpy(), out / "eigenvalues.png", rate=contraction["rate"],
                                     title=f"contraction condition on {args.samples} fresh samples")
        written.append("eigenvalues.png")
    lines = []
    if contraction is not None:
        lines.append(f"contraction condition holds on {contraction['frac_holds']:.2%} of {args.samples} samples "
                     f"({contraction['frac_holds_v_ge_0.5']:.2%} where v >= 0.5 m/s; target "
                     f"{TARGET_FRAC_HOLDS:.1%}); by true speed: " + ", ".join(
                         f"{band} {b['frac_holds']:.2%}" for band, b in contraction["frac_holds_by_speed"].items()))
    for c, per_variant in summary.items():
        for v, s in per_variant.items():
            lines.append(f"{c:9s} {v:9s} median error t=0/1/5/10 s: " + "/".join(f"{m:.3f}" for m in s["median"])
                         + " m; 95th: " + "/".join(f"{m:.3f}" for m in s["p95"]) + " m; median(10 s) / median(0 s) "
                         + f"= {s['median'][-1] / s['median'][0]:.2%} (target <= {TARGET_MEDIAN_RATIO:.0%})")
    print("\n".join(lines))
    print(f"wrote {', '.join(str(out / w) for w in written)}")
    return 0

"""``density-planner data density``, ``train density`` and ``validate density``: the learned density predictors."""

from __future__ import annotations

import argparse
import shlex
import time
from pathlib import Path

import torch

from . import group
from ._common import add_config, add_out, add_progress, out_dir, show_progress


def _threads(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threads", type=int, default=None,
                   help="CPU threads for torch in this process (default: torch's choice; 1 is faster on a busy "
                        "machine)")


def _set_threads(n: int | None) -> None:
    if n is not None:
        if n < 1:
            raise ValueError(f"--threads must be >= 1, got {n}")
        torch.set_num_threads(n)


def _system_flags(p: argparse.ArgumentParser) -> None:
    """``--system`` and ``--models``: which model set (a registered system in a domain, with its controllers and
    density weights) the command is about."""
    from ..systems.registry import system_names

    p.add_argument("--system", default=None, metavar="NAME",
                   help=f"dynamics: {', '.join(system_names())} (default car; with --models unset, the system's first "
                        "model set: paper for the car, ks for the kinematic single-track model)")
    p.add_argument("--models", default=None, metavar="SET",
                   help="model set: paper or road for the car, ks for the kinematic single-track model (default: "
                        "from --system)")


def _model_set(args: argparse.Namespace, fallback: str | None = None):
    """The model set named by ``--models`` / ``--system`` (``fallback``: the set when neither is given)."""
    from ..control.registry import model_set, model_set_for_scene

    if args.models is None and args.system is None:
        return model_set(fallback)
    return model_set_for_scene(None, override=args.models, system=args.system)


def register(sub: argparse._SubParsersAction, groups: dict) -> None:
    data = group(sub, groups, "data")
    p = data.add_parser(
        "density",
        help="generate training data for the learned density predictors (exact Liouville)",
        description="Random feasible references and initial errors in the XE0 box, propagated with the exact "
        "Liouville equation along the closed loop of the controller, batched over the references of a shard. "
        "Writes DIR/shard_NNNNN.pt (atomically, one task per shard) and DIR/manifest.json. Run the same command "
        "again to resume an interrupted run.",
    )
    from ..density.data import DensityDataConfig

    dd = DensityDataConfig()  # the help states the dataclass's defaults (one place for each value)
    p.add_argument("--references", type=int, default=None,
                   help=f"number of references (default {dd.references})")
    p.add_argument("--samples", type=int, default=None,
                   help=f"initial errors per reference (default {dd.samples})")
    p.add_argument("--seed", type=int, default=None, help=f"seed (default {dd.seed})")
    p.add_argument("--controller", default=None, metavar="NAME|FILE",
                   help=f"tracking controller: for the car c3m, analytic or a C3M weights file (default "
                        f"{dd.controller}), for another system one of its own (default: its model set's, analytic "
                        "for ks)")
    _system_flags(p)
    p.add_argument("--workers", type=int, default=None, help="local worker processes (default: number of cores)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="Dask scheduler address (tcp://host:8786) to run the shards on a cluster")
    add_config(p, example="references_per_shard=128")
    add_progress(p)
    add_out(p)
    p.set_defaults(func=run_data)

    train = group(sub, groups, "train")
    p = train.add_parser(
        "density",
        help="train a learned density predictor (trajectory head or pointwise MLP)",
        description="Train a density predictor on a data directory written by `data density` (early stopping on "
        "its held-out references). Writes DIR/density_ARCH.pt + .json (state_dict with the normalisation, and "
        "metadata with the architecture, training configuration, data size, times and validation errors), "
        "DIR/history.json and DIR/checkpoint.pt (resumable: run the same command again to continue).",
    )
    p.add_argument("--arch", choices=("trajectory", "pointwise"), default="trajectory",
                   help="trajectory: whole horizon per evaluation (ours); pointwise: the paper's per-time MLP")
    p.add_argument("--data", type=Path, required=True, metavar="DIR", help="data directory (`data density`)")
    p.add_argument("--epochs", type=int, default=None, help="maximum epochs (default from the configuration)")
    p.add_argument("--time-limit", type=float, default=None, metavar="S",
                   help="stop after S seconds of training, keeping the best state")
    p.add_argument("--export", type=Path, default=None, metavar="FILE.pt",
                   help="also write the weights to FILE.pt + FILE.json (e.g. the package's shipped weights)")
    p.add_argument("--no-resume", action="store_true", help="start afresh even if DIR/checkpoint.pt exists")
    add_config(p, example="batch_size=1024")
    _threads(p)
    add_progress(p)
    add_out(p)
    p.set_defaults(func=run_train)

    validate = group(sub, groups, "validate")
    p = validate.add_parser(
        "density",
        help="compare a learned density predictor with exact Liouville on fresh references",
        description="Fresh held-out references (seed not used for training): per-time median and 95th "
        "percentile of the position error and of the log-density error of the learned predictor against exact "
        "Liouville, overall error MSE and log-density RMSE (comparable with the paper's 0.018 / 9.3), timing. "
        "Writes DIR/density_report.json, DIR/density_errors.png and DIR/density_heatmaps.png (network vs exact "
        "at t = 0.5, 4, 10 s).",
    )
    p.add_argument("--density", default=None, metavar="NAME|FILE[,...]",
                   help="learned predictor(s), comma-separated: trajectory, pointwise, learned or weights files "
                        "(default: the model set's shipped ones, trajectory,pointwise for the car)")
    p.add_argument("--controller", default=None, metavar="NAME|FILE",
                   help="tracking controller (default: the one the predictor was trained for, c3m)")
    _system_flags(p)
    p.add_argument("--references", type=int, default=200, help="fresh references (default 200)")
    p.add_argument("--samples", type=int, default=100, help="initial errors per reference (default 100)")
    p.add_argument("--seed", type=int, default=1_000_003, help="seed of the fresh references (default 1000003)")
    p.add_argument("--figure-samples", type=int, default=5000,
                   help="samples of the heat-map figure (one reference; default 5000)")
    _threads(p)
    add_out(p)
    p.set_defaults(func=run_validate)


# ------------------------------------------------------------------------------------------------------- data
def run_data(args: argparse.Namespace) -> int:
    from ..config import load_config, update
    from ..density.data import DensityDataConfig, generate_density_data

    config = load_config(DensityDataConfig, args.config, args.overrides)
    changes = {k: v for k, v in (("references", args.references), ("samples", args.samples), ("seed", args.seed),
                                 ("controller", args.controller)) if v is not None}
    if args.system is not None or args.models is not None:
        changes["domain"] = _model_set(args).name
    if changes:
        config = update(config, changes)
    out = out_dir(args.out)
    t0 = time.perf_counter()
    manifest = generate_density_data(config, out, workers=args.workers, scheduler=args.scheduler,
                                     progress=show_progress(args), command=_command(args))
    s = manifest["sizes"]
    print(f"wrote {config.n_shards} shards to {out} in {time.perf_counter() - t0:.1f} s "
          f"({s['references_train']} training + {s['references_val']} validation references x "
          f"{s['samples_per_reference']} samples, {s['bytes'] / 1e6:.0f} MB); manifest {out / 'manifest.json'}")
    return 0


def _command(args: argparse.Namespace) -> str:
    argv = list(getattr(args, "argv", []) or [])
    return shlex.join(["density-planner", *argv])


# ------------------------------------------------------------------------------------------------------ train
def run_train(args: argparse.Namespace) -> int:
    from ..config import load_config, to_dict, update
    from ..density.data import load_density_data, read_manifest
    from ..density.network import save_density_model
    from ..density.train import DensityTrainConfig, train_density
    from ..io.atomic import atomic_write_json

    _set_threads(args.threads)
    config = load_config(DensityTrainConfig, args.config, args.overrides)
    changes: dict = {"arch": args.arch}
    if args.epochs is not None:
        changes["epochs"] = args.epochs
    if args.time_limit is not None:
        changes["time_limit_s"] = args.time_limit
    config = update(config, changes)
    manifest = read_manifest(args.data)
    out = out_dir(args.out)
    t0 = time.perf_counter()
    train = load_density_data(args.data, "train")
    val = load_density_data(args.data, "val")
    t_load = time.perf_counter() - t0
    result = train_density(config, train, val, out, resume=not args.no_resume, progress=show_progress(args))
    atomic_write_json(out / "history.json", result.history)
    best = {k: v[result.history["epoch"].index(float(result.best_epoch))] for k, v in result.history.items()}

    # fresh held-out references (a seed not used for the data): the numbers stored with the weights
    fresh = _fresh_validation(result.model, manifest, n_references=50, samples=100, seed=2_000_003)
    data_cfg = manifest["config"]
    diagnostics = {
        "validation_split": {k: best[k] for k in ("val_loss", "val_position_rmse_m", "val_log_density_rmse")},
        "fresh_references": fresh,
        "best_epoch": result.best_epoch,
        "epochs_run": result.epochs_run,
        "stopped": result.stopped,
    }
    extra = {
        "controller": {"spec": data_cfg["controller"], "fingerprint": manifest.get("controller_fingerprint")},
        "data": {
            "directory": str(args.data),
            "command": manifest.get("command"),
            "config": data_cfg,
            "sizes": manifest.get("sizes"),
            "generation_wall_time_s": manifest.get("wall_time_s"),
            "generation_shard_time_total_s": manifest.get("shard_time_total_s"),
            "generation_workers": manifest.get("workers"),
        },
        "training": {
            "wall_time_s": result.wall_time,
            "normalisation_time_s": result.normalisation_time,
            "data_load_time_s": t_load,
            "threads": torch.get_num_threads(),
            "device": config.device,
            "n_train_trajectories": result.n_train_trajectories,
            "n_val_trajectories": result.n_val_trajectories,
        },
        "commands": {
            "data": manifest.get("command"),
            "train": _command(args),
            "validate": "density-planner validate density --out results/density_validation"
                        + ("" if data_cfg.get("domain", "paper") == "paper" else f" --models {data_cfg['domain']}"),
        },
    }
    name = f"density_{config.arch}"
    paths = [save_density_model(out / name, result.model, config=to_dict(config), diagnostics=diagnostics,
                                command=_command(args), extra=extra)[0]]
    if args.export is not None:
        paths.append(save_density_model(args.export, result.model, config=to_dict(config), diagnostics=diagnostics,
                                        command=_command(args), extra=extra)[0])
    print(f"trained the {config.arch} predictor in {result.wall_time / 60:.1f} min ({result.epochs_run} epochs, "
          f"best {result.best_epoch}, stopped: {result.stopped}); fresh references: position error median/95th "
          f"{fresh['position_error_m']['overall']['median']:.3f}/{fresh['position_error_m']['overall']['p95']:.3f} m, "
          f"error MSE {fresh['error_state_mse']:.4f} (paper 0.018), log-density RMSE {fresh['log_density_rmse']:.2f} "
          f"(paper 9.3)")
    print("wrote " + ", ".join(str(p) for p in paths) + " (+ .json), " + str(out / "history.json"))
    return 0


def _fresh_validation(model, manifest: dict, *, n_references: int, samples: int, seed: int) -> dict:
    """Compact accuracy summary of ``model`` on fresh references (per-time curves left out)."""
    from ..control.registry import load_controller, model_set
    from ..density.liouville import ExactLiouville
    from ..density.network import LearnedDensity
    from ..density.validation import compare_with_exact, fresh_references

    domain = manifest["config"].get("domain", "paper")
    system = model_set(domain).make_system()
    controller = load_controller(manifest["config"]["controller"], models=domain)
    ref, x0 = fresh_references(n_references, samples, seed, domain=domain)
    cmp = compare_with_exact(LearnedDensity(model), ExactLiouville(system, controller), ref, x0)
    s = cmp.summary()
    for key in ("position_error_m", "log_density_abs_error", "log_density_relative_abs_error"):
        s[key] = {"overall": s[key]["overall"], "final_time": {q: s[key]["per_time"][q][-1]
                                                               for q in ("median", "p95")}}
    s.pop("t")
    s["seed"] = seed
    return s


# --------------------------------------------------------------------------------------------------- validate
def run_validate(args: argparse.Namespace) -> int:
    from ..control.registry import load_controller
    from ..density.liouville import ExactLiouville
    from ..density.registry import load_learned_predictor
    from ..density.validation import compare_with_exact, fresh_references
    from ..io.atomic import atomic_write_json
    from ..viz.density import plot_density_errors, plot_density_heatmaps

    _set_threads(args.threads)
    if args.references < 1 or args.samples < 1 or args.figure_samples < 1:
        raise ValueError("--references, --samples and --figure-samples must be >= 1")
    out = out_dir(args.out)
    mset = _model_set(args)
    system = mset.make_system()
    if args.density is None:
        from ..density.network import ARCHITECTURES, shipped_density_path

        specs = [a for a in ARCHITECTURES if shipped_density_path(a, mset.name).is_file()]
        if not specs:
            raise ValueError(f"the package ships no learned density predictor for the model set {mset.name!r}; name "
                             "one with --density FILE.pt")
    else:
        specs = [s.strip() for s in str(args.density).split(",") if s.strip()]
    predictors = {}
    for spec in specs:
        pred = load_learned_predictor(spec, models=mset.name, system=system)
        name = pred.name if spec in ("trajectory", "pointwise", "learned") else Path(spec).stem
        if name in predictors:
            name = f"{name} ({spec})"
        predictors[name] = pred
    first = next(iter(predictors.values()))
    ctrl_spec = args.controller or (first.meta.get("controller") or {}).get("spec") or None
    controller = load_controller(ctrl_spec, models=mset.name)
    predictors = {name: load_learned_predictor(spec, controller, models=mset.name, system=system)
                  for name, spec in zip(predictors, specs)}
    exact = ExactLiouville(system, controller)

    ref, x0 = fresh_references(args.references, args.samples, args.seed, domain=mset.name)
    report: dict = {"seed": args.seed, "controller": ctrl_spec, "models": mset.name,
                    "initial_errors": "uniform in the XE0 box",
                    "exact": {"integrator": exact.config.integrator, "dt": exact.config.dt},
                    "threads": torch.get_num_threads(), "predictors": {}}
    summaries = {}
    for name, pred in predictors.items():
        cmp = compare_with_exact(pred, exact, ref, x0)
        s = cmp.summary()
        s["weights"] = {k: pred.meta.get(k) for k in ("command",)}
        s["architecture"] = pred.architecture.to_dict()
        summaries[name] = s
        report["predictors"][name] = s
    atomic_write_json(out / "density_report.json", report)
    plot_density_errors(summaries, out / "density_errors.png",
                        title=f"learned density vs exact Liouville on {args.references} fresh references x "
                              f"{args.samples} samples")

    # the paper-style figure: one fresh reference, many samples
    fig_ref, fig_x0 = fresh_references(1, args.figure_samples, args.seed + 1, domain=mset.name)
    lr0 = torch.zeros(fig_x0.shape[:-1])
    clouds = {}
    with torch.no_grad():
        ex = exact.predict(fig_x0, lr0, fig_ref)
        for name, pred in predictors.items():
            p = pred.predict(fig_x0, lr0, fig_ref)
            clouds[f"network ({name})"] = (p.x[0].numpy(), p.log_rho[0].numpy())
    clouds["exact Liouville"] = (ex.x[0].numpy(), ex.log_rho[0].numpy())
    plot_density_heatmaps(ex.t.numpy(), clouds, fig_ref.x_plan[0].numpy(), out / "density_heatmaps.png",
                          title=f"density of {args.figure_samples} samples (initial errors uniform in XE0): "
                                "network vs exact Liouville")
    for name, s in summaries.items():
        pe, le = s["position_error_m"], s["log_density_abs_error"]
        print(f"{name:10s} position error median/95th {pe['overall']['median']:.3f}/{pe['overall']['p95']:.3f} m "
              f"(t = 10 s: {pe['per_time']['median'][-1]:.3f}/{pe['per_time']['p95'][-1]:.3f}); |log-density "
              f"error| median/95th {le['overall']['median']:.2f}/{le['overall']['p95']:.2f}; error MSE "
              f"{s['error_state_mse']:.4f} (paper 0.018), log-density RMSE {s['log_density_rmse']:.2f} (paper 9.3); "
              f"{s['time_predictor_per_500_trajectories_s'] * 1e3:.1f} ms vs exact "
              f"{s['time_exact_per_500_trajectories_s'] * 1e3:.0f} ms per 500 trajectories")
        for band, b in s["by_speed_band"].items():
            print(f"{'':10s} {band:16s} ({b['n_references']:3d} refs) position error median/95th "
                  f"{b['position_error_m']['median']:.3f}/{b['position_error_m']['p95']:.3f} m; |log-density "
                  f"error| median/95th {b['log_density_abs_error']['median']:.2f}/"
                  f"{b['log_density_abs_error']['p95']:.2f}")
    print(f"wrote {out / 'density_report.json'}, {out / 'density_errors.png'}, {out / 'density_heatmaps.png'}")
    return 0

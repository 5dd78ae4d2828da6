"""``density-planner bench SETTING`` (the paper's comparisons) and ``density-planner report DIR``."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ._common import (
    add_config,
    add_out,
    add_progress,
    add_system,
    add_threads,
    apply_system_args,
    out_dir,
    show_progress,
)


def register(sub: argparse._SubParsersAction, groups: dict) -> None:
    from ..evaluation.benchmark_settings import SETTINGS

    settings = "; ".join(
        f"{s.name}: {s.description} (planners {', '.join(s.planners)}; variants {', '.join(s.variants)}; "
        f"{s.default_envs} environments)" for s in SETTINGS.values()
    )
    p = sub.add_parser(
        "bench",
        help="run one of the paper's benchmarks (ablation, artificial, real)",
        description="Run a benchmark sweep: every planner on every environment, one JSON record per run under "
        "DIR/records/<setting>/ written as soon as it finishes; a re-run with the same --out skips finished records "
        "and completes the rest. Then writes DIR/summary.csv, DIR/summary.md and the figures in DIR/figures/. "
        f"Settings: {settings}.",
    )
    p.add_argument("setting", choices=tuple(SETTINGS), help="benchmark setting")
    p.add_argument("--envs", type=int, default=None, metavar="N",
                   help="number of environments (numbers 0..N-1; default: the setting's, 50 for artificial)")
    p.add_argument("--seeds", default=None, metavar="A:B",
                   help="environment numbers A..B-1 instead of --envs (random scene numbers; real: scenario and "
                   "start/goal index)")
    p.add_argument("--planners", default=None, metavar="LIST", help="comma-separated planners (default: the setting's)")
    p.add_argument("--mode", default="offline", choices=("offline", "online"),
                   help="online: the default planners gain the density planner run online (replanning every "
                   "online.period from the measurement; density_online with the observed-only prediction and, on "
                   "CommonRoad scenes, density_online_oracle with the recorded future) next to the offline density "
                   "planner and MPC M0, on the same scenarios and true initial states")
    p.add_argument("--variants", default=None, metavar="LIST",
                   help="comma-separated measurement variants: unbiased, biased (default: both; ablation: nominal)")
    p.add_argument("--data-dir", type=Path, default=None, metavar="D",
                   help="real: folder with inD recordings (NN_tracks.csv, ...) or CommonRoad scenarios (*.xml); "
                   "default: the two shipped CommonRoad NGSIM scenarios")
    p.add_argument("--scenarios", type=Path, default=None, metavar="DIR",
                   help="commonroad: folder of CommonRoad scenarios (*.xml), each planned with its own planning "
                   "problem and judged by the verdict (--envs N / --seeds A:B pick scenarios by their sorted index)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local worker processes (default: the number of cores; 1 = serial in this process)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run on a Dask distributed cluster at ADDRESS (e.g. tcp://host:8786; extra 'dask')")
    add_system(p)
    add_config(p)
    add_threads(p)
    p.add_argument("--validate-risk", action="store_true",
                   help="check each tracked plan's collision probability against 10000 Monte-Carlo closed loops "
                   "(risk.validate_samples; records gain risk_check, the summary the share of passing plans)")
    p.add_argument("--retry-errors", action="store_true", help="re-run records whose run raised or whose worker died")
    p.add_argument("--redo-stale", action="store_true",
                   help="recompute records of --out made with another configuration (e.g. new controller weights; "
                   "MPC and oracle records do not depend on the controller and predictor and are kept)")
    p.add_argument("--plot-envs", type=int, default=3, metavar="K",
                   help="trajectory figures for the first K environments (default 3)")
    add_progress(p)
    add_out(p)
    p.set_defaults(func=run_bench)

    r = sub.add_parser(
        "report",
        help="regenerate the tables and figures of a benchmark directory from its records",
        description="Read DIR/records/*/*.json and (re)write DIR/summary.csv, DIR/summary.md and DIR/figures/*.png.",
    )
    r.add_argument("dir", type=Path, metavar="DIR", help="benchmark output directory (the --out of bench)")
    r.add_argument("--plot-envs", type=int, default=3, metavar="K",
                   help="trajectory figures for the first K environments of each setting (default 3)")
    r.set_defaults(func=run_report)


def _list(text: str | None, what: str) -> tuple[str, ...] | None:
    if text is None:
        return None
    items = tuple(s.strip() for s in text.split(",") if s.strip())
    if not items:
        raise ValueError(f"--{what} must name at least one entry")
    if len(set(items)) != len(items):
        raise ValueError(f"--{what} lists an entry twice: {text!r}")
    return items


def parse_seeds(text: str) -> range:
    """``"A:B"`` -> ``range(A, B)`` with ``0 <= A < B``."""
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        a, b = int(parts[0]), int(parts[1])
    except ValueError:
        raise ValueError(f"--seeds must be A:B with integers A < B (e.g. 0:50), got {text!r}") from None
    if a < 0 or b <= a:
        raise ValueError(f"--seeds must be A:B with 0 <= A < B, got {text!r}")
    return range(a, b)


def _default_variants(variants: tuple[str, ...], run_config) -> tuple[str, ...]:
    """The setting's variants, without "biased" for a system with no hidden state (nothing to bias: it would repeat
    "unbiased")."""
    from ..planners.context import run_system

    if run_system(run_config, None).hidden_states:
        return tuple(variants)
    return tuple(v for v in variants if v != "biased") or tuple(variants)


def spec_from_args(args: argparse.Namespace, run_config):
    """The :class:`BenchmarkSpec` of the command line (validates every choice with a one-line error)."""
    from ..evaluation.benchmark import BenchmarkSpec
    from ..evaluation.benchmark_settings import SETTINGS
    from ..evaluation.environments import artificial_envs, real_envs
    from ..planners.registry import planner_names

    setting = SETTINGS[args.setting]
    if args.envs is not None and args.seeds is not None:
        raise ValueError("give either --envs N or --seeds A:B, not both")
    if args.envs is not None and args.envs < 1:
        raise ValueError(f"--envs must be >= 1, got {args.envs}")
    if args.setting == "commonroad":
        return _commonroad_spec(args, run_config)
    if args.scenarios is not None:
        raise ValueError(f"--scenarios is only used by the commonroad setting, not {args.setting}")
    indices = parse_seeds(args.seeds) if args.seeds is not None else range(args.envs or setting.default_envs)
    if args.data_dir is not None:
        if args.setting != "real":
            raise ValueError(f"--data-dir is only used by the real setting, not {args.setting}")
        if not args.data_dir.is_dir():
            raise ValueError(f"--data-dir {args.data_dir} does not exist or is not a directory")
    planners = _list(args.planners, "planners") or _mode_planners(args, setting.planners)
    known = planner_names()
    for name in planners:
        if name not in known:
            raise ValueError(f"unknown planner {name!r} in --planners; valid choices: {', '.join(known)}")
    variants = _list(args.variants, "variants") or _default_variants(setting.variants, run_config)
    allowed = setting.variants
    for v in variants:
        if v not in allowed:
            raise ValueError(f"unknown variant {v!r} for {args.setting}; valid choices: {', '.join(allowed)}")
    from ..memory import check_memory

    # the sweep holds one environment spec and one job / record key per run in memory (~1 KB + ~2 KB per run)
    flag = f"--envs {len(indices)}" if args.seeds is None else f"--seeds {args.seeds}"
    check_memory(len(indices) * (1024 + 2048 * len(planners) * len(variants)), f"{flag} ({len(indices)} environments)",
                 "lower --envs (or run the sweep in parts with --seeds A:B)")
    envs = real_envs(indices, args.data_dir) if args.setting == "real" else artificial_envs(indices)
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    _check_scheduler(args)
    return BenchmarkSpec(args.setting, envs, planners, variants, run_config)


def _mode_planners(args: argparse.Namespace, default: tuple[str, ...]) -> tuple[str, ...]:
    """The default planners of ``--mode``: offline, the setting's; online, density offline and online (observed and,
    on CommonRoad scenes, oracle prediction) and MPC M0."""
    if getattr(args, "mode", "offline") != "online":
        return default
    online = ("density_online", "density_online_oracle") if args.setting == "commonroad" else ("density_online",)
    return ("density", *online, "mpc")


def _check_planners(args, default: tuple[str, ...]) -> tuple[str, ...]:
    from ..planners.registry import planner_names

    planners = _list(args.planners, "planners") or default
    known = planner_names()
    for name in planners:
        if name not in known:
            raise ValueError(f"unknown planner {name!r} in --planners; valid choices: {', '.join(known)}")
    return planners


def _commonroad_spec(args: argparse.Namespace, run_config):
    """The spec of ``bench commonroad --scenarios DIR``: one environment per scenario file."""
    from ..evaluation.benchmark import BenchmarkSpec
    from ..evaluation.benchmark_settings import SETTINGS
    from ..evaluation.commonroad_bench import commonroad_envs

    if args.scenarios is None:
        raise ValueError("bench commonroad needs --scenarios DIR (a folder of CommonRoad *.xml files)")
    if args.data_dir is not None:
        raise ValueError("--data-dir is not used by bench commonroad (use --scenarios DIR)")
    if args.variants is not None:
        raise ValueError("--variants is not used by bench commonroad (every run uses the unbiased measurement)")
    if args.envs is not None and args.seeds is not None:
        raise ValueError("give either --envs N or --seeds A:B, not both")
    envs = commonroad_envs(args.scenarios)
    if args.envs is not None:
        if args.envs < 1:
            raise ValueError(f"--envs must be >= 1, got {args.envs}")
        envs = envs[: args.envs]
    elif args.seeds is not None:
        r = parse_seeds(args.seeds)
        envs = envs[r.start: r.stop]
        if not envs:
            raise ValueError(f"--seeds {args.seeds} selects no scenario of {args.scenarios}")
    if args.workers is not None and args.workers < 1:
        raise ValueError(f"--workers must be >= 1, got {args.workers}")
    _check_scheduler(args)
    planners = _check_planners(args, _mode_planners(args, SETTINGS["commonroad"].planners))
    return BenchmarkSpec("commonroad", envs, planners, ("unbiased",), run_config)


def _check_scheduler(args: argparse.Namespace) -> None:
    if args.scheduler is not None:
        try:
            import distributed  # noqa: F401
        except ImportError:
            from ..errors import OptionalDependencyError

            raise OptionalDependencyError("distributed", "dask", "--scheduler (a Dask cluster)") from None


def _resolve_components(spec):
    """Load the controller and the density predictor once here (a bad name fails before the sweep, exactly as the
    workers will resolve it) and put their names and the digest of their weights into the spec."""
    from dataclasses import replace

    from ..evaluation.benchmark import component_digest
    from ..planners.context import build_context

    planning = spec.run_config.planning  # an explicit horizon is known before the scenes: check the predictor now
    par = planning.parameterization() if planning.horizon is not None else None
    # the package's default model set, whatever the scenes' (the digest of existing records depends on it)
    ctx = build_context(spec.run_config, controller=spec.controller, density=spec.density, parameterization=par)
    controller, predictor = ctx.controller, ctx.predictor()
    label = (f"{type(controller).__name__}/{getattr(predictor, 'name', type(predictor).__name__)}/"
             f"{component_digest(controller, predictor) or '-'}")
    return replace(spec, components=label)


def write_report(out: Path, plot_envs: int = 3) -> list[Path]:
    """Tables and figures of ``out`` from its records (and the verdict summary of a commonroad sweep)."""
    import sys

    from ..evaluation.records import scan_records
    from ..evaluation.report import write_tables
    from ..viz.benchmark import write_figures

    records, rows, paths = write_tables(out)
    bad = scan_records(out)[1]
    if bad:
        print(f"density-planner: warning: {len(bad)} record file(s) are not usable and count as missing runs in the "
              f"summary (first: {bad[0].path}: {bad[0].reason})", file=sys.stderr)
    paths += write_figures(out, rows, records, plot_envs=plot_envs)
    if any(r.get("setting") == "commonroad" for r in records):
        from ..evaluation.commonroad_bench import write_commonroad_summary

        paths += write_commonroad_summary(out)
    return paths


def _commonroad_table(out: Path) -> str:
    return (Path(out) / "summary_commonroad.md").read_text()


def run_bench(args: argparse.Namespace) -> int:
    from ..config import load_config
    from ..evaluation.benchmark import run_benchmark
    from ..settings import RunConfig
    from .plan import versions

    run_config = apply_system_args(args, load_config(RunConfig, args.config, args.overrides))
    if args.validate_risk and not run_config.risk.validate_samples:
        from ..config import update

        run_config = update(run_config, {"risk": {"validate_samples": 10_000}})
    spec = _resolve_components(spec_from_args(args, run_config))
    if args.plot_envs < 0:
        raise ValueError(f"--plot-envs must be >= 0, got {args.plot_envs}")
    out = out_dir(args.out)
    t0 = time.perf_counter()
    info = {"versions": versions(), "command": "density-planner " + " ".join(getattr(args, "argv", []) or [])}
    if args.threads is not None:  # threads of every worker process (and of a serial run): not part of the records
        if args.threads < 0:
            raise ValueError(f"--threads must be >= 0, got {args.threads}")
        threads = args.threads or None
    else:
        threads = spec.evaluation.threads_per_worker
    job_fn = None
    if spec.setting == "commonroad":
        from ..evaluation.commonroad_bench import run_commonroad_job

        job_fn = run_commonroad_job
    report = run_benchmark(spec, out, workers=args.workers, scheduler=args.scheduler, progress=show_progress(args),
                           retry_errors=args.retry_errors, redo_stale=args.redo_stale, run_info=info,
                           threads_per_worker=threads, job_fn=job_fn)
    paths = write_report(out, args.plot_envs)
    if spec.setting == "commonroad":
        print(_commonroad_table(out))
    print(f"bench {spec.setting}: {report.total} runs ({report.skipped} already done, {report.written} written, "
          f"{report.failed_runs} failed, {report.errors} errors) in {time.perf_counter() - t0:.1f} s; "
          f"wrote {out / 'summary.md'}, {out / 'summary.csv'} and {len(paths) - 2} figures in {out / 'figures'}")
    return 0


def run_report(args: argparse.Namespace) -> int:
    if not args.dir.is_dir():
        raise ValueError(f"benchmark directory {args.dir} does not exist")
    if args.plot_envs < 0:
        raise ValueError(f"--plot-envs must be >= 0, got {args.plot_envs}")
    paths = write_report(args.dir, args.plot_envs)
    print(f"report: wrote {args.dir / 'summary.md'}, {args.dir / 'summary.csv'} and {len(paths) - 2} figures in "
          f"{args.dir / 'figures'}")
    return 0

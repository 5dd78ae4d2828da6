"""``density-planner plan``: plan in a scene and write the plan, its figures and the effective configuration."""

from __future__ import annotations

import argparse
import time

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
    from ..planners.registry import planner_help

    helps = "; ".join(f"{k}: {v}" for k, v in planner_help().items())
    p = sub.add_parser(
        "plan",
        help="plan a motion in a scene (the main job)",
        description="Build a scene, plan with the chosen planner and write DIR/plan.json (the plan's verdict: "
        "goal reached in its time interval, collision-free against the true shapes, on the road, within the model; "
        "parameters, costs, collision probability, timings, configuration, versions), DIR/plan.png, DIR/plan.gif, "
        "DIR/costs.png, DIR/config.toml (the effective configuration; pass it back with --config to reproduce the "
        "run) and, on CommonRoad scenes, DIR/solution.xml (CommonRoad solution format; [solution] in the "
        "configuration). Exit code 0: the plan passed its verdict; 3: a plan was made but failed it (every file is "
        "still written); 1: no plan; 2: bad input.",
    )
    add_scene_args(p)
    p.add_argument("--planner", default="density", metavar="NAME", help=f"planner ({helps})")
    p.add_argument("--distribution-seed", type=int, default=None, metavar="S",
                   help="seed of the random initial distribution (default: --seed)")
    add_system(p)
    add_config(p)
    add_device(p)
    p.add_argument("--no-gif", action="store_true", help="skip plan.gif")
    add_progress(p)
    add_out(p)
    p.set_defaults(func=run, fast_exit=True)


def versions() -> dict[str, str]:
    """Versions of the package and its main dependencies (written next to results)."""
    import platform
    import sys

    import numpy
    import torch

    from .. import __version__

    out = {"density_planner": __version__, "python": sys.version.split()[0], "torch": torch.__version__,
           "numpy": numpy.__version__, "platform": platform.platform()}
    from importlib.metadata import PackageNotFoundError, version

    for package in ("casadi", "commonroad-io", "shapely"):  # without importing them (casadi alone takes ~0.3 s)
        try:
            out[package] = version(package)
        except PackageNotFoundError:
            pass
    return out


def run(args: argparse.Namespace) -> int:
    from ..checks import check_seed
    from ..config import load_config
    from ..settings import RunConfig

    check_out(args.out)
    if args.distribution_seed is not None:
        check_seed("--distribution-seed", args.distribution_seed)
    run_config = apply_system_args(args, load_config(RunConfig, args.config, args.overrides))
    from contextlib import nullcontext

    from ..cost.road import requesting_road_terms, start_road_terms
    from ..environment.road_sdf import cancel_road_sdf
    from ..parallel import default_workers

    clock = _Clock()
    # the road's distance field on the second core from when the importer knows the road (or after the build)
    beside = default_workers() > 1 and args.device == "cpu"
    cost = run_config.density_planner.cost
    with requesting_road_terms(cost) if beside else nullcontext():
        scene = scene_from_args(args, run_config, both_cores=True)
    t_scene = clock.lap("scene")
    if beside:
        start_road_terms(scene, cost)
    try:
        return _set_up_and_plan(args, run_config, scene, clock, t_scene)
    finally:
        cancel_road_sdf(scene)  # a distance field the planner did not read (another planner, an error)


def _set_up_and_plan(args, run_config, scene, clock, t_scene) -> int:
    """The rest of :func:`run` once the scene is built: problem, planner (:func:`density_planner.api.set_up`),
    output process, then :func:`_plan_and_write`."""
    from ..api import default_distribution_seed, set_up
    from ..density.split import using_prediction_processes
    from ..parallel import default_workers

    dist_seed = default_distribution_seed(args.distribution_seed, args.seed)
    setup = set_up(scene, run_config, kind=args.kind, planner=args.planner, distribution_seed=dist_seed,
                   device=resolve_device(args.device), dtype=resolve_dtype(args.dtype),
                   progress=show_progress(args))
    out = out_dir(args.out)  # inputs are valid: only now create the output directory
    # the process that will draw the figures (and write solution.xml) loads its libraries while this one plans
    outputs = _OutputProcess.start(out, scene, setup.problem, run_config, gif=not args.no_gif,
                                   solution=args.kind == "commonroad")
    clock.lap("setup")
    # the exact re-check of the plan split over two cores (same figures)
    processes = min(2, default_workers()) if setup.context.device.type == "cpu" else None
    try:
        if default_workers() > 1:  # e.g. the density planner's route seeds on the second core, meanwhile
            setup.planner.prepare(setup.problem)
        with using_prediction_processes(processes):
            return _plan_and_write(args, setup, out, outputs, clock, t_scene)
    finally:  # an error, Ctrl-C or no plan: the output process ends here (after its files: nothing to do)
        from ..planners.routes import cancel_route_seeds

        cancel_route_seeds(setup.problem)
        if outputs is not None:
            outputs.cancel()


def _plan_and_write(args, setup, out, outputs, clock, t_scene) -> int:
    """The rest of :func:`run`: plan, judge (:func:`density_planner.api.judge`), write (through ``outputs``, an
    :class:`_OutputProcess`, if given)."""
    from ..api import PlanOutcome, judge, write_plan_figures, write_plan_solution
    from ..config import dumps_toml
    from ..io.atomic import atomic_write_json, atomic_write_text

    scene, problem, run_config = setup.scene, setup.problem, setup.run_config
    result = setup.planner.plan(problem)
    clock.lap("plan")

    verdict = judge(setup, result)
    clock.lap("verdict")
    outcome = PlanOutcome(setup, result, verdict)
    body = outcome.body()
    if body is not None and outputs is not None:  # the figures start now; plan.json is written meanwhile
        outputs.send(result, verdict, body)
    atomic_write_text(out / "config.toml", dumps_toml(run_config))
    summary = outcome.summary()
    summary.update({
        "scene_build_time_s": t_scene,
        "versions": versions(),
        "command": "density-planner " + " ".join(getattr(args, "argv", []) or []),
    })
    atomic_write_json(out / "plan.json", summary)
    written = ["plan.json", "config.toml"]
    if body is not None and outputs is not None:
        written += outputs.wait()
        clock.lap("outputs")
        summary["output_process_timings"] = outputs.laps
    elif body is not None:  # no fork: in turn, here
        if args.kind == "commonroad":
            write_plan_solution(out / "solution.xml", scene, result, problem, run_config)
            written.append("solution.xml")
            clock.lap("solution")
        written += write_plan_figures(out, scene, result, verdict, gif=not args.no_gif, clock=clock, body=body)
    # wall time of each step of this command (start-up before run() excluded), for benchmarks/bench_plan_command.py
    summary["command_timings"] = clock.laps
    atomic_write_json(out / "plan.json", summary)
    dist = float("nan") if verdict is None else verdict.details.get("final_goal_distance", float("nan"))
    p_max = float(result.collision.max) if result.collision is not None else float("nan")
    coll = result.collision
    p_any = "" if coll is None or coll.any_time is None else (
        f" (at some time >= {float(coll.any_time):.3f}" + (
            "" if coll.any_time_upper is None else f", <= {float(coll.any_time_upper):.3f}") + ")")
    print(f"{result.planner} on {scene.name}: {'no plan' if verdict is None else verdict.summary()}; final "
          f"distance to the goal {dist:.2f} m; collision probability max {p_max:.3f}{p_any}; planning time "
          f"{result.timings.get('total', float('nan')):.2f} s; wrote {', '.join(str(out / w) for w in written)}")
    if verdict is None:
        print(f"density-planner: planning {result.status.value}: {result.message}", flush=True)
    from . import plan_exit_code

    return plan_exit_code(verdict)


class _Clock:
    """Wall time per named step (``laps``) and since creation (``laps["total"]``)."""

    def __init__(self) -> None:
        self.t0 = self.t = time.perf_counter()
        self.laps: dict[str, float] = {}

    def lap(self, name: str) -> float:
        now = time.perf_counter()
        dt = now - self.t
        self.laps[name] = self.laps.get(name, 0.0) + dt
        self.laps["total"] = now - self.t0
        self.t = now
        return dt


class _OutputProcess:
    """solution.xml and the figures of a plan (:func:`density_planner.api.write_plan_solution`,
    :func:`density_planner.api.write_plan_figures`), written by a
    process forked before planning: it imports and warms the plotting and CommonRoad writing libraries on the
    second core while this process plans (~0.5-0.8 s of the command's wall time otherwise), then waits for the plan
    (:meth:`send`: the result, verdict and footprint are sent through a pipe, ~1 MB; this process writes plan.json
    meanwhile, then :meth:`wait` s for the files). ``None`` from
    :meth:`start` where ``fork`` does not exist."""

    def __init__(self, proc, conn) -> None:
        self.proc, self.conn = proc, conn
        self.laps: dict[str, float] = {}

    @classmethod
    def start(cls, out, scene, problem, run_config, *, gif: bool, solution: bool) -> _OutputProcess | None:
        import multiprocessing as mp
        import sys

        if "fork" not in mp.get_all_start_methods():
            return None
        ctx = mp.get_context("fork")
        here, there = ctx.Pipe()
        for stream in (sys.stdout, sys.stderr):  # the child would print what is still buffered here once more
            stream.flush()
        # not a daemon: it forks the process that draws the GIF (write_plan_figures); it ends when this one closes
        # its end of the pipe (cancel, or this process's death)
        proc = ctx.Process(target=_output_process, args=(there, here, out, scene, problem, run_config, gif, solution))
        proc.start()
        there.close()
        return cls(proc, here)

    def send(self, result, verdict, body) -> None:
        """Send the plan: its files are written from now on (:meth:`wait` for them)."""
        import pickle

        try:  # plain pickling (torch's multiprocessing reductions would pass shared memory by file descriptor)
            self.conn.send_bytes(pickle.dumps((result, verdict, body), protocol=pickle.HIGHEST_PROTOCOL))
        except (OSError, BrokenPipeError):  # the process ended: wait() reports it
            pass

    def wait(self) -> list[str]:
        """Wait until the files of the plan :meth:`send` sent are written; returns their names."""
        try:
            status, value, laps = self.conn.recv()
        except (EOFError, OSError, BrokenPipeError):
            status, value, laps = "error", None, {}
        self.proc.join()
        self.conn.close()
        self.laps = laps or {}
        if status != "ok":
            cause = value or f"the process writing them ended with exit code {self.proc.exitcode}"
            raise RuntimeError(f"writing the figures and solution of the plan failed ({cause}); rerun with --no-gif "
                               "or --debug")
        return value

    def cancel(self) -> None:
        """No plan to write (or an error or Ctrl-C here): end the process now (its files are written atomically, so
        none is left half-written). Nothing happens after :meth:`wait`."""
        from ..parallel import end_child

        end_child(self.proc, self.conn)


def _output_process(conn, parent_end, out, scene, problem, run_config, gif: bool, solution: bool) -> None:
    """Target of :class:`_OutputProcess`: warm up, wait for ``(result, verdict, body)`` (the pipe's end: nothing to
    write), write the files, answer ``("ok", names, laps)`` or ``("error", message, laps)``."""
    import gc

    from ..parallel import enter_child

    # Ctrl-C is the parent's (it ends this process: cancel); the warm-up takes only a core the planner's helpers
    # (road distance field, route seeds) leave idle
    enter_child(threads=1, nice=19)
    parent_end.close()  # the parent's end, inherited: else the pipe never reports the parent's end
    from ..viz.plan import warm_up

    try:
        warm_up(scene)
    except Exception:  # noqa: BLE001 - only a warm-up: drawing the plan's figure reports what is wrong
        pass
    if solution:
        from ..io.commonroad_solution import preload

        preload(run_config.solution)
    import pickle

    # the warm-up's garbage collected now, and every object alive so far (matplotlib's, the warm-up's) moved out of
    # the collector's sight: a full collection while the figures are drawn then scans only what they make (it
    # scanned the whole heap, ~0.15 s of plan.png's time)
    gc.collect()
    gc.freeze()
    try:
        result, verdict, body = pickle.loads(conn.recv_bytes())
    except EOFError:  # the parent ended or cancelled
        return
    from ..api import write_plan_figures, write_plan_solution

    clock = _Clock()
    try:
        written = []
        if solution:
            write_plan_solution(out / "solution.xml", scene, result, problem, run_config)
            written.append("solution.xml")
            clock.lap("solution")
        written += write_plan_figures(out, scene, result, verdict, gif=gif, clock=clock, body=body)
        conn.send(("ok", written, clock.laps))
    except Exception as exc:  # noqa: BLE001 - reported by the parent as one line
        conn.send(("error", f"{type(exc).__name__}: {exc}", clock.laps))

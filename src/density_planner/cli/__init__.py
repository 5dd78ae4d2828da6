"""Command-line interface: ``density-planner <command> ...``.

Each command lives in its own module with a ``register(subparsers, groups)`` function that adds its parser and
sets ``func``. Grouped commands (``train controller``, ``validate density``, ``data density``) register into the
shared groups. Every error is printed as one line (``--debug`` shows the traceback instead) with one exit-code
rule: 2 for bad input (arguments, configuration, files, data), 1 for an internal failure, 3 when ``plan`` made a
plan that failed its verdict (see :data:`EXIT_BAD_INPUT`, :func:`classify_error`, :func:`plan_exit_code`).
"""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import os
import sys
from collections.abc import Sequence

from ..errors import DensityPlannerError

__all__ = ["main", "console", "build_parser"]

#: command modules, in the order they appear in ``--help``
COMMAND_MODULES = ("env", "density", "controller", "density_nn", "plan", "drive", "risk", "bench")

#: command groups with sub-commands: name -> help
GROUPS = {
    "train": "train a model (controller or density predictor)",
    "validate": "validate a model and write a report with figures",
    "data": "generate training data",
}


class _VersionAction(argparse.Action):
    """``--version``: print the installed version and exit. It is looked up only then (importlib.metadata and the
    package's metadata take ~0.05 s of every command's start-up otherwise)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="show program's version number and exit"):  # noqa: A002 - argparse's keyword
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from .. import __version__

        print(f"density-planner {__version__}", flush=True)
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="density-planner",
        description="Risk-minimising motion planning with Liouville density propagation.",
    )
    parser.add_argument("--version", action=_VersionAction)
    parser.add_argument("--debug", action="store_true", help="show full tracebacks on errors")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    groups: dict[str, argparse._SubParsersAction] = {}
    for module_name in COMMAND_MODULES:
        module = importlib.import_module(f"{__name__}.{module_name}")
        module.register(sub, groups)
    return parser


def group(sub: argparse._SubParsersAction, groups: dict, name: str) -> argparse._SubParsersAction:
    """Sub-parsers of the command group ``name`` (created on first use)."""
    if name not in groups:
        p = sub.add_parser(name, help=GROUPS[name], description=GROUPS[name])
        groups[name] = p.add_subparsers(dest=f"{name}_what", metavar="WHAT")
        groups[name].required = True
    return groups[name]


#: exit codes (README, "Bad input"): 0 success; 1 internal failure (a bug, a solver or planner failure without a
#: plan, out of memory, a full disk); 2 bad input (arguments, configuration, files, data, missing optional extras);
#: 3 ``plan`` made a plan but it failed its verdict (every file still written); 130 interrupted
EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_VERDICT_FAILED, EXIT_INTERRUPTED = 0, 1, 2, 3, 130


def plan_exit_code(verdict) -> int:
    """Exit code of ``plan`` from its plan's verdict: 0 passed, 3 failed, 1 no plan (``None``)."""
    if verdict is None:
        return EXIT_FAILURE
    return EXIT_OK if verdict.ok else EXIT_VERDICT_FAILED

#: OSErrors that are the user's input (a path that is missing, not a directory, not readable)
_INPUT_OS_ERRORS = (FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError, FileExistsError)

#: integer options that are seeds: one rule for all of them (:func:`density_planner.checks.check_seed`)
_SEED_OPTIONS = ("seed", "distribution_seed")


def classify_error(exc: BaseException) -> int:
    """Exit code of an exception: :data:`EXIT_BAD_INPUT` for bad input, :data:`EXIT_FAILURE` otherwise."""
    if isinstance(exc, (ValueError, DensityPlannerError, ImportError, _INPUT_OS_ERRORS)):
        return EXIT_BAD_INPUT
    return EXIT_FAILURE


def _check_seeds(args: argparse.Namespace) -> None:
    from ..checks import check_seed

    for name in _SEED_OPTIONS:
        value = getattr(args, name, None)
        if value is not None:
            check_seed("--" + name.replace("_", "-"), value)


def _remove_if_created_empty(path, existed: bool) -> None:
    """Remove ``--out`` if this run created it and left it empty (a rejected command leaves no directory)."""
    if path is None or existed:
        return
    try:
        if path.is_dir() and not any(path.iterdir()):
            path.rmdir()
    except OSError:  # pragma: no cover - best effort
        pass


def console() -> None:
    """The ``density-planner`` console script and ``python -m density_planner``: :func:`main`, then exit.

    Commands that set ``fast_exit`` (``plan``, ``drive``: every file written, no worker processes left) end with
    ``os._exit`` once the output streams and logs are flushed: the interpreter's teardown (freeing the scene's
    grids, finalising torch and matplotlib) took 0.5-1 s of a ``plan`` command's wall time
    (``benchmarks/bench_plan_command.py``). Other commands exit normally (their worker pools shut down at exit).

    Python's cyclic garbage collector is off while the command's modules are imported and then sees only what the
    command makes (:func:`_start_up_done`): importing torch set off three full collections (~0.1 s), and every later
    full collection scanned the whole imported heap again (~0.1 s each, in this process and in every forked one)."""
    global _START_UP
    gc.disable()
    _START_UP = True
    _prefetch_scene(sys.argv[1:])
    code = main(fast_exit=True)
    sys.exit(code)


#: whether :func:`console` turned the garbage collector off for the start-up (:func:`_start_up_done` turns it on)
_START_UP = False


def _start_up_done() -> None:
    """After the console script's imports: the objects alive so far (modules, torch, the parser) moved to the
    collector's permanent generation (``gc.freeze``: never scanned again, nor written to by a collection in a forked
    process, whose memory pages then stay shared), and the collector turned back on."""
    global _START_UP
    if _START_UP:
        _START_UP = False
        gc.freeze()
        gc.enable()


#: commands whose ``--env commonroad --file F`` scene is read by a second process while this one imports torch
_PREFETCH_COMMANDS = ("plan", "drive")


def _prefetch_scene(argv: Sequence[str]) -> None:
    """Start reading the CommonRoad file of a ``plan`` / ``drive`` command line in a second process
    (:mod:`density_planner.prefetch`; ~0.2-1 s of the command's start-up). A light look at the raw arguments only:
    the parser (built later) decides what they mean, and an unused read is ended at exit."""
    if len(argv) < 3 or argv[0] not in _PREFETCH_COMMANDS or "commonroad" not in argv or "-h" in argv \
            or "--help" in argv:
        return
    files = [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--file"]
    files += [a.split("=", 1)[1] for a in argv if a.startswith("--file=")]
    if len(files) == 1 and files[0].lower().endswith(".xml"):
        from ..prefetch import start_commonroad_read

        start_commonroad_read(files[0])


def _exit_now(code: int) -> None:
    """Flush what the command printed or logged, then end the process without the interpreter's teardown."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # pragma: no cover - a closed pipe
            pass
    os._exit(code)


def main(argv: Sequence[str] | None = None, *, fast_exit: bool = False) -> int:
    """Run one command; returns its exit code. ``fast_exit`` (the console script): end the process at once after
    a command that allows it (:func:`console`)."""
    code, allowed = _main(argv)
    if fast_exit and allowed:
        _exit_now(code)
    return code


def _main(argv: Sequence[str] | None) -> tuple[int, bool]:
    """Exit code of the command, and whether the command allows :func:`_exit_now` (``set_defaults(fast_exit=
    True)``)."""
    parser = build_parser()  # imports every command's module (torch among them)
    _start_up_done()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    args.argv = argv
    allowed = bool(getattr(args, "fast_exit", False))
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    out = getattr(args, "out", None)
    out_existed = out is None or out.exists()
    try:
        from ._common import apply_threads

        _check_seeds(args)
        apply_threads(getattr(args, "threads", None))
        result = args.func(args)
    except KeyboardInterrupt:
        _remove_if_created_empty(out, out_existed)
        print("density-planner: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED, False
    except Exception as exc:  # noqa: BLE001 - every error becomes one line and an exit code (--debug: traceback)
        _remove_if_created_empty(out, out_existed)
        if args.debug:
            raise
        code = classify_error(exc)
        text = str(exc).strip()
        message = text.splitlines()[0] if text else type(exc).__name__
        if isinstance(exc, MemoryError):
            message = ("out of memory" + (f" ({message})" if text else "") + "; reduce the size of the request "
                       "(e.g. --samples, --envs, the scene's cell_size or n_slices)")
        elif code != EXIT_BAD_INPUT:
            message = f"internal error: {type(exc).__name__}: {message} (run with --debug for the traceback)"
        print(f"density-planner: error: {message}", file=sys.stderr)
        return code, False
    if result and out is not None:
        _remove_if_created_empty(out, out_existed)
    return int(result or 0), allowed


if __name__ == "__main__":  # pragma: no cover
    console()

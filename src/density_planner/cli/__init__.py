"""Command-line interface: ``density-planner <command> ...``.

Each command lives in its own module with a ``register(subparsers, groups)`` function that adds its parser and
sets ``func``. Grouped commands (``train controller``, ``validate density``, ``data density``) register into the
shared groups. Errors caused by user input are printed as one line and give exit code 2 (``--debug`` shows the
traceback instead).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from ..errors import DensityPlannerError

__all__ = ["main", "build_parser"]

#: command modules, in the order they appear in ``--help``
COMMAND_MODULES = ("env", "density", "controller", "density_nn", "plan", "risk", "bench")

#: command groups with sub-commands: name -> help
GROUPS = {
    "train": "train a model (controller or density predictor)",
    "validate": "validate a model and write a report with figures",
    "data": "generate training data",
}


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="density-planner",
        description="Risk-minimising motion planning with Liouville density propagation.",
    )
    parser.add_argument("--version", action="version", version=f"density-planner {__version__}")
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


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    args.argv = argv
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    try:
        from ._common import apply_threads

        apply_threads(getattr(args, "threads", None))
        result = args.func(args)
    except KeyboardInterrupt:
        print("density-planner: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, ImportError, RuntimeError, DensityPlannerError) as exc:
        if args.debug:
            raise
        text = str(exc).strip()
        message = text.splitlines()[0] if text else type(exc).__name__
        if not isinstance(exc, (ValueError, OSError, DensityPlannerError, ImportError)):
            message = f"{type(exc).__name__}: {message} (run with --debug for the traceback)"
        print(f"density-planner: error: {message}", file=sys.stderr)
        return 2
    return int(result or 0)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

"""Planner registry: names usable with ``density-planner plan --planner NAME`` and in benchmark sweeps.

A planner is registered once, with everything the rest of the package needs to know about it::

    @register_planner("my_planner", "one line for --help", section="my_planner", label="MP", colour="tab:pink")
    def _make(ctx: PlannerContext) -> MyPlanner:
        return MyPlanner(ctx.predictor(), ctx.config.my_planner)

The :class:`PlannerInfo` holds the factory ``factory(context) -> Planner``, the help line, the run-configuration
section its settings live in (seeded per run by the benchmarks and part of their configuration hash), its
:class:`ExecutionMode` (how the evaluation executes it), whether it plans from the true state (the benchmarks then
plan once per measurement variant, and its records do not depend on the tracking controller and the density
predictor) and its label and colour in tables and figures. The CLI, the benchmarks, the reports and the figures all
read it (:func:`planner_info`); nothing else lists planners. The :class:`PlannerContext` carries the system, the
tracking controller, a lazily built density predictor, the run configuration and device/progress settings.
"""

from __future__ import annotations

import enum
import importlib
from collections.abc import Callable
from dataclasses import dataclass

from .base import Planner
from .context import PlannerContext

__all__ = ["PlannerContext", "ExecutionMode", "PlannerInfo", "register_planner", "planner_info", "make_planner",
           "planner_names", "planner_help"]


class ExecutionMode(str, enum.Enum):
    """How the evaluation executes a planner's output (:mod:`density_planner.evaluation.simulate`)."""

    #: the planned reference (from the initial distribution) is tracked by the controller in closed loop
    TRACK = "track"
    #: the planner runs step by step from the measured state: ``plan_from(problem, true_state)`` (MPC, online)
    RECEDING = "receding"
    #: the planner plans from the true state and its inputs are applied open loop: ``plan_from`` (oracle)
    OPEN_LOOP = "open_loop"


@dataclass(frozen=True)
class PlannerInfo:
    """A planner's registration (see the module docstring)."""

    #: registry name (``--planner NAME``, record file names)
    name: str
    #: ``factory(context) -> Planner``
    factory: Callable[[PlannerContext], Planner]
    #: one line for ``--help``
    help: str
    #: the :class:`~density_planner.settings.RunConfig` section (attribute) its settings live in, or ``None``
    section: str | None = None
    #: further sections its results depend on (part of the benchmarks' configuration hash)
    reads: tuple[str, ...] = ()
    #: how the evaluation executes it
    execution: ExecutionMode = ExecutionMode.TRACK
    #: it plans from the true initial state (MPC, oracle): one plan per measurement variant, and its results do not
    #: depend on the tracking controller and the density predictor
    plans_from_true_state: bool = False
    #: short name in tables and figures (the paper's: DP, M0, O, ...)
    label: str = ""
    #: matplotlib colour in figures (``None``: one picked from the name)
    colour: str | None = None


_REGISTRY: dict[str, PlannerInfo] = {}

#: modules whose import registers planners (optional extras are imported lazily by their factories)
_PLANNER_MODULES = ("density_planner", "mpc", "oracle", "search", "sampling", "online")


def register_planner(
    name: str,
    help: str,
    *,
    section: str | None = None,
    reads: tuple[str, ...] = (),
    execution: ExecutionMode | str = ExecutionMode.TRACK,
    plans_from_true_state: bool = False,
    label: str | None = None,
    colour: str | None = None,
) -> Callable[[Callable[[PlannerContext], Planner]], Callable[[PlannerContext], Planner]]:
    """Decorator registering ``factory(context) -> Planner`` under ``name`` with its :class:`PlannerInfo` fields
    (``label`` defaults to ``name``)."""
    mode = ExecutionMode(execution)

    def deco(factory: Callable[[PlannerContext], Planner]) -> Callable[[PlannerContext], Planner]:
        if name in _REGISTRY and _REGISTRY[name].factory is not factory:
            raise ValueError(f"planner {name!r} registered twice")
        _REGISTRY[name] = PlannerInfo(name, factory, help, section=section, reads=tuple(reads), execution=mode,
                                      plans_from_true_state=plans_from_true_state, label=label or name,
                                      colour=colour)
        return factory

    return deco


def _load_all() -> None:
    for module in _PLANNER_MODULES:
        importlib.import_module(f"{__package__}.{module}")


def planner_names() -> list[str]:
    """Registered planner names."""
    _load_all()
    return list(_REGISTRY)


def planner_help() -> dict[str, str]:
    _load_all()
    return {name: info.help for name, info in _REGISTRY.items()}


def planner_info(name: str, *, default: bool = False) -> PlannerInfo:
    """The registration of planner ``name``. Unknown names raise ``ValueError`` listing the valid ones, or, with
    ``default=True`` (records of planners no longer registered), give a bare :class:`PlannerInfo` (label = name,
    tracked execution)."""
    _load_all()
    if name not in _REGISTRY:
        if default:
            return PlannerInfo(name, _unregistered, "", label=name)
        raise ValueError(f"unknown planner {name!r}; valid choices: {', '.join(_REGISTRY)}")
    return _REGISTRY[name]


def _unregistered(context: PlannerContext) -> Planner:  # pragma: no cover - never called
    raise ValueError("this planner is not registered")


def make_planner(name: str, context: PlannerContext) -> Planner:
    """The planner ``name`` built from ``context``; its ``execution_mode`` is the registration's."""
    info = planner_info(name)
    planner = info.factory(context)
    planner.execution_mode = info.execution  # type: ignore[attr-defined]
    return planner

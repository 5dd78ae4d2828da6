"""The paper's benchmark settings (§V): which planners, measurement variants and environments each sweep runs.

See :mod:`density_planner.evaluation.benchmark` for what a sweep does with them.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Setting", "SETTINGS", "VARIANTS", "planner_variants"]


@dataclass(frozen=True)
class Setting:
    """A benchmark setting of the paper."""

    name: str
    #: planners compared (registry names)
    planners: tuple[str, ...]
    #: measurement variants of every run
    variants: tuple[str, ...]
    #: number of environments when ``--envs`` is not given
    default_envs: int
    #: execute the plans in closed loop (False: the ablation compares the planned references)
    closed_loop: bool
    description: str = ""
    #: configuration sections its scenes are built from (the others cannot change its records' numbers)
    scene_sections: tuple[str, ...] = ("random_scene",)


SETTINGS: dict[str, Setting] = {
    "ablation": Setting(
        "ablation", ("density", "search", "sampling"), ("nominal",), 10, False,
        description="gradient vs search vs sampling optimisation of the reference (planned references)",
    ),
    "artificial": Setting(
        "artificial", ("density", "mpc", "tube_mpc_0.3", "tube_mpc_0.5", "tube_mpc_1.0", "oracle"),
        ("unbiased", "biased"), 50, True,
        description="all planners on random artificial scenes, perfect and biased heading measurement",
    ),
    "real": Setting(
        "real", ("density", "mpc", "tube_mpc_0.5", "oracle"), ("unbiased", "biased"), 30, True,
        description="density planner, M0, M2 and oracle on recorded traffic (inD, or the shipped CommonRoad scenes)",
        scene_sections=("ind", "commonroad"),
    ),
    "commonroad": Setting(
        "commonroad", ("density", "mpc"), ("unbiased",), 0, True,
        description="every CommonRoad scenario of --scenarios DIR as its author posed it, judged by the verdict "
        "(evaluation/commonroad_bench.py)",
        scene_sections=("commonroad",),
    ),
}

#: every measurement variant: ``nominal`` (the ablation's planned references), ``unbiased``, ``biased`` heading
VARIANTS = ("nominal", "unbiased", "biased")


def planner_variants(planner: str, variants: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """The variants run for ``planner``: only the first for a planner executed open loop (the oracle: it plans from
    the true state and measures nothing, so the heading bias cannot matter), else all."""
    from ..planners.registry import ExecutionMode, planner_info

    if planner_info(planner, default=True).execution == ExecutionMode.OPEN_LOOP:
        return tuple(variants[:1])
    return tuple(variants)

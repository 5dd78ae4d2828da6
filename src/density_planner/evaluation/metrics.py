"""Scores of one executed run and their aggregation over environments (paper §V, ``docs/spec.md`` §13).

Per run (:func:`run_metrics`), on the executed trajectory ``x(t_k)`` (0.1-s grid, weight one):

* ``goal_cost`` J_G = ||p(t_N) - p_goal||^2 [m^2] and ``final_distance`` = its square root [m];
* ``input_cost`` J_I = sum_k ||u(t_k)||^2 of the inputs the method *plans* (the paper's definition: for a
  tracked reference the reference inputs, for MPC and oracle the applied inputs) and ``input_cost_applied`` of the
  inputs actually applied (for a tracked reference: the controller's outputs at the planning-grid times);
* ``bounds_cost`` J_B of the *evaluation* box (the car's state box, or the map for recorded scenes: see
  :attr:`EvaluationConfig.position_bounds`), not the tighter planning box;
* ``collision_cost`` J_C, the paper's surrogate (desired-position trick) along the trajectory;
* ``collision_probability``: the collision probability of the executed trajectory, which for a single trajectory
  is the occupancy seen by the vehicle's body at every time (``per_slice``, ``max``, ``sum``;
  :class:`~density_planner.risk.collision.CollisionModel`);
* Monte-Carlo collision frequency over ``M`` initial states drawn from the planner's initial distribution, each
  executed like the run: ``mc_collision_mean`` = mean over samples of ``max_t P_body(x_i(t), t)`` (expected worst
  occupancy met) and ``mc_collision_frequency`` = fraction of samples whose ``max_t P_occ`` exceeds
  :attr:`EvaluationConfig.collision_threshold` (0.5); also ``mc_final_distance_mean`` [m].

Failure (:func:`failure_flags`): no solution, ``J_C > 10``, final distance > 4.5 m, or ``J_B > 1e-4``. On road
scenes (CommonRoad) the verdict decides instead (:func:`~density_planner.evaluation.verdict.verdict_failure`): a run
fails unless its verdict is a success, with the failed parts as reasons (``goal``, ``collision``, ``off_road``,
``outside_model``).

Aggregation (:func:`summarise`), per method = (planner, variant):

* failure rate = failed runs / runs;
* CRI, GCI, ICI: for every environment the minimum collision / goal / input cost over the methods that are
  *valid* (not failed) there; every valid method accumulates its excess over that minimum; the reported value is
  the mean over the method's valid runs (so a method is only compared where it did not fail, against the best
  valid method there);
* offline time, online time per step, final distance, collision probability: means over valid runs only (the
  paper's code divided sums that still contained failed runs by the number of valid runs);
* Monte-Carlo figures: means over all runs that have them (a failed run's risk is informative too).
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import torch
from torch import Tensor

from ..cost.composite import CostConfig
from ..cost.terms import BoundsCost, CollisionCost, CostInputs
from ..environment.scene import Scene
from ..risk.collision import CollisionModel
from .config import EvaluationConfig

__all__ = [
    "evaluation_box",
    "run_metrics",
    "monte_carlo_metrics",
    "failure_flags",
    "FAILURE_REASONS",
    "MethodSummary",
    "cost_increase",
    "summarise",
    "method_key",
]

#: failure reasons, in the order they are reported
FAILURE_REASONS = ("no_solution", "collision", "goal", "bounds")

#: costs compared against the best valid method per environment: summary name -> metric
INCREASE_METRICS = {"cri": "collision_cost", "gci": "goal_cost", "ici": "input_cost"}


def evaluation_box(scene: Scene, state_min: Sequence[float], state_max: Sequence[float],
                   position_bounds: str = "auto") -> tuple[tuple[float, ...], tuple[float, ...]]:
    """``(low, high)`` of the evaluation box: the car's state box, with the map extent as position bounds when
    ``position_bounds == "map"`` (or ``"auto"`` and the map does not lie inside the car's position box)."""
    low, high = list(map(float, state_min)), list(map(float, state_max))
    xmin, xmax, ymin, ymax = scene.grid.bounds
    inside = low[0] <= xmin and xmax <= high[0] and low[1] <= ymin and ymax <= high[1]
    if position_bounds == "map" or (position_bounds == "auto" and not inside):
        low[0], high[0], low[1], high[1] = xmin, xmax, ymin, ymax
    elif position_bounds not in ("auto", "car"):
        raise ValueError(f"unknown position_bounds {position_bounds!r}; valid choices: auto, car, map")
    return tuple(low), tuple(high)


def _slices(scene: Scene, n: int, plan_dt: float, device: torch.device | str = "cpu") -> Tensor:
    """Slices of the ``n`` planning times ``scene.t_start + k plan_dt`` (absolute; the grid's one conversion)."""
    t_start = scene.grid.t0 if scene.t_start is None else scene.t_start  # set by Scene.__post_init__
    return scene.grid.slices_for(t_start, plan_dt, n).to(device)


@torch.no_grad()
def run_metrics(
    scene: Scene,
    states: Tensor,
    planned_inputs: Tensor,
    applied_inputs: Tensor | None = None,
    *,
    box: tuple[Sequence[float], Sequence[float]],
    cost_config: CostConfig | None = None,
    plan_dt: float = 0.1,
    collision: CollisionModel | None = None,
) -> dict[str, Any]:
    """Scores of one executed trajectory ``states (T, nx)`` (planning grid, step ``plan_dt`` [s]) with the inputs
    ``planned_inputs (T - 1, nu)`` (J_I) and ``applied_inputs`` (``input_cost_applied``); see the module
    docstring. All values are plain floats (JSON-ready)."""
    cost_config = cost_config or CostConfig()
    states = states.detach().to("cpu", torch.float32)
    if states.ndim != 2 or states.shape[0] < 1:
        raise ValueError(f"states must have shape (T, nx) with T >= 1, got {tuple(states.shape)}")
    T = states.shape[0]
    slices = _slices(scene, T, plan_dt)
    model = (collision or CollisionModel(scene.grid)).to("cpu")
    goal = torch.tensor(scene.goal, dtype=states.dtype)
    j_g = float((model.positions(states[-1]) - goal).pow(2).sum())
    inputs = CostInputs.single(states, planned_inputs.detach().to("cpu", states.dtype), slices)
    bounds = BoundsCost(*box)
    collision_cost = CollisionCost(model, beta=cost_config.beta, plateau_scales=cost_config.plateau_scales)
    report = model.probability(states[None], slices)
    per_slice = [float(v) for v in report.per_slice]
    out = {
        "goal_cost": j_g,
        "final_distance": math.sqrt(j_g),
        "input_cost": float(planned_inputs.detach().double().pow(2).sum()),
        "input_cost_applied": float("nan") if applied_inputs is None else float(
            applied_inputs.detach().double().pow(2).sum()),
        "bounds_cost": float(bounds(inputs)),
        "collision_cost": float(collision_cost(inputs)),
        "collision_probability_max": max(per_slice),
        "collision_probability_sum": float(sum(per_slice)),
        "collision_probability": per_slice,
        "steps": T - 1,
    }
    return out


@torch.no_grad()
def monte_carlo_metrics(
    scene: Scene,
    trajectories: Sequence[Tensor],
    *,
    threshold: float = 0.5,
    plan_dt: float = 0.1,
    collision: CollisionModel | None = None,
) -> dict[str, Any]:
    """Collision frequency of Monte-Carlo trajectories (each ``(T_i, nx)``): ``mc_samples``, ``mc_collision_mean``
    (mean of ``max_t P_occ``) with its standard error ``mc_collision_se``, ``mc_collision_frequency`` (fraction
    with ``max_t P_occ > threshold``), ``mc_final_distance_mean`` [m]; ``None`` values without samples."""
    if not trajectories:
        return {"mc_samples": 0, "mc_collision_mean": None, "mc_collision_se": None, "mc_collision_frequency": None,
                "mc_final_distance_mean": None}
    model = (collision or CollisionModel(scene.grid)).to("cpu")
    goal = torch.tensor(scene.goal, dtype=torch.float32)
    worst, dist = [], []
    lengths = {int(t.shape[0]) for t in trajectories}
    if len(lengths) == 1:  # one batched call
        x = torch.stack([t.detach().to("cpu", torch.float32) for t in trajectories])  # (M, T, nx)
        slices = _slices(scene, x.shape[1], plan_dt)
        occ = model.occupancy(x, slices)  # (M, T)
        worst = occ.amax(-1).tolist()
        dist = (model.positions(x[:, -1]) - goal).norm(dim=-1).tolist()
    else:
        for t in trajectories:
            x = t.detach().to("cpu", torch.float32)
            slices = _slices(scene, x.shape[0], plan_dt)
            worst.append(float(model.occupancy(x, slices).max()))
            dist.append(float((model.positions(x[-1]) - goal).norm()))
    n = len(worst)
    mean = float(sum(worst) / n)
    return {
        "mc_samples": n,
        "mc_collision_mean": mean,
        # standard error of the mean (sample standard deviation / sqrt(n); 0 for one sample)
        "mc_collision_se": float(math.sqrt(sum((w - mean) ** 2 for w in worst) / (n - 1) / n)) if n > 1 else 0.0,
        "mc_collision_frequency": float(sum(1 for w in worst if w > threshold) / n),
        "mc_final_distance_mean": float(sum(dist) / n),
    }


def failure_flags(metrics: Mapping[str, Any] | None, solved: bool, config: EvaluationConfig,
                  *, cost_thresholds: bool = True) -> tuple[dict[str, bool], str]:
    """Failure flags of a run and the failure reason (the flagged reasons joined by ``+``, ``""`` if valid).

    ``solved`` is False when the planner returned no solution (or timed out, or raised); ``cost_thresholds``
    False checks only that (the ablation, as the paper). Non-finite costs count as exceeding the thresholds."""

    def above(key: str, limit: float) -> bool:
        v = None if metrics is None else metrics.get(key)
        return v is None or not math.isfinite(v) or v > limit

    flags = {
        "no_solution": not solved,
        "collision": cost_thresholds and above("collision_cost", config.max_collision_cost),
        "goal": cost_thresholds and above("final_distance", config.max_goal_distance),
        "bounds": cost_thresholds and above("bounds_cost", config.max_bounds_cost),
    }
    if metrics is None:
        flags["no_solution"] = True
    return flags, "+".join(r for r in FAILURE_REASONS if flags[r])


# ------------------------------------------------------------------------------------------------ aggregation
def method_key(record: Mapping[str, Any]) -> tuple[str, str, str]:
    """``(setting, planner, variant)`` of a record."""
    return (str(record["setting"]), str(record["planner"]), str(record["variant"]))


@dataclass
class MethodSummary:
    """Aggregated scores of one method (planner and variant) in one setting; times in seconds."""

    setting: str
    planner: str
    variant: str
    runs: int
    valid: int
    failures: int
    errors: int
    failure_rate: float
    cri: float
    gci: float
    ici: float
    final_distance: float
    goal_cost: float
    collision_cost: float
    input_cost: float
    collision_probability_max: float
    offline_time: float
    online_time: float
    mc_collision_mean: float
    mc_collision_frequency: float
    mc_runs: int
    failure_reasons: dict[str, int]

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _mean(values: Iterable[float | None]) -> float:
    vals = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return sum(vals) / len(vals) if vals else math.nan


def _metric(record: Mapping[str, Any], key: str) -> float | None:
    v = (record.get("metrics") or {}).get(key)
    return None if v is None else float(v)


def cost_increase(records: Sequence[Mapping[str, Any]], metric: str) -> dict[tuple[str, str, str], float]:
    """Mean excess of ``metric`` over the best valid method of each environment, per method (valid runs only).

    Environments are grouped by ``(setting, env)``; a method without valid runs gets NaN."""
    by_env: dict[tuple[str, str], list[Mapping[str, Any]]] = defaultdict(list)
    for r in records:
        by_env[(str(r["setting"]), str(r["env"]))].append(r)
    sums: dict[tuple[str, str, str], float] = defaultdict(float)
    counts: dict[tuple[str, str, str], int] = defaultdict(int)
    for group in by_env.values():
        scored = [(r, _metric(r, metric)) for r in group if not r.get("failed", True)]
        valid = [(r, v) for r, v in scored if v is not None and math.isfinite(v)]
        if not valid:
            continue
        best = min(v for _, v in valid)
        for r, v in valid:
            sums[method_key(r)] += v - best
            counts[method_key(r)] += 1
    keys = {method_key(r) for r in records}
    return {k: (sums[k] / counts[k] if counts[k] else math.nan) for k in keys}


def summarise(records: Sequence[Mapping[str, Any]]) -> list[MethodSummary]:
    """One :class:`MethodSummary` per (setting, planner, variant), in order of first appearance."""
    increases = {name: cost_increase(records, metric) for name, metric in INCREASE_METRICS.items()}
    groups: dict[tuple[str, str, str], list[Mapping[str, Any]]] = {}
    for r in records:
        groups.setdefault(method_key(r), []).append(r)
    out = []
    for key, rs in groups.items():
        valid = [r for r in rs if not r.get("failed", True)]
        reasons: dict[str, int] = defaultdict(int)
        for r in rs:
            for reason in (r.get("failure_reason") or "").split("+"):
                if reason:
                    reasons[reason] += 1
        mc = [r for r in rs if _metric(r, "mc_collision_frequency") is not None]
        out.append(MethodSummary(
            setting=key[0], planner=key[1], variant=key[2],
            runs=len(rs), valid=len(valid), failures=len(rs) - len(valid),
            errors=sum(1 for r in rs if r.get("status") == "error"),
            failure_rate=(len(rs) - len(valid)) / len(rs) if rs else math.nan,
            cri=increases["cri"][key], gci=increases["gci"][key], ici=increases["ici"][key],
            final_distance=_mean(_metric(r, "final_distance") for r in valid),
            goal_cost=_mean(_metric(r, "goal_cost") for r in valid),
            collision_cost=_mean(_metric(r, "collision_cost") for r in valid),
            input_cost=_mean(_metric(r, "input_cost") for r in valid),
            collision_probability_max=_mean(_metric(r, "collision_probability_max") for r in valid),
            offline_time=_mean((r.get("timings") or {}).get("offline") for r in valid),
            online_time=_mean((r.get("timings") or {}).get("online_per_step") for r in valid),
            mc_collision_mean=_mean(_metric(r, "mc_collision_mean") for r in mc),
            mc_collision_frequency=_mean(_metric(r, "mc_collision_frequency") for r in mc),
            mc_runs=len(mc),
            failure_reasons=dict(reasons),
        ))
    return out

"""Sampling-based optimiser (ablation baseline, paper §V "Trajectory optimization"; ``docs/spec.md`` §11).

An RRT-like tree of partial parameter sequences. Each new candidate is either a new root (a first segment
``(omega, a) ~ clip(0.5 N(0, 1), -3, 3)``), with probability ``10 / (n + 10)`` for ``n`` stored nodes, or the
extension of a stored node by one such random segment; the node to extend is drawn among the nodes whose
selection cost is at most the mean, with probability proportional to ``mean - cost``, and its selection cost
grows by 0.1 each time it is chosen (so that the tree does not keep extending the same node). Candidates are
scored with density predictions and the acceptance test of :mod:`._tree` (weights alpha_G 0.1, alpha_C 14,
alpha_B 1; the path cost has no input term); accepted ones are stored. The first solution found is returned.

``batch_size`` candidates are drawn and scored per predictor call (the original scored one at a time; batching
changes only the speed: the draws follow the same rule, each seeing the nodes stored before its batch).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..cost.composite import CostConfig, CostWeights
from ._tree import Node, TreeConfig, TreePlanner, _Context
from .registry import PlannerContext, register_planner

__all__ = ["SamplingConfig", "SamplingPlanner"]

log = logging.getLogger(__name__)


def _sampling_cost() -> CostConfig:
    return CostConfig(weights=CostWeights(goal=0.1, input=1e-3, bounds=1.0, collision=14.0), goal_far_factor=1.0)


@dataclass(frozen=True)
class SamplingConfig(TreeConfig):
    """Settings of the sampling-based optimiser (defaults: ``docs/spec.md`` §11)."""

    #: standard deviation of the random segment inputs (clipped to the input bounds)
    init_std: float = 0.5
    #: a new root is drawn with probability new_root_weight / (n + new_root_weight), n = stored nodes
    new_root_weight: float = 10.0
    #: added to a node's selection cost each time it is extended
    selection_penalty: float = 0.1
    #: candidates scored per predictor call
    batch_size: int = 25
    #: cost weights of the node scores (alpha_G 0.1, alpha_C 14, alpha_B 1)
    cost: CostConfig = field(default_factory=_sampling_cost)
    #: the original's sampling path cost has no input term
    include_input_cost: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("init_std", "new_root_weight", "selection_penalty"):
            v = getattr(self, name)
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
        if isinstance(self.batch_size, bool) or not isinstance(self.batch_size, int) or self.batch_size < 1:
            raise ValueError(f"batch_size must be a positive integer, got {self.batch_size!r}")


class SamplingPlanner(TreePlanner):
    """RRT-like sampling over piecewise-constant reference inputs (see the module docstring)."""

    name = "sampling"
    config: SamplingConfig

    def __init__(self, predictor, config: SamplingConfig | None = None, **kwargs: Any):
        super().__init__(predictor, config or SamplingConfig(), **kwargs)

    def _segment(self, ctx: _Context, rng: np.random.Generator) -> torch.Tensor:
        lo, hi = ctx.problem.system.input_bounds
        u = self.config.init_std * rng.standard_normal(len(lo))
        return torch.from_numpy(np.clip(u, lo, hi))[:, None]

    def _select(self, sel_cost: np.ndarray, eligible: np.ndarray, rng: np.random.Generator) -> int | None:
        """Index of the node to extend, or None (no eligible node)."""
        idx = np.flatnonzero(eligible)
        if idx.size == 0:
            return None
        c = sel_cost[idx]
        weights = np.maximum(c.mean() - c, 0.0) + 1e-12  # below-mean nodes (equal ones only if all are equal)
        weights[c > c.mean()] = 0.0
        return int(idx[rng.choice(idx.size, p=weights / weights.sum())])

    def _search(self, ctx: _Context, rng: np.random.Generator):
        cfg = self.config
        S = ctx.problem.parameterization.n_segments
        nodes: list[Node] = []
        sel_cost: list[float] = []
        best_partial: Node | None = None
        history: list[float] = []
        n_roots = 0
        while self.time_left(ctx):
            cands: list[torch.Tensor] = []
            parent_goal: list[float] = []
            costs = np.asarray(sel_cost)
            eligible = np.array([n.depth < S for n in nodes], dtype=bool)
            for _ in range(cfg.batch_size):
                n = len(nodes)
                pick = None
                if rng.random() >= cfg.new_root_weight / (n + cfg.new_root_weight):
                    pick = self._select(costs, eligible, rng)
                if pick is None:
                    cands.append(self._segment(ctx, rng))
                    parent_goal.append(ctx.goal0)
                    n_roots += 1
                else:
                    costs[pick] += cfg.selection_penalty
                    cands.append(torch.cat([nodes[pick].params, self._segment(ctx, rng)], dim=-1))
                    parent_goal.append(nodes[pick].goal)
            sel_cost = costs.tolist()
            scores = self.score(ctx, cands, torch.tensor(parent_goal, dtype=torch.float64))
            accepted = self.make_nodes(cands, scores)
            solutions = [a for a in accepted if a.complete]
            if solutions:
                best = min(solutions, key=lambda a: a.cost)
                log.info("sampling: solution after %d predictor calls (%d nodes)", ctx.calls, len(nodes))
                return best, None, self._info(nodes, n_roots, history + [best.cost])
            for a in accepted:
                nodes.append(a)
                sel_cost.append(a.cost)
                if best_partial is None or (a.depth, -a.cost) > (best_partial.depth, -best_partial.cost):
                    best_partial = a
            if nodes:
                history.append(min(n.cost for n in nodes))
        return None, best_partial, self._info(nodes, n_roots, history)

    @staticmethod
    def _info(nodes: list[Node], n_roots: int, history: list[float]) -> dict[str, Any]:
        depth = [n.depth for n in nodes]
        return {"stored_nodes": len(nodes), "roots_drawn": n_roots, "max_depth": max(depth, default=0),
                "history": history}


@register_planner("sampling", "sampling-based optimiser: RRT-like tree of random 1-s segments (ablation)",
                  section="sampling", label="Sampling", colour="tab:olive")
def _make_sampling(ctx: PlannerContext) -> SamplingPlanner:
    return SamplingPlanner(ctx.predictor(), ctx.config.sampling, evaluation_cost=ctx.config.density_planner.cost,
                           dtype=ctx.dtype, device=ctx.device)

"""Search-based optimiser (ablation baseline, paper §V "Trajectory optimization"; ``docs/spec.md`` §11).

Best-first search over the ten one-second segments of the reference parameters: every node fixes the first
``d`` segments; its children append one segment with ``(omega, a)`` from a 5 x 5 lattice
(``{-2, -1, 0, 1, 2}^2``). The 25 children of a node are scored together in one density-predictor call
(:class:`~density_planner.planners._tree.TreePlanner`), accepted children enter a priority queue ordered by
their path cost ``alpha_C J_C + alpha_G J_G + alpha_I J_I`` (weights 10, 0.002, 0.1 x 0.01 of the original,
planning box bounds weight 1), and the cheapest node is expanded next. The first full-length solution taken from
the queue is returned (it is the cheapest node in the queue).
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..cost.composite import CostConfig, CostWeights
from ._tree import Node, TreeConfig, TreePlanner, _Context
from .registry import PlannerContext, register_planner

__all__ = ["SearchConfig", "SearchPlanner"]

log = logging.getLogger(__name__)


def _search_cost() -> CostConfig:
    # the original's weights; its J_I carried a factor 0.01, hence input = 0.1 * 0.01 on our sum of squares
    return CostConfig(weights=CostWeights(goal=0.002, input=1e-3, bounds=1.0, collision=10.0), goal_far_factor=1.0)


@dataclass(frozen=True)
class SearchConfig(TreeConfig):
    """Settings of the search-based optimiser (defaults: ``docs/spec.md`` §11)."""

    #: values of each input channel per segment (rad/s and m/s^2); the children are all pairs
    choices: tuple[float, ...] = (-2.0, -1.0, 0.0, 1.0, 2.0)
    #: cost weights of the node scores (alpha_G 0.002, alpha_I 0.1 x 0.01, alpha_B 1, alpha_C 10)
    cost: CostConfig = field(default_factory=_search_cost)

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.choices or not all(math.isfinite(c) for c in self.choices):
            raise ValueError(f"choices must be a non-empty list of finite numbers, got {self.choices!r}")


class SearchPlanner(TreePlanner):
    """Best-first search over piecewise-constant reference inputs (see the module docstring)."""

    name = "search"
    config: SearchConfig

    def __init__(self, predictor, config: SearchConfig | None = None, **kwargs: Any):
        super().__init__(predictor, config or SearchConfig(), **kwargs)

    def _children(self, node: Node) -> list[torch.Tensor]:
        vals = torch.tensor(self.config.choices, dtype=torch.float64)
        pairs = torch.cartesian_prod(vals, vals)  # (K^2, 2): omega, a
        return [torch.cat([node.params, pair[:, None]], dim=-1) for pair in pairs]

    def _search(self, ctx: _Context, rng: np.random.Generator):
        S = ctx.problem.parameterization.n_segments
        counter = itertools.count()
        root = Node(torch.zeros(ctx.problem.system.nu, 0, dtype=torch.float64), ctx.goal0, 0.0)
        queue: list[tuple[float, int, Node]] = [(0.0, next(counter), root)]
        best_partial: Node | None = None
        popped: list[float] = []
        expansions = 0
        while queue:
            cost, _, node = heapq.heappop(queue)
            if node.complete:
                log.info("search: solution after %d expansions, path cost %.4g", expansions, node.cost)
                return node, None, self._info(expansions, len(queue), popped)
            if node.depth >= S:
                continue
            if not self.time_left(ctx):
                heapq.heappush(queue, (cost, next(counter), node))
                done = sorted((e for e in queue if e[2].complete), key=lambda e: e[:2])
                if done:  # a full plan was found but not yet taken from the queue
                    return done[0][2], None, self._info(expansions, len(queue), popped)
                break
            popped.append(cost)
            children = self._children(node)
            scores = self.score(ctx, children, torch.full((len(children),), node.goal, dtype=torch.float64))
            expansions += 1
            for child in self.make_nodes(children, scores):
                heapq.heappush(queue, (child.cost, next(counter), child))
                if best_partial is None or (child.depth, -child.cost) > (best_partial.depth, -best_partial.cost):
                    best_partial = child
        return None, best_partial, self._info(expansions, len(queue), popped)

    @staticmethod
    def _info(expansions: int, queued: int, popped: list[float]) -> dict[str, Any]:
        return {"expansions": expansions, "queued": queued, "history": popped}


@register_planner("search", "search-based optimiser: best-first over 5x5 inputs per 1-s segment (ablation)",
                  section="search", label="Search", colour="tab:red")
def _make_search(ctx: PlannerContext) -> SearchPlanner:
    return SearchPlanner(ctx.predictor(), ctx.config.search, evaluation_cost=ctx.config.density_planner.cost,
                         dtype=ctx.dtype, device=ctx.device)

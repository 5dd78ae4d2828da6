"""The planner's cost ``J = alpha_G J_G + alpha_I J_I + alpha_B J_B + alpha_C J_C`` (paper Eq. (3)).

:class:`CostConfig` holds the weights and factors (defaults from ``docs/spec.md`` §9); :func:`build_cost` makes the
four terms for a scene; :class:`WeightedCost` evaluates the total and the per-term breakdown, optionally with a
per-candidate mask of active terms (the staged weights of the planner's first stage).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..environment.scene import Scene
from ..risk.collision import CollisionModel, RiskConfig
from ..systems.base import System
from .road import RoadCostConfig, with_road_terms
from .terms import BoundsCost, CollisionCost, CostInputs, CostTerm, GoalCost, InputCost

__all__ = ["CostWeights", "CostConfig", "CostBreakdown", "WeightedCost", "build_cost", "TERM_NAMES"]

TERM_NAMES = ("goal", "input", "bounds", "collision")


@dataclass(frozen=True)
class CostWeights:
    """Weights ``alpha`` of the cost terms (``docs/spec.md`` §9)."""

    #: alpha_G, goal distance [1/m^2]
    goal: float = 1e-2
    #: alpha_I, reference input effort; 1e-6 = the original's alpha_I (1e-4) times its input factor (0.01)
    input: float = 1e-6
    #: alpha_B, state-bound violations: dominates when a trajectory leaves the box
    bounds: float = 10.0
    #: alpha_C, collision surrogate J_C
    collision: float = 0.1

    def __post_init__(self) -> None:
        for name in TERM_NAMES:
            v = getattr(self, name)
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"cost weight {name} must be a finite number >= 0, got {v}")

    def as_dict(self) -> dict[str, float]:
        return {name: getattr(self, name) for name in TERM_NAMES}


@dataclass(frozen=True)
class CostConfig:
    """Cost terms and their factors."""

    weights: CostWeights = field(default_factory=CostWeights)
    #: step of the desired-position trick, in cells (paper's beta; the original used 100 cells = 10 m per unit
    #: of per-cell gradient)
    beta: float = 100.0
    #: wider stencils [cells] used where the occupancy gradient vanishes inside an obstacle (``docs/spec.md`` §8)
    plateau_scales: tuple[int, ...] = (5, 15, 25, 35, 45)
    #: J_G is multiplied by this while J_G >= goal_close_threshold during optimisation (original: 10; 1 = paper)
    goal_far_factor: float = 10.0
    #: [m^2] threshold of the goal-far factor and of switching on the bounds term in stage 1 (original: 3)
    goal_close_threshold: float = 3.0
    #: road terms on scenes with a road (goal region in time, road barrier); unused on random scenes
    road: RoadCostConfig = field(default_factory=RoadCostConfig)

    def __post_init__(self) -> None:
        if not math.isfinite(self.beta) or self.beta < 0:
            raise ValueError(f"beta must be >= 0, got {self.beta}")
        if any(s < 1 for s in self.plateau_scales):
            raise ValueError("plateau_scales must be positive cell counts")
        if self.goal_far_factor < 1:
            raise ValueError(f"goal_far_factor must be >= 1, got {self.goal_far_factor}")
        if self.goal_close_threshold <= 0:
            raise ValueError(f"goal_close_threshold must be > 0, got {self.goal_close_threshold}")


@dataclass
class CostBreakdown:
    """Total weighted cost and the unweighted terms, each ``(*batch,)``."""

    total: Tensor
    terms: dict[str, Tensor]

    def detach(self) -> CostBreakdown:
        return CostBreakdown(self.total.detach(), {k: v.detach() for k, v in self.terms.items()})

    def select(self, index) -> CostBreakdown:
        return CostBreakdown(self.total[index], {k: v[index] for k, v in self.terms.items()})

    def to_dict(self) -> dict[str, float]:
        out = {k: float(v) for k, v in self.terms.items()}
        out["total"] = float(self.total)
        return out


class WeightedCost:
    """Weighted sum of named cost terms."""

    def __init__(self, terms: Sequence[CostTerm], weights: Mapping[str, float]):
        self.terms = {t.name: t for t in terms}
        missing = set(self.terms) - set(weights)
        if missing:
            raise ValueError(f"no weight for cost term(s) {sorted(missing)}")
        self.weights = {name: float(weights[name]) for name in self.terms}

    def __call__(self, inputs: CostInputs, active: Mapping[str, Tensor] | None = None) -> CostBreakdown:
        """Evaluate all terms; ``active[name]`` (bool ``(M,)`` over the first batch dimension) switches a term off
        per candidate. Switched-off terms are not evaluated (their reported value is 0 there)."""
        active = active or {}
        values: dict[str, Tensor] = {}
        total: Tensor | float = 0.0
        for name, term in self.terms.items():
            mask = active.get(name)
            if mask is None or bool(mask.all()):
                v = term(inputs)
            elif not bool(mask.any()):
                v = inputs.x.new_zeros(inputs.x.shape[:-3])
            else:
                v = inputs.x.new_zeros(inputs.x.shape[:-3]).index_put((mask,), term(inputs.select(mask)))
            values[name] = v
            total = total + self.weights[name] * v
        assert isinstance(total, Tensor), "a cost needs at least one term"
        return CostBreakdown(total=total, terms=values)


def build_cost(
    scene: Scene,
    config: CostConfig | None = None,
    *,
    optimisation: bool = True,
    device: torch.device | str | None = None,
    system: System | None = None,
    risk: RiskConfig | None = None,
) -> WeightedCost:
    """The four cost terms for ``scene``: goal, input, bounds and collision.

    The bounds term keeps the positions in the scene's planning box and the other states in the system's planning
    bounds (``system.planning_bounds()``; the paper's X_MIN_MP / X_MAX_MP for the car); without a system only the
    positions (the first two state entries) are bounded.

    With ``optimisation=False`` the goal term has no far factor (the reported, paper-defined ``J_G``).
    ``system`` (positions, heading, body) and ``risk`` define collision (:class:`CollisionModel`); without a
    system the vehicle is a point at the first two state entries. On scenes with a road (``scene.road``) the goal
    term is the goal region in time and the road barrier ``"road"`` is added
    (:func:`~density_planner.cost.road.with_road_terms`).
    """
    config = config or CostConfig()
    xmin, xmax, ymin, ymax = scene.planning_box
    if system is None:
        bounds = BoundsCost((xmin, ymin), (xmax, ymax))
    else:
        lo, hi = (list(b) for b in system.planning_bounds())
        (ix, iy) = system.position_indices
        lo[ix], lo[iy], hi[ix], hi[iy] = xmin, ymin, xmax, ymax
        bounds = BoundsCost(lo, hi)
    goal = GoalCost(
        scene.goal,
        far_factor=config.goal_far_factor if optimisation else 1.0,
        close_threshold=config.goal_close_threshold,
        positions=None if system is None else system.positions,
    )
    # road scenes: road users only, the road is the barrier's
    model = CollisionModel.for_scene(scene, system, risk, device=device)
    collision = CollisionCost(model, beta=config.beta, plateau_scales=config.plateau_scales)
    terms, weights = with_road_terms(scene, config, [goal, InputCost(), bounds, collision], config.weights.as_dict(),
                                     optimisation=optimisation, device=device, system=system)
    return WeightedCost(terms, weights)

"""The planning problem: a scene, the initial-state distribution, the system and the reference parameterisation."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..control.reference import PiecewiseConstantInputs
from ..density.distributions import InitialDistribution, paper_gaussian_mixture
from ..environment.scene import Scene, validate_scene
from ..risk.collision import CollisionModel, RiskConfig
from ..systems.base import System
from ..systems.car import BIAS, KinematicCar

__all__ = ["PlanningProblem"]


@dataclass
class PlanningProblem:
    """Everything a planner needs.

    Attributes:
        scene: occupancy grid, nominal start, goal position and planning box.
        initial_distribution: law of the true initial state (full state, ``system.nx`` dimensions).
        system: the dynamics (default: the kinematic car).
        parameterization: reference-input parameterisation (10 segments of 1 s, 0.01-s fine grid, 0.1-s planning
            grid); its horizon must not exceed the scene's time span.
        risk: how collision is read (body) and its probability estimated (section ``[risk]``).
    """

    scene: Scene
    initial_distribution: InitialDistribution
    system: System = field(default_factory=KinematicCar)
    parameterization: PiecewiseConstantInputs = field(default_factory=PiecewiseConstantInputs)
    risk: RiskConfig = field(default_factory=RiskConfig)

    def collision(self, device: torch.device | str | None = None) -> CollisionModel:
        """The collision model of this problem (scene grid, system, risk settings) on ``device``."""
        grid = self.scene.grid if device is None else self.scene.grid.to(device)
        return CollisionModel(grid, self.system, self.risk)

    def __post_init__(self) -> None:
        validate_scene(self.scene)
        if not isinstance(self.initial_distribution, InitialDistribution):
            raise ValueError(
                f"initial_distribution must be an InitialDistribution, got {type(self.initial_distribution).__name__}"
            )
        if self.initial_distribution.dim != self.system.nx:
            raise ValueError(
                f"initial_distribution has dimension {self.initial_distribution.dim}, the system state has "
                f"{self.system.nx}"
            )
        grid = self.scene.grid
        span = grid.t0 + (grid.n_slices - 1) * grid.dt
        if self.parameterization.horizon > span + 1e-6:
            raise ValueError(
                f"planning horizon {self.parameterization.horizon} s exceeds the occupancy grid's time span {span} s"
            )

    @classmethod
    def from_scene(
        cls,
        scene: Scene,
        *,
        seed: int = 0,
        system: System | None = None,
        parameterization: PiecewiseConstantInputs | None = None,
        risk: RiskConfig | None = None,
    ) -> PlanningProblem:
        """The paper's default problem: its 5-component Gaussian mixture on the XE0 box around the scene start,
        drawn with ``seed``."""
        system = system or KinematicCar()
        half_width = getattr(getattr(system, "config", None), "initial_error_max", None)
        if half_width is None:
            raise ValueError("from_scene needs a system with config.initial_error_max (the XE0 box)")
        dist = paper_gaussian_mixture(scene.start, half_width, torch.Generator().manual_seed(seed))
        return cls(scene, dist, system, parameterization or PiecewiseConstantInputs(), risk or RiskConfig())

    def reference_start(self, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> Tensor:
        """Start of the reference: the mean of the initial distribution, with zero heading bias (the reference is
        the nominal, unbiased trajectory; the bias only enters the measurement)."""
        start = self.initial_distribution.mean.clone()
        if isinstance(self.system, KinematicCar):
            start[BIAS] = 0.0
        return start.to(dtype=dtype, device=device)

    @property
    def goal(self) -> tuple[float, float]:
        return self.scene.goal

"""Collision: the one owner of "is this state in collision, and with which probability".

:class:`CollisionModel` binds an occupancy grid to a system (which state entries are the position and the heading,
and the body, :mod:`density_planner.risk.body`). Every consumer calls it: the reported collision probability
(:meth:`CollisionModel.probability`), the cost surrogate ``J_C`` (:class:`~density_planner.cost.terms.CollisionCost`
reads :meth:`CollisionModel.centres` and :attr:`CollisionModel.body_grid`), the MPC and oracle CasADi terms (they
interpolate :attr:`CollisionModel.body_grid` at the disc centres), the evaluation metrics and figures.

**Occupancy of a state** ``P_body(x, t_k)``: the maximum over the body's disc centres ``c_j(x)`` of the disc-dilated
grid ``D_r`` at the nearest cell of ``c_j`` in the slice of ``t_k``; 1 when the state's *position* is outside the
map (it left the planning domain, as the paper's point vehicle). A disc centre beyond the border reads the nearest
border cell: the map's cells its disc reaches are all within ``r`` of that cell (the map is a convex box), so this is
still conservative for the map, and the border itself is not an obstacle (a car starting 2 m from the border of
the artificial map sticks out of it).

**Collision probability** ``P_coll(t_k) = E[P_body(x(t_k), t_k)]`` over the initial law ``rho0``, estimated from
samples ``x0_i ~ q0`` propagated to ``x_i(t_k)`` (docs/planner.md, "Collision probability"):

* ``"is"`` (default): self-normalised importance sampling, unbiased as ``N`` grows::

      w_i = rho0(x0_i) / q0(x0_i),   P_coll(t) = sum_i w_i P_body(x_i(t), t) / sum_i w_i

  The weights do not depend on the predicted log-density (the flow conserves probability mass).
* ``"paper"`` (paper §IV-B): samples binned into the nearest cell of their position; the densities
  ``rho(x_i(t), t)`` averaged per cell and normalised over the plane (``P_ego``); ``P_coll = sum_c P_ego(c) P(c)``
  with ``P(c)`` the mean body occupancy of the cell's samples (the cell's ``P_occ`` for a point). Equivalent to
  per-sample weights ``w_i = rho_i / (n_c(i) Z)``. Biased (docs/planner.md); kept to reproduce the paper.

Both report the standard error of the weighted mean from the effective sample size (delta method for a
self-normalised estimator): ``SE^2 = sum_i w_i^2 (P_i - P_coll)^2`` with normalised ``w``, and
``ESS = 1 / sum_i w_i^2``. For a single trajectory (one sample of weight 1) ``SE = 0``.

**Collision at some time** (``"is"`` only): ``max_t P_coll(t)`` is the worst *instant*; the probability that the
plan's execution collides at *some* time is larger when different executions meet obstacles at different times (two
equally likely executions, each certain to collide, one at 2 s and one at 3 s: ``max_t P_coll = 0.5``, collision
certain). The grid holds the marginal occupancy of each instant, not the joint law of an obstacle's path, so the
report gives the lower bound that holds for any joint law::

    P_any = sum_i w_i max_k P_body(x_i(t_k), t_k)  <=  P(collision at some t_k)

(for one execution, a collision at some time is at least as likely as at the worst instant), with its standard error
as above. It is the planner's own estimate of the Monte-Carlo ``mc_collision_mean`` of the benchmarks. The union
bound over the planning times gives the matching upper bound, which also holds for any joint law::

    P(collision at some t_k)  <=  P_any_upper = sum_i w_i min(1, sum_k P_body(x_i(t_k), t_k))

so the trajectory-level probability lies in ``[P_any, P_any_upper]`` (up to the estimators' standard errors). The
upper bound is loose where an execution stays near an obstacle for many steps (each step adds its marginal); it is
tight where the hits of one execution are confined to one instant.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from ..checks import check_choice, check_tensor
from ..environment.grid import OccupancyGrid
from ..systems.base import System
from .body import DiscCover, body_grid, masked_grid

__all__ = ["RiskConfig", "CollisionModel", "CollisionReport", "collision_probability", "collision_grid",
           "collision_mask", "ESTIMATORS", "ROAD_EDGES"]

ESTIMATORS = ("is", "paper")
ROAD_EDGES = ("barrier", "occupied")


@dataclass(frozen=True)
class RiskConfig:
    """How collision is read and how its probability is estimated (section ``[risk]``)."""

    #: "is": self-normalised importance sampling with w = rho0 / q0 (unbiased, default); "paper": the paper's
    #: density binning (§IV-B), biased, for reproducing its numbers
    estimator: Literal["is", "paper"] = "is"
    #: use the system's footprint (the car's rectangle through a cover of discs); false: a point vehicle (paper)
    body: bool = True
    #: discs covering a rectangular footprint; 0 = ceil(length / width) + 1 (4 for the car: 28 % area excess)
    n_discs: int = 0
    #: benchmarks: Monte-Carlo closed loops per tracked plan for the risk check (0 = no check; `bench
    #: --validate-risk` sets 10000); see density_planner.evaluation.risk_validation
    validate_samples: int = 0
    #: the road's edge on scenes with a road (CommonRoad), whose grid marks the cells off the drivable area occupied:
    #: "barrier" (default): the collision probability and the collision cost read the road users and static
    #: obstacles only (off-road cells read 0), the road is the road barrier's (cost.road, exact outline against the
    #: road's signed distance) and the verdict's ``on_road``; the MPC and oracle, which have no road term, still
    #: read off-road cells as occupied in their constraints. "occupied": off-road cells count as a collision
    #: (probability 1) everywhere (before; on a 3.5-m lane the body's disc cover, its grid dilation and the
    #: initial spread then read P_coll up to 1 at t = 0 for a car that is on the road)
    road_edge: Literal["barrier", "occupied"] = "barrier"

    def __post_init__(self) -> None:
        check_choice("risk.estimator", self.estimator, ESTIMATORS)
        check_choice("risk.road_edge", self.road_edge, ROAD_EDGES)
        if isinstance(self.n_discs, bool) or not isinstance(self.n_discs, int) or self.n_discs < 0:
            raise ValueError(f"risk.n_discs must be an integer >= 0 (0 = automatic), got {self.n_discs!r}")
        if isinstance(self.validate_samples, bool) or not isinstance(self.validate_samples, int) or not (
                self.validate_samples == 0 or self.validate_samples >= 2):
            raise ValueError(f"risk.validate_samples must be 0 (off) or an integer >= 2, got {self.validate_samples!r}")


@dataclass
class CollisionReport:
    """Collision probability per time slice with its standard error.

    Attributes:
        per_slice: ``(*batch, T)`` estimated probability of collision at each planning time.
        max: ``(*batch,)`` maximum over time.
        sum: ``(*batch,)`` sum over time (the discrete integral ``sum_k P_coll(t_k)``; not a probability).
        se: ``(*batch, T)`` standard error of ``per_slice`` (0 for a single trajectory).
        ess: ``(*batch, T)`` effective sample size ``1 / sum_i w_i^2``.
        estimator: ``"is"`` or ``"paper"``.
        any_time: ``(*batch,)`` collision at some time, the lower bound ``sum_i w_i max_k P_body(x_i(t_k))``
            (module docstring; ``None`` for the paper's estimator, whose weights change with time).
        any_time_se: ``(*batch,)`` its standard error.
        any_time_upper: ``(*batch,)`` the union bound ``sum_i w_i min(1, sum_k P_body(x_i(t_k)))`` on collision at
            some time (module docstring); any_time_upper_se: its standard error.
    """

    per_slice: Tensor
    max: Tensor
    sum: Tensor
    se: Tensor | None = None
    ess: Tensor | None = None
    estimator: str = "is"
    any_time: Tensor | None = None
    any_time_se: Tensor | None = None
    any_time_upper: Tensor | None = None
    any_time_upper_se: Tensor | None = None

    def to_dict(self) -> dict:
        out = {
            "estimator": self.estimator,
            "per_slice": self.per_slice.detach().cpu().tolist(),
            "max": self.max.detach().cpu().tolist(),
            "sum": self.sum.detach().cpu().tolist(),
        }
        if self.se is not None:
            out["se"] = self.se.detach().cpu().tolist()
            out["se_at_max"] = _at_argmax(self.per_slice, self.se).detach().cpu().tolist()
        if self.ess is not None:
            out["ess_min"] = self.ess.detach().amin(-1).cpu().tolist()
        if self.any_time is not None:
            out["any_time"] = self.any_time.detach().cpu().tolist()
            if self.any_time_se is not None:
                out["any_time_se"] = self.any_time_se.detach().cpu().tolist()
        if self.any_time_upper is not None:
            out["any_time_upper"] = self.any_time_upper.detach().cpu().tolist()
            if self.any_time_upper_se is not None:
                out["any_time_upper_se"] = self.any_time_upper_se.detach().cpu().tolist()
        return out


def _at_argmax(values: Tensor, other: Tensor) -> Tensor:
    idx = values.argmax(-1, keepdim=True)
    return other.gather(-1, idx).squeeze(-1)


class CollisionModel:
    """Collision of a system's body with an occupancy grid (module docstring).

    Args:
        grid: occupancy grid of the scene.
        system: the system (positions, heading, footprint); ``None`` means a point at the first two state entries.
        config: risk settings (estimator, body on/off, discs).
    """

    def __init__(self, grid: OccupancyGrid, system: System | None = None, config: RiskConfig | None = None, *,
                 ignore: Tensor | None = None):
        self.grid = grid
        self.system = system
        self.config = config or RiskConfig()
        #: ``(NX, NY)`` cells of ``grid`` that are not obstacles for collision (a road scene's off-road cells with
        #: ``road_edge = "barrier"``: the road barrier's); ``None``: every cell counts
        self.ignore = ignore
        if system is None or not self.config.body:
            from ..systems.base import Footprint

            footprint, has_heading = Footprint(), False
        else:
            footprint, has_heading = system.footprint, system.heading_index is not None
        self.cover = DiscCover.of(footprint, has_heading=has_heading, n_discs=self.config.n_discs)
        self.body_grid = body_grid(grid, self.cover.radius, ignore=ignore)

    @classmethod
    def for_scene(cls, scene, system: System | None = None, config: RiskConfig | None = None, *,
                  device: torch.device | str | None = None, road_edge: str | None = None) -> CollisionModel:
        """The model of ``scene``'s grid (on ``device``) with the cells :func:`collision_mask` leaves to the road
        barrier ignored; equal to ``CollisionModel(collision_grid(scene, ...), ...)`` without forming that grid."""
        grid = scene.grid if device is None else scene.grid.to(device)
        mask = collision_mask(scene, config, road_edge=road_edge)
        return cls(grid, system, config, ignore=mask)

    def to(self, device: torch.device | str) -> CollisionModel:
        grid = self.grid.to(device)
        if grid is self.grid:
            return self
        return CollisionModel(grid, self.system, self.config,
                              ignore=None if self.ignore is None else self.ignore.to(grid.device))

    # ------------------------------------------------------------------ geometry
    def positions(self, x: Tensor) -> Tensor:
        """``(..., 2)`` positions [m] of states ``x (..., nx)`` (the system's accessor)."""
        if self.system is None:
            return x[..., 0:2]
        return self.system.positions(x)

    def centres(self, x: Tensor) -> Tensor:
        """``(..., m, 2)`` disc centres [m] of the body of states ``x (..., nx)``; differentiable in ``x``."""
        heading = None if self.system is None or self.cover.n == 1 else self.system.headings(x)
        return self.cover.centres(self.positions(x), heading)

    # ----------------------------------------------------------------- occupancy
    @torch.no_grad()
    def occupancy(self, x: Tensor, slices: Tensor | None = None) -> Tensor:
        """Occupancy seen by the body of states ``x (..., T, nx)`` at the planning times: ``(..., T)``.

        ``slices (T,)`` are the grid slices of the planning times (default ``0..T-1``; clamped to the grid).
        """
        t = x.shape[-2]
        slices = self._slices(slices, t, x.device)
        grid = self.body_grid.to(x.device)
        c = self.centres(x)  # (..., T, m, 2)
        idx, _ = grid.cell_index(c)  # nearest cell, clamped to the map
        vals = grid.cell_values(slices[:, None], idx[..., 0], idx[..., 1]).to(x.dtype).amax(-1)  # (..., T)
        _, inside = grid.cell_index(self.positions(x))
        return torch.where(inside, vals, torch.ones_like(vals))

    def outline(self, x: Tensor) -> Tensor:
        """Corners ``(..., 4, 2)`` [m] of the footprint rectangle of states ``x (..., nx)`` (for figures; the
        square of side ``length`` for a disc footprint, a degenerate point for a point)."""
        fp = self.cover.footprint
        pos = self.positions(x)
        heading = None if self.system is None else self.system.headings(x)
        if heading is None:
            heading = torch.zeros(pos.shape[:-1], dtype=pos.dtype, device=pos.device)
        half = torch.tensor([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=pos.dtype, device=pos.device) * torch.tensor(
            [fp.length / 2, (fp.width if fp.width else fp.length) / 2], dtype=pos.dtype, device=pos.device)
        c, s = torch.cos(heading)[..., None], torch.sin(heading)[..., None]
        return pos.unsqueeze(-2) + torch.stack([c * half[:, 0] - s * half[:, 1], s * half[:, 0] + c * half[:, 1]], -1)

    def clamp_to_map(self, centres: Tensor) -> Tensor:
        """Disc centres ``(..., 2)`` moved onto the map's lattice hull (where their dilated occupancy is read)."""
        xmin, xmax, ymin, ymax = self.grid.bounds
        lo = torch.tensor([xmin, ymin], dtype=centres.dtype, device=centres.device)
        hi = torch.tensor([xmax, ymax], dtype=centres.dtype, device=centres.device)
        return torch.clamp(centres, lo, hi)

    @property
    def is_point(self) -> bool:
        """Whether the body is a point (one disc of radius 0 at the position: the paper's vehicle)."""
        return self.cover.radius == 0 and self.cover.offsets == (0.0,)

    def _slices(self, slices: Tensor | None, t: int, device: torch.device) -> Tensor:
        if slices is None:
            slices = torch.arange(t, device=device)
        slices = torch.as_tensor(slices, device=device).long().clamp(0, self.grid.n_slices - 1)
        if slices.shape != (t,):
            raise ValueError(f"slices must have shape ({t},) (one grid slice per planning time), got "
                             f"{tuple(slices.shape)}")
        return slices

    # --------------------------------------------------------------- probability
    @torch.no_grad()
    def probability(
        self,
        x: Tensor,
        slices: Tensor | None = None,
        *,
        log_rho0: Tensor | None = None,
        log_q0: Tensor | None = None,
        log_rho: Tensor | None = None,
        estimator: str | None = None,
    ) -> CollisionReport:
        """Collision probability of sample clouds ``x (*batch, N, T, nx)`` (module docstring).

        Args:
            x: closed-loop sample states at the planning times.
            slices: ``(T,)`` grid slice of each planning time.
            log_rho0: ``(*batch, N)`` initial log-density ``log rho0(x0_i)`` (``"is"``; ``None``: equal weights,
                i.e. samples drawn from ``rho0`` itself).
            log_q0: ``(*batch, N)`` log-density of the proposal the samples were drawn from (``None`` with
                ``log_rho0`` given: a uniform proposal, ``q0`` constant).
            log_rho: ``(*batch, N, T)`` predicted log-densities (``"paper"`` only; ``None``: equal densities).
            estimator: ``"is"`` or ``"paper"`` (default: the model's configuration).
        """
        x = check_tensor("x", x)
        if x.ndim < 3:
            raise ValueError(f"x must have shape (*batch, N, T, nx), got {tuple(x.shape)}")
        estimator = estimator or self.config.estimator
        check_choice("estimator", estimator, ESTIMATORS)
        *batch, n, t, _ = x.shape
        occ = self.occupancy(x, slices)  # (*batch, N, T)
        any_time = any_se = upper = upper_se = None
        if estimator == "is":
            w_i = importance_weights(x, log_rho0, log_q0)  # (*batch, N)

            def weighted_mean(v: Tensor) -> tuple[Tensor, Tensor]:  # self-normalised mean of (*batch, N), its SE
                m = (w_i * v).sum(-1)
                return m, torch.sqrt((w_i.pow(2) * (v - m.unsqueeze(-1)).pow(2)).sum(-1))

            any_time, any_se = weighted_mean(occ.amax(-1))  # each execution's worst instant: the lower bound
            upper, upper_se = weighted_mean(occ.sum(-1).clamp(max=1.0))  # the union bound over the instants
            w = w_i.unsqueeze(-1).expand_as(occ)
        else:
            w = self._paper_weights(x, log_rho)
        p = (w * occ).sum(-2)
        se = torch.sqrt((w.pow(2) * (occ - p.unsqueeze(-2)).pow(2)).sum(-2))
        ess = 1.0 / w.pow(2).sum(-2)
        return CollisionReport(per_slice=p, max=p.amax(-1), sum=p.sum(-1), se=se, ess=ess, estimator=estimator,
                               any_time=any_time, any_time_se=any_se, any_time_upper=upper,
                               any_time_upper_se=upper_se)

    def _paper_weights(self, x: Tensor, log_rho: Tensor | None) -> Tensor:
        """Per-sample weights of the paper's estimator: ``rho_i / (n_c(i) Z)``, ``(*batch, N, T)``."""
        *batch, n, t, _ = x.shape
        device = x.device
        if log_rho is None:
            log_rho = torch.zeros(x.shape[:-1], dtype=x.dtype, device=device)
        else:
            log_rho = check_tensor("log_rho", log_rho, dtype=x.dtype, device=device)
            if log_rho.shape != x.shape[:-1]:
                raise ValueError(f"log_rho must have shape {tuple(x.shape[:-1])}, got {tuple(log_rho.shape)}")
        pos = self.positions(x).movedim(-2, -3).reshape(-1, n, 2)  # (G, N, 2), groups = (batch, time)
        lr = log_rho.movedim(-1, -2).reshape(-1, n)
        g = pos.shape[0]
        rel = torch.exp(lr - lr.max(dim=-1, keepdim=True).values)
        idx, inside = self.grid.to(device).cell_index(pos)
        _, nx, ny = self.grid.shape
        n_cells = nx * ny
        cell = idx[..., 0] * ny + idx[..., 1]
        # samples outside the map get a private key each, so they are never averaged together
        key_in_group = torch.where(inside, cell, n_cells + torch.arange(n, device=device).expand(g, n))
        key = torch.arange(g, device=device)[:, None] * (n_cells + n) + key_in_group
        _, inverse, counts = torch.unique(key.reshape(-1), return_inverse=True, return_counts=True)
        count = counts[inverse].reshape(g, n).to(rel.dtype)
        # sum_c mean_rho_c = sum_i rho_i / n_c(i)
        w = rel / count
        w = w / w.sum(-1, keepdim=True)
        return w.reshape(*batch, t, n).movedim(-1, -2)


def importance_weights(x: Tensor, log_rho0: Tensor | None, log_q0: Tensor | None) -> Tensor:
    """Normalised self-normalised importance weights ``w_i ∝ rho0(x0_i) / q0(x0_i)``, ``(*batch, N)``."""
    shape = x.shape[:-2]
    if log_rho0 is None:
        return torch.full(shape, 1.0 / shape[-1], dtype=x.dtype, device=x.device)
    lw = torch.as_tensor(log_rho0, dtype=x.dtype, device=x.device)
    if log_q0 is not None:
        lw = lw - torch.as_tensor(log_q0, dtype=x.dtype, device=x.device)
    try:
        lw = lw.expand(shape)
    except RuntimeError:
        raise ValueError(f"log_rho0 / log_q0 must have shape {tuple(shape)} (one value per sample), got "
                         f"{tuple(lw.shape)}") from None
    if not bool(torch.isfinite(lw).all()):
        raise ValueError("log_rho0 - log_q0 must be finite for every sample (samples outside the proposal's support?)")
    return torch.softmax(lw, dim=-1)


def collision_mask(scene, config: RiskConfig | None = None, *, road_edge: str | None = None) -> Tensor | None:
    """``(NX, NY)`` cells of ``scene``'s grid that collision does not read as obstacles: with ``road_edge =
    "barrier"`` (default ``config.road_edge``) on a scene whose grid marks its off-road cells, those cells
    (:func:`~density_planner.environment.commonroad.offroad_mask`, one tensor per road and grid geometry); else
    ``None``."""
    from ..environment.commonroad import offroad_mask

    edge = road_edge or (config or RiskConfig()).road_edge
    check_choice("road_edge", edge, ROAD_EDGES)
    return None if edge == "occupied" else offroad_mask(scene)


def collision_grid(scene, config: RiskConfig | None = None, *, road_edge: str | None = None) -> OccupancyGrid:
    """The grid collision reads on ``scene``: the scene's own grid, or that grid with the cells of
    :func:`collision_mask` at 0 (road users and static obstacles only), cached on the scene's grid. The planners
    build :meth:`CollisionModel.for_scene`, which reads the same values without forming this grid."""
    mask = collision_mask(scene, config, road_edge=road_edge)
    return scene.grid if mask is None else masked_grid(scene.grid, mask)


def collision_probability(
    grid: OccupancyGrid,
    x: Tensor,
    slices: Tensor | None = None,
    *,
    system: System | None = None,
    config: RiskConfig | None = None,
    log_rho0: Tensor | None = None,
    log_q0: Tensor | None = None,
    log_rho: Tensor | None = None,
) -> CollisionReport:
    """Collision probability of sample clouds ``x (*batch, N, T, nx)``: :meth:`CollisionModel.probability` of a
    model built for ``grid`` and ``system`` (the body cover is cached on the grid)."""
    return CollisionModel(grid, system, config).probability(x, slices, log_rho0=log_rho0, log_q0=log_q0,
                                                            log_rho=log_rho)

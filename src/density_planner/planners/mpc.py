"""Receding-horizon MPC baselines (paper §V "Baseline methods"): standard MPC (M0) and tube MPC (M1-M3).

At every step ``h`` (``t_h = h * 0.1 s``) the controller solves, from the measured state ``x_hat``::

    min   w_G(h) ||p_H - p_goal||^2  +  alpha_C sum_{k=1}^{H} S_k^2  +  alpha_I sum_{k=0}^{H-1} ||u_k||^2
    s.t.  x_{k+1} = F(x_k, u_k)                       (multiple shooting; F = 10 Euler steps of 0.01 s)
          u_k in the input box,  the other states in the state box   (the car: |omega|, |a| <= 3; theta, v)
          p_k in the map, shrunk by the tube radius r      (tube MPC: constraints enforced within the tube)

for any system with symbolic dynamics (:meth:`~density_planner.systems.base.System.f_symbolic`): ``x`` is its
nominal state (:attr:`~density_planner.systems.base.System.nominal_indices`: the hidden states, e.g. the car's
heading bias, are not modelled; the car: ``[p_x, p_y, theta, v]``), ``F`` its explicit-Euler step
(:func:`~density_planner.planners._nlp.step_function`), the bounds its state and input boxes. ``x_0 = x_hat``,
``H = 10`` stages of 0.1 s, and ``S_k = sum_j sum_{d in D_r} D(c_j(x_k) + d, t_{h+k})``: the bilinear
interpolation of the body occupancy ``D`` (the disc-dilated grid of
:class:`~density_planner.risk.collision.CollisionModel`) at the body's disc centres ``c_j`` (the position for a point
vehicle; the sum over the discs is a smooth stand-in for their maximum), at the predicted position (M0,
``D_0 = {0}``) or summed over the 0.1-m lattice offsets inside the tube disc (tube MPC, 29 / 81 / 317 offsets for
r = 0.3 / 0.5 / 1 m, as the paper's code). This is the paper's ``J_MPC`` (Eq. (11)) with its weights ``alpha``
(``docs/spec.md`` §9, §12).
The stage-0 collision term depends on the measurement only and is left out of the NLP. ``w_G(h) = alpha_G`` (the
paper) or ``alpha_G (h / N)^2`` (``goal_weight_growth``, the paper's code).

**Built once, re-solved with parameters.** The NLP is built with CasADi (``nlpsol`` + IPOPT) on the first use and
rebuilt only if the map's cell size or the system's model changes (:attr:`MPCPlanner.n_builds` counts
constructions). Its parameters
are the measured state, the goal, the goal weight and, per stage ``k``, a square window of the occupancy slice
of time ``t_{h+k}`` around the measured position, read by a *parametric* linear interpolant
(``casadi.interpolant(..., 'linear', grid, 1)``, values as an input). The window of stage ``k`` has a fixed size
covering every position reachable in ``k`` stages (``k * 0.1 s * (v_max + a_max * 0.1 s)``, the bound of
:func:`~density_planner.planners._nlp.position_rate_bound`: the system's speed box, or for a system without a speed
state its position rate over the state box) plus the tube radius and the body,
so the NLP structure is the same for every step and every map, the parameter vector stays small (1.8e5 values
for M0 at 0.1 m instead of 10 x 241 x 401 for full slices) and large recorded maps cost no
more than the artificial ones.
The reachable box is also imposed as (non-binding) variable bounds, so that intermediate IPOPT iterates never
leave the windows. Cells of a window outside the map read 1 ("outside the map is occupied").
Each step warm-starts IPOPT from the previous solution shifted by one stage (the first step: zero inputs and
the zero-input rollout of ``F``). The solve is limited by ``max_iter`` and ``max_cpu_time``; when IPOPT stops
without converging, the first input of its last iterate is applied (as the paper's code) and the step is
recorded as failed. The iteration limit is deterministic; the CPU-time cap is not (how many iterations fit in
0.1 s depends on the machine and its load). M0 keeps the paper's cap of 0.1 s per step by default (its real-time
budget, which it reaches on 20-40 % of the steps near obstacles); the tube MPCs stop after the paper code's
10 iterations and have no cap by default, so their runs are reproducible; tests set ``max_cpu_time = inf``.

The planner solves one step from a given state (:meth:`MPCPlanner.solve`). The closed loop around it is the
plant, in :mod:`density_planner.evaluation.receding` (:meth:`MPCPlanner.plan_from` and :meth:`MPCPlanner.plan` run
it): the first input is applied to the true state with the nominal Euler model, the next state is measured
(heading biased by ``theta_bias`` when ``biased_measurement``), and the run stops early within
``goal_stop_distance`` of the goal. Step times count the whole step (window extraction, parameter update,
solve, warm-start shift), not only IPOPT.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import torch
from torch import Tensor

from ..checks import check_choice
from ..cost.composite import CostConfig, CostWeights
from ..environment.grid import OccupancyGrid
from ..risk.collision import CollisionModel
from ..systems.base import System
from ._nlp import (
    BufferedNLP,
    NLPModel,
    SolveInfo,
    check_ipopt_limits,
    import_casadi,
    ipopt_options,
    position_rate_bound,
    step_function,
)
from ._report import evaluate_trajectory
from .base import Planner, PlanResult, PlanStatus
from .problem import PlanningProblem
from .registry import PlannerContext, register_planner

if TYPE_CHECKING:
    from ..evaluation.receding import ClosedLoopRun

__all__ = [
    "MPCWeights",
    "ResolvedWeights",
    "MPCConfig",
    "TubeMPCConfig",
    "MPCStep",
    "MPCPlanner",
    "TUBE_RADII",
    "tube_offsets",
    "tube_mpc_name",
    "disc_sum",
    "mpc_objective",
]

log = logging.getLogger(__name__)

#: tube radii [m] of the paper's M1, M2, M3
TUBE_RADII = (0.3, 0.5, 1.0)


@dataclass(frozen=True)
class MPCWeights:
    """Weights ``alpha`` of ``J_MPC`` (paper Eq. (11)). The paper takes them from the density planner's cost (§9):
    a weight left unset (``None``, the default; omitted from ``config.toml``) is the one of
    ``[density_planner.cost.weights]`` (:class:`~density_planner.cost.composite.CostWeights`: 1e-2, 1e-6, 0.1); a
    number overrides it (``--set mpc.weights.collision=0.3``). :meth:`resolved` fills them in."""

    #: alpha_G on the squared terminal distance to the goal [1/m^2] (None: the density planner's)
    goal: float | None = None
    #: alpha_I on the squared inputs, summed over the stages (None: the density planner's)
    input: float | None = None
    #: alpha_C on the squared (tube-summed) occupancy at the predicted positions (None: the density planner's)
    collision: float | None = None

    def __post_init__(self) -> None:
        for name in _WEIGHT_NAMES:
            v = getattr(self, name)
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"MPC weight {name} must be a finite number >= 0 (or unset), got {v!r}")

    def resolved(self, cost: CostWeights | None = None) -> ResolvedWeights:
        """The weights with each unset one taken from ``cost`` (default: :class:`CostWeights`, the density
        planner's defaults)."""
        cost = cost or CostWeights()
        return ResolvedWeights(*(float(getattr(cost, n) if getattr(self, n) is None else getattr(self, n))
                                 for n in _WEIGHT_NAMES))


#: the terms of J_MPC, in the order of :class:`ResolvedWeights`
_WEIGHT_NAMES = ("goal", "input", "collision")


@dataclass(frozen=True)
class ResolvedWeights:
    """The numbers of :class:`MPCWeights` after :meth:`MPCWeights.resolved`."""

    goal: float
    input: float
    collision: float


@dataclass(frozen=True)
class MPCConfig:
    """Settings of the MPC baselines (defaults: M0 of ``docs/spec.md`` §12; tube variants set ``tube_radius``
    and ``max_iter = 10``)."""

    #: H, prediction stages
    horizon: int = 10
    #: duration of one stage and of one closed-loop step [s]
    stage_dt: float = 0.1
    #: explicit-Euler sub-steps per stage (0.01 s each by default)
    substeps: int = 10
    #: IPOPT iteration limit per step (original: 300 for M0, 10 for the tube variants); deterministic
    max_iter: int = 300
    #: IPOPT CPU-time cap per step [s] (inf: none). M0's 0.1 s is the paper's real-time budget; it makes a run
    #: depend on the machine's load, so tests and reproducible studies set inf and rely on ``max_iter``
    max_cpu_time: float = 0.1
    #: IPOPT Hessian: "exact" or "limited-memory" (L-BFGS)
    hessian: Literal["exact", "limited-memory"] = "exact"
    #: weights of J_MPC
    weights: MPCWeights = field(default_factory=MPCWeights)
    #: multiply alpha_G by (h / N)^2 at step h of N (the paper's code; not in the paper, hence off by default)
    goal_weight_growth: bool = True
    #: tube radius r [m]: 0 for standard MPC (M0); 0.3, 0.5, 1.0 for M1, M2, M3
    tube_radius: float = 0.0
    #: spacing of the lattice of offsets inside the tube disc [m]
    tube_lattice: float = 0.1
    #: how the tube sum is evaluated: "offsets" (one interpolant call per offset and stage, as the paper's code),
    #: "precomputed" (interpolate the disc sum of the occupancy, computed once per scene: the same function when
    #: the lattice is a whole number of cells, since bilinear interpolation commutes with whole-cell shifts), or
    #: "auto" (precomputed where it is exact, else offsets)
    tube_method: Literal["auto", "offsets", "precomputed"] = "auto"
    #: shrink the position constraints (the map) by the tube radius (the paper; the paper's code did not)
    tighten_constraints: bool = True
    #: feed the controller the biased heading theta + theta_bias (the paper's "biased" variants)
    biased_measurement: bool = False
    #: stop the closed loop once the car is within this distance of the goal [m] (0: never stop early)
    goal_stop_distance: float = 1.0
    #: closed-loop steps (None: the problem's horizon / stage_dt, i.e. 100 for 10 s)
    n_steps: int | None = None
    #: extra window size around the reachable box [m]
    window_margin: float = 0.1

    def __post_init__(self) -> None:
        check_ipopt_limits(self.max_iter, self.max_cpu_time)
        for name in ("horizon", "substeps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if self.n_steps is not None and (not isinstance(self.n_steps, int) or self.n_steps < 1):
            raise ValueError(f"n_steps must be a positive integer or None, got {self.n_steps!r}")
        for name in ("stage_dt", "tube_lattice"):
            v = getattr(self, name)
            if not math.isfinite(v) or v <= 0:
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
        for name in ("tube_radius", "goal_stop_distance", "window_margin"):
            v = getattr(self, name)
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
        check_choice("hessian", self.hessian, ("exact", "limited-memory"))
        check_choice("tube_method", self.tube_method, ("auto", "offsets", "precomputed"))


def tube_mpc_name(radius: float) -> str:
    """Registered name of the tube MPC with ``radius`` [m]: ``tube_mpc_0.3``, ``tube_mpc_0.5``, ``tube_mpc_1.0``."""
    text = f"{radius:g}"
    return f"tube_mpc_{text if '.' in text else text + '.0'}"


@dataclass(frozen=True)
class TubeMPCConfig(MPCConfig):
    """Settings of the tube MPC (M1-M3): :class:`MPCConfig` with the paper code's 10 IPOPT iterations per step and
    no CPU-time cap (the iteration limit binds first: 10 iterations take 15-60 ms, so the paper's 0.1-s cap only
    made runs depend on the machine's load). The registered planners ``tube_mpc_0.3/0.5/1.0`` replace
    ``tube_radius``; ``tube_mpc`` uses it."""

    #: IPOPT iteration limit per step (original: 10 for the tube variants)
    max_iter: int = 10
    #: IPOPT CPU-time cap per step [s] (inf: none, the default; the paper's code had 0.1 s)
    max_cpu_time: float = math.inf
    #: tube radius r [m] of the planner "tube_mpc"
    tube_radius: float = 0.5


def _lattice_cells(lattice: float, cell: float) -> int | None:
    """``lattice / cell`` if it is a whole number (1e-6 tolerance), else None."""
    ratio = lattice / cell
    n = round(ratio)
    return n if n >= 1 and abs(ratio - n) <= 1e-6 * max(1.0, ratio) else None


def disc_sum(probs: np.ndarray, offsets_cells: np.ndarray, fill: float = 1.0) -> np.ndarray:
    """``S[k, i, j] = sum_d P[k, i + d_i, j + d_j]`` over integer cell offsets ``d`` (``(M, 2)``), with cells
    outside the map reading ``fill``; float32 ``(T, NX, NY)``. Bilinear interpolation of ``S`` at ``p`` equals the
    sum of the bilinear interpolations of ``P`` at ``p + d * cell`` (both are linear in the cell values).

    Computed per slice as sums of contiguous runs along ``y`` (prefix sums), one pass per row offset ``d_i``.
    """
    offsets_cells = np.asarray(offsets_cells, dtype=int).reshape(-1, 2)
    n = int(np.abs(offsets_cells).max(initial=0))
    T, NX, NY = probs.shape
    rows: dict[int, list[int]] = {}
    for di, dj in offsets_cells.tolist():
        rows.setdefault(di, []).append(dj)
    out = np.empty((T, NX, NY), dtype=np.float32)
    pad = np.full((NX + 2 * n, NY + 2 * n + 1), fill, dtype=np.float64)
    for k in range(T):
        pad[n : n + NX, n + 1 : n + 1 + NY] = probs[k]
        pad[:, 0] = 0.0
        csum = np.cumsum(pad, axis=1)  # csum[:, c] = sum of pad[:, 1..c] (column 0 is the zero prefix)
        acc = np.zeros((NX, NY))
        for di, djs in rows.items():
            lo, hi = min(djs), max(djs)
            if hi - lo + 1 != len(djs):
                raise ValueError("disc_sum needs the offsets of each row to be contiguous")
            block = csum[n + di : n + di + NX]
            acc += block[:, n + 1 + hi : n + 1 + hi + NY] - block[:, n + lo : n + lo + NY]
        out[k] = acc
    return out


def tube_offsets(radius: float, lattice: float = 0.1) -> np.ndarray:
    """``(M, 2)`` lattice offsets ``(i, j) * lattice`` [m] with ``i^2 + j^2 <= (radius / lattice)^2``.

    29 / 81 / 317 offsets for 0.3 / 0.5 / 1 m at 0.1 m; ``[[0, 0]]`` for radius 0. (The paper's code compared
    floating-point distances and lost the four boundary points at 0.3 m, giving 25.)
    """
    n = int(math.floor(radius / lattice + 1e-9))
    r2 = (radius / lattice) ** 2 + 1e-9
    ij = np.array([(i, j) for i in range(-n, n + 1) for j in range(-n, n + 1) if i * i + j * j <= r2], dtype=float)
    return ij.reshape(-1, 2) * lattice


@dataclass
class MPCStep:
    """One MPC step.

    Attributes:
        step: closed-loop step index ``h`` (time ``h * stage_dt``).
        input: ``(nu,)`` applied input (the car: ``[omega, a]``; first input of the returned iterate, clipped to the
            bounds).
        predicted: ``(H + 1, nn)`` predicted nominal states (the car: ``[p_x, p_y, theta, v]``) from the measured
            state.
        predicted_inputs: ``(H, nu)`` predicted inputs.
        status: IPOPT return status (``"Solve_Succeeded"``, ``"Maximum_CpuTime_Exceeded"``, ...), or
            ``"Exception"`` / ``"Invalid_Iterate"`` when no usable iterate came back.
        success: IPOPT converged.
        iterations: IPOPT iterations.
        objective: J_MPC of the returned iterate (without the constant stage-0 collision term).
        solve_time: wall time of the IPOPT call [s].
        step_time: wall time of the whole step [s] (occupancy windows, parameters, solve, warm start).
        message: detail on failures.
    """

    step: int
    input: np.ndarray
    predicted: np.ndarray
    predicted_inputs: np.ndarray
    status: str
    success: bool
    iterations: int
    objective: float
    solve_time: float
    step_time: float
    message: str = ""


@dataclass(frozen=True)
class _Model:
    """What the MPC's NLP reads from the system: its nominal model and bounds, and the bound on the position's rate
    that sizes the occupancy windows (two equal models build the same NLP)."""

    model: NLPModel
    #: bound [m/s] on the rate of either position coordinate within a stage (:func:`position_rate_bound`)
    rate: float


class _MPCProgram:
    """The NLP of one MPC configuration for one map cell size: structure, windows and the buffered solver."""

    def __init__(self, ca: Any, system: System, config: MPCConfig, weights: ResolvedWeights, cell: float,
                 limits: _Model, precomputed: bool, body: tuple[float, ...] = (0.0,)):
        self.config, self.cell, self.limits, self.precomputed = config, cell, limits, precomputed
        model = limits.model
        if model.heading is None and any(body):
            raise ValueError(f"{model.system} has no heading: its body must be a single disc centred on the position")
        #: nominal states, inputs, nominal indices of the position and of the heading
        self.nn, self.nu, self.pos, self.heading = model.nn, model.nu, model.position, model.heading
        #: longitudinal offsets [m] of the body's disc centres from the position (CollisionModel.cover.offsets)
        self.body = tuple(body)
        H = config.horizon
        dt = config.stage_dt
        self.H = H
        #: offsets of the tube disc [m] (all of them are summed, by the NLP or by the precomputed map)
        self.tube = tube_offsets(config.tube_radius, config.tube_lattice)
        #: offsets evaluated by the NLP
        self.offsets = np.zeros((1, 2)) if precomputed else self.tube
        radius = float(np.linalg.norm(self.offsets, axis=1).max()) + max(abs(v) for v in self.body)
        v_reach = limits.rate
        #: reachable distance [m] after k stages (k = 1..H) from the measured position (a bound of F)
        self.reach = np.array([k * dt * v_reach for k in range(1, H + 1)])
        #: window half-width [cells] and edge length [cells] per stage
        self.half = np.ceil((self.reach + radius + config.window_margin) / cell).astype(int) + 1
        self.size = 2 * self.half + 2
        n_win = self.size**2
        nn, nu = self.nn, self.nu
        # parameter layout: x0 (nn), goal (2), goal weight (1), window origins (2 H), windows
        self.i_x0, self.i_goal, self.i_wg, self.i_org = 0, nn, nn + 2, nn + 3
        self.win_start = self.i_org + 2 * H + np.concatenate([[0], np.cumsum(n_win)[:-1]])
        n_p = int(self.i_org + 2 * H + n_win.sum())

        F = step_function(ca, system, dt, config.substeps)
        #: the constant-input rollout of the first step's initial guess: (x0 (nn,), U (nu, H)) -> X (nn, H)
        self.rollout = F.mapaccum("rollout", H)
        X = ca.MX.sym("X", nn, H)
        U = ca.MX.sym("U", nu, H)
        P = ca.MX.sym("p", n_p)
        x0 = P[0:nn]
        goal = P[self.i_goal : self.i_goal + 2]
        w_goal = P[self.i_wg]
        i, j = self.pos
        th = self.heading

        def position(k: int) -> Any:
            return X[i : i + 2, k] if j == i + 1 else ca.vertcat(X[i, k], X[j, k])

        D = ca.DM(self.offsets.T)
        M = self.offsets.shape[0]
        w = weights
        J = w_goal * ca.sumsqr(position(H - 1) - goal) + w.input * ca.sumsqr(U)
        g = []
        prev = x0
        for k in range(H):
            g.append(X[:, k] - F(prev, U[:, k]))
            prev = X[:, k]
            s = int(self.size[k])
            axis = [float(v) for v in np.arange(s) * cell]
            occ = ca.interpolant(f"occ_{k + 1}", "linear", [axis, axis], 1)
            origin = P[self.i_org + 2 * k : self.i_org + 2 * k + 2]
            start = int(self.win_start[k])
            values = P[start : start + s * s]
            s_k = 0
            for off in self.body:
                centre = position(k) + (off * ca.vertcat(ca.cos(X[th, k]), ca.sin(X[th, k])) if off else 0)
                pts = ca.repmat(centre - origin, 1, M) + D
                s_k = s_k + ca.sum2(occ(pts, values))
            J = J + w.collision * s_k**2
        nlp = {"x": ca.vertcat(ca.vec(X), ca.vec(U)), "p": P, "f": J, "g": ca.vertcat(*g)}
        opts = ipopt_options(max_iter=config.max_iter, max_cpu_time=config.max_cpu_time, hessian=config.hessian)
        self.nlp = BufferedNLP(ca.nlpsol("mpc", "ipopt", nlp, opts))
        self.n_x = nn * H
        # Fortran-order views on the windows inside the parameter vector (first grid axis fastest, as CasADi)
        p = self.nlp.args["p"]
        self.windows = [
            p[int(a) : int(a) + int(s) * int(s)].reshape(int(s), int(s), order="F")
            for a, s in zip(self.win_start, self.size)
        ]
        # constant bounds: inputs and the non-position states (the system's box); positions are set per step
        lbx, ubx = self.nlp.args["lbx"], self.nlp.args["ubx"]
        for m in range(nu):
            lbx[self.n_x + m :: nu], ubx[self.n_x + m :: nu] = model.input_lo[m], model.input_hi[m]
        for m in range(nn):
            if m not in self.pos:
                lbx[m : self.n_x : nn], ubx[m : self.n_x : nn] = model.state_lo[m], model.state_hi[m]

    def cold_start(self, x0: np.ndarray) -> None:
        """Initial guess of the first step: zero inputs and the states of the zero-input rollout of the nominal
        model (the car: constant speed and heading)."""
        guess = self.nlp.args["x0"]
        xs = np.asarray(self.rollout(x0, np.zeros((self.nu, self.H))))  # (nn, H)
        guess[: self.n_x] = xs.T.reshape(-1)
        guess[self.n_x :] = 0.0

    def shift(self) -> None:
        """Warm start of the next step: the last solution shifted by one stage (last stage repeated)."""
        sol, guess = self.nlp.res["x"], self.nlp.args["x0"]
        H = self.H
        xs = sol[: self.n_x].reshape(H, self.nn)
        us = sol[self.n_x :].reshape(H, self.nu)
        guess[: self.n_x] = np.concatenate([xs[1:], xs[-1:]]).reshape(-1)
        guess[self.n_x :] = np.concatenate([us[1:], us[-1:]]).reshape(-1)


@dataclass
class _Binding:
    """The scene an :class:`MPCPlanner` currently controls in (numpy copies for the per-step work)."""

    problem: PlanningProblem
    probs: np.ndarray  # (T, NX, NY) float32
    origin: np.ndarray  # (2,)
    cell: float
    slices: np.ndarray  # occupancy slice of every closed-loop time step + horizon
    pos_lo: np.ndarray  # (2,) position bounds (map, tightened)
    pos_hi: np.ndarray
    goal: np.ndarray
    n_steps: int
    outside: float = 1.0  # value of cells outside the map
    edge: bool = False  # cells outside the map repeat the border (a body's disc centres; CollisionModel)
    warm: bool = False


class MPCPlanner(Planner):
    """Standard MPC (``tube_radius = 0``, M0) or tube MPC (M1-M3); see the module docstring.

    :meth:`reset` then :meth:`solve` step by step; :meth:`plan` / :meth:`plan_from` run the closed loop of
    :func:`density_planner.evaluation.receding.run_receding` around them.
    """

    name = "mpc"

    def __init__(
        self,
        config: MPCConfig | None = None,
        *,
        name: str | None = None,
        system: System | None = None,
        evaluation_cost: CostConfig | None = None,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str = "cpu",
    ):
        """
        Args:
            config: MPC settings.
            name: planner name in results (default ``"mpc"``, or ``"tube_mpc_<r>"`` when the tube radius is > 0).
            system: the system planned for (its nominal dynamics and bounds enter the NLP); :meth:`reset` replaces
                it by the problem's system.
            evaluation_cost: cost configuration of the reported (evaluation-form) cost, shared with the density
                planner for comparability (default :class:`CostConfig`); its weights are those of ``J_MPC`` that
                ``config.weights`` leaves unset.
            dtype, device: of the returned tensors.

        Raises:
            OptionalDependencyError: CasADi (extra ``mpc``) is not installed.
        """
        self._ca = import_casadi("MPC baselines")
        self.config = config or MPCConfig()
        self.name = name or ("mpc" if self.config.tube_radius == 0 else tube_mpc_name(self.config.tube_radius))
        self.system = system
        self.evaluation_cost = evaluation_cost or CostConfig()
        #: the weights of J_MPC: the configuration's, unset ones from the density planner's cost (evaluation_cost)
        self.weights = self.config.weights.resolved(self.evaluation_cost.weights)
        self.dtype = dtype
        self.device = torch.device(device)
        #: number of NLP constructions so far (one per planner and map cell size)
        self.n_builds = 0
        #: wall time of the last NLP construction [s]
        self.build_time = 0.0
        self._program: _MPCProgram | None = None
        self._bound: _Binding | None = None
        self._disc_cache: tuple[OccupancyGrid, np.ndarray] | None = None
        #: wall time of the last tube disc-sum precomputation [s] (0 when cached or not needed)
        self.precompute_time = 0.0
        #: NLP construction and precomputation times of the last reset (a construction counts once)
        self._reset_times = (0.0, 0.0)

    # ------------------------------------------------------------------ set-up
    def _limits(self, system: System) -> _Model:
        """The system's NLP model and window bound (errors name the fact the system lacks)."""
        model = NLPModel.of(self._ca, system)
        return _Model(model, position_rate_bound(self._ca, system, self.config.stage_dt))

    def _precomputed(self, cell: float) -> bool:
        cfg = self.config
        if cfg.tube_radius == 0:
            return False
        exact = _lattice_cells(cfg.tube_lattice, cell) is not None
        if cfg.tube_method == "precomputed" and not exact:
            raise ValueError(f"tube_method='precomputed' needs tube_lattice ({cfg.tube_lattice} m) to be a whole "
                             f"number of map cells ({cell} m); use 'offsets' or 'auto'")
        return cfg.tube_method == "precomputed" or (cfg.tube_method == "auto" and exact)

    def _program_for(self, system: System, cell: float, limits: _Model,
                     body: tuple[float, ...] = (0.0,)) -> _MPCProgram:
        prog = self._program
        pre = self._precomputed(cell)
        if (prog is None or not math.isclose(prog.cell, cell, rel_tol=1e-9) or prog.limits != limits
                or prog.precomputed != pre or prog.body != tuple(body)):
            t0 = time.perf_counter()
            prog = _MPCProgram(self._ca, system, self.config, self.weights, cell, limits, pre, body)
            self.build_time = time.perf_counter() - t0
            self.n_builds += 1
            self._program = prog
            log.info("%s: NLP built in %.3f s (%d parameters, %d offsets per stage)", self.name, self.build_time,
                     prog.nlp.args["p"].size, prog.offsets.shape[0])
        return prog

    def reset(self, problem: PlanningProblem) -> None:
        """Bind ``problem``'s scene and goal (building the NLP if this is the first map of its cell size) and
        forget the warm start. Raises :class:`NotImplementedError` for a system without symbolic dynamics
        (:meth:`System.f_symbolic`) and :class:`ValueError` when no bound on its speed follows from its facts
        (:func:`~density_planner.planners._nlp.position_rate_bound`)."""
        system = problem.system
        self.system = system
        builds = self.n_builds
        # no road term here: the road's edge stays occupied in the constraints
        collision = problem.collision(road_edge="occupied")
        grid: OccupancyGrid = collision.body_grid  # occupancy seen by a body disc (the point's P_occ for a point)
        prog = self._program_for(system, grid.cell_size, self._limits(system), collision.cover.offsets)
        cfg = self.config
        n_steps = cfg.n_steps or int(round(problem.parameterization.horizon / cfg.stage_dt))
        # occupancy slices of the absolute times t_start + k stage_dt: the closed loop's own steps must lie in the
        # grid (ValueError otherwise); the prediction stages after the last step look past the plan's horizon and
        # hold the grid's last slice where the scene ends there
        problem.slices(n_steps + 1, dt=cfg.stage_dt)
        slices = grid.slices_for(problem.t_start, cfg.stage_dt, n_steps + cfg.horizon + 1, clamp=True)
        xmin, xmax, ymin, ymax = grid.bounds
        shrink = cfg.tube_radius if cfg.tighten_constraints else 0.0
        lo = np.array([xmin + shrink, ymin + shrink])
        hi = np.array([xmax - shrink, ymax - shrink])
        if np.any(lo > hi):
            raise ValueError(f"tube radius {cfg.tube_radius} m leaves no room in the map {grid.bounds}")
        probs = grid.probs.detach().to("cpu", torch.float32).numpy()
        self.precompute_time = 0.0
        if prog.precomputed:
            if self._disc_cache is None or self._disc_cache[0] is not grid:
                t0 = time.perf_counter()
                step = _lattice_cells(cfg.tube_lattice, grid.cell_size)
                cells = np.rint(prog.tube / cfg.tube_lattice).astype(int) * step
                self._disc_cache = (grid, disc_sum(probs, cells))
                self.precompute_time = time.perf_counter() - t0
            probs = self._disc_cache[1]
        self._bound = _Binding(
            problem=problem,
            probs=probs,
            origin=np.asarray(grid.origin, dtype=float),
            cell=grid.cell_size,
            slices=slices.numpy(),
            pos_lo=lo,
            pos_hi=hi,
            goal=np.asarray(problem.goal, dtype=float),
            n_steps=n_steps,
            outside=float(prog.tube.shape[0]) if prog.precomputed else 1.0,
            edge=not collision.is_point,
        )
        prog.nlp.args["lam_x0"][:] = 0.0
        prog.nlp.args["lam_g0"][:] = 0.0
        self._reset_times = (self.build_time if self.n_builds > builds else 0.0, self.precompute_time)

    # ------------------------------------------------------------------ one step
    def _fill_windows(self, prog: _MPCProgram, b: _Binding, pos: np.ndarray, step: int) -> None:
        p = prog.nlp.args["p"]
        T, NX, NY = b.probs.shape
        ic = np.floor((pos - b.origin) / b.cell).astype(int)
        last = b.slices.shape[0] - 1
        for k in range(prog.H):
            half, s = int(prog.half[k]), int(prog.size[k])
            i0, j0 = ic[0] - half, ic[1] - half
            win = prog.windows[k]
            a0, a1 = max(i0, 0), min(i0 + s, NX)
            c0, c1 = max(j0, 0), min(j0 + s, NY)
            sl = int(b.slices[min(step + k + 1, last)])
            if (a0 - i0 > 0 or c0 - j0 > 0 or a1 - i0 < s or c1 - j0 < s) and b.edge:
                ii = np.clip(np.arange(i0, i0 + s), 0, NX - 1)
                jj = np.clip(np.arange(j0, j0 + s), 0, NY - 1)
                win[:, :] = b.probs[sl][np.ix_(ii, jj)]
            elif a0 - i0 > 0 or c0 - j0 > 0 or a1 - i0 < s or c1 - j0 < s:
                win.fill(b.outside)  # part of the window lies outside the map
                if a0 < a1 and c0 < c1:
                    win[a0 - i0 : a1 - i0, c0 - j0 : c1 - j0] = b.probs[sl, a0:a1, c0:c1]
            elif a0 < a1 and c0 < c1:
                win[a0 - i0 : a1 - i0, c0 - j0 : c1 - j0] = b.probs[sl, a0:a1, c0:c1]
            p[prog.i_org + 2 * k : prog.i_org + 2 * k + 2] = b.origin + b.cell * np.array([i0, j0])

    def solve(self, state: np.ndarray | Tensor, step: int) -> MPCStep:
        """One MPC step from the measured state at step ``step`` (time ``step * stage_dt``) of the problem bound by
        :meth:`reset`: the full state ``(nx,)`` (its hidden states, e.g. the car's bias, are dropped) or the nominal
        state ``(nn,)`` (the car: ``[p_x, p_y, theta, v]``). Never raises for solver trouble."""
        t_start = time.perf_counter()
        if self._bound is None or self._program is None:
            raise ValueError("call reset(problem) before solve(state, step)")
        b, prog, cfg = self._bound, self._program, self.config
        model = prog.limits.model
        x0 = np.asarray(state.detach().cpu() if isinstance(state, Tensor) else state, dtype=float).reshape(-1)
        if x0.shape == (len(b.problem.system.state_names),) and x0.shape != (model.nn,):
            x0 = model.nominal_of(x0)
        if x0.shape != (model.nn,) or not np.all(np.isfinite(x0)):
            raise ValueError(f"state must hold {len(b.problem.system.state_names)} (the state) or {model.nn} (the "
                             f"nominal state) finite numbers, got {x0!r}")
        args = prog.nlp.args
        p = args["p"]
        p[prog.i_x0 : prog.i_x0 + model.nn] = x0
        p[prog.i_goal : prog.i_goal + 2] = b.goal
        growth = (step / b.n_steps) ** 2 if cfg.goal_weight_growth else 1.0
        p[prog.i_wg] = self.weights.goal * growth
        pos = x0[list(prog.pos)]
        self._fill_windows(prog, b, pos, step)
        # per-stage position bounds: the map (tightened) intersected with the reachable box of the windows
        lbx, ubx = args["lbx"], args["ubx"]
        for axis, i in enumerate(prog.pos):
            lo = np.maximum(b.pos_lo[axis], pos[axis] - prog.reach)
            hi = np.minimum(b.pos_hi[axis], pos[axis] + prog.reach)
            lbx[i : prog.n_x : prog.nn], ubx[i : prog.n_x : prog.nn] = lo, np.maximum(hi, lo)
        if not b.warm:
            prog.cold_start(x0)
        info: SolveInfo = prog.nlp.solve()
        sol = prog.nlp.res["x"]
        xs = sol[: prog.n_x].reshape(prog.H, prog.nn)
        us = sol[prog.n_x :].reshape(prog.H, prog.nu)
        status, message = info.status, info.message
        lo_u, hi_u = np.asarray(model.input_lo), np.asarray(model.input_hi)
        finite = bool(np.all(np.isfinite(sol)))
        if finite:
            u = np.clip(us[0], lo_u, hi_u)
            prog.shift()
            b.warm = True
        else:
            # no usable iterate: continue the previous plan (its next input is the warm start's first input)
            u = (np.clip(np.nan_to_num(args["x0"][prog.n_x : prog.n_x + prog.nu]), lo_u, hi_u) if b.warm
                 else np.zeros(prog.nu))
            status = "Invalid_Iterate" if status != "Exception" else status
            message = message or "IPOPT returned a non-finite iterate"
            b.warm = False
        predicted = np.concatenate([x0[None], xs])
        return MPCStep(
            step=step, input=u, predicted=predicted, predicted_inputs=us.copy(), status=status,
            success=info.success and finite, iterations=info.iterations, objective=info.objective,
            solve_time=info.time, step_time=time.perf_counter() - t_start, message=message,
        )

    # -------------------------------------------------------------- closed loop
    @property
    def n_steps(self) -> int:
        """Closed-loop steps of the problem bound by :meth:`reset` (``n_steps``, or the horizon / ``stage_dt``)."""
        if self._bound is None:
            raise ValueError("call reset(problem) before reading n_steps")
        return self._bound.n_steps

    def plan(self, problem: PlanningProblem) -> PlanResult:
        """Closed-loop run from the problem's reference start (mean of the initial law, no bias)."""
        return self.plan_from(problem, problem.reference_start(torch.float64))

    def plan_from(self, problem: PlanningProblem, true_state: Tensor) -> PlanResult:
        """Closed-loop run from the true initial state ``true_state (nx,)`` (its bias enters the measurement
        when ``biased_measurement``), simulated by :func:`density_planner.evaluation.receding.run_receding` (the
        plant loop; this planner solves one step at a time). Never raises: failures are reported in the result's
        status."""
        from ..evaluation.receding import run_receding  # evaluation drives the planner (imported on use)

        return run_receding(self, problem, true_state)

    def closed_loop_result(self, problem: PlanningProblem, run: ClosedLoopRun) -> PlanResult:
        """The result of a closed-loop run of :func:`~density_planner.evaluation.receding.run_receding`: executed
        states, per-step records in ``extras``, evaluation-form cost and ``J_MPC``; ``ERROR`` if it stopped on an
        exception (the states so far are kept)."""
        if run.error:
            return self._result(problem, PlanStatus.ERROR, run.states, run.inputs, run.steps, run.t_start, 0.0, 0.0,
                                run.error)
        t_build, t_pre = self._reset_times
        return self._result(problem, PlanStatus.SUCCESS, run.states, run.inputs, run.steps, run.t_start, t_build,
                            t_pre, "")

    def _result(self, problem: PlanningProblem, status: PlanStatus, states: list[Tensor], inputs: list[Tensor],
                steps: list[Any], t_start: float, t_build: float, t_pre: float, message: str) -> PlanResult:
        counts = Counter(s.status for s in steps)
        n_fail = sum(1 for s in steps if not s.success)
        step_times = [s.step_time for s in steps]
        extras: dict[str, Any] = {
            "tube_radius": self.config.tube_radius,
            "n_tube_offsets": int(tube_offsets(self.config.tube_radius, self.config.tube_lattice).shape[0]),
            "tube_precomputed": bool(self._program is not None and self._program.precomputed),
            "biased_measurement": self.config.biased_measurement,
            "n_builds": self.n_builds,
            "n_failed_steps": n_fail,
            "step_status_counts": dict(counts),
            "step_status": [s.status for s in steps],
            "step_iterations": [s.iterations for s in steps],
            "step_times": step_times,
            "solve_times": [s.solve_time for s in steps],
            "step_time_median": float(np.median(step_times)) if steps else math.nan,
            "applied_inputs": [s.input.tolist() for s in steps],
            "predicted_states": [s.predicted.tolist() for s in steps],
        }
        if n_fail and not message:
            message = (f"{n_fail} of {len(steps)} steps did not converge ({dict(counts)}); the last iterate was "
                       "applied")
        result = PlanResult(planner=self.name, status=status, message=message, extras=extras,
                            iterations={"steps": len(steps), "ipopt": sum(s.iterations for s in steps)})
        if len(states) >= 2:
            x = torch.stack(states).to(dtype=self.dtype, device=self.device)
            u = torch.stack(inputs).to(dtype=self.dtype, device=self.device)
            result.states = x
            try:
                result.cost, result.collision = evaluate_trajectory(problem, x, u, cost_config=self.evaluation_cost)
                result.extras["objective"] = mpc_objective(problem.scene.grid, x, u, problem.goal,
                                                           self.weights, dt=self.config.stage_dt,
                                                           collision=problem.collision(),
                                                           t_start=problem.t_start)
            except Exception as exc:  # noqa: BLE001
                result.message += f" (evaluation failed: {exc})"
        elif states:
            result.states = torch.stack(states).to(dtype=self.dtype, device=self.device)
        online = float(sum(step_times))
        result.timings = {"nlp_build": t_build, "tube_precompute": t_pre, "online": online,
                          "total": time.perf_counter() - t_start}
        return result


@torch.no_grad()
def mpc_objective(
    grid: OccupancyGrid,
    states: Tensor,
    inputs: Tensor,
    goal: tuple[float, float],
    weights: MPCWeights | ResolvedWeights,
    *,
    offsets: np.ndarray | None = None,
    dt: float = 0.1,
    collision: CollisionModel | None = None,
    t_start: float | None = None,
) -> dict[str, float]:
    """``J_MPC`` (paper Eq. (11)) of a whole trajectory ``states (T, nx)`` on the 0.1-s grid with
    ``inputs (T - 1, 2)``, from ``h = 0`` over ``T - 1`` stages: the oracle's objective, also used to compare the
    closed-loop MPC runs with it. Terms unweighted, ``total`` weighted; body occupancy (``collision``'s
    disc-dilated grid at the disc centres, summed over the discs; default a point on ``grid``) interpolated
    bilinearly (fill 1 outside the map), summed over ``offsets (M, 2)`` [m] if given. ``states[k]`` lies at the
    absolute time ``t_start + k dt`` (default ``t_start``: the grid's ``t0``). Unset :class:`MPCWeights` are the
    density planner's default weights (:class:`CostWeights`); planners pass their resolved ``weights``."""
    states = states.detach().to("cpu", torch.float64)
    inputs = inputs.detach().to("cpu", torch.float64)
    model = (collision or CollisionModel(grid)).to("cpu")
    g = model.body_grid
    T = states.shape[0]
    k = g.slices_for(g.t0 if t_start is None else t_start, dt, T)
    pos = model.centres(states)  # (T, m, 2)
    if not model.is_point:  # disc centres beyond the border read the border (CollisionModel)
        pos = model.clamp_to_map(pos)
    if offsets is not None:
        pos = pos[:, :, None, :] + torch.as_tensor(offsets, dtype=torch.float64)[None, None]
        occ = g.lookup(pos, k[:, None, None]).sum(dim=(-1, -2))
    else:
        occ = g.lookup(pos, k[:, None]).sum(-1)
    terms = {
        "goal": float((model.positions(states[-1]) - torch.tensor(goal, dtype=torch.float64)).pow(2).sum()),
        "input": float(inputs.pow(2).sum()),
        "collision": float(occ.pow(2).sum()),
    }
    if isinstance(weights, MPCWeights):
        weights = weights.resolved()
    terms["total"] = weights.goal * terms["goal"] + weights.input * terms["input"] + weights.collision * terms[
        "collision"]
    return terms


def _mpc_factory(ctx: PlannerContext, config: MPCConfig, name: str) -> MPCPlanner:
    return MPCPlanner(config, name=name, system=ctx.system, evaluation_cost=ctx.config.density_planner.cost,
                      dtype=ctx.dtype, device=ctx.device)


@register_planner("mpc", "standard MPC M0 (CasADi/IPOPT, 1-s horizon, collision term P_occ^2; extra 'mpc')",
                  section="mpc", execution="receding", plans_from_true_state=True, label="M0", colour="tab:blue")
def _make_mpc(ctx: PlannerContext) -> MPCPlanner:
    return _mpc_factory(ctx, replace(ctx.config.mpc, tube_radius=0.0), "mpc")


@register_planner("tube_mpc", "tube MPC with the radius of [tube_mpc] tube_radius (extra 'mpc')", section="tube_mpc",
                  execution="receding", plans_from_true_state=True)
def _make_tube_mpc(ctx: PlannerContext) -> MPCPlanner:
    cfg = ctx.config.tube_mpc
    return _mpc_factory(ctx, cfg, tube_mpc_name(cfg.tube_radius))


def _register_tube(radius: float, label: str, colour: str) -> None:
    name = tube_mpc_name(radius)

    @register_planner(name, f"tube MPC {label} (radius {radius:g} m, [tube_mpc] settings; extra 'mpc')",
                      section="tube_mpc", execution="receding", plans_from_true_state=True, label=label, colour=colour)
    def _make(ctx: PlannerContext) -> MPCPlanner:
        return _mpc_factory(ctx, replace(ctx.config.tube_mpc, tube_radius=radius), name)


for _r, _label, _colour in zip(TUBE_RADII, ("M1", "M2", "M3"), ("tab:cyan", "tab:purple", "tab:brown")):
    _register_tube(_r, _label, _colour)

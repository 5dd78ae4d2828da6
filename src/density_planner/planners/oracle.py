"""The oracle baseline O (paper §V "Baseline methods"): the full-horizon ``J_MPC`` problem (``h = 0``,
``H = N = 100``) solved offline from the TRUE initial state with the exact model and no time limit.

One NLP (CasADi ``nlpsol`` + IPOPT)::

    min   alpha_G ||p_N - p_goal||^2 + alpha_C sum_{k=1}^{N} P_occ(p_k, t_k)^2 + alpha_I sum_{k=0}^{N-1} ||u_k||^2
    s.t.  x_{k+1} = F(x_k, u_k),  x_0 = true initial state (nominal states only; the car's bias is not seen)
          u_k = p[:, segment(k)]     (the planner's piecewise-constant inputs: 10 segments of 1 s)
          p in the input box (the car: |p| <= 3),  p_k in the map,  the other states in the state box

over the parameters ``p (nu, 10)`` and the nominal states ``x_1..x_N`` (:attr:`System.nominal_indices`; the car:
``[p_x, p_y, theta, v]``) of any system with symbolic dynamics (:meth:`System.f_symbolic`; multiple shooting on
the 0.1-s planning grid, ``F`` = 10 explicit-Euler steps of 0.01 s, identical to the reference rollout). The
occupancy enters through a linear interpolant over (x, y, slice) whose values are the scene's whole occupancy grid
as constant data, so the NLP is built once per scene (``n_builds`` counts it; the restarts and later
:meth:`OraclePlanner.plan_from` calls on the same scene reuse it): the full grid is 101 x 241 x 401 values, too
many to pass as a parameter on every function evaluation. With a body, the interpolated grid is the body's
disc-dilated grid (:class:`~density_planner.risk.collision.CollisionModel`) and ``P_occ(p_k, t_k)`` becomes the
sum of its values at the disc centres of ``x_k`` (a smooth stand-in for their maximum).

Restarts (``docs/spec.md`` §12): a zero initial guess, then ``restarts - 1`` random guesses
``p = clip(0.5 N(0, 1), -3, 3)`` (seeded), each with the states of its rollout as the state guess. Every returned
iterate (converged or stopped by ``max_iter``: IPOPT returns its last iterate) is re-simulated open loop and scored
with the same ``J_MPC`` (:func:`~density_planner.planners.mpc.mpc_objective`); the best one whose re-simulation
respects the state bounds is kept (the paper's code kept the lowest collision term). Status SUCCESS when such a
feasible plan exists (``extras["best_converged"]`` says whether IPOPT converged on it), FAILED otherwise (the best
infeasible one is reported). The reported planning time is the sum of all restarts plus the NLP construction.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from ..checks import check_choice, check_seed
from ..control.reference import make_reference
from ..cost.composite import CostConfig
from ._nlp import BufferedNLP, NLPModel, SolveInfo, check_ipopt_limits, import_casadi, ipopt_options, step_function
from ._report import evaluate_trajectory
from .base import Planner, PlanResult, PlanStatus
from .mpc import MPCWeights, ResolvedWeights, mpc_objective
from .problem import PlanningProblem
from .registry import PlannerContext, register_planner

__all__ = ["OracleConfig", "OraclePlanner"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class OracleConfig:
    """Settings of the oracle (``docs/spec.md`` §12)."""

    #: number of IPOPT solves: a zero initial guess, then random guesses
    restarts: int = 10
    #: standard deviation of the random initial parameters (clipped to the input bounds)
    init_std: float = 0.5
    #: seed of the random initial guesses
    seed: int = 0
    #: IPOPT iteration limit per restart (deterministic)
    max_iter: int = 5000
    #: IPOPT CPU-time cap per restart [s] (inf: none, as the paper; a finite cap makes the result depend on the
    #: machine's load)
    max_cpu_time: float = math.inf
    #: IPOPT Hessian: "exact" or "limited-memory"
    hessian: Literal["exact", "limited-memory"] = "exact"
    #: weights of J_MPC (unset ones: the density planner's alphas, as the paper)
    weights: MPCWeights = field(default_factory=MPCWeights)

    def __post_init__(self) -> None:
        if isinstance(self.restarts, bool) or not isinstance(self.restarts, int) or self.restarts < 1:
            raise ValueError(f"restarts must be a positive integer, got {self.restarts!r}")
        check_ipopt_limits(self.max_iter, self.max_cpu_time)
        check_seed("seed", self.seed)
        if not math.isfinite(self.init_std) or self.init_std < 0:
            raise ValueError(f"init_std must be a finite number >= 0, got {self.init_std!r}")
        check_choice("hessian", self.hessian, ("exact", "limited-memory"))


class _OracleProgram:
    """The oracle NLP for one scene (grid values are constants of the interpolant)."""

    def __init__(self, ca: Any, config: OracleConfig, weights: ResolvedWeights, problem: PlanningProblem,
                 model: NLPModel):
        par = problem.parameterization
        # no road term here: the road's edge stays occupied in the constraints
        collision = problem.collision(road_edge="occupied")
        grid = collision.body_grid  # occupancy seen by a body disc (the scene's P_occ for a point vehicle)
        if model.heading is None and any(collision.cover.offsets):
            raise ValueError(f"{model.system} has no heading: its body must be a single disc centred on the position")
        self.model = model
        self.grid = grid
        self.n_seg = par.n_segments
        self.N = par.n_plan - 1  # stages of plan_dt
        if self.N % self.n_seg:
            raise ValueError(f"{self.N} planning steps do not split into {self.n_seg} segments")
        per_seg = self.N // self.n_seg
        T, NX, NY = grid.shape
        xs = [float(v) for v in grid.xs]
        ys = [float(v) for v in grid.ys]
        ts = [float(k) for k in range(T)] if T > 1 else [0.0, 1.0]
        probs = grid.probs.detach().to("cpu", torch.float64).numpy()
        if T == 1:
            probs = np.concatenate([probs, probs])
        values = np.ascontiguousarray(probs.transpose(0, 2, 1)).ravel()  # x fastest, then y, then slice
        occ = ca.interpolant("occ", "linear", [xs, ys, ts], values)
        slices = problem.slices(self.N + 1).tolist()  # absolute times t_start + k plan_dt

        nn, nu = model.nn, model.nu
        (i, j), th = model.position, model.heading
        F = step_function(ca, problem.system, par.plan_dt, par.plan_stride)
        Pm = ca.MX.sym("params", nu, self.n_seg)
        X = ca.MX.sym("X", nn, self.N)
        prm = ca.MX.sym("p", nn + 2)  # x0 (nn), goal (2)
        w = weights
        g = []
        prev = prm[0:nn]
        for k in range(self.N):
            g.append(X[:, k] - F(prev, Pm[:, k // per_seg]))
            prev = X[:, k]
        # body: the interpolated disc-dilated occupancy summed over the disc centres (a smooth stand-in for the max)
        occ_sum = 0

        def positions(cols: Any) -> Any:
            return X[i : i + 2, cols] if j == i + 1 else ca.vertcat(X[i, cols], X[j, cols])

        for off in collision.cover.offsets:
            centre = positions(slice(None)) + (off * ca.vertcat(ca.cos(X[th, :]), ca.sin(X[th, :])) if off else 0)
            occ_sum = occ_sum + occ(ca.vertcat(centre, ca.DM([slices[1:]])))
        J = (w.goal * ca.sumsqr(positions(self.N - 1) - prm[nn : nn + 2]) + w.collision * ca.sumsqr(occ_sum)
             + w.input * per_seg * ca.sumsqr(Pm))
        nlp = {"x": ca.vertcat(ca.vec(Pm), ca.vec(X)), "p": prm, "f": J, "g": ca.vertcat(*g)}
        opts = ipopt_options(max_iter=config.max_iter, max_cpu_time=config.max_cpu_time, hessian=config.hessian)
        self.nlp = BufferedNLP(ca.nlpsol("oracle", "ipopt", nlp, opts))
        self.n_p = nu * self.n_seg
        lbx, ubx = self.nlp.args["lbx"], self.nlp.args["ubx"]
        for m in range(nu):
            lbx[m : self.n_p : nu], ubx[m : self.n_p : nu] = model.input_lo[m], model.input_hi[m]
        xmin, xmax, ymin, ymax = grid.bounds
        self.state_lo, self.state_hi = list(model.state_lo), list(model.state_hi)  # the system's box, and the map:
        (self.state_lo[i], self.state_hi[i]), (self.state_lo[j], self.state_hi[j]) = (xmin, xmax), (ymin, ymax)
        for m in range(nn):
            lbx[self.n_p + m :: nn], ubx[self.n_p + m :: nn] = self.state_lo[m], self.state_hi[m]
        self.limits = (model.input_lo, model.input_hi)

    def feasible(self, x_plan: Tensor, tol: float = 1e-3) -> bool:
        """Whether re-simulated states ``(T, nx)`` respect the NLP's bounds on the nominal states (positions in the
        map, the others in the system's box) within ``tol`` (a non-converged iterate may violate the dynamics, so
        its re-simulation may leave them)."""
        lo = torch.as_tensor(self.state_lo, dtype=x_plan.dtype)
        hi = torch.as_tensor(self.state_hi, dtype=x_plan.dtype)
        x = x_plan[1:, list(self.model.nominal)]
        return bool(((x >= lo - tol) & (x <= hi + tol)).all())

    def params_of(self, sol: np.ndarray) -> np.ndarray:
        """``(nu, n_segments)`` parameters of a solution vector."""
        return sol[: self.n_p].reshape(self.n_seg, self.model.nu).T.copy()


class OraclePlanner(Planner):
    """Full-horizon NLP from the true initial state with restarts (see the module docstring)."""

    name = "oracle"

    def __init__(
        self,
        config: OracleConfig | None = None,
        *,
        evaluation_cost: CostConfig | None = None,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str = "cpu",
    ):
        """
        Args:
            config: oracle settings.
            evaluation_cost: cost configuration of the reported (evaluation-form) cost (default :class:`CostConfig`);
                its weights are those of ``J_MPC`` that ``config.weights`` leaves unset.

        Raises:
            OptionalDependencyError: CasADi (extra ``mpc``) is not installed.
        """
        self._ca = import_casadi("the oracle baseline")
        self.config = config or OracleConfig()
        self.evaluation_cost = evaluation_cost or CostConfig()
        #: the weights of J_MPC: the configuration's, unset ones from the density planner's cost (evaluation_cost)
        self.weights = self.config.weights.resolved(self.evaluation_cost.weights)
        self.dtype = dtype
        self.device = torch.device(device)
        #: number of NLP constructions so far (one per scene)
        self.n_builds = 0
        self._program: _OracleProgram | None = None
        self._program_key: tuple | None = None

    def _program_for(self, problem: PlanningProblem) -> tuple[_OracleProgram, float]:
        system = problem.system
        model = NLPModel.of(self._ca, system)  # the dynamics and bounds the NLP reads
        key = (problem.scene.grid, problem.t_start, problem.parameterization, model, system.footprint, problem.risk)
        if self._program is None or self._program_key is None or any(
            a is not b and a != b for a, b in zip(self._program_key, key)
        ):
            t0 = time.perf_counter()
            self._program = _OracleProgram(self._ca, self.config, self.weights, problem, model)
            self._program_key = key
            self.n_builds += 1
            t = time.perf_counter() - t0
            log.info("oracle: NLP built in %.2f s", t)
            return self._program, t
        return self._program, 0.0

    def plan(self, problem: PlanningProblem) -> PlanResult:
        """Plan from the problem's reference start (the mean of the initial law, without bias)."""
        return self.plan_from(problem, problem.reference_start(torch.float64))

    def plan_from(self, problem: PlanningProblem, true_state: Tensor) -> PlanResult:
        """Plan from the true initial state ``true_state (nx,)`` (its bias is ignored). Never raises."""
        t_start = time.perf_counter()
        try:
            return self._plan(problem, true_state, t_start)
        except Exception as exc:  # noqa: BLE001 - a benchmark never crashes on one planner
            log.warning("oracle failed: %s", exc)
            return PlanResult(self.name, PlanStatus.ERROR, message=f"{type(exc).__name__}: {exc}",
                              timings={"total": time.perf_counter() - t_start})

    def _guesses(self, problem: PlanningProblem) -> Tensor:
        cfg = self.config
        lo, hi = problem.system.input_bounds
        n_seg = problem.parameterization.n_segments
        gen = torch.Generator().manual_seed(cfg.seed)
        nu = problem.system.nu
        rand = cfg.init_std * torch.randn(cfg.restarts - 1, nu, n_seg, dtype=torch.float64, generator=gen)
        p = torch.cat([torch.zeros(1, nu, n_seg, dtype=torch.float64), rand])
        low = torch.tensor(lo, dtype=torch.float64)[:, None]
        high = torch.tensor(hi, dtype=torch.float64)[:, None]
        return torch.maximum(torch.minimum(p, high), low)

    def _plan(self, problem: PlanningProblem, true_state: Tensor, t_start: float) -> PlanResult:
        system, par = problem.system, problem.parameterization
        start = torch.as_tensor(true_state, dtype=torch.float64).detach().cpu().reshape(-1).clone()
        if start.shape != (system.nx,) or not bool(torch.isfinite(start).all()):
            raise ValueError(f"true_state must hold {system.nx} finite numbers, got {true_state!r}")
        prog, t_build = self._program_for(problem)
        nominal, nn = list(prog.model.nominal), prog.model.nn
        start = system.nominal_state(start)  # the oracle knows the exact model: hidden states (a bias) at 0
        args = prog.nlp.args
        args["p"][0:nn] = start[nominal].numpy()
        args["p"][nn : nn + 2] = problem.goal
        stride = par.plan_stride
        restarts: list[dict[str, Any]] = []
        best: tuple[int, float] | None = None
        t_solve = 0.0
        for r, p0 in enumerate(self._guesses(problem)):
            ref0 = make_reference(system, start, p0, par)
            args["x0"][: prog.n_p] = p0.T.reshape(-1).numpy()
            args["x0"][prog.n_p :] = ref0.x[stride::stride][:, nominal].reshape(-1).numpy()
            args["lam_x0"][:] = 0.0
            args["lam_g0"][:] = 0.0
            info: SolveInfo = prog.nlp.solve()
            t_solve += info.time
            sol = prog.nlp.res["x"]
            entry: dict[str, Any] = {"status": info.status, "success": info.success, "iterations": info.iterations,
                                     "time": info.time, "objective": math.nan}
            if np.all(np.isfinite(sol)):
                params = torch.from_numpy(prog.params_of(sol)).clamp(-1e9, 1e9)
                lo, hi = prog.limits
                params = torch.maximum(torch.minimum(params, torch.tensor(hi, dtype=torch.float64)[:, None]),
                                       torch.tensor(lo, dtype=torch.float64)[:, None])
                ref = make_reference(system, start, params, par)
                obj = mpc_objective(problem.scene.grid, ref.x_plan, ref.u_plan, problem.goal, self.weights,
                                    collision=problem.collision(), dt=par.plan_dt,
                                    t_start=problem.t_start)
                feasible = prog.feasible(ref.x_plan)
                entry["objective"] = obj["total"]
                entry["feasible"] = feasible
                entry["params"] = params
                rank = (0 if feasible else 1, obj["total"])
                if math.isfinite(obj["total"]) and (best is None or rank < best):
                    best = rank
                    entry["best"] = True
            restarts.append(entry)
            log.debug("oracle restart %d: %s, %d iterations, J = %.4g", r, info.status, info.iterations,
                      entry["objective"])
        t_total = time.perf_counter() - t_start
        summary = [{k: v for k, v in e.items() if k not in ("params", "best")} for e in restarts]
        extras: dict[str, Any] = {"restarts": summary, "n_builds": self.n_builds}
        timings = {"nlp_build": t_build, "solve": t_solve, "total": t_total}
        iterations = {"restarts": len(restarts), "ipopt": sum(e["iterations"] for e in restarts)}
        if best is None:
            return PlanResult(self.name, PlanStatus.FAILED, timings=timings, iterations=iterations, extras=extras,
                              message="no restart returned a finite iterate")
        i_best = max(i for i, e in enumerate(restarts) if e.get("best"))
        params = restarts[i_best]["params"]
        feasible = best[0] == 0
        ref = make_reference(system, start.to(dtype=self.dtype, device=self.device),
                             params.to(dtype=self.dtype, device=self.device), par)
        cost, coll = evaluate_trajectory(problem, ref.x_plan, ref.u_plan, cost_config=self.evaluation_cost)
        extras["best_restart"] = i_best
        extras["best_converged"] = bool(restarts[i_best]["success"])
        extras["objective"] = mpc_objective(problem.scene.grid, ref.x_plan, ref.u_plan, problem.goal, self.weights,
                                            collision=problem.collision(), dt=par.plan_dt,
                                            t_start=problem.t_start)
        n_conv = sum(1 for e in restarts if e["success"])
        message = (f"{n_conv} of {len(restarts)} restarts converged; kept restart {i_best} "
                   f"({restarts[i_best]['status']})")
        if not feasible:
            message = (f"no restart gave a plan within the state bounds; {message} is the best infeasible one "
                       f"({n_conv} converged)")
        return PlanResult(
            planner=self.name,
            status=PlanStatus.SUCCESS if feasible else PlanStatus.FAILED,
            params=params.to(dtype=self.dtype, device=self.device),
            reference=ref,
            states=ref.x_plan,
            cost=cost,
            collision=coll,
            timings=timings,
            iterations=iterations,
            message=message,
            extras=extras,
        )


@register_planner("oracle", "oracle O: full-horizon NLP from the true start, 10 restarts (CasADi/IPOPT; extra 'mpc')",
                  section="oracle", execution="open_loop", plans_from_true_state=True, label="O", colour="tab:green")
def _make_oracle(ctx: PlannerContext) -> OraclePlanner:
    return OraclePlanner(ctx.config.oracle, evaluation_cost=ctx.config.density_planner.cost, dtype=ctx.dtype,
                         device=ctx.device)

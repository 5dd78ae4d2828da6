"""CasADi/IPOPT plumbing shared by the MPC baselines and the oracle (optional extra ``mpc``).

CasADi is imported lazily (:func:`import_casadi`), so that importing the planner modules, listing the planner
names and running everything else works without the extra.

:class:`BufferedNLP` calls an ``nlpsol`` through ``casadi.Function.buffer()``: the solver reads its inputs from
(and writes its outputs to) numpy arrays that are allocated once, so re-solving with new parameters converts
nothing. This matters for the MPC, whose parameter vector carries ~10^5 occupancy values per step: passing them
as a numpy array to an ordinary CasADi call (or ``Opti.set_value``) converts them element by element, which
alone costs 15-30 ms per step on the development machine.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import OptionalDependencyError
from ..systems.base import System

__all__ = [
    "SUCCESS_STATUSES",
    "check_ipopt_limits",
    "import_casadi",
    "casadi_available",
    "step_function",
    "NLPModel",
    "position_rate_bound",
    "ipopt_options",
    "BufferedNLP",
    "SolveInfo",
]

#: IPOPT return statuses that count as a converged solve
SUCCESS_STATUSES = frozenset({"Solve_Succeeded", "Solved_To_Acceptable_Level"})


def import_casadi(purpose: str = "MPC baselines") -> Any:
    """The ``casadi`` module, or :class:`OptionalDependencyError` naming the extra to install."""
    try:
        import casadi
    except ImportError as exc:
        raise OptionalDependencyError("casadi", "mpc", purpose) from exc
    return casadi


def casadi_available() -> bool:
    """Whether the optional ``casadi`` package can be imported."""
    try:
        import_casadi()
    except OptionalDependencyError:
        return False
    return True


def check_ipopt_limits(max_iter: int, max_cpu_time: float) -> None:
    """:class:`ValueError` unless ``max_iter`` is a positive integer and ``max_cpu_time`` a number > 0 (``inf``:
    no cap; ``--set mpc.max_cpu_time=inf`` on the command line, since TOML has no ``None``)."""
    if isinstance(max_iter, bool) or not isinstance(max_iter, int) or max_iter < 1:
        raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
    if isinstance(max_cpu_time, bool) or not isinstance(max_cpu_time, (int, float)) or not max_cpu_time > 0:
        raise ValueError(f"max_cpu_time must be a number > 0 in seconds (inf: no cap), got {max_cpu_time!r}")


def step_function(ca: Any, system: System, dt: float, substeps: int, name: str = "step") -> Any:
    """CasADi function ``F(x (nn,), u (nu,)) -> x (nn,)``: ``substeps`` explicit-Euler steps of ``dt / substeps``
    [s] of the system's nominal dynamics (:meth:`System.f_symbolic` on its :attr:`~System.nominal_indices`, ``nn``
    of them; hidden states such as the car's heading bias are not part of the NLP models) with the input held
    constant. Identical to :meth:`System.rollout` on the fine grid.

    Raises:
        NotImplementedError: the system has no symbolic dynamics (:meth:`System.f_symbolic`).
        ValueError: ``f_symbolic`` returns the wrong number of entries.
    """
    nn, nu = len(system.nominal_indices), system.nu
    x = ca.SX.sym("x", nn)
    u = ca.SX.sym("u", nu)
    rate = system.f_symbolic(x, u, ca)
    if rate.shape != (nn, 1):
        raise ValueError(f"{type(system).__name__}.f_symbolic returned shape {rate.shape}, expected ({nn}, 1): one "
                         "entry per nominal state")
    h = dt / substeps
    xn = x
    for _ in range(substeps):
        xn = xn + h * system.f_symbolic(xn, u, ca)
    return ca.Function(name, [x, u], [xn], ["x", "u"], ["x_next"])


@dataclass(frozen=True)
class NLPModel:
    """What the NLP baselines (MPC, oracle) read from a system, in the order of its nominal state
    (:attr:`System.nominal_indices`, ``nn`` entries): built by :meth:`of`.

    Attributes:
        nn: number of nominal states (the NLP's state dimension).
        nu: number of inputs.
        nominal: :attr:`System.nominal_indices` (which full-state entries the nominal state holds).
        position: nominal indices of ``(p_x, p_y)``.
        heading: nominal index of the heading, ``None`` for a system without one.
        state_lo, state_hi: the system's state box on the nominal states, with the position entries infinite (the
            map bounds them).
        input_lo, input_hi: :attr:`System.input_bounds`.
        dynamics: the symbolic nominal dynamics as text (two models with the same text build the same NLP).
        system: the class name of the system (error messages).
    """

    nn: int
    nu: int
    nominal: tuple[int, ...]
    position: tuple[int, int]
    heading: int | None
    state_lo: tuple[float, ...]
    state_hi: tuple[float, ...]
    input_lo: tuple[float, ...]
    input_hi: tuple[float, ...]
    dynamics: str
    system: str

    @classmethod
    def of(cls, ca: Any, system: System) -> NLPModel:
        """The model of ``system``. Raises :class:`NotImplementedError` ("... has no symbolic dynamics ...") for a
        system without :meth:`System.f_symbolic`."""
        nominal = tuple(system.nominal_indices)
        nn, nu = len(nominal), system.nu
        i, j = system.position_indices
        if i not in nominal or j not in nominal or (system.heading_index is not None
                                                    and system.heading_index not in nominal):
            raise ValueError(f"{type(system).__name__}: the position and heading must be nominal states (not in "
                             "hidden_states)")
        x, u = ca.SX.sym("x", nn), ca.SX.sym("u", nu)
        dynamics = str(system.f_symbolic(x, u, ca))
        lo_full, hi_full = (tuple(float(v) for v in b) for b in system.state_bounds)
        lo = [lo_full[k] for k in nominal]
        hi = [hi_full[k] for k in nominal]
        position = (nominal.index(i), nominal.index(j))
        for k in position:
            lo[k], hi[k] = -math.inf, math.inf
        u_lo, u_hi = (tuple(float(v) for v in b) for b in system.input_bounds)
        if len(u_lo) != nu or len(u_hi) != nu:
            raise ValueError(f"{type(system).__name__}: input_bounds must hold {nu} entries each")
        return cls(nn=nn, nu=nu, nominal=nominal, position=position, heading=system.nominal_index(system.heading_index),
                   state_lo=tuple(lo), state_hi=tuple(hi), input_lo=u_lo, input_hi=u_hi, dynamics=dynamics,
                   system=type(system).__name__)

    def nominal_of(self, x: np.ndarray) -> np.ndarray:
        """The nominal states ``(nn,)`` of a full state ``(nx,)`` (hidden states dropped)."""
        return x[list(self.nominal)]


def _linear_sup(ca: Any, expr: Any, var: Any, lo: list[float], hi: list[float]) -> float | None:
    """``max |expr|`` over the box ``lo <= var <= hi`` if the scalar SX ``expr`` is affine in ``var`` (exact: an
    affine function reaches its extremes at a vertex), else ``None``; ``inf`` where the box is unbounded along a
    direction ``expr`` depends on."""
    if not ca.is_linear(expr, var):
        return None
    jac = ca.Function("affine_rate", [var], [ca.jacobian(expr, var), expr])
    row, value0 = jac(np.zeros(var.shape[0]))
    row = np.asarray(ca.DM(row)).reshape(-1)
    top = bottom = float(value0)
    for a, lo_k, hi_k in zip(row.tolist(), lo, hi):
        if a != 0:
            top += max(a * lo_k, a * hi_k)
            bottom += min(a * lo_k, a * hi_k)
    return max(abs(top), abs(bottom))


def position_rate_bound(ca: Any, system: System, dt: float) -> float:
    """An upper bound [m/s] on the rate of either position coordinate during one stage of ``dt`` [s] that starts in
    the system's state box: how far the vehicle can move, which sizes the MPC's occupancy windows.

    With a speed state (:attr:`System.speed_index`): the largest ``|speed|`` of the state box plus ``dt`` times the
    largest ``|speed'|`` (the speed may leave its box between two stages; for the car ``v_max + a_max dt``). Without
    one: the largest ``|p'|`` of the state box widened by one stage of drift, when the position rate is affine in
    state and input (a double integrator: ``|v| + a_max dt``). The rates' bounds are exact suprema of affine
    expressions over the state and input boxes.

    Raises:
        ValueError: no finite bound follows from the system's facts (the message names the missing one).
    """
    name = type(system).__name__
    nominal = system.nominal_indices
    nn, nu = len(nominal), system.nu
    x, u = ca.SX.sym("x", nn), ca.SX.sym("u", nu)
    rate = system.f_symbolic(x, u, ca)
    xu = ca.vertcat(x, u)
    lo_full, hi_full = (tuple(float(v) for v in b) for b in system.state_bounds)
    u_lo, u_hi = (list(map(float, b)) for b in system.input_bounds)
    lo = [lo_full[k] for k in nominal] + u_lo
    hi = [hi_full[k] for k in nominal] + u_hi

    def sup(k: int, what: str) -> float:
        value = _linear_sup(ca, rate[k], xu, lo, hi)
        if value is None:
            raise ValueError(f"{name}: the rate of its {what} is not affine in state and input, so the MPC cannot "
                             "bound how far the vehicle moves in a stage (its occupancy windows need that); give the "
                             "system a speed state (speed_index) with an affine rate")
        if not math.isfinite(value):
            raise ValueError(f"{name}: the rate of its {what} is unbounded over its state and input boxes, so the "
                             "MPC cannot bound how far the vehicle moves in a stage (its occupancy windows need "
                             "that); give the system finite input bounds and state bounds")
        return value

    speed = system.nominal_index(system.speed_index)
    if speed is not None:
        v_abs = max(abs(lo[speed]), abs(hi[speed]))
        if not math.isfinite(v_abs):
            raise ValueError(f"{name}: its speed state has no finite bound in state_bounds, so the MPC cannot bound "
                             "how far the vehicle moves in a stage; give the speed a finite state box")
        return v_abs + sup(speed, "speed") * dt
    # no speed state: the position rate over the box, the states it depends on widened by one stage of drift
    position = sorted({nominal.index(i) for i in system.position_indices})
    needed = [any(ca.depends_on(rate[k], x[m]) for k in position) for m in range(nn)]
    widen = [sup(m, f"state {system.state_names[nominal[m]]!r}") * dt
             if needed[m] and m not in position and math.isfinite(lo[m]) and math.isfinite(hi[m]) else 0.0
             for m in range(nn)]
    lo = [v - w for v, w in zip(lo[:nn], widen)] + u_lo
    hi = [v + w for v, w in zip(hi[:nn], widen)] + u_hi
    return max(sup(k, "position (it has no speed state, speed_index)") for k in position)


def ipopt_options(
    *,
    max_iter: int,
    max_cpu_time: float = math.inf,
    hessian: str = "exact",
    tol: float | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """``nlpsol`` options for a quiet IPOPT (``print_level 0``, no banner) with the given limits.

    ``max_iter`` is deterministic; ``max_cpu_time`` [s] (``inf``: no cap) makes the returned iterate depend on the
    machine's speed and load, since IPOPT stops after however many iterations fit in that time."""
    ipopt: dict[str, Any] = {"print_level": 0, "sb": "yes", "max_iter": int(max_iter)}
    if math.isfinite(max_cpu_time):
        ipopt["max_cpu_time"] = float(max_cpu_time)
    if hessian != "exact":
        ipopt["hessian_approximation"] = hessian
    if tol is not None:
        ipopt["tol"] = float(tol)
    ipopt.update(extra or {})
    return {"print_time": False, "error_on_fail": False, "ipopt": ipopt}


@dataclass
class SolveInfo:
    """Outcome of one IPOPT call.

    Attributes:
        status: IPOPT return status (e.g. ``"Solve_Succeeded"``, ``"Maximum_CpuTime_Exceeded"``), or
            ``"Exception"`` when CasADi raised (``message`` says why).
        success: the solve converged (:data:`SUCCESS_STATUSES`).
        iterations: IPOPT iterations.
        objective: objective value of the returned iterate (NaN if unavailable).
        time: wall time of the solver call [s].
        message: exception text, if any.
    """

    status: str
    success: bool
    iterations: int
    objective: float
    time: float
    message: str = ""


class BufferedNLP:
    """An ``nlpsol`` evaluated through ``Function.buffer()`` on preallocated numpy arrays.

    ``args[name]`` (``x0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0``) are written in place by the caller;
    ``res[name]`` (``x, f, g, lam_x, lam_g, lam_p``) hold the last iterate after :meth:`solve` (IPOPT returns its
    last iterate also when it stops on a limit or fails).
    """

    def __init__(self, solver: Any):
        self.solver = solver
        self.args = {n: np.zeros(solver.nnz_in(i)) for i, n in enumerate(solver.name_in())}
        self.res = {n: np.zeros(solver.nnz_out(i)) for i, n in enumerate(solver.name_out())}
        self._buf, self._eval = solver.buffer()
        for name, arr in self.args.items():
            self._buf.set_arg(solver.index_in(name), arr.data)  # the array's own buffer (a memoryview)
        for name, arr in self.res.items():
            self._buf.set_res(solver.index_out(name), arr.data)

    def solve(self) -> SolveInfo:
        """Run IPOPT on the current arguments; never raises (CasADi errors become ``status="Exception"``)."""
        t0 = time.perf_counter()
        try:
            self._eval()
        except Exception as exc:  # noqa: BLE001 - solver errors are reported, never raised
            self.res["x"][:] = np.nan
            return SolveInfo("Exception", False, 0, math.nan, time.perf_counter() - t0, str(exc).strip()[-500:])
        elapsed = time.perf_counter() - t0
        stats = self._buf.stats()
        status = str(stats.get("return_status", "unknown"))
        return SolveInfo(
            status=status,
            success=status in SUCCESS_STATUSES,
            iterations=int(stats.get("iter_count", 0)),
            objective=float(self.res["f"][0]) if self.res["f"].size else math.nan,
            time=elapsed,
        )

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

__all__ = [
    "SUCCESS_STATUSES",
    "check_ipopt_limits",
    "import_casadi",
    "casadi_available",
    "car_step_function",
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


def car_step_function(ca: Any, dt: float, substeps: int, name: str = "car_step") -> Any:
    """CasADi function ``F(x (4,), u (2,)) -> x (4,)``: ``substeps`` explicit-Euler steps of ``dt / substeps`` [s]
    of the nominal kinematic car ``[v cos(theta), v sin(theta), omega, a]`` with the input held constant
    (the bias state is not part of the NLP models). Identical to :meth:`KinematicCar.rollout` on the fine grid."""
    x = ca.SX.sym("x", 4)
    u = ca.SX.sym("u", 2)
    h = dt / substeps
    xn = x
    for _ in range(substeps):
        xn = xn + h * ca.vertcat(xn[3] * ca.cos(xn[2]), xn[3] * ca.sin(xn[2]), u[0], u[1])
    return ca.Function(name, [x, u], [xn], ["x", "u"], ["x_next"])


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

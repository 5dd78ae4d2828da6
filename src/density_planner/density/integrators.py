"""Explicit Runge-Kutta integrators for a state tuple driven by a time-varying reference.

Each integrator is a Butcher tableau (``stages``, ``a``, ``b``); :meth:`FixedStepIntegrator.step` takes the
vector field ``func(y, x_ref, u_ref) -> dy/dt`` (``y`` a tuple of tensors), the reference values at the stage
times, and the step size. Only time is looped over; every stage is evaluated on the whole batch at once.

:data:`DOPRI5` is the embedded pair of Dormand and Prince (1980), "A family of embedded Runge-Kutta formulae",
J. Comput. Appl. Math. 6(1): a 5th-order solution, a 4th-order one from the same stages whose difference estimates
the local error, and a last stage at the new state ("first same as last"); its continuous extension of order 4
(Shampine 1986, in Hairer, Norsett & Wanner, "Solving Ordinary Differential Equations I", section II.6) gives the
solution anywhere inside a step from the same stages.

:data:`RK43` is the classical RK4 with an embedded order-3 solution from its own four stages and the stage at the
new state (``b_hat = (1/6, 1/3, 1/3, 0, 1/6)``, which meets the four order-3 conditions; the local error estimate is
``h (k_4 - k_5) / 6``), and the cubic Hermite interpolant of the two ends as its continuous extension (order 3):
RK4's four evaluations per step with error control. The error-controlled loop that uses both lives in
:mod:`density_planner.density.liouville`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from torch import Tensor

from ..checks import check_choice

__all__ = ["FixedStepIntegrator", "EmbeddedPair", "EULER", "RK4", "DOPRI5", "RK43", "INTEGRATORS", "PAIRS",
           "get_integrator"]

State = tuple[Tensor, ...]
VectorField = Callable[[State, Tensor, Tensor], State]


@dataclass(frozen=True)
class FixedStepIntegrator:
    """Explicit Runge-Kutta method given by its Butcher tableau."""

    name: str
    order: int
    #: stage times as fractions of the step (c_i)
    stages: tuple[float, ...]
    #: lower-triangular coupling coefficients a_ij (row i has i entries)
    a: tuple[tuple[float, ...], ...]
    #: weights b_i
    b: tuple[float, ...]

    def step(self, func: VectorField, y: State, x_ref: Sequence[Tensor] | Tensor, u_ref: Sequence[Tensor] | Tensor,
             dt: float) -> State:
        """One step from ``y``; ``x_ref[i]``, ``u_ref[i]`` are the reference values at stage ``i``."""
        ks: list[State] = []
        for i in range(len(self.stages)):
            yi = y
            if i:
                yi = tuple(
                    y_j + dt * sum(a_ik * k[j] for a_ik, k in zip(self.a[i], ks) if a_ik != 0.0)
                    for j, y_j in enumerate(y)
                )
            ks.append(func(yi, x_ref[i], u_ref[i]))
        return tuple(
            y_j + dt * sum(b_i * k[j] for b_i, k in zip(self.b, ks) if b_i != 0.0) for j, y_j in enumerate(y)
        )


EULER = FixedStepIntegrator("euler", 1, (0.0,), ((),), (1.0,))
RK4 = FixedStepIntegrator(
    "rk4",
    4,
    (0.0, 0.5, 0.5, 1.0),
    ((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0)),
    (1 / 6, 1 / 3, 1 / 3, 1 / 6),
)
INTEGRATORS = {"euler": EULER, "rk4": RK4}


@dataclass(frozen=True)
class EmbeddedPair:
    """Explicit Runge-Kutta pair with an error estimate: ``b`` gives the propagated solution, ``error`` =
    ``b - b_hat`` the difference to the embedded lower-order one, whose local error is ``O(h^order)`` (so a step
    scales with ``err^(-1 / order)``). The last stage is evaluated at the new solution (its row of ``a`` equals
    ``b``) and is the next step's first ("first same as last")."""

    name: str
    order: int
    stages: tuple[float, ...]
    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    error: tuple[float, ...]
    #: coefficients ``d_i`` of the continuous extension, see :meth:`interpolate` (all zero: the cubic Hermite)
    dense: tuple[float, ...]
    #: default tolerance of the error-controlled loop (``LiouvilleConfig.tolerance = None``), measured in
    #: docs/core.md ("Error control")
    tolerance: float
    #: weights ``w_i`` of a continuous extension at the step's middle from the stages before the last,
    #: ``y(t + h / 2) = y + h sum_i w_i k_i`` (empty: none; the loop then uses :meth:`interpolate`, which needs the
    #: last stage): the log-density's quadrature then evaluates the middle together with the last stage
    midpoint: tuple[float, ...] = ()

    def interpolate(self, y0: Tensor, y1: Tensor, ks: Sequence[Tensor], h: Tensor, theta: Tensor) -> Tensor:
        """The solution at ``t + theta h`` inside a step from ``y0`` to ``y1`` with stages ``ks`` (first and last
        included); ``h``, ``theta`` per row, broadcast over the trailing dimensions::

            y0 + theta (r2 + (1 - theta) (r3 + theta (r4 + (1 - theta) r5)))

        with ``r2 = y1 - y0``, ``r3 = h k_1 - r2``, ``r4 = r2 - h k_last - r3``, ``r5 = h sum_i d_i k_i``: a Hermite
        cubic through both ends and their slopes plus a correction that makes it order 4."""
        shape = (-1, *([1] * (y0.ndim - 1)))
        h, th = h.to(y0.dtype).reshape(shape), theta.to(y0.dtype).reshape(shape)
        r2 = y1 - y0
        r3 = h * ks[0] - r2
        r4 = r2 - h * ks[-1] - r3
        r5 = h * sum(d * k for d, k in zip(self.dense, ks) if d != 0.0)
        return y0 + th * (r2 + (1 - th) * (r3 + th * (r4 + (1 - th) * r5)))


_DP_B = (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0)
_DP_B_HAT = (5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40)
DOPRI5 = EmbeddedPair(
    "dopri5",
    5,
    (0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0),
    (
        (),
        (1 / 5,),
        (3 / 40, 9 / 40),
        (44 / 45, -56 / 15, 32 / 9),
        (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
        (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
        _DP_B[:6],
    ),
    _DP_B,
    tuple(b - bh for b, bh in zip(_DP_B, _DP_B_HAT)),
    (-12715105075 / 11282082432, 0.0, 87487479700 / 32700410799, -10690763975 / 1880347072,
     701980252875 / 199316789632, -1453857185 / 822651844, 69997945 / 29380423),
    5e-5,
)


RK43 = EmbeddedPair(
    "rk43",
    4,
    (0.0, 0.5, 0.5, 1.0, 1.0),
    ((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0), (1 / 6, 1 / 3, 1 / 3, 1 / 6)),
    (1 / 6, 1 / 3, 1 / 3, 1 / 6, 0.0),
    (0.0, 0.0, 0.0, 1 / 6, -1 / 6),
    (0.0, 0.0, 0.0, 0.0, 0.0),
    3e-3,
    # RK4's order-3 continuous extension at theta = 1/2 (Hairer, Norsett & Wanner I, II.6): b_1 = theta - 3
    # theta^2 / 2 + 2 theta^3 / 3, b_2 = b_3 = theta^2 - 2 theta^3 / 3, b_4 = -theta^2 / 2 + 2 theta^3 / 3
    (5 / 24, 1 / 6, 1 / 6, -1 / 24),
)
PAIRS = {"dopri5": DOPRI5, "rk43": RK43}


def get_integrator(name: str) -> FixedStepIntegrator:
    """Integrator by name (``"euler"`` or ``"rk4"``)."""
    check_choice("integrator", name, tuple(INTEGRATORS))
    return INTEGRATORS[name]

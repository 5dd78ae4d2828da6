"""Explicit Runge-Kutta integrators for a state tuple driven by a time-varying reference.

Each integrator is a Butcher tableau (``stages``, ``a``, ``b``); :meth:`FixedStepIntegrator.step` takes the
vector field ``func(y, x_ref, u_ref) -> dy/dt`` (``y`` a tuple of tensors), the reference values at the stage
times, and the step size. Only time is looped over; every stage is evaluated on the whole batch at once.

:data:`DOPRI5` is the embedded pair of Dormand and Prince (1980), "A family of embedded Runge-Kutta formulae",
J. Comput. Appl. Math. 6(1): a 5th-order solution, a 4th-order one from the same stages whose difference estimates
the local error, and a last stage at the new state ("first same as last"). The error-controlled loop that uses it
lives in :mod:`density_planner.density.liouville`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from torch import Tensor

from ..checks import check_choice

__all__ = ["FixedStepIntegrator", "EmbeddedPair", "EULER", "RK4", "DOPRI5", "INTEGRATORS", "get_integrator"]

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
    """Explicit Runge-Kutta pair with an error estimate: ``b`` gives the propagated solution (order ``order``),
    ``error`` = ``b - b_hat`` the difference to the embedded lower-order one. With ``fsal`` the last stage is
    evaluated at the new solution (its row of ``a`` equals ``b``) and is the next step's first stage."""

    name: str
    order: int
    stages: tuple[float, ...]
    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    error: tuple[float, ...]
    fsal: bool


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
    True,
)


def get_integrator(name: str) -> FixedStepIntegrator:
    """Integrator by name (``"euler"`` or ``"rk4"``)."""
    check_choice("integrator", name, tuple(INTEGRATORS))
    return INTEGRATORS[name]

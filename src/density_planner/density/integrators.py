"""Fixed-step explicit integrators for a state tuple driven by a time-varying reference.

Each integrator is a Butcher tableau (``stages``, ``a``, ``b``); :meth:`FixedStepIntegrator.step` takes the
vector field ``func(y, x_ref, u_ref) -> dy/dt`` (``y`` a tuple of tensors), the reference values at the stage
times, and the step size. Only time is looped over; every stage is evaluated on the whole batch at once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from torch import Tensor

from ..checks import check_choice

__all__ = ["FixedStepIntegrator", "EULER", "RK4", "INTEGRATORS", "get_integrator"]

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


def get_integrator(name: str) -> FixedStepIntegrator:
    """Integrator by name (``"euler"`` or ``"rk4"``)."""
    check_choice("integrator", name, tuple(INTEGRATORS))
    return INTEGRATORS[name]

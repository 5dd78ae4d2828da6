"""Toy problems with closed-form answers used across the tests."""

from __future__ import annotations

import torch

from density_planner.control.analytic import LinearFeedbackController
from density_planner.control.reference import PiecewiseConstantInputs, make_reference
from density_planner.systems.linear import LinearSystem

#: a stable, non-normal 2-D system with tr(A) = -0.7
A2 = ((-0.5, 1.0), (-0.3, -0.2))
B2 = ((0.0,), (1.0,))


def linear_problem(dtype=torch.float64, K=((0.0, 0.0),)):
    """Linear system ``x' = A x + B u`` with ``u = u_ref - K (x - x_ref)`` and a zero reference input.

    With K = 0 the closed loop is ``x' = A x``: ``x(t) = expm(A t) x0`` and ``log rho(t) = log rho0 - tr(A) t``.
    """
    system = LinearSystem(A2, B2)
    controller = LinearFeedbackController(K).to(dtype)
    par = PiecewiseConstantInputs()
    params = torch.zeros(1, par.n_segments, dtype=dtype)
    reference = make_reference(system, torch.zeros(2, dtype=dtype), params, par)
    return system, controller, reference


def expm_solution(x0: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``expm(A t) x0`` for every time in ``t``: ``(N, T, 2)``."""
    a = torch.tensor(A2, dtype=x0.dtype)
    mats = torch.linalg.matrix_exp(t[:, None, None].to(x0.dtype) * a)  # (T, 2, 2)
    return torch.einsum("tij,nj->nti", mats, x0)

"""Linear time-invariant system ``x' = A x + B u``: the analytic test problem of the density code.

With a linear feedback ``u = u_ref - K (x - x_ref)`` the closed loop is ``x' = (A - B K) x + c(t)`` whose
divergence is the constant ``tr(A - B K)``, so ``log rho(t) = log rho_0 - tr(A - B K) t`` exactly.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from .base import ControlAffineSystem, Footprint

__all__ = ["LinearSystem"]


class LinearSystem(ControlAffineSystem):
    """``x' = A x + B u`` with unbounded states and inputs (unless bounds are given)."""

    def __init__(
        self,
        A: Sequence[Sequence[float]],
        B: Sequence[Sequence[float]],
        *,
        input_bounds: tuple[Sequence[float], Sequence[float]] | None = None,
        footprint: Footprint | None = None,
    ):
        """``footprint``: the body (no heading, so ``length == width``: a disc; default a point); the position is
        the first two state components."""
        a = torch.as_tensor(A, dtype=torch.float64)
        b = torch.as_tensor(B, dtype=torch.float64)
        if a.ndim != 2 or a.shape[0] != a.shape[1]:
            raise ValueError(f"A must be a square matrix, got shape {tuple(a.shape)}")
        if b.ndim != 2 or b.shape[0] != a.shape[0]:
            raise ValueError(f"B must have shape ({a.shape[0]}, nu), got {tuple(b.shape)}")
        self._a = a
        self._b = b
        self.state_names = tuple(f"x{i}" for i in range(a.shape[0]))
        self.input_names = tuple(f"u{j}" for j in range(b.shape[1]))
        self.constant_input_matrix = tuple(tuple(float(v) for v in row) for row in b.tolist())
        inf = float("inf")
        self._input_bounds = input_bounds or ((-inf,) * b.shape[1], (inf,) * b.shape[1])
        if footprint is not None:
            if footprint.length != footprint.width:
                raise ValueError("a LinearSystem has no heading: its footprint must be a disc (length == width)")
            self.footprint = footprint

    @property
    def state_bounds(self):
        inf = float("inf")
        return (-inf,) * self.nx, (inf,) * self.nx

    @property
    def input_bounds(self):
        return self._input_bounds

    def A(self, like: Tensor) -> Tensor:
        return self._a.to(dtype=like.dtype, device=like.device)

    def drift(self, x: Tensor) -> Tensor:
        return x @ self.A(x).T

    def input_matrix(self, x: Tensor) -> Tensor:
        return self._b.to(dtype=x.dtype, device=x.device)

    def f_symbolic(self, x, u, ops):
        """``A x + B u`` for symbolic vectors (every state is nominal)."""
        a, b = self._a.tolist(), self._b.tolist()
        return ops.vertcat(*[sum(a[i][j] * x[j] for j in range(self.nx) if a[i][j])
                             + sum(b[i][j] * u[j] for j in range(self.nu) if b[i][j]) for i in range(self.nx)])

    def drift_divergence(self, x: Tensor) -> Tensor:
        return torch.full(x.shape[:-1], float(torch.trace(self._a)), dtype=x.dtype, device=x.device)

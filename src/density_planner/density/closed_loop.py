"""Closed-loop dynamics ``f_cl(x, t) = f(x, pi(h(x), x_ref(t), u_ref(t)))`` and its divergence.

The Liouville equation in log form needs ``div f_cl`` along every trajectory (paper Eq. (2)). Two ways:

* ``"autodiff"`` (any system): ``div f_cl = sum_i d f_cl,i / d x_i`` with one forward-mode ``jvp`` per state.
* ``"structured"`` (control-affine systems with a constant input matrix ``B``)::

      div f_cl = tr(da/dx) + tr(B du/dx) = tr(da/dx) + sum_{i,j} B_ij du_j/dx_i

  which needs tangents only along the states that ``B`` actuates. For the car ``tr(da/dx) = 0`` and only
  ``d omega / d theta + d a / d v`` remain: two tangents, pushed through the controller in one pass.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from ..checks import check_choice
from ..control.base import TrackingController
from ..systems.base import ControlAffineSystem, System

__all__ = ["ClosedLoop", "DivergenceMethod"]

DivergenceMethod = Literal["structured", "autodiff"]


class ClosedLoop:
    """A system tracking a reference with a controller; evaluates ``f_cl`` and ``div f_cl`` on batches."""

    def __init__(self, system: System, controller: TrackingController):
        self.system = system
        self.controller = controller
        self._structure: tuple[list[int], Tensor] | None = None
        b = getattr(system, "constant_input_matrix", None)
        if isinstance(system, ControlAffineSystem) and b is not None:
            b_t = torch.as_tensor(b, dtype=torch.float64)
            rows = [i for i in range(b_t.shape[0]) if bool((b_t[i] != 0).any())]
            self._structure = (rows, b_t[rows])  # actuated states and the matching rows of B

    @property
    def supports_structured(self) -> bool:
        return self._structure is not None

    def inputs(self, x: Tensor, x_ref: Tensor, u_ref: Tensor) -> Tensor:
        """Applied (clipped) input at true states ``x``."""
        return self.controller(self.system.measure(x), x_ref, u_ref)

    def rhs(self, x: Tensor, x_ref: Tensor, u_ref: Tensor) -> Tensor:
        """``f_cl(x)``."""
        return self.rhs_with_raw(x, x_ref, u_ref)[0]

    def rhs_with_raw(self, x: Tensor, x_ref: Tensor, u_ref: Tensor) -> tuple[Tensor, Tensor]:
        """``(f_cl(x), u_raw)``: also the controller's raw (unbounded) input, at no extra cost."""
        x_hat = self.system.measure(x)
        raw = self.controller.raw(x_hat, x_ref, u_ref)
        return self.system.f(x, self.controller.bound(raw, x_hat)), raw

    def rhs_and_divergence(
        self, x: Tensor, x_ref: Tensor, u_ref: Tensor, method: DivergenceMethod = "structured"
    ) -> tuple[Tensor, Tensor]:
        """``(f_cl(x), div f_cl(x))`` for ``x (*batch, nx)``; differentiable (usable inside an optimisation)."""
        return self.rhs_divergence_with_raw(x, x_ref, u_ref, method)[:2]

    def rhs_divergence_with_raw(
        self, x: Tensor, x_ref: Tensor, u_ref: Tensor, method: DivergenceMethod = "structured"
    ) -> tuple[Tensor, Tensor, Tensor]:
        """:meth:`rhs_and_divergence` and the controller's raw input (at no extra cost on the structured path)."""
        check_choice("divergence method", method, ("structured", "autodiff"))
        if method == "structured" and self._structure is not None:
            return self._structured(x, x_ref, u_ref)
        f, div = self._autodiff(x, x_ref, u_ref)
        return f, div, self.controller.raw(self.system.measure(x), x_ref, u_ref).detach()

    def _structured(self, x: Tensor, x_ref: Tensor, u_ref: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        assert self._structure is not None
        rows, b_rows = self._structure
        system = self.system
        eye = torch.eye(system.nx, dtype=x.dtype, device=x.device)[rows]  # (K, nx)
        tangents = eye.reshape(len(rows), *([1] * (x.ndim - 1)), system.nx)
        x_hat = system.measure(x)
        dx_hat = system.measure_jvp(x, tangents)
        raw, du_raw = self.controller.raw_with_tangents(x_hat, x_ref, u_ref, dx_hat)
        u, du = self.controller.bound_with_tangents(raw, du_raw, x_hat, dx_hat)  # du: (K, *batch, nu)
        b = b_rows.to(dtype=x.dtype, device=x.device)  # (K, nu)
        div_u = (du * b.reshape(len(rows), *([1] * (du.ndim - 2)), -1)).sum(dim=(0, -1))
        assert isinstance(system, ControlAffineSystem)
        div = system.drift_divergence(x) + div_u
        return system.f(x, u), div, raw

    def _autodiff(self, x: Tensor, x_ref: Tensor, u_ref: Tensor) -> tuple[Tensor, Tensor]:
        def fn(z: Tensor) -> Tensor:
            return self.rhs(z, x_ref, u_ref)

        eye = torch.eye(self.system.nx, dtype=x.dtype, device=x.device)
        div = torch.zeros(x.shape[:-1], dtype=x.dtype, device=x.device)
        fx = None
        for i in range(self.system.nx):
            fx, d = torch.func.jvp(fn, (x,), (eye[i].expand_as(x),))[:2]
            div = div + d[..., i]
        assert fx is not None
        return fx, div

"""Tracking-controller interface: ``u = controller(x_measured, x_ref, u_ref)``.

A tracking controller maps the *measured* state (for the car: the heading-biased measurement, see
:meth:`density_planner.systems.KinematicCar.measure`), the reference state and the reference (feed-forward)
input to the applied input, clipped to the input bounds. Tensors are batch-first and broadcast:
``x_hat (*batch, nx)``, ``x_ref (*batch, nx)``, ``u_ref (*batch, nu)`` -> ``u (*batch, nu)``.

For the exact Liouville density the closed-loop divergence needs directional derivatives of ``u`` w.r.t. the
state. :meth:`TrackingController.forward_with_tangents` returns them for a stack of tangent directions; the
default uses ``torch.func.jvp`` and learned controllers override it with a hand-written forward-mode pass.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Sequence

import torch
from torch import Tensor, nn

__all__ = ["TrackingController"]


class TrackingController(nn.Module):
    """Base class: implement :meth:`raw` (the unclipped control law); clipping and tangents are handled here."""

    def __init__(self, input_min: Sequence[float], input_max: Sequence[float]):
        super().__init__()
        self.register_buffer("input_min", torch.as_tensor(input_min, dtype=torch.get_default_dtype()))
        self.register_buffer("input_max", torch.as_tensor(input_max, dtype=torch.get_default_dtype()))

    @property
    def nu(self) -> int:
        return int(self.input_min.numel())

    @abstractmethod
    def raw(self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor) -> Tensor:
        """Unclipped control law."""

    def raw_with_tangents(
        self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor, dx_hat: Tensor
    ) -> tuple[Tensor, Tensor]:
        """``raw`` and its directional derivatives w.r.t. ``x_hat`` along ``dx_hat (K, *batch, nx)``.

        Returns ``(u (*batch, nu), du (K, *batch, nu))``. Generic forward-mode version (one ``jvp`` per tangent).
        """
        def fn(x: Tensor) -> Tensor:
            return self.raw(x, x_ref, u_ref)

        u = None
        dus = []
        for d in dx_hat.unbind(0):
            u, du = torch.func.jvp(fn, (x_hat,), (d.expand_as(x_hat),))
            dus.append(du)
        if u is None:
            u = fn(x_hat)
        return u, torch.stack(dus, 0) if dus else u.new_zeros((0, *u.shape))

    def _bounds(self, like: Tensor) -> tuple[Tensor, Tensor]:
        return self.input_min.to(like), self.input_max.to(like)

    def forward(self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor) -> Tensor:
        lo, hi = self._bounds(x_hat)
        return torch.clamp(self.raw(x_hat, x_ref, u_ref), lo, hi)

    def forward_with_tangents(
        self, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor, dx_hat: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Clipped input and its directional derivatives (zero in channels where the clip is active)."""
        u, du = self.raw_with_tangents(x_hat, x_ref, u_ref, dx_hat)
        lo, hi = self._bounds(u)
        inside = (u > lo) & (u < hi)
        return torch.clamp(u, lo, hi), du * inside.to(du.dtype)

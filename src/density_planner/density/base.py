"""Density predictors: one interface for exact Liouville propagation and learned predictors.

A predictor maps initial samples ``x0 (*batch, N, nx)`` with initial log-densities ``log_rho0 (*batch, N)`` and
a :class:`~density_planner.control.reference.Reference` to a :class:`DensityTrajectory` on the planning grid:
the closed-loop states of every sample and the log-density along each trajectory,
``log rho(x(t), t) = log rho0(x0) - int_0^t div f_cl`` (paper Eq. (2)).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from ..checks import broadcast_shape, check_tensor
from ..control.reference import Reference

__all__ = ["DensityTrajectory", "DensityPredictor", "sample_weights", "expand_samples", "expand_log_rho0", "WeightMode"]

WeightMode = Literal["density", "mass"]


def expand_samples(x0: Tensor, reference: Reference, nx: int) -> Tensor:
    """Check initial samples ``x0 (*batch, N, nx)`` against ``reference`` and expand them to its batch shape.

    ``x0`` takes the reference's dtype and device; its batch shape must broadcast with the reference's.

    Raises:
        ValueError: ``reference`` is not a :class:`Reference`, ``x0`` has the wrong shape or non-finite values,
            or the batch shapes do not broadcast.
    """
    if not isinstance(reference, Reference):
        raise ValueError(f"reference must be a Reference (see make_reference), got {type(reference).__name__}")
    x0 = check_tensor("x0", x0, last_dims=(None, nx), dtype=reference.x.dtype, device=reference.x.device)
    try:
        batch = broadcast_shape(x0.shape[:-2], reference.batch_shape)
    except ValueError:
        raise ValueError(
            f"batch shape of x0 {tuple(x0.shape[:-2])} (samples are the second-to-last axis) does not broadcast "
            f"with the reference batch shape {tuple(reference.batch_shape)}"
        ) from None
    return x0.expand(*batch, *x0.shape[-2:])


def expand_log_rho0(log_rho0: Tensor, x0: Tensor) -> Tensor:
    """Check initial log-densities against samples ``x0 (*batch, N, nx)`` and expand them to ``(*batch, N)``.

    Raises:
        ValueError: ``log_rho0`` has non-finite values or does not broadcast to one value per sample.
    """
    log_rho0 = check_tensor("log_rho0", log_rho0, dtype=x0.dtype, device=x0.device)
    try:
        return log_rho0.expand(x0.shape[:-1])
    except RuntimeError:
        raise ValueError(
            f"log_rho0 must have shape {tuple(x0.shape[:-1])} (one value per sample), got {tuple(log_rho0.shape)}"
        ) from None


@dataclass
class DensityTrajectory:
    """Predicted sample trajectories and log-densities.

    Attributes:
        t: ``(T,)`` output times [s].
        x: ``(*batch, N, T, nx)`` closed-loop states.
        log_rho: ``(*batch, N, T)`` log-density at ``x`` (natural log, same normalisation as ``log_rho0``).
        log_rho0: ``(*batch, N)`` initial log-density (the proposal-independent density of the initial law).
    """

    t: Tensor
    x: Tensor
    log_rho: Tensor
    log_rho0: Tensor

    @property
    def n_samples(self) -> int:
        return self.x.shape[-3]

    @property
    def positions(self) -> Tensor:
        """``(*batch, N, T, 2)`` positions (the first two state components)."""
        return self.x[..., :2]

    def detach(self) -> DensityTrajectory:
        return DensityTrajectory(self.t, self.x.detach(), self.log_rho.detach(), self.log_rho0.detach())

    def weights(self, mode: WeightMode = "density", log_q0: Tensor | None = None) -> Tensor:
        """Normalised sample weights ``(*batch, N, T)`` (sum 1 over samples per time); see :func:`sample_weights`."""
        return sample_weights(self.log_rho, self.log_rho0, mode=mode, log_q0=log_q0)


def sample_weights(
    log_rho: Tensor, log_rho0: Tensor, *, mode: WeightMode = "density", log_q0: Tensor | None = None
) -> Tensor:
    """Per-time sample weights, normalised over the sample axis (``-2`` of ``log_rho (*batch, N, T)``).

    * ``"density"`` (the paper): ``w_i(t) ∝ rho(x_i(t), t)``, the density *value* at each sample. Computed as a
      softmax over samples, so it never overflows or produces NaN.
    * ``"mass"``: ``w_i ∝ rho0(x0_i) / q0(x0_i)`` constant in time (importance weights of the samples' proposal
      ``q0``, default uniform): the probability mass a sample carries, which the flow conserves. Weighted sums
      are then expectations under the propagated law.
    """
    if mode == "density":
        return torch.softmax(log_rho, dim=-2)
    if mode == "mass":
        lw = log_rho0 if log_q0 is None else log_rho0 - log_q0
        return torch.softmax(lw, dim=-1).unsqueeze(-1).expand_as(log_rho)
    raise ValueError(f"unknown weight mode {mode!r}; valid choices: density, mass")


class DensityPredictor(ABC):
    """Predicts closed-loop sample trajectories and their log-densities along a reference."""

    #: short name used in results and on the command line
    name: str = "predictor"

    @abstractmethod
    def predict(self, x0: Tensor, log_rho0: Tensor, reference: Reference) -> DensityTrajectory:
        """Trajectories on the planning grid of ``reference`` for samples ``x0 (*batch, N, nx)``.

        ``reference`` has batch shape ``batch`` (or broadcastable to it); ``log_rho0 (*batch, N)``.
        Differentiable w.r.t. ``reference.params`` (and ``reference.start``).
        """

    def predict_states(self, x0: Tensor, log_rho0: Tensor, reference: Reference) -> DensityTrajectory:
        """Like :meth:`predict` for callers that need the trajectories and ``log_rho0`` but not the log-densities
        along them (costs weighted by the samples' initial mass, ``weighting = "mass"``): a predictor may leave
        ``log_rho`` out (NaN, so that any use shows) where that saves work. Default: :meth:`predict`."""
        return self.predict(x0, log_rho0, reference)

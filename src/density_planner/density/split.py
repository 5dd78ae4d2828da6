"""Predictions without gradient split over the samples between this process and forked helper processes.

Samples are independent given the reference (each follows its own closed loop and carries its own log-density), so
a prediction of ``N`` samples is the concatenation of the predictions of any split of them. :func:`predict_split`
predicts the first part here and the others in processes forked for the call (each with one torch thread), which
inherit the predictor, the samples and the reference (nothing is pickled on the way out; the parts come back
through a pipe). On a CPU with idle cores this cuts the wall time of a long prediction, without OpenMP threads
(which slow down badly when the other cores are busy): the density planner's exact re-check of its plan uses
:func:`prediction_processes` processes, an execution setting like torch's thread count (1 by default: a library
call forks nothing unless asked; the ``plan`` command sets the usable cores, at most 2, with
:func:`set_prediction_processes`).
Measured on two suite scenes (2-core machine): 0.90 -> 0.58-0.66 s and 2.9-3.3 -> 1.9-2.3 s. The parts are the
unsplit prediction's values (equal bit for bit in that measurement; at most float rounding of matrix products of
another batch size).
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import Tensor

from ..control.reference import Reference
from ..parallel import ForkedCall, ForkedCallError
from .base import DensityPredictor, DensityTrajectory

__all__ = ["predict_split", "split_possible", "prediction_processes", "set_prediction_processes",
           "using_prediction_processes"]

_PROCESSES = 1


def set_prediction_processes(processes: int) -> None:
    """Processes (this one included) that predictions without gradient may use where a caller splits them
    (:func:`prediction_processes`); 1 = none forked."""
    global _PROCESSES
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise ValueError(f"prediction processes must be an integer >= 1, got {processes!r}")
    _PROCESSES = processes


def prediction_processes() -> int:
    """The number set by :func:`set_prediction_processes` (default 1)."""
    return _PROCESSES


@contextmanager
def using_prediction_processes(processes: int | None) -> Iterator[None]:
    """:func:`set_prediction_processes` for the duration of a ``with`` block, then the number before; ``None``: as
    set."""
    before = _PROCESSES
    if processes is not None:
        set_prediction_processes(processes)
    try:
        yield
    finally:
        set_prediction_processes(before)


def split_possible(processes: int, *tensors: Tensor) -> bool:
    """Whether :func:`predict_split` can use ``processes > 1`` processes here: ``fork`` exists, gradients are off
    and every tensor is on the CPU (forking a process that drives a GPU is not safe)."""
    return (processes > 1 and "fork" in mp.get_all_start_methods() and not torch.is_grad_enabled()
            and all(t.device.type == "cpu" for t in tensors))


def predict_split(predictor: DensityPredictor, x0: Tensor, log_rho0: Tensor, reference: Reference, *,
                  processes: int = 2, states_only: bool = False) -> DensityTrajectory:
    """``predictor.predict(x0 (*batch, N, nx), log_rho0, reference)`` with the ``N`` samples cut into
    ``processes`` contiguous parts, all but the first predicted in forked processes (module docstring). Runs
    ``predictor.predict`` unsplit where :func:`split_possible` says no or there are fewer samples than processes.
    ``states_only``: :meth:`~density_planner.density.base.DensityPredictor.predict_states` instead (the
    log-densities along the trajectories may be NaN).
    Without gradient every part is predicted in inference mode (:func:`_predict_part`); the result holds ordinary
    tensors.

    Raises:
        RuntimeError: a helper process failed (its error) or died (its exit code).
    """
    n = x0.shape[-2]
    if processes < 1:
        raise ValueError(f"processes must be >= 1, got {processes}")
    if not split_possible(processes, x0, log_rho0, reference.x) or n < processes:
        if torch.is_grad_enabled():
            return (predictor.predict_states if states_only else predictor.predict)(x0, log_rho0, reference)
        traj = _predict_part(predictor, x0, log_rho0, reference, states_only)
        return DensityTrajectory(t=traj.t.clone(), x=traj.x.clone(), log_rho=traj.log_rho.clone(),
                                 log_rho0=traj.log_rho0.clone())  # ordinary tensors (below)
    log_rho0 = log_rho0.expand(x0.shape[:-1])
    cuts = [round(i * n / processes) for i in range(processes + 1)]
    helpers: list[ForkedCall] = []
    try:
        for a, b in zip(cuts[1:-1], cuts[2:]):
            call = ForkedCall.start(_predict_part, predictor, x0[..., a:b, :], log_rho0[..., a:b], reference,
                                    states_only)
            assert call is not None  # split_possible: fork exists
            helpers.append(call)
        parts = [_predict_part(predictor, x0[..., : cuts[1], :], log_rho0[..., : cuts[1]], reference, states_only)]
        for call in helpers:
            try:
                parts.append(call.result())
            except ForkedCallError as exc:
                raise RuntimeError(f"a process predicting part of the samples failed ({exc.cause}); set the number "
                                   "of processes to 1") from None
    finally:
        for call in helpers:
            call.cancel()
    return DensityTrajectory(t=parts[0].t.clone(), x=torch.cat([p.x for p in parts], dim=-3),
                             log_rho=torch.cat([p.log_rho for p in parts], dim=-2),
                             log_rho0=torch.cat([p.log_rho0 for p in parts], dim=-1))


def _predict_part(predictor: DensityPredictor, x0: Tensor, log_rho0: Tensor, reference: Reference,
                  states_only: bool = False) -> DensityTrajectory:
    """What :func:`predict_split` computes here and in each helper (a :class:`~density_planner.parallel.ForkedCall`):
    a part of the samples, with contiguous tensors. In inference mode: without autograd's bookkeeping each of the
    prediction's many small operations is cheaper (exact Liouville: ~10 % of its time). Its tensors are inference
    tensors; the caller returns ordinary ones (a concatenation, a clone, or the helper's pickled copy), which may be
    edited in place or used in a later computation with gradient."""
    with torch.inference_mode():
        traj = (predictor.predict_states if states_only else predictor.predict)(x0, log_rho0, reference)
    return DensityTrajectory(t=traj.t, x=traj.x.contiguous(), log_rho=traj.log_rho.contiguous(),
                             log_rho0=traj.log_rho0.contiguous())

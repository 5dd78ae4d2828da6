"""Predictions split over forked processes (density/split.py): the same values as one process, the fallbacks,
a helper's error as one line."""

from __future__ import annotations

import multiprocessing as mp

import pytest
import torch

from density_planner.control.analytic import CarTrackingController
from density_planner.control.reference import make_reference
from density_planner.density.liouville import ExactLiouville
from density_planner.density.split import (
    predict_split,
    prediction_processes,
    set_prediction_processes,
    split_possible,
)
from density_planner.systems.car import KinematicCar


def _new_children(before: set) -> list:
    return [p for p in mp.active_children() if p not in before]


pytestmark = pytest.mark.skipif("fork" not in mp.get_all_start_methods(), reason="needs fork")


def _setup(n=41):
    g = torch.Generator().manual_seed(3)
    car = KinematicCar()
    predictor = ExactLiouville(car, CarTrackingController())
    start = torch.tensor([0.0, -20.0, 1.5, 4.0, 0.0])
    reference = make_reference(car, start, (0.3 * torch.randn(2, 10, generator=g)).unsqueeze(0))
    hw = torch.tensor(car.config.initial_error_max)
    x0 = (start + (2 * torch.rand(n, 5, generator=g) - 1) * hw).unsqueeze(0)
    return predictor, reference, x0, torch.randn(1, n, generator=g)


@pytest.mark.parametrize("processes", [2, 3])
def test_split_prediction_equals_one_process(processes):
    before = set(mp.active_children())  # pools of earlier tests may live on
    predictor, reference, x0, log_rho0 = _setup()
    with torch.no_grad():
        whole = predictor.predict(x0, log_rho0, reference)
        split = predict_split(predictor, x0, log_rho0, reference, processes=processes)
    assert split.x.shape == whole.x.shape == (1, 41, 101, 5) and split.log_rho.shape == whole.log_rho.shape
    # per-sample closed loops: only float rounding of another batch size may differ
    torch.testing.assert_close(split.x, whole.x, atol=1e-5, rtol=0)
    torch.testing.assert_close(split.log_rho, whole.log_rho, atol=1e-4, rtol=0)
    torch.testing.assert_close(split.log_rho0, whole.log_rho0.expand(1, 41), atol=0, rtol=0)
    torch.testing.assert_close(split.t, whole.t)
    assert _new_children(before) == []


@pytest.mark.parametrize("processes", [1, 2])
def test_split_states_only_equals_predict_states(processes):
    """``states_only``: every part by ``predict_states`` (exact Liouville: no divergence, NaN log-densities), the
    same trajectories as the full prediction."""
    before = set(mp.active_children())
    predictor, reference, x0, log_rho0 = _setup()
    with torch.no_grad():
        whole = predictor.predict(x0, log_rho0, reference)
        split = predict_split(predictor, x0, log_rho0, reference, processes=processes, states_only=True)
    assert split.x.shape == whole.x.shape and split.log_rho.shape == whole.log_rho.shape
    torch.testing.assert_close(split.x, whole.x, atol=1e-5, rtol=0)
    assert torch.isnan(split.log_rho[..., 1:]).all()  # left out, so that any use shows
    torch.testing.assert_close(split.log_rho0, whole.log_rho0.expand(1, 41), atol=0, rtol=0)
    assert _new_children(before) == []


def test_split_falls_back_to_one_process():
    before = set(mp.active_children())
    predictor, reference, x0, log_rho0 = _setup(n=3)
    assert not split_possible(2, x0)  # gradients on
    with torch.no_grad():
        assert split_possible(2, x0) and not split_possible(1, x0)
        few = predict_split(predictor, x0[:, :1], log_rho0[:, :1], reference, processes=2)  # 1 sample, 2 processes
    assert few.x.shape[1] == 1
    x0g = x0.clone().requires_grad_(True)
    out = predict_split(predictor, x0g, log_rho0, reference, processes=2)  # with gradient: here, differentiable
    out.x.sum().backward()
    assert x0g.grad is not None and _new_children(before) == []
    with pytest.raises(ValueError, match="processes must be >= 1"):
        predict_split(predictor, x0, log_rho0, reference, processes=0)


class _FailsOnMarker(ExactLiouville):
    """Raises on a sample whose speed is exactly 7 (placed in the helper's part)."""

    def predict(self, x0, log_rho0, reference):
        if bool((x0[..., 3] == 7.0).any()):
            raise ArithmeticError("marker seen")
        return super().predict(x0, log_rho0, reference)


def test_helper_error_is_raised_here():
    before = set(mp.active_children())
    predictor, reference, x0, log_rho0 = _setup(n=6)
    failing = _FailsOnMarker(predictor.system, predictor.controller)
    x0 = x0.clone()
    x0[0, -1, 3] = 7.0
    with torch.no_grad(), pytest.raises(RuntimeError, match=r"failed \(ArithmeticError: marker seen\)"):
        predict_split(failing, x0, log_rho0, reference, processes=2)
    assert _new_children(before) == []


def test_prediction_processes_setting():
    assert prediction_processes() == 1  # the library forks nothing unless asked
    set_prediction_processes(2)
    try:
        assert prediction_processes() == 2
    finally:
        set_prediction_processes(1)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="integer >= 1"):
            set_prediction_processes(bad)

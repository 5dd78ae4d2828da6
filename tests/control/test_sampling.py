"""Seeded sampling of feasible references, initial errors and tracking states."""

from __future__ import annotations

import math

import pytest
import torch

from density_planner.control.sampling import (
    box_violation_fraction,
    sample_feasible_references,
    sample_initial_errors,
    sample_tracking_states,
)
from density_planner.systems.car import BIAS, CarConfig, KinematicCar


def test_feasible_references_stay_in_the_box_and_are_seeded():
    car = KinematicCar()
    cfg = car.config
    ref = sample_feasible_references(car, 64, torch.Generator().manual_seed(0), dtype=torch.float64)
    assert ref.x.shape == (64, 1001, 5) and ref.u.shape == (64, 1000, 2) and ref.params.shape == (64, 2, 10)
    assert bool((box_violation_fraction(ref.x, cfg.state_min, cfg.state_max) <= 0.01).all())
    lo, hi = torch.tensor(cfg.reference_start_min, dtype=torch.float64), torch.tensor(cfg.reference_start_max,
                                                                                     dtype=torch.float64)
    assert bool(((ref.start >= lo) & (ref.start <= hi)).all())
    assert float(ref.params.abs().max()) <= 3.0
    # about 13 % of clamp(2 N(0,1), -3, 3) sit exactly on a bound (P(|N| > 1.5)); accept a wide band
    on_bound = float((ref.params.abs() == 3.0).double().mean())
    assert 0.03 < on_bound < 0.25
    again = sample_feasible_references(car, 64, torch.Generator().manual_seed(0), dtype=torch.float64)
    torch.testing.assert_close(ref.params, again.params, rtol=0, atol=0)
    other = sample_feasible_references(car, 64, torch.Generator().manual_seed(1), dtype=torch.float64)
    assert not torch.equal(ref.params, other.params)


def test_feasible_references_float32_matches_float64_draws():
    car = KinematicCar()
    r32 = sample_feasible_references(car, 8, torch.Generator().manual_seed(5))
    r64 = sample_feasible_references(car, 8, torch.Generator().manual_seed(5), dtype=torch.float64)
    torch.testing.assert_close(r32.params.double(), r64.params, rtol=0, atol=1e-6)


def test_feasible_references_give_up_with_a_clear_error():
    car = KinematicCar()
    with pytest.raises(ValueError, match="could only sample"):
        # a speed box that no reference starting at v >= 1 m/s can satisfy
        sample_feasible_references(car, 4, torch.Generator().manual_seed(0), state_low=(-50, -50, -10, 0, -1),
                                   state_high=(50, 50, 10, 0.5, 1), max_attempts=3)
    with pytest.raises(ValueError, match="n must be a positive integer"):
        sample_feasible_references(car, 0, torch.Generator())


def test_initial_errors_in_box_with_and_without_bias():
    box = CarConfig().initial_error_max
    e = sample_initial_errors(5000, torch.Generator().manual_seed(0), dtype=torch.float64)
    e0 = sample_initial_errors(5000, torch.Generator().manual_seed(0), with_bias=False, dtype=torch.float64)
    half = torch.tensor(box, dtype=torch.float64)
    assert bool((e.abs() <= half).all())
    # uniform: the largest |component| of 5000 draws is within 0.5 % of the half-width with overwhelming odds
    assert bool((e.abs().max(0).values > 0.995 * half).all())
    assert float(e0[:, BIAS].abs().max()) == 0.0
    torch.testing.assert_close(e0[:, :BIAS], e[:, :BIAS], rtol=0, atol=0)
    assert box[BIAS] == pytest.approx(math.pi / 16)


def test_tracking_states_boxes():
    cfg = CarConfig()
    s = sample_tracking_states(20_000, torch.Generator().manual_seed(0), dtype=torch.float64)
    lo, hi = torch.tensor(cfg.state_min, dtype=torch.float64), torch.tensor(cfg.state_max, dtype=torch.float64)
    assert bool(((s.x_ref[:, :4] >= lo[:4]) & (s.x_ref[:, :4] <= hi[:4])).all())
    assert float(s.x_ref[:, BIAS].abs().max()) == 0.0
    e = s.x - s.x_ref
    assert bool((e.abs() <= torch.tensor(cfg.error_max, dtype=torch.float64)).all())
    assert float(e[:, BIAS].abs().max()) > 0.99 * math.pi / 8  # the bias covers +-pi/8
    assert bool((s.u_ref.abs() <= 3.0).all())
    torch.testing.assert_close(s.x_hat, KinematicCar().measure(s.x), rtol=0, atol=0)
    assert len(s) == 20_000

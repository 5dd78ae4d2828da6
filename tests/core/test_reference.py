"""Reference trajectories: loop-free rollout equals the Euler loop, gradients, grids and stage values."""

from __future__ import annotations

import pytest
import torch

from density_planner.control.reference import PiecewiseConstantInputs, make_reference
from density_planner.systems.base import System
from density_planner.systems.car import KinematicCar


def test_cumsum_rollout_equals_plain_euler_loop():
    car = KinematicCar()
    g = torch.Generator().manual_seed(0)
    params = (2 * torch.randn(4, 2, 10, generator=g, dtype=torch.float64)).clamp(-3, 3)
    start = torch.tensor([1.0, -2.0, 0.7, 4.0, 0.1], dtype=torch.float64).expand(4, 5)
    ref = make_reference(car, start, params)
    loop = System.rollout(car, start, ref.u, ref.dt)  # the generic step-by-step Euler loop
    # identical arithmetic up to summation order: float64 round-off over 1000 steps
    torch.testing.assert_close(ref.x, loop, atol=1e-10, rtol=0)


def test_shapes_and_grids():
    car = KinematicCar()
    params = torch.zeros(3, 2, 10)
    ref = make_reference(car, torch.tensor([0.0, 0.0, 0.0, 2.0, 0.0]), params)
    assert ref.x.shape == (3, 1001, 5) and ref.u.shape == (3, 1000, 2)
    assert ref.x_plan.shape == (3, 101, 5) and ref.u_plan.shape == (3, 100, 2)
    assert torch.allclose(ref.t_plan[[0, 1, -1]], torch.tensor([0.0, 0.1, 10.0]))
    # constant speed 2 m/s straight ahead: 20 m after 10 s
    assert torch.allclose(ref.x_plan[:, -1, 0], torch.full((3,), 20.0), atol=1e-3)


def test_inputs_are_piecewise_constant_segments():
    par = PiecewiseConstantInputs()
    params = torch.arange(20.0).reshape(1, 2, 10)
    u = par.inputs(params)
    assert u.shape == (1, 1000, 2)
    assert torch.equal(u[0, 0], torch.tensor([0.0, 10.0])) and torch.equal(u[0, 99], torch.tensor([0.0, 10.0]))
    assert torch.equal(u[0, 100], torch.tensor([1.0, 11.0])) and torch.equal(u[0, 999], torch.tensor([9.0, 19.0]))


def test_gradcheck_wrt_params_and_start():
    car = KinematicCar()
    par = PiecewiseConstantInputs(n_segments=3, segment_duration=0.5, dt=0.05)
    params = (0.5 * torch.randn(1, 2, 3, dtype=torch.float64)).requires_grad_(True)
    start = torch.tensor([0.0, 0.0, 0.3, 2.0, 0.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p, s: make_reference(car, s, p, par).x, (params, start))


def test_stage_values_interpolate_states_and_take_left_limit_of_inputs():
    car = KinematicCar()
    params = torch.arange(20.0, dtype=torch.float64).reshape(2, 10) / 10
    ref = make_reference(car, torch.tensor([0.0, 0.0, 0.0, 1.0, 0.0], dtype=torch.float64), params)
    x_st, u_st = ref.stage_values(0.1, 100, (0.0, 0.5, 1.0))
    assert x_st.shape == (100, 3, 5) and u_st.shape == (100, 3, 2)
    torch.testing.assert_close(x_st[:, 0], ref.x[0:1000:10])
    torch.testing.assert_close(x_st[:, 1], ref.x[5:1000:10])
    torch.testing.assert_close(x_st[:, 2], ref.x[10:1001:10])
    # step 9 ends on the switching instant t = 1 s: its last stage still sees segment 0
    torch.testing.assert_close(u_st[9, 2], ref.u[0])
    torch.testing.assert_close(u_st[10, 0], ref.u[100])
    # half-steps between fine points are linear interpolations
    x_half, _ = ref.stage_values(0.005, 4, (0.0,))
    torch.testing.assert_close(x_half[1, 0], 0.5 * (ref.x[0] + ref.x[1]))


@pytest.mark.parametrize(
    "params,start,match",
    [
        (torch.zeros(2, 9), torch.zeros(5), "params"),
        (torch.zeros(3, 10), torch.zeros(5), "params"),
        (torch.full((2, 10), float("nan")), torch.zeros(5), "params"),
        (torch.zeros(2, 10), torch.zeros(4), "start"),
        (torch.zeros(2, 10), torch.tensor([0, 0, float("inf"), 0, 0.0]), "start"),
    ],
)
def test_bad_reference_input_names_the_argument(params, start, match):
    with pytest.raises(ValueError, match=match):
        make_reference(KinematicCar(), start, params)


@pytest.mark.parametrize(
    "kwargs,match",
    [({"dt": 0.0}, "dt"), ({"dt": -0.01}, "dt"), ({"segment_duration": 0.015}, "segment_duration"),
     ({"n_segments": 0}, "n_segments")],
)
def test_bad_parameterization(kwargs, match):
    with pytest.raises(ValueError, match=match):
        PiecewiseConstantInputs(**kwargs)

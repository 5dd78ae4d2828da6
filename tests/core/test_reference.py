"""Reference trajectories: loop-free rollout equals the Euler loop, gradients, grids and stage values."""

from __future__ import annotations

import pytest
import torch

from density_planner.control.reference import PiecewiseConstantInputs, make_reference, plan_grid_reference
from density_planner.systems.base import System, hold_speeds
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


def test_hold_speeds_is_the_stepwise_standstill():
    """Lindley's closed form equals ``w_{k+1} = max(0, w_k + dv_k)`` step by step, also from a negative start
    speed (kept as the first value) and for sequences that stop, restart and stop again."""
    g = torch.Generator().manual_seed(3)
    dv = 0.7 * torch.randn(6, 300, generator=g, dtype=torch.float64) - 0.05
    v0 = torch.tensor([3.0, 0.0, -0.4, 10.0, 0.2, 1.0], dtype=torch.float64)
    free = torch.cat([v0[:, None], v0[:, None] + dv.cumsum(-1)], dim=-1)
    w = [v0]
    for k in range(dv.shape[1]):
        w.append((w[-1] + dv[:, k]).clamp(min=0.0))
    loop = torch.stack(w, dim=-1)
    held = hold_speeds(free)
    torch.testing.assert_close(held, loop, atol=1e-12, rtol=0)
    assert bool((held[:, 1:] >= 0).all()) and float(held[2, 0]) == -0.4
    # stops, then restarts: both happen in this draw
    stopped = (held[:, 1:-1] == 0) & (held[:, 2:] > 0)
    assert bool(stopped.any())
    ok = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    assert hold_speeds(ok) is ok  # nothing to hold


# a reference braking from 4 m/s: it stops in segment 1 (t ~ 1.33 s), stands, restarts in segment 3, brakes to a
# stop again in segment 5 and stays (segments 6-9 brake further: they must not reverse it)
_STOPPING = [[0.1, 0.0, -0.2, 0.0, 0.3, 0.0, 0.0, 0.1, 0.0, 0.0],
             [-2.0, -2.3, -1.0, 1.5, 0.0, -2.0, -1.0, -0.5, -3.0, -1.0]]


def test_a_stopping_reference_stands_instead_of_reversing():
    car = KinematicCar()
    start = torch.tensor([1.0, -2.0, 0.7, 4.0, 0.1], dtype=torch.float64)
    params = torch.tensor(_STOPPING, dtype=torch.float64)[None]
    ref = make_reference(car, start, params)
    v = ref.x[0, :, 3]
    assert float(v.min()) == 0.0 and float(v[-1]) == 0.0
    # the plant (generic Euler loop with the hold after every step) on the commanded inputs
    plant = System.rollout(car, start, PiecewiseConstantInputs().inputs(params), ref.dt)
    torch.testing.assert_close(ref.x, plant, atol=1e-10, rtol=0)
    # the inputs it applied drive the model itself (no hold needed) along the same states
    model = [start.expand(1, 5)]
    for k in range(ref.n_steps):
        model.append(model[-1] + ref.dt * car.f(model[-1], ref.u[:, k]))
    torch.testing.assert_close(ref.x, torch.stack(model, dim=-2), atol=1e-10, rtol=0)
    # per segment the mean applied input: the turn rates as commanded, the braking that stopped the car, 0 at rest
    seg = ref.segment_inputs[0]
    assert torch.equal(seg[0], params[0, 0]) and torch.equal(seg[1, 6:], torch.zeros(4, dtype=torch.float64))
    v_seg = ref.x[0, ::100, 3]
    torch.testing.assert_close(seg[1], (v_seg[1:] - v_seg[:-1]) / 1.0, atol=1e-9, rtol=0)
    moving = make_reference(car, start, params.abs())  # never stops: the commanded inputs themselves
    assert torch.equal(moving.segment_inputs, moving.params)
    standing = (v[:-1] == 0) & (v[1:] == 0)
    assert int(standing.sum()) > 300 and bool((ref.u[0, standing, 1] == 0).all())  # no braking feed-forward at rest
    assert bool((ref.u[0, ~standing, 1] >= params[0, 1].min()).all())
    # the planning grid gives the same states and applied inputs
    x_plan, u_plan = plan_grid_reference(car, start, params)
    torch.testing.assert_close(x_plan, ref.x_plan, atol=1e-10, rtol=0)
    torch.testing.assert_close(u_plan, ref.u_plan, atol=1e-9, rtol=0)


def test_gradient_through_the_hold_matches_finite_differences():
    car = KinematicCar()
    par = PiecewiseConstantInputs(n_segments=4, segment_duration=0.5, dt=0.05)
    params = torch.tensor([[[0.2, -0.1, 0.0, 0.3], [-3.0, -1.3, 2.0, 0.5]]], dtype=torch.float64, requires_grad=True)
    start = torch.tensor([0.0, 0.0, 0.3, 1.7, 0.0], dtype=torch.float64, requires_grad=True)
    assert float(make_reference(car, start.detach(), params.detach(), par).x[0, :, 3].min()) == 0.0  # hold acts
    assert torch.autograd.gradcheck(lambda p, s: make_reference(car, s, p, par).x, (params, start))
    # the planning grid's piecewise form of the hold (segment-level running minimum)
    assert torch.autograd.gradcheck(lambda p, s: plan_grid_reference(car, s, p, par)[0], (params, start))


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


def test_switch_table_finds_every_input_switch():
    """``next_switch`` gives the first instant after ``t`` where the applied input changes: the segment boundaries
    of a moving reference, the stop inside a segment of a braking one (its input drops to 0 on the fine grid), and
    the horizon after the last."""
    car = KinematicCar()
    start = torch.tensor([1.0, -2.0, 0.7, 4.0, 0.1], dtype=torch.float64)
    params = torch.tensor(_STOPPING, dtype=torch.float64)[None]
    moving = make_reference(car, start, params.abs())
    stopping = make_reference(car, start, params)
    flat = type(moving)(torch.cat([moving.params, stopping.params]), torch.cat([moving.x, stopping.x]),
                        torch.cat([moving.u, stopping.u]), moving.parameterization)
    table = flat.switch_table()
    changes = (flat.u[:, 1:] != flat.u[:, :-1]).any(-1)
    rows = torch.tensor([0, 0, 0, 0, 0], dtype=torch.long)
    t = torch.tensor([0.0, 0.5, 0.999, 1.0, 9.5], dtype=torch.float64)
    # the moving reference switches at the segment boundaries
    got = flat.next_switch(table, rows, t)
    torch.testing.assert_close(got, torch.tensor([1.0, 1.0, 1.0, 2.0, 10.0], dtype=torch.float64))
    # every fine index: the next switch strictly after it, as a loop over the switches finds it
    for r in range(2):
        instants = [(j + 1) * flat.dt for j in torch.nonzero(changes[r]).squeeze(-1).tolist()]
        for t0 in torch.linspace(0.0, 9.995, 400, dtype=torch.float64).tolist():
            expected = next((s for s in instants if s > t0 + 1e-9), 10.0)
            assert float(flat.next_switch(table, torch.tensor([r]), torch.tensor([t0], dtype=torch.float64))[0]) \
                == pytest.approx(expected, abs=1e-9)
    # the braking reference stops (and its input drops) off the segment boundaries
    assert any(abs(s / 1.0 - round(s)) > 1e-6 for s in
               [(j + 1) * flat.dt for j in torch.nonzero(changes[1]).squeeze(-1).tolist()])


def test_reference_start_is_the_given_start_without_the_roll_out_graph():
    """``Reference.start`` equals the first state; it carries the start's own gradient only (none for a start that
    needs none), through ``select`` and ``detach`` too; the learned density predictor's gradient in the parameters is
    the same as when it reads the first state off the roll-out (``origin`` unset)."""
    from density_planner.control.reference import Reference
    from density_planner.control.registry import load_controller
    from density_planner.density.registry import load_predictor

    car = KinematicCar()
    params = (0.3 * torch.randn(2, 2, 10, generator=torch.Generator().manual_seed(5))).requires_grad_(True)
    start = torch.tensor([0.5, -1.0, 0.2, 4.0, 0.0])
    ref = make_reference(car, start, params)
    assert torch.equal(ref.start, ref.x[..., 0, :]) and ref.start.shape == (2, 5) and not ref.start.requires_grad
    assert torch.equal(ref.select(1).start, ref.x[1, 0]) and ref.detach().origin is not None
    s = start.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(make_reference(car, s, params).start.sum(), s)
    torch.testing.assert_close(g, torch.full((5,), 2.0))  # two references from the one start
    pred = load_predictor(None, car, load_controller(None))
    x0 = start + 0.1 * torch.randn(2, 30, 5, generator=torch.Generator().manual_seed(6))
    lr0 = torch.zeros(2, 30)
    grads = []
    for origin in (True, False):
        r = make_reference(car, start, params)  # a fresh graph each
        out = pred.predict(x0, lr0, r if origin else Reference(r.params, r.x, r.u, r.parameterization))
        grads.append(torch.autograd.grad(out.x.square().sum() + out.log_rho.sum(), params)[0])
    assert float(grads[0].abs().max()) > 0
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-5, atol=1e-6)

"""The kinematic single-track model (CommonRoad KS): dynamics against closed forms and finite differences, the
registry, its tracking controller, and the exact Liouville density of its closed loop."""

from __future__ import annotations

import math

import pytest
import torch

from density_planner.control.ks import KSTrackingController
from density_planner.control.reference import PiecewiseConstantInputs, make_reference
from density_planner.control.registry import load_controller, model_set_for_scene
from density_planner.density.closed_loop import ClosedLoop
from density_planner.density.liouville import LiouvilleConfig, propagate_density, simulate_closed_loop
from density_planner.systems.ks import KS_VEHICLES, KinematicSingleTrack, KSConfig
from density_planner.systems.registry import make_system, system_names


def _setup(n=32, seed=0, dtype=torch.float64, speed=10.0, segments=10):
    g = torch.Generator().manual_seed(seed)
    ks = KinematicSingleTrack()
    controller = KSTrackingController(config=ks.config).to(dtype)
    params = torch.stack([0.1 * torch.randn(segments, generator=g, dtype=dtype),
                          0.5 * torch.randn(segments, generator=g, dtype=dtype)]).clamp(-0.3, 3.0)
    start = torch.tensor([0.0, 0.0, 0.0, speed, 0.3], dtype=dtype)
    reference = make_reference(ks, start, params, PiecewiseConstantInputs(n_segments=segments))
    hw = torch.tensor(ks.initial_error_max, dtype=dtype)
    x0 = start + (2 * torch.rand(n, 5, generator=g, dtype=dtype) - 1) * hw
    return ks, controller, reference, x0


def test_registered_with_model_set_and_controller():
    assert "ks" in system_names()
    ks = make_system("ks")
    assert isinstance(ks, KinematicSingleTrack) and ks.nx == 5 and ks.nu == 2
    mset = model_set_for_scene("commonroad", system="ks")
    assert mset.name == "ks" and mset.system == "ks"
    assert model_set_for_scene("random", system="ks").name == "ks"
    assert isinstance(load_controller(None, models=mset), KSTrackingController)
    with pytest.raises(ValueError, match="model set 'road' is for the system 'car'"):
        model_set_for_scene("commonroad", "road", system="ks")


def test_vehicle_parameters_match_commonroad_vehicle_models():
    vm = pytest.importorskip("vehiclemodels.parameters_vehicle2")
    p = vm.parameters_vehicle2()
    v = KS_VEHICLES["BMW_320i"]
    assert (v.length, v.width, v.a, v.b) == pytest.approx((p.l, p.w, p.a, p.b), abs=1e-12)
    assert (v.steering_min, v.steering_max, v.steering_rate_min, v.steering_rate_max) == pytest.approx(
        (p.steering.min, p.steering.max, p.steering.v_min, p.steering.v_max), abs=1e-12)
    assert (v.v_min, v.v_max, v.a_max, v.v_switch) == pytest.approx(
        (p.longitudinal.v_min, p.longitudinal.v_max, p.longitudinal.a_max, p.longitudinal.v_switch), abs=1e-12)
    ks = KinematicSingleTrack()
    assert ks.footprint.length == p.l and ks.footprint.width == p.w
    assert ks.wheelbase == pytest.approx(p.a + p.b)


def test_dynamics_match_commonroad_ks_inside_the_limits():
    """``f`` equals CommonRoad's ``vehicle_dynamics_ks`` where its input constraints are inactive."""
    ks_mod = pytest.importorskip("vehiclemodels.vehicle_dynamics_ks")
    from vehiclemodels.parameters_vehicle2 import parameters_vehicle2

    p = parameters_vehicle2()
    ks = KinematicSingleTrack()
    g = torch.Generator().manual_seed(1)
    for _ in range(20):
        x = torch.tensor([5.0, -3.0, 0.0, 0.0, 0.0], dtype=torch.float64)
        x[2] = 0.8 * (2 * torch.rand(1, generator=g, dtype=torch.float64) - 1)
        x[3] = 6.0 * torch.rand(1, generator=g, dtype=torch.float64)  # below v_switch: no acceleration cap
        x[4] = 3.0 * (2 * torch.rand(1, generator=g, dtype=torch.float64) - 1)
        u = torch.tensor([0.3, 2.0], dtype=torch.float64) * (2 * torch.rand(2, generator=g, dtype=torch.float64) - 1)
        expected = torch.tensor(ks_mod.vehicle_dynamics_ks(x.tolist(), u.tolist(), p), dtype=torch.float64)
        torch.testing.assert_close(ks.f(x, u), expected, atol=1e-12, rtol=0)


def test_constant_steering_drives_a_circle_of_radius_wheelbase_over_tan_delta():
    ks = KinematicSingleTrack()
    delta, v, dt, steps = 0.2, 8.0, 1e-3, 4000
    x0 = torch.tensor([0.0, 0.0, delta, v, 0.0], dtype=torch.float64)
    u = torch.zeros(steps, 2, dtype=torch.float64)
    xs = ks.rollout(x0, u, dt)
    radius = ks.wheelbase / math.tan(delta)
    # the centre of the circle is at (0, R) for a start at the origin heading along +x, turning left
    dist = torch.linalg.vector_norm(xs[:, :2] - torch.tensor([0.0, radius], dtype=torch.float64), dim=-1)
    # explicit Euler spirals outwards by O(dt): R (1 + (v dt / R)^2)^(k/2) - R, here ~ 1e-3 m
    assert float((dist - radius).abs().max()) < 5e-3
    torch.testing.assert_close(xs[-1, 4], torch.tensor(v * math.tan(delta) / ks.wheelbase * steps * dt,
                                                       dtype=torch.float64), atol=1e-9, rtol=0)


def test_rollout_equals_stepwise_euler_and_f_matches_finite_differences():
    ks = KinematicSingleTrack()
    g = torch.Generator().manual_seed(2)
    x0 = torch.tensor([[1.0, 2.0, 0.1, 12.0, -0.4], [0.0, 0.0, -0.3, 3.0, 2.0]], dtype=torch.float64)
    u = 0.3 * torch.randn(2, 50, 2, generator=g, dtype=torch.float64)
    fast = ks.rollout(x0, u, 0.01)
    slow = super(KinematicSingleTrack, ks).rollout(x0, u, 0.01)
    torch.testing.assert_close(fast, slow, atol=1e-12, rtol=0)
    # braking to a stop: the hold at rest (standstill) in both, no reversing
    brake = u.clone()
    brake[..., 1] = -3.0
    fast = ks.rollout(x0, brake, 0.1)
    torch.testing.assert_close(fast, super(KinematicSingleTrack, ks).rollout(x0, brake, 0.1), atol=1e-12, rtol=0)
    assert float(fast[..., 3].min()) == 0.0 and bool((fast[:, -10:, :2] == fast[:, -1:, :2]).all())
    # f is the derivative of the flow: (x(h) - x(-h)) / 2h with an accurate integrator
    x, uu = x0[0], u[0, 0]
    jac = torch.autograd.functional.jacobian(lambda z: ks.f(z, uu), x)
    h = 1e-6
    fd = torch.stack([(ks.f(x + h * e, uu) - ks.f(x - h * e, uu)) / (2 * h) for e in torch.eye(5,
                                                                                            dtype=torch.float64)], 1)
    torch.testing.assert_close(jac, fd, atol=1e-7, rtol=0)
    assert float(torch.trace(jac)) == pytest.approx(0.0, abs=1e-12)  # drift divergence 0, B constant


def test_state_from_pose_round_trip():
    ks = KinematicSingleTrack()
    for heading in (-3.0, 0.0, 1.2, 7.5, -9.0):
        state = ks.state_from_pose(3.0, -4.0, heading, 12.0)
        x = torch.tensor(state, dtype=torch.float64)
        assert tuple(ks.positions(x).tolist()) == (3.0, -4.0)
        assert float(ks.speeds(x)) == 12.0 and state[2] == 0.0
        assert math.cos(float(ks.headings(x))) == pytest.approx(math.cos(heading), abs=1e-12)
        assert math.sin(float(ks.headings(x))) == pytest.approx(math.sin(heading), abs=1e-12)
        assert -math.pi <= float(ks.headings(x)) < math.pi
    lo, hi = ks.planning_bounds()
    assert lo[0] == -math.inf and hi[3] == pytest.approx(39.9) and hi[2] == pytest.approx(0.9 * 1.066)


def test_config_validation():
    with pytest.raises(ValueError, match="vehicle must be one of"):
        KSConfig(vehicle="TRABANT")
    with pytest.raises(ValueError, match="actuator box"):
        KSConfig(actuator_max=(0.2, 4.5))


def test_controller_returns_reference_input_on_the_reference():
    ks, controller, reference, _ = _setup()
    x_ref, u_ref = reference.x[:-1:50], reference.u[::50]
    u = controller(x_ref, x_ref, u_ref)
    torch.testing.assert_close(u, u_ref, atol=1e-12, rtol=0)


def test_controller_tracks_from_initial_errors():
    ks, controller, reference, x0 = _setup(n=64, seed=4)
    t, x = simulate_closed_loop(ks, controller, x0, reference, config=LiouvilleConfig("rk4", 0.02))
    err = torch.linalg.vector_norm(x[..., :2] - reference.x[::10][None, :, :2], dim=-1)
    assert float(err[:, 0].median()) > 0.3
    # after 10 s the median position error has shrunk by more than a factor 5 and none exceeds 0.5 m (the
    # reference turns at up to 14 m/s^2 lateral acceleration; the steering lags it, measured: 0.82 -> 0.10 m)
    assert float(err[:, -1].median()) < 0.2 * float(err[:, 0].median())
    assert float(err[:, -1].max()) < 0.5
    lo, hi = ks.state_bounds
    assert float(x[..., 2].abs().max()) <= hi[2]  # the steering stays within the vehicle's limit


def test_structured_divergence_equals_autodiff():
    ks, controller, reference, x0 = _setup(n=100, seed=5)
    x0 = x0.clone()
    x0[:, :2] += 6.0 * torch.randn(100, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    loop = ClosedLoop(ks, controller)
    for k in (0, 300, 700):
        f1, d1 = loop.rhs_and_divergence(x0, reference.x[k], reference.u[k], "structured")
        f2, d2 = loop.rhs_and_divergence(x0, reference.x[k], reference.u[k], "autodiff")
        torch.testing.assert_close(f1, f2, atol=1e-12, rtol=0)
        torch.testing.assert_close(d1, d2, atol=1e-10, rtol=0)


def test_log_density_equals_inverse_flow_jacobian_determinant():
    """exp(log rho) = rho0 / |det dPhi/dx0| with dPhi/dx0 by central finite differences (3 s, small initial
    errors: no input saturates, so the flow is smooth). The structured divergence equals the autodiff one
    (:func:`test_structured_divergence_equals_autodiff`), which is slower by far."""
    ks, controller, reference, x0 = _setup(n=8, seed=3, segments=3)
    x0 = reference.start + 0.3 * (x0 - reference.start)
    cfg = LiouvilleConfig("rk4", 0.01)
    out = propagate_density(ks, controller, x0, reference, config=cfg)
    h = 1e-6
    cols = []
    for i in range(5):
        e = torch.zeros(5, dtype=torch.float64)
        e[i] = h
        _, xp = simulate_closed_loop(ks, controller, x0 + e, reference, config=cfg)
        _, xm = simulate_closed_loop(ks, controller, x0 - e, reference, config=cfg)
        cols.append((xp[:, -1] - xm[:, -1]) / (2 * h))
    det = torch.linalg.det(torch.stack(cols, dim=-1)).abs()
    rel = (torch.exp(out.log_rho[:, -1] - out.log_rho0) * det - 1.0).abs()
    # finite-difference truncation/round-off and the O(dt^4) difference of RK4's discrete flow
    assert float(rel.max()) < 1e-4, float(rel.max())


def test_controller_tangents_equal_autodiff():
    ks, controller, reference, x0 = _setup(n=40, seed=7)
    x0 = x0.clone()
    x0[:, :2] += 5.0 * torch.randn(40, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    x0[:20, 2] = torch.linspace(-1.0, 1.0, 20, dtype=torch.float64)  # near and past the steering knee
    x_ref, u_ref = reference.x[200], reference.u[200]
    tangents = torch.randn(5, 40, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    u, du = controller.raw_with_tangents(x0, x_ref, u_ref, tangents)
    u2, du2 = super(KSTrackingController, controller).raw_with_tangents(x0, x_ref, u_ref, tangents)
    torch.testing.assert_close(u, u2, atol=1e-14, rtol=0)
    torch.testing.assert_close(du, du2, atol=1e-12, rtol=0)


def test_scaled_adam_is_adam_in_scaled_coordinates():
    """``BatchedAdam(scale=s)`` on ``p`` takes the steps of plain Adam on ``q = p / s`` (the KS steering rate's
    ``input_step_scale``): same iterates up to the ``eps`` term."""
    from density_planner.planners.optim import BatchedAdam

    g = torch.Generator().manual_seed(0)
    s = torch.tensor([[0.1], [1.0]], dtype=torch.float64)
    p = torch.randn(3, 2, 4, generator=g, dtype=torch.float64) * s
    q = p / s
    a = BatchedAdam(p, lr=0.01, update_clip=0.02, low=-0.3 * torch.ones(2, 1), high=torch.ones(2, 1) * 3, scale=s)
    b = BatchedAdam(q, lr=0.01, update_clip=0.02, low=-0.3 / s, high=3 / s, eps=1e-9)
    for _ in range(20):
        grad_p = torch.randn(3, 2, 4, generator=g, dtype=torch.float64)
        a.step(grad_p)
        b.step(grad_p * s)
    torch.testing.assert_close(p, q * s, atol=1e-7, rtol=0)
    assert bool((p[:, 0].abs() <= 0.3 + 1e-12).all())


def test_symbolic_dynamics_equal_f():
    casadi = pytest.importorskip("casadi")
    ks = KinematicSingleTrack()
    xs, us = casadi.SX.sym("x", 5), casadi.SX.sym("u", 2)
    fn = casadi.Function("f", [xs, us], [ks.f_symbolic(xs, us, casadi)])
    x = torch.tensor([1.0, -2.0, 0.3, 7.0, 2.5], dtype=torch.float64)
    u = torch.tensor([0.1, -1.0], dtype=torch.float64)
    got = torch.tensor(fn(x.numpy(), u.numpy()).full().ravel(), dtype=torch.float64)
    torch.testing.assert_close(got, ks.f(x, u), atol=1e-12, rtol=0)

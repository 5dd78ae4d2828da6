"""Exact Liouville propagation against analytic truths, convergence orders and flow-map Jacobians."""

from __future__ import annotations

import math

import pytest
import torch

from density_planner.control.analytic import CarTrackingController
from density_planner.control.reference import make_reference
from density_planner.density.closed_loop import ClosedLoop
from density_planner.density.liouville import LiouvilleConfig, propagate_density, simulate_closed_loop
from density_planner.systems.car import KinematicCar
from problems import expm_solution, linear_problem

TR_A = -0.7  # trace of problems.A2


@pytest.mark.parametrize("integrator,dt", [("euler", 0.01), ("euler", 0.1), ("rk4", 0.1), ("rk4", 0.05)])
@pytest.mark.parametrize("divergence", ["structured", "autodiff"])
def test_linear_log_density_falls_by_trace(integrator, dt, divergence):
    system, controller, reference = linear_problem()
    x0 = torch.randn(7, 2, dtype=torch.float64)
    log_rho0 = torch.randn(7, dtype=torch.float64)
    cfg = LiouvilleConfig(integrator=integrator, dt=dt, divergence=divergence)
    out = propagate_density(system, controller, x0, reference, log_rho0=log_rho0, config=cfg)
    expected = log_rho0[:, None] - TR_A * out.t[None, :]
    # div f = tr(A) is constant, so every consistent scheme integrates it exactly (float64 round-off only)
    torch.testing.assert_close(out.log_rho, expected, atol=1e-10, rtol=0)
    assert out.x.shape == (7, 101, 2) and out.t.shape == (101,)


def _state_error(integrator: str, dt: float) -> float:
    system, controller, reference = linear_problem()
    x0 = torch.tensor([[1.0, -0.5], [0.3, 0.8]], dtype=torch.float64)
    cfg = LiouvilleConfig(integrator=integrator, dt=dt)
    t, x = simulate_closed_loop(system, controller, x0, reference, config=cfg)
    return float((x - expm_solution(x0, t)).abs().max())


@pytest.mark.parametrize("integrator,order", [("euler", 1), ("rk4", 4)])
def test_convergence_order_on_linear_system(integrator, order):
    dts = [0.1, 0.05, 0.025]
    errs = [_state_error(integrator, dt) for dt in dts]
    slopes = [math.log2(errs[i] / errs[i + 1]) for i in range(len(errs) - 1)]
    # the observed order on halving the step must match the theoretical one (asymptotic regime: +-0.15)
    for s in slopes:
        assert abs(s - order) < 0.15, (errs, slopes)


def _car_setup(n=64, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    car = KinematicCar()
    controller = CarTrackingController().to(dtype)
    params = (0.4 * torch.randn(2, 10, generator=g, dtype=dtype)).clamp(-3, 3)
    start = torch.tensor([0.0, -28.0, 1.5, 3.0, 0.0], dtype=dtype)
    reference = make_reference(car, start, params)
    hw = torch.tensor(car.config.initial_error_max, dtype=dtype)
    x0 = start + (2 * torch.rand(n, 5, generator=g, dtype=dtype) - 1) * hw
    return car, controller, reference, x0


def test_car_log_density_order_of_convergence():
    """Log-density error against a fine RK4 solution shrinks at the scheme's order (smooth, unsaturated case)."""
    car, controller, reference, x0 = _car_setup(n=16)
    x0 = reference.start + 0.3 * (x0 - reference.start)  # small errors: inputs stay away from the clip
    fine = propagate_density(car, controller, x0, reference, config=LiouvilleConfig("rk4", 0.005))
    for integrator, order, dts in [("euler", 1, (0.02, 0.01)), ("rk4", 4, (0.05, 0.025))]:
        errs = []
        for dt in dts:
            out = propagate_density(car, controller, x0, reference, config=LiouvilleConfig(integrator, dt))
            errs.append(float((out.log_rho - fine.log_rho).abs().max()))
        slope = math.log2(errs[0] / errs[1])
        # tolerance 0.35: pre-asymptotic effects at these steps; the order must be clearly visible
        assert abs(slope - order) < 0.35, (integrator, errs, slope)


def test_car_density_equals_inverse_flow_jacobian_determinant():
    """exp(log rho) = rho0 / |det dPhi/dx0| with dPhi/dx0 from central finite differences (float64)."""
    car, controller, reference, x0 = _car_setup(n=24, seed=3)
    cfg = LiouvilleConfig("rk4", 0.02)
    out = propagate_density(car, controller, x0, reference, config=cfg)
    # samples whose input saturates at the clip somewhere are set aside: there the flow map is only piecewise
    # smooth and a finite difference across the switching surface is not a derivative
    t_all, x_all = simulate_closed_loop(car, controller, x0, reference, config=cfg, all_steps=True)
    x_st, u_st = reference.stage_values(cfg.dt, x_all.shape[-2] - 1, (0.0,))
    u_raw = controller.raw(car.measure(x_all[..., :-1, :]), x_st[:, 0].unsqueeze(0), u_st[:, 0].unsqueeze(0))
    saturated = (u_raw.abs() >= 3.0).any(-1).any(-1)
    keep = ~saturated
    assert int(keep.sum()) >= 12, f"too few unsaturated samples: {int(keep.sum())} of {len(keep)}"

    h = 1e-6
    cols = []
    for i in range(5):
        e = torch.zeros(5, dtype=torch.float64)
        e[i] = h
        _, xp = simulate_closed_loop(car, controller, x0 + e, reference, config=cfg)
        _, xm = simulate_closed_loop(car, controller, x0 - e, reference, config=cfg)
        cols.append((xp[:, -1] - xm[:, -1]) / (2 * h))
    jac = torch.stack(cols, dim=-1)  # (N, 5, 5): d x(T) / d x0
    det = torch.linalg.det(jac).abs()
    rho_ratio = torch.exp(out.log_rho[:, -1] - out.log_rho0)
    rel = (rho_ratio * det - 1.0).abs()[keep]
    # 1e-3: finite-difference truncation (h^2 ~ 1e-12) and round-off (eps/h ~ 1e-10 amplified by the 5x5 determinant
    # of a strongly contracting flow, det ~ e^-35) plus the RK4 discretisation difference between the discrete
    # flow's Jacobian determinant and exp(-integral of div) (O(dt^4)); measured ~1e-6
    assert float(rel.max()) < 1e-3, f"max relative error {float(rel.max()):.2e} ({int(saturated.sum())} set aside)"


@pytest.mark.parametrize("dtype", [torch.float64])
def test_structured_divergence_equals_autodiff(dtype):
    car, controller, reference, x0 = _car_setup(n=200, seed=5, dtype=dtype)
    x0 = x0.clone()
    x0[:, 4] = torch.linspace(-0.3, 0.3, x0.shape[0], dtype=dtype)  # include the bias direction
    loop = ClosedLoop(car, controller)
    x_ref, u_ref = reference.x[300], reference.u[300]
    f1, d1 = loop.rhs_and_divergence(x0, x_ref, u_ref, "structured")
    f2, d2 = loop.rhs_and_divergence(x0, x_ref, u_ref, "autodiff")
    torch.testing.assert_close(f1, f2, atol=1e-12, rtol=0)
    torch.testing.assert_close(d1, d2, atol=1e-10, rtol=0)


def test_structured_divergence_with_saturated_inputs_matches_autodiff():
    car, controller, reference, x0 = _car_setup(n=50, seed=6)
    x0 = x0.clone()
    x0[:, :2] += 8.0 * torch.randn(50, 2, dtype=torch.float64)  # far off: the inputs clip
    loop = ClosedLoop(car, controller)
    _, d1 = loop.rhs_and_divergence(x0, reference.x[0], reference.u[0], "structured")
    _, d2 = loop.rhs_and_divergence(x0, reference.x[0], reference.u[0], "autodiff")
    torch.testing.assert_close(d1, d2, atol=1e-10, rtol=0)


def test_batched_references_match_single_reference_runs():
    car, controller, _, _ = _car_setup()
    g = torch.Generator().manual_seed(9)
    params = (0.5 * torch.randn(3, 2, 10, generator=g, dtype=torch.float64)).clamp(-3, 3)
    starts = torch.tensor([[0.0, -28.0, 1.5, 3.0, 0.0], [1.0, 0.0, 0.3, 5.0, 0.0], [-2.0, 3.0, 4.0, 1.0, 0.0]],
                          dtype=torch.float64)
    reference = make_reference(car, starts, params)
    x0 = starts[:, None, :] + 0.2 * torch.randn(3, 6, 5, generator=g, dtype=torch.float64)
    batched = propagate_density(car, controller, x0, reference)
    assert batched.x.shape == (3, 6, 101, 5) and batched.log_rho.shape == (3, 6, 101)
    for b in range(3):
        single = propagate_density(car, controller, x0[b], reference.select(b))
        torch.testing.assert_close(batched.x[b], single.x, atol=1e-12, rtol=0)
        torch.testing.assert_close(batched.log_rho[b], single.log_rho, atol=1e-12, rtol=0)


def test_float32_matches_float64():
    car, controller, reference, x0 = _car_setup(n=32, seed=2)
    out64 = propagate_density(car, controller, x0, reference)
    ref32 = make_reference(car, reference.start.float(), reference.params.float())
    out32 = propagate_density(car, controller.float(), x0.float(), ref32)
    # float32 round-off accumulated over 100 RK4 steps of a contracting system: positions to ~1e-4 m
    assert float((out32.x.double() - out64.x).abs().max()) < 2e-3
    assert float((out32.log_rho.double() - out64.log_rho).abs().max()) < 2e-3


def test_gradient_flows_to_reference_parameters():
    car, controller, reference, x0 = _car_setup(n=8)
    params = reference.params.clone().requires_grad_(True)
    ref = make_reference(car, reference.start, params)
    out = propagate_density(car, controller, x0, ref, config=LiouvilleConfig("rk4", 0.1))
    loss = out.x[..., -1, :2].pow(2).sum() + out.log_rho[..., -1].sum()
    (grad,) = torch.autograd.grad(loss, params)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


def test_log_density_never_nan_for_extreme_divergence():
    """Huge contraction rates would make the paper's log(1 - dt div f) NaN; the log form stays finite."""
    from density_planner.control.analytic import LinearFeedbackController
    from density_planner.systems.linear import LinearSystem

    system = LinearSystem(((-200.0,),), ((1.0,),))
    controller = LinearFeedbackController(((0.0,),)).double()
    reference = make_reference(system, torch.zeros(1, dtype=torch.float64), torch.zeros(1, 10, dtype=torch.float64))
    out = propagate_density(system, controller, torch.ones(3, 1, dtype=torch.float64), reference,
                            config=LiouvilleConfig("euler", 0.01))
    assert torch.isfinite(out.log_rho).all()
    torch.testing.assert_close(out.log_rho[:, -1], torch.full((3,), 2000.0, dtype=torch.float64))



#: initial-error scale (fraction of the initial-error box) per controller: the C3M feedback has higher gains, so
#: smaller errors keep its inputs off the bounds
_GRADCHECK_ERROR = {"analytic": 0.3, "c3m": 0.05}


def _gradcheck_controller(kind: str):
    if kind == "analytic":
        return CarTrackingController().double()
    from density_planner.control.c3m import load_c3m_controller

    return load_c3m_controller().double()  # the shipped C3M weights (tanh networks: smooth)


@pytest.fixture
def one_thread():
    """gradcheck makes hundreds of tiny calls: extra OpenMP threads on a shared machine make them 20x slower."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize("controller_kind", ["analytic", "c3m"])
@pytest.mark.parametrize("divergence", ["structured", "autodiff"])
def test_gradcheck_of_exact_liouville(controller_kind, divergence, one_thread):
    """``torch.autograd.gradcheck`` (float64 central differences against the analytical Jacobian) of the predicted
    states and log-densities (every 0.2 s) w.r.t. the reference parameters and the initial states: 2 samples,
    2 segments of 0.5 s (RK4 at 0.1 s), initial errors small enough that no input reaches its bound (the clip's
    kink). The autodiff divergence differentiates a Jacobian trace (second derivatives of the closed loop), ~50x
    slower per call: checked in gradcheck's fast mode (a random projection of the Jacobian)."""
    from density_planner.control.reference import PiecewiseConstantInputs

    g = torch.Generator().manual_seed(11)
    car = KinematicCar()
    controller = _gradcheck_controller(controller_kind)
    par = PiecewiseConstantInputs(n_segments=2, segment_duration=0.5)
    start = torch.tensor([0.0, -28.0, 1.5, 3.0, 0.0], dtype=torch.float64)
    params = (0.3 * torch.randn(2, 2, generator=g, dtype=torch.float64)).requires_grad_(True)
    hw = _GRADCHECK_ERROR[controller_kind] * torch.tensor(car.config.initial_error_max, dtype=torch.float64)
    x0 = (start + (2 * torch.rand(2, 5, generator=g, dtype=torch.float64) - 1) * hw).requires_grad_(True)
    log_rho0 = torch.randn(2, generator=g, dtype=torch.float64)
    cfg = LiouvilleConfig("rk4", 0.1, divergence=divergence)

    def predict(p, x):
        out = propagate_density(car, controller, x, make_reference(car, start, p, par), log_rho0=log_rho0,
                                config=cfg)
        return out.x[:, ::2], out.log_rho[:, ::2]

    with torch.no_grad():
        x, log_rho = predict(params, x0)
        ref = make_reference(car, start, params, par)
        u = controller(car.measure(x[:, :-1].reshape(-1, 5)), ref.x_plan[:-1:2].repeat(2, 1),
                       ref.u_plan[::2].repeat(2, 1))
    assert x.shape == (2, 6, 5) and log_rho.shape == (2, 6)
    # an informative case: the densities change along the run; every input stays off its bound (3)
    assert float((log_rho[:, -1] - log_rho0).abs().min()) > 1.0
    assert float(u.abs().max()) < 2.0
    fast = divergence == "autodiff"
    assert torch.autograd.gradcheck(predict, (params, x0), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=fast)


# --------------------------------------------------------------------------- the step schedule for fast references
def _road_references(speeds, dtype=torch.float64):
    """The road model set's car and analytic controller; references at constant ``speeds`` [m/s] (one per batch
    element), with 0.2 rad/s turns, and 6 initial states around each start."""
    from density_planner.control.registry import model_set

    car = model_set("road").make_system()
    controller = CarTrackingController().to(dtype)
    g = torch.Generator().manual_seed(4)
    n = len(speeds)
    starts = torch.zeros(n, 5, dtype=dtype)
    starts[:, 3] = torch.tensor(speeds, dtype=dtype)
    params = torch.zeros(n, 2, 10, dtype=dtype)
    params[:, 0, 3:6] = 0.04  # a gentle turn (inside every speed's turn-rate limit)
    reference = make_reference(car, starts, params)
    hw = torch.tensor(car.config.initial_error_max, dtype=dtype)
    x0 = starts[:, None, :] + (2 * torch.rand(n, 6, 5, generator=g, dtype=dtype) - 1) * hw
    return car, controller, reference, x0


def test_speed_schedule_picks_the_step_by_top_speed():
    cfg = LiouvilleConfig()
    car, _, reference, _ = _road_references([5.0, 17.0, 22.0, 33.0])
    assert [cfg.step_for_speed(v, car) for v in (0.0, 14.9, 15.0, 19.9, 20.0, 24.9, 25.0, 40.0)] == [
        0.1, 0.1, 0.05, 0.05, 0.025, 0.025, 0.02, 0.02]
    # dt is the largest step: the schedule only refines it
    assert LiouvilleConfig(dt=0.01, integrator="euler").step_for_speed(40.0, car) == 0.01
    assert LiouvilleConfig(speed_steps=()).step_for_speed(40.0, car) == 0.1
    steps = cfg.steps_for(car, reference)
    assert steps is not None and steps.tolist() == [0.1, 0.05, 0.025, 0.02]
    assert cfg.steps_for(car, reference.select(slice(0, 1))) is None  # slow references: the fixed step
    system, _, linear_reference = linear_problem()
    assert cfg.steps_for(system, linear_reference) is None  # no speed state


def test_speed_schedule_is_the_systems_own_unless_configured():
    """The default schedule is the system's: the car's road domain has one, the paper's box and KS none (their
    fixed 0.1-s step is accurate); a configured schedule applies to every system, ``()`` to none."""
    from density_planner.control.registry import model_set

    road, paper, ks = (model_set(name).make_system() for name in ("road", "paper", "ks"))
    assert LiouvilleConfig().schedule(road) == ((15.0, 0.05), (20.0, 0.025), (25.0, 0.02))
    assert LiouvilleConfig().schedule(paper) == () and LiouvilleConfig().schedule(ks) == ()
    assert LiouvilleConfig().step_for_speed(30.0, ks) == 0.1
    assert LiouvilleConfig(speed_steps=[[20, 0.05]]).step_for_speed(30.0, ks) == 0.05
    assert LiouvilleConfig(speed_steps=()).schedule(road) == ()


@pytest.mark.parametrize("bad", [[[-1.0, 0.05]], [[15.0, 0.0]], [[15.0]], [[math.nan, 0.05]]])
def test_speed_schedule_rejects_bad_pairs(bad):
    with pytest.raises(ValueError, match="speed_steps"):
        LiouvilleConfig(speed_steps=bad)


def test_speed_schedule_rounds_a_step_down_to_a_divisor_of_the_output_step():
    assert LiouvilleConfig(speed_steps=[[15.0, 0.03]]).step_for_speed(20.0) == pytest.approx(0.025)
    cfg = LiouvilleConfig(dt=0.15, output_dt=0.15, speed_steps=((15.0, 0.05), (20.0, 0.025), (25.0, 0.02)))
    assert cfg.step_for_speed(30.0) == pytest.approx(0.15 / 8)  # 0.02 does not divide 0.15: 0.01875 does
    steps = [cfg.step_for_speed(v) for v in (16.0, 21.0, 30.0)]
    assert all(abs(0.15 / s - round(0.15 / s)) < 1e-9 for s in steps)


def test_speed_schedule_from_toml_lists_is_a_tuple():
    cfg = LiouvilleConfig(speed_steps=[[15, 0.05], [30, 0.02]])
    assert cfg.speed_steps == ((15.0, 0.05), (30.0, 0.02))
    assert hash(cfg) == hash(LiouvilleConfig(speed_steps=((15.0, 0.05), (30.0, 0.02))))


def test_scheduled_batch_equals_each_reference_at_its_own_step():
    """A batch of references of four speeds is integrated group by group: each reference's states and densities
    are those of a fixed-step run at its scheduled step (to round-off), and the fast ones differ from 0.1 s."""
    car, controller, reference, x0 = _road_references([5.0, 17.0, 22.0, 33.0])
    out = propagate_density(car, controller, x0, reference)
    states = simulate_closed_loop(car, controller, x0, reference)[1]
    torch.testing.assert_close(states, out.x, atol=1e-12, rtol=0)
    assert out.x.shape == (4, 6, 101, 5) and out.t.shape == (101,)
    for b, step in enumerate((0.1, 0.05, 0.025, 0.02)):
        fixed = propagate_density(car, controller, x0[b], reference.select(b),
                                  config=LiouvilleConfig(dt=step, speed_steps=()))
        torch.testing.assert_close(out.x[b], fixed.x, atol=1e-12, rtol=0)
        torch.testing.assert_close(out.log_rho[b], fixed.log_rho, atol=1e-12, rtol=0)
        if step < 0.1:
            coarse = propagate_density(car, controller, x0[b], reference.select(b),
                                       config=LiouvilleConfig(speed_steps=()))
            assert float((coarse.x - fixed.x).abs().max()) > 1e-9


def test_scheduled_batch_gradient_equals_per_reference_gradients():
    car, controller, reference, x0 = _road_references([5.0, 22.0, 33.0])
    params = reference.params.clone().requires_grad_(True)
    out = propagate_density(car, controller, x0, make_reference(car, reference.start, params))
    (grad,) = torch.autograd.grad(out.x[..., -1, :2].pow(2).sum() + out.log_rho[..., -1].sum(), params)
    for b in range(3):
        p = reference.params[b].clone().requires_grad_(True)
        one = propagate_density(car, controller, x0[b], make_reference(car, reference.start[b], p))
        (g,) = torch.autograd.grad(one.x[..., -1, :2].pow(2).sum() + one.log_rho[..., -1].sum(), p)
        torch.testing.assert_close(grad[b], g, atol=1e-9, rtol=1e-9)

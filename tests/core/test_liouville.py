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


@pytest.mark.parametrize("models", ["paper", "road"])
def test_raw_input_comes_with_the_closed_loop_unchanged(models):
    """``rhs_with_raw`` / ``rhs_divergence_with_raw`` give the same field and divergence as ``rhs`` /
    ``rhs_and_divergence`` and, beside them, the controller's raw (unbounded) input, on both paths; the applied input
    is its bound (here far off the reference, so that many inputs saturate)."""
    from density_planner.control.registry import load_controller, model_set

    car = model_set(models).make_system()
    controller = load_controller(None, models=models).double()
    g = torch.Generator().manual_seed(3)
    x = torch.zeros(64, 5, dtype=torch.float64)
    x[:, 3] = torch.linspace(0.5, car.speed_max - 0.5, 64, dtype=torch.float64)
    x_ref = x + torch.randn(64, 5, generator=g, dtype=torch.float64) * torch.tensor([2.0, 2.0, 0.4, 1.0, 0.0],
                                                                                    dtype=torch.float64)
    x_ref[:, 4] = 0.0
    u_ref = torch.zeros(64, 2, dtype=torch.float64)
    loop = ClosedLoop(car, controller)
    raw = controller.raw(car.measure(x), x_ref, u_ref)
    assert bool((controller.bound(raw, car.measure(x)) != raw).any())  # some saturate
    f, r = loop.rhs_with_raw(x, x_ref, u_ref)
    torch.testing.assert_close(f, loop.rhs(x, x_ref, u_ref), atol=1e-12, rtol=0)
    torch.testing.assert_close(r, raw, atol=1e-12, rtol=0)
    for method in ("structured", "autodiff"):
        f2, div, r2 = loop.rhs_divergence_with_raw(x, x_ref, u_ref, method)
        f3, div3 = loop.rhs_and_divergence(x, x_ref, u_ref, method)
        torch.testing.assert_close(f2, f, atol=1e-12, rtol=0)
        torch.testing.assert_close((div, r2), (div3, raw), atol=1e-10, rtol=0)


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
def _road_references(speeds, dtype=torch.float64, learned=False):
    """The road model set's car and analytic controller (``learned``: its C3M controller, whose smooth saturation
    the error control resolves by ``LiouvilleConfig.saturation_step``); references at constant ``speeds`` [m/s] (one
    per batch element), with 0.2 rad/s turns, and 6 initial states around each start."""
    from density_planner.control.registry import load_controller, model_set

    car = model_set("road").make_system()
    controller = (load_controller(None, models="road") if learned else CarTrackingController()).to(dtype)
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


def test_scheme_is_the_systems_own_unless_configured():
    """The default scheme is the system's: the error-controlled "rk43" for the car's road domain, RK4 for the
    paper's box and KS (their fixed 0.1-s step is accurate); a configured scheme applies to every system, and the
    tolerance defaults to the scheme's own."""
    from density_planner.control.registry import model_set

    road, paper, ks = (model_set(name).make_system() for name in ("road", "paper", "ks"))
    assert LiouvilleConfig().scheme(road) == "rk43"
    assert LiouvilleConfig().scheme(paper) == "rk4" and LiouvilleConfig().scheme(ks) == "rk4"
    assert LiouvilleConfig(integrator="rk4").scheme(road) == "rk4"
    assert LiouvilleConfig(integrator="dopri5").scheme(ks) == "dopri5"
    assert "tolerance 0.003" in LiouvilleConfig().describe(road) and LiouvilleConfig().describe(paper) == "rk4 at 0.1 s"
    assert "tolerance 5e-05" in LiouvilleConfig("dopri5").describe(road)
    assert "tolerance 1e-06" in LiouvilleConfig("dopri5", tolerance=1e-6).describe(road)
    assert LiouvilleConfig("rk4").pair(road) is None


@pytest.mark.parametrize("kwargs,match", [({"tolerance": 0.0}, "tolerance"), ({"tolerance": math.nan}, "tolerance"),
                                          ({"integrator": "rk45"}, "integrator"),
                                          ({"saturation_step": -1.0}, "saturation_step"),
                                          ({"saturation_step": math.nan}, "saturation_step"),
                                          ({"log_density_rule": "trapezoid"}, "log_density_rule")])
def test_liouville_config_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LiouvilleConfig(**kwargs)


@pytest.mark.parametrize("scheme,learned", [("rk43", True), ("dopri5", False)])
def test_error_control_converges_as_its_tolerance_shrinks(scheme, learned):
    """Error control: on references of 5, 17 and 33 m/s the states and log-densities approach the solution at a
    tolerance of 1e-10 as the tolerance shrinks: "dopri5" with the analytic controller, whose hard clip a fixed step
    resolves slowly (RK4 at 0.005 s is still 0.015 nats off); "rk43" with the learned controller and its smooth
    saturation (rk43's estimate compares two evaluations at the step's end, blind to a kink inside a step: a hard
    clip is dopri5's, docs/core.md)."""
    car, controller, reference, x0 = _road_references([5.0, 17.0, 33.0], learned=learned)
    best = propagate_density(car, controller, x0, reference, config=LiouvilleConfig("dopri5", tolerance=1e-10))
    errors = []
    for tol in (1e-3, 1e-5, 1e-7):
        out = propagate_density(car, controller, x0, reference, config=LiouvilleConfig(scheme, tolerance=tol))
        assert out.x.shape == best.x.shape == (3, 6, 101, 5) and torch.equal(out.t, best.t)
        errors.append(max(float((out.log_rho - best.log_rho).abs().max()), float((out.x - best.x).abs().max())))
    assert errors[0] > errors[1] > errors[2] and errors[2] < 1e-3
    torch.testing.assert_close(best.x[..., 0, :], x0)  # the first output is the initial state, exactly


@pytest.mark.parametrize("scheme", ["rk43", "dopri5"])
def test_error_control_samples_keep_their_own_steps_independently(scheme):
    """Every sample has its own clock: a batch of references gives each the result of integrating it alone (to
    float64 round-off)."""
    car, controller, reference, x0 = _road_references([5.0, 22.0, 33.0])
    config = LiouvilleConfig(scheme)
    out = propagate_density(car, controller, x0, reference, config=config)
    for b in range(3):
        one = propagate_density(car, controller, x0[b], reference.select(b), config=config)
        torch.testing.assert_close(out.x[b], one.x, atol=1e-9, rtol=0)
        torch.testing.assert_close(out.log_rho[b], one.log_rho, atol=1e-9, rtol=0)


def test_error_control_gradient_matches_finite_differences():
    """The solution is differentiable along its (gradient-free) steps: at a tight tolerance its gradient w.r.t. the
    reference parameters matches central differences of the solution (the default rk43 with the learned controller
    and its smooth saturation; dopri5 shares the loop)."""
    car, controller, reference, x0 = _road_references([12.0, 30.0], learned=True)
    x0 = x0[:, :2]
    config = LiouvilleConfig("rk43", tolerance=1e-7)

    def loss(p):
        out = propagate_density(car, controller, x0, make_reference(car, reference.start, p), config=config)
        return out.x[..., -1, :2].pow(2).sum() + out.log_rho[..., -1].sum()

    p = reference.params.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(loss(p), p)
    eps = 1e-5
    for idx in ((0, 0, 2), (1, 1, 4), (1, 0, 7)):
        d = torch.zeros_like(p)
        d[idx] = eps
        with torch.no_grad():
            fd = (loss(reference.params + d) - loss(reference.params - d)) / (2 * eps)
        assert float(g[idx]) == pytest.approx(float(fd), rel=1e-4, abs=1e-5)


def test_saturation_step_resolves_a_fast_sweep_through_the_bend():
    """A highway reference (31.8 m/s, one of the random road references of docs/core.md) on which the learned
    controller's raw turn rate sweeps from deep in one tail through the linear band into the other within ~0.15 s:
    the divergence jumps from 6 to 14.5 /s and back within 50-ms bends. With ``saturation_step`` the default
    "rk43" follows it to 0.02 nats; without, the coupled rule's error estimate sees no stage inside the bends and
    errs by > 0.2 nats, the fixed RK4 step by > 0.5. (Without the saturation step the quadrature rule controls
    its own Simpson-against-trapezoid estimate, which catches these bends; on random draws it misses others,
    docs/core.md.)"""
    from density_planner.control.registry import load_controller, model_set

    car = model_set("road").make_system()
    controller = load_controller(None, models="road").double()
    start = torch.tensor([-1.1797, -5.358, -0.7799, 31.801, 0.0], dtype=torch.float64)
    params = torch.tensor([[0.0334, 0.0725, -0.0272, 0.0677, -0.0912, -0.0939, 0.026, -0.0098, -0.0192, 0.083],
                           [2.2552, -0.6339, 0.3768, -0.347, 1.1616, -3.7474, 3.0, 2.0814, -0.1776, -1.6596]],
                          dtype=torch.float64)
    reference = make_reference(car, start, params)
    x0 = (start + torch.tensor([0.769, -0.9531, 0.3107, -0.1042, 0.1338], dtype=torch.float64))[None]

    def error(config):
        out = propagate_density(car, controller, x0, reference, config=config)
        return float((out.log_rho - best.log_rho).abs().max())

    best = propagate_density(car, controller, x0, reference, config=LiouvilleConfig("rk4", 0.01))
    assert error(LiouvilleConfig()) < 0.02
    assert error(LiouvilleConfig(log_density_rule="coupled")) < 0.02
    assert error(LiouvilleConfig(saturation_step=0.0, log_density_rule="coupled")) > 0.2
    assert error(LiouvilleConfig(saturation_step=0.0)) < 0.02
    assert error(LiouvilleConfig("rk4")) > 0.5


def test_simpson_interpolation_integrates_a_quadratic_rate_exactly():
    """The quadrature rule's output inside a step is the integral of the quadratic through the rates at theta =
    0, 1/2, 1: exact for a quadratic rate (closed form), Simpson's value at theta = 1."""
    from density_planner.density.liouville import _simpson_interpolate

    a, b, c = 0.7, -2.0, 3.0  # rate r(s) = a + b s + c s^2 on [0, h]
    h = torch.tensor([0.1, 0.05], dtype=torch.float64)
    y0 = torch.tensor([1.5, -0.5], dtype=torch.float64)
    rates = [a + b * f * h + c * (f * h) ** 2 for f in (0.0, 0.5, 1.0)]
    for th in (0.0, 0.3, 0.5, 1.0):
        theta = torch.full((2,), th, dtype=torch.float64)
        s = th * h
        exact = y0 + a * s + b * s ** 2 / 2 + c * s ** 3 / 3
        torch.testing.assert_close(_simpson_interpolate(y0, None, rates, h, theta), exact)


@pytest.mark.parametrize("speeds", [[5.0], [17.0, 33.0]])
def test_quadrature_rule_agrees_with_the_coupled_rule_and_costs_fewer_tangents(speeds, monkeypatch):
    """The default quadrature rule (divergence at the ends and the middle of a step only) and the coupled rule
    (divergence at every stage) reach the same log-densities within their tolerance on the learned road closed
    loop, while the quadrature evaluates the divergence (its two tangents) on fewer rows: per accepted step 2
    instead of 4."""
    from density_planner.density.closed_loop import ClosedLoop

    car, controller, reference, x0 = _road_references(speeds, learned=True)
    counts = {"div": 0, "field": 0}
    with_div, field = ClosedLoop.rhs_divergence_with_raw, ClosedLoop.rhs_with_raw

    def count_div(self, x, *args, **kwargs):
        counts["div"] += x.shape[0]
        return with_div(self, x, *args, **kwargs)

    def count_field(self, x, *args, **kwargs):
        counts["field"] += x.shape[0]
        return field(self, x, *args, **kwargs)

    monkeypatch.setattr(ClosedLoop, "rhs_divergence_with_raw", count_div)
    monkeypatch.setattr(ClosedLoop, "rhs_with_raw", count_field)
    fine = propagate_density(car, controller, x0, reference, config=LiouvilleConfig("rk4", 0.005))
    runs = {}
    for rule in ("quadrature", "coupled"):
        counts.update(div=0, field=0)
        runs[rule] = (propagate_density(car, controller, x0, reference,
                                        config=LiouvilleConfig(log_density_rule=rule)), dict(counts))
    (quad, n_quad), (coupled, n_coupled) = runs["quadrature"], runs["coupled"]
    for out in (quad, coupled):
        assert float((out.log_rho - fine.log_rho).abs().max()) < 0.03
        assert float((out.x - fine.x).abs().max()) < 1e-2
    # the states' steps are alike (not equal: the coupled rule's error estimate also controls the log-density)
    torch.testing.assert_close(quad.x, coupled.x, atol=2e-3, rtol=0)
    assert n_coupled["field"] == 0 and n_quad["field"] > 0
    assert n_quad["div"] < 0.7 * n_coupled["div"]
    counts.update(div=0, field=0)  # the states alone (the planner's exact re-check): no divergence at all
    _, x = simulate_closed_loop(car, controller, x0, reference)
    assert counts["div"] == 0 and counts["field"] > 0
    torch.testing.assert_close(x, quad.x)


def test_error_control_refuses_what_needs_a_common_grid():
    car, controller, reference, x0 = _road_references([5.0])
    with pytest.raises(ValueError, match="rk43.*fixed step"):
        propagate_density(car, controller, x0, reference, all_steps=True)
    with pytest.raises(ValueError, match="rk43.*fixed step"):
        simulate_closed_loop(car, controller, x0, reference, plant=True)
    # the executed vehicle with a fixed step still runs on the road domain
    simulate_closed_loop(car, controller, x0, reference, plant=True, config=LiouvilleConfig("rk4"))


def test_liouville_accuracy_reports_the_default_from_the_run_of_the_same_scheme():
    """The default scheme (the road domain's rk43 at 0.1 s) is integrated once: when it is among the listed
    schemes its report is that run's; otherwise it is run on its own, and every report has its speed bands."""
    from density_planner.control.registry import model_set
    from density_planner.density.validation import liouville_accuracy

    car = model_set("road").make_system()
    controller = CarTrackingController()
    rep = liouville_accuracy(car, controller, n_references=2, samples=2, seed=0,
                             schemes=(("rk4", 0.1), ("rk43", 0.1)))
    assert list(rep["schemes"]) == ["rk4 0.1", "rk43 0.1", "default"]
    assert rep["schemes"]["default"] is rep["schemes"]["rk43 0.1"]
    alone = liouville_accuracy(car, controller, n_references=2, samples=2, seed=0, schemes=(("rk4", 0.1),))
    assert list(alone["schemes"]) == ["rk4 0.1", "default"]
    assert alone["schemes"]["default"]["max_abs_log_density_error"] == pytest.approx(
        rep["schemes"]["default"]["max_abs_log_density_error"], rel=1e-6)
    assert all(r["by_top_speed"] for r in alone["schemes"].values())

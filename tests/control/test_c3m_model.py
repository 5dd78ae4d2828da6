"""C3M controller and metric: shapes, batching, clipping, hand-written forward mode against autodiff, metric bounds."""

from __future__ import annotations

import pytest
import torch

from density_planner.control.c3m import C3MArchitecture, C3MController, C3MModel, ContractionMetric
from density_planner.control.reference import make_reference
from density_planner.control.sampling import sample_tracking_states
from density_planner.density.closed_loop import ClosedLoop
from density_planner.systems.car import KinematicCar

ARCHS = [
    C3MArchitecture(),
    C3MArchitecture(angle_encoding="raw"),
    C3MArchitecture(speed_feature_scale=0.2, hidden=32, metric_hidden=16, rank=5),
]


def _model(arch: C3MArchitecture, dtype=torch.float64) -> C3MModel:
    torch.manual_seed(0)
    model = C3MModel(arch).to(dtype)
    # larger random weights than the default initialisation, so that every nonlinearity is exercised
    with torch.no_grad():
        for p in model.parameters():
            p.mul_(3.0)
    return model.requires_grad_(False)


def _states(n: int, dtype=torch.float64, seed: int = 0):
    s = sample_tracking_states(n, torch.Generator().manual_seed(seed), dtype=dtype)
    return s.x, s.x_hat, s.x_ref, s.u_ref


def test_parameter_count_of_paper_architecture():
    # docs/spec.md §3: two MLPs 4-128-128-48 and 4-128-128-24 with 43,592 parameters (raw angle inputs)
    ctrl = C3MController(C3MArchitecture(angle_encoding="raw"))
    assert sum(p.numel() for p in ctrl.parameters()) == 43_592


@pytest.mark.parametrize("arch", ARCHS)
def test_shapes_and_batching(arch):
    ctrl = _model(arch, torch.float32).controller
    _, x_hat, x_ref, u_ref = _states(12, torch.float32)
    u = ctrl(x_hat, x_ref, u_ref)
    assert u.shape == (12, 2) and u.dtype == torch.float32
    # (B, N, 5) samples against (B, 1, 5) references as in the Liouville code
    xb = x_hat.reshape(3, 4, 5)
    ub = ctrl(xb, x_ref[:3, None], u_ref[:3, None])
    assert ub.shape == (3, 4, 2)
    # every sample alone gives the same as in the batch (float32 matmul blocking: 1e-5 relative)
    for i in range(3):
        for j in range(4):
            single = ctrl(xb[i, j], x_ref[i], u_ref[i])
            torch.testing.assert_close(single, ub[i, j], rtol=1e-5, atol=1e-5)
    # the 4-D training state gives the same input as the 5-D car state
    torch.testing.assert_close(ctrl(x_hat[:, :4], x_ref[:, :4], u_ref), u)


def test_output_is_clipped_and_zero_error_gives_feedforward():
    ctrl = _model(ARCHS[0]).controller
    _, x_hat, x_ref, u_ref = _states(500)
    u = ctrl(x_hat, x_ref, u_ref)
    assert float(u.abs().max()) <= 3.0
    assert bool((ctrl.raw(x_hat, x_ref, u_ref).abs() > 3.0).any())  # the clip is active somewhere
    # e = 0: tanh(W1 0) = 0, the feedback vanishes exactly
    torch.testing.assert_close(ctrl.raw(x_ref, x_ref, u_ref), u_ref, rtol=0, atol=0)


@pytest.mark.parametrize("arch", ARCHS)
def test_raw_with_tangents_equals_jvp(arch):
    ctrl = _model(arch).controller
    _, x_hat, x_ref, u_ref = _states(64)
    eye = torch.eye(5, dtype=torch.float64)
    # broadcast tangents (K, 1, 5) as ClosedLoop passes them, and full per-sample tangents (K, n, 5)
    tangents = [eye.reshape(5, 1, 5), torch.randn(3, 64, 5, dtype=torch.float64)]
    for dx in tangents:
        u, du = ctrl.raw_with_tangents(x_hat, x_ref, u_ref, dx)
        assert du.shape == (dx.shape[0], 64, 2)
        torch.testing.assert_close(u, ctrl.raw(x_hat, x_ref, u_ref), rtol=0, atol=1e-12)
        for k in range(dx.shape[0]):
            _, ref = torch.func.jvp(lambda z: ctrl.raw(z, x_ref, u_ref), (x_hat,), (dx[k].expand_as(x_hat),))
            # float64 forward mode vs the same operations differentiated by torch: rounding only
            torch.testing.assert_close(du[k], ref, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("arch", ARCHS)
def test_jacobian_equals_jacfwd(arch):
    ctrl = _model(arch).controller
    _, x_hat, x_ref, u_ref = _states(32)
    u, k = ctrl.jacobian(x_hat, x_ref, u_ref)
    ref = torch.func.vmap(torch.func.jacfwd(ctrl.raw))(x_hat, x_ref, u_ref)  # (n, 2, 5)
    torch.testing.assert_close(u, ctrl.raw(x_hat, x_ref, u_ref), rtol=0, atol=1e-12)
    torch.testing.assert_close(k, ref[..., :4], rtol=1e-10, atol=1e-10)  # rounding only (float64)
    assert float(ref[..., 4].abs().max()) == 0.0  # the bias slot of x_hat is unused


@pytest.mark.parametrize("arch", ARCHS)
def test_metric_is_spd_above_lower_bound(arch):
    metric = _model(arch).metric
    x, _, _, _ = _states(20_000)
    w = metric(x)
    torch.testing.assert_close(w, w.transpose(-1, -2), rtol=0, atol=0)
    eig = torch.linalg.eigvalsh(w)
    # W = L L^T + w_lb I: eigenvalues >= w_lb up to the rounding of eigvalsh (float64, |W| ~ 1e2: 1e-10)
    assert float(eig.min()) >= arch.w_lb - 1e-10
    # the block of the unactuated states (p_x, p_y) does not depend on the state (C3M condition C2)
    torch.testing.assert_close(w[:, :2, :2], w[:1, :2, :2].expand(len(x), 2, 2), rtol=0, atol=1e-12)


@pytest.mark.parametrize("arch", ARCHS)
def test_metric_derivatives_equal_jacfwd(arch):
    metric = _model(arch).metric
    x, _, _, _ = _states(16)
    w, dw = metric.with_derivatives(x)
    jac = torch.func.vmap(torch.func.jacfwd(metric))(x)  # (n, 4, 4, 5)
    torch.testing.assert_close(w, metric(x), rtol=0, atol=1e-12)
    torch.testing.assert_close(dw[0], jac[..., 2], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(dw[1], jac[..., 3], rtol=1e-10, atol=1e-10)
    assert float(jac[..., [0, 1, 4]].abs().max()) == 0.0  # W depends on (theta, v) only


def test_metric_standalone_module():
    metric = ContractionMetric(C3MArchitecture(metric_hidden=8))
    assert metric(torch.zeros(3, 7, 4)).shape == (3, 7, 4, 4)


@pytest.mark.parametrize("arch", ARCHS)
def test_structured_divergence_equals_autodiff(arch):
    car = KinematicCar()
    ctrl = _model(arch).controller
    params = 0.5 * torch.randn(2, 2, 10, dtype=torch.float64)
    start = torch.tensor([[0.0, 0.0, 0.3, 3.0, 0.0], [1.0, -2.0, 2.0, 6.0, 0.0]], dtype=torch.float64)
    ref = make_reference(car, start, params)
    x = ref.x[:, 37:38] + 0.3 * torch.randn(2, 50, 5, dtype=torch.float64)  # (B, N, 5) around the reference
    x_ref, u_ref = ref.x[:, 37:38], ref.u[:, 37:38]
    loop = ClosedLoop(car, ctrl)
    f_s, div_s = loop.rhs_and_divergence(x, x_ref, u_ref, method="structured")
    f_a, div_a = loop.rhs_and_divergence(x, x_ref, u_ref, method="autodiff")
    torch.testing.assert_close(f_s, f_a, rtol=0, atol=1e-12)
    torch.testing.assert_close(div_s, div_a, rtol=1e-10, atol=1e-10)  # two float64 routes, rounding only

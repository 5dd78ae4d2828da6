"""Contraction conditions: hand-built linear examples with known answers, and the car terms against autodiff."""

from __future__ import annotations

import math

import pytest
import torch

from density_planner.control.c3m import C3MArchitecture, C3MModel
from density_planner.control.contraction import (
    CAR_B_PERP,
    ContractionTerms,
    car_contraction_terms,
    closed_loop_condition,
    condition_holds,
    contraction_loss,
    max_eigenvalue,
    uncontrolled_conditions,
)
from density_planner.control.sampling import sample_tracking_states
from density_planner.systems.car import KinematicCar

F64 = torch.float64


def _linear_terms(a: torch.Tensor, b: torch.Tensor, k: torch.Tensor, w: torch.Tensor, rate: float) -> ContractionTerms:
    """Constant metric W for ``x' = A x + B u``, ``u = K x``: ``W' = 0`` and ``d_f W = d_b W = 0``."""
    n, m = b.shape
    b_perp = torch.linalg.svd(b.T, full_matrices=True).Vh[m:].T  # (n, n - m), B_perp^T B = 0
    assert float((b_perp.T @ b).abs().max()) < 1e-12
    zero = torch.zeros(n, n, dtype=F64)
    cl = closed_loop_condition(a + b @ k, w, zero, rate)
    c1, c2 = uncontrolled_conditions(a, w, zero, zero.expand(m, n, n), b_perp, rate)
    return ContractionTerms(cl=cl[None], c1=c1[None], c2=c2[:, None], w=w[None], w_perp=(b_perp.T @ w @ b_perp)[None])


def test_loss_zero_for_contracting_linear_example():
    # x' = A x + B u with u = K x: A + B K = diag(-1, -2) contracts at rate 1 in the metric W = I; with lambda = 0.5:
    # C = 2 diag(-1, -2) + I = diag(-1, -3) < 0; C1 = B_perp^T (A + A^T + I) B_perp = 2 * (-1) + 1 = -1 < 0
    a = torch.tensor([[-1.0, 0.0], [0.0, 0.0]], dtype=F64)
    b = torch.tensor([[0.0], [1.0]], dtype=F64)
    k = torch.tensor([[0.0, -2.0]], dtype=F64)
    terms = _linear_terms(a, b, k, torch.eye(2, dtype=F64), rate=0.5)
    torch.testing.assert_close(max_eigenvalue(terms.cl), torch.tensor([-1.0], dtype=F64))
    torch.testing.assert_close(max_eigenvalue(terms.c1), torch.tensor([-1.0], dtype=F64))
    loss = contraction_loss(terms, margin=0.1, margin_c1=0.1)
    assert float(loss.total) == 0.0 and loss.frac_cl == 1.0 and loss.frac_c1 == 1.0
    holds, lam, lam_n = condition_holds(terms)
    assert bool(holds.all())
    torch.testing.assert_close(lam, lam_n)  # W = I: generalised = ordinary eigenvalues


def test_loss_positive_for_non_contracting_linear_example():
    # unstable open loop A = diag(1, -1), no feedback: C = diag(2 + 1, -2 + 1) has the eigenvalue 3 > 0
    a = torch.diag(torch.tensor([1.0, -1.0], dtype=F64))
    b = torch.tensor([[0.0], [1.0]], dtype=F64)
    terms = _linear_terms(a, b, torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64), rate=0.5)
    loss = contraction_loss(terms, margin=0.0)
    # (CL): relu(3) = 3; (C1) along the unactuated x_1: 2 * 1 + 2 * 0.5 = 3
    assert float(loss.total) == pytest.approx(6.0, abs=1e-12)
    assert not bool(condition_holds(terms)[0].any())


def test_margin_makes_a_barely_contracting_example_positive():
    # A_cl = -0.5 I contracts exactly at rate 0.5: C = 0; a margin 0.2 gives a penalty 0.2 per condition
    a = -0.5 * torch.eye(2, dtype=F64)
    b = torch.tensor([[0.0], [1.0]], dtype=F64)
    terms = _linear_terms(a, b, torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64), rate=0.5)
    assert float(contraction_loss(terms, margin=0.0, margin_c1=0.0).total) == 0.0
    assert float(contraction_loss(terms, margin=0.2, margin_c1=0.0).total) == pytest.approx(0.2, abs=1e-12)


def test_generalised_eigenvalue_is_scale_invariant_and_correct():
    gen = torch.Generator().manual_seed(0)
    m = torch.randn(50, 4, 4, generator=gen, dtype=F64)
    w = m @ m.transpose(-1, -2) + 0.1 * torch.eye(4, dtype=F64)
    c = torch.randn(50, 4, 4, generator=gen, dtype=F64)
    c = c + c.transpose(-1, -2)
    lam = max_eigenvalue(c, w)
    # reference: largest (real) eigenvalue of W^{-1} C
    ref = torch.linalg.eigvals(torch.linalg.solve(w, c)).real.max(-1).values
    torch.testing.assert_close(lam, ref, rtol=1e-8, atol=1e-8)  # conditioning of W (~1e3) times 1e-13
    torch.testing.assert_close(max_eigenvalue(7.0 * c, 7.0 * w), lam, rtol=1e-10, atol=1e-10)
    assert bool(((lam < 0) == (max_eigenvalue(c) < 0)).all())  # same sign: "holds" does not depend on the form


def test_car_terms_against_autodiff():
    """A_cl = d f(x, u(x + bias e_theta)) / dx and W' = dW/dx f: built independently with torch.func."""
    torch.manual_seed(1)
    model = C3MModel(C3MArchitecture(hidden=16, metric_hidden=16, rank=4, speed_feature_scale=0.3)).double()
    model.requires_grad_(False)
    s = sample_tracking_states(40, torch.Generator().manual_seed(3), dtype=F64)
    car = KinematicCar()
    rate = 0.7
    terms = car_contraction_terms(model, s.x[:, :4], s.x_hat[:, :4], s.x_ref[:, :4], s.u_ref, rate)

    def closed_loop(x4, bias, x_ref, u_ref):
        x5 = torch.cat([x4, bias[None]])
        u = model.controller.raw(car.measure(x5), x_ref, u_ref)
        return car.f(x5, u)[:4]

    bias = s.x[:, 4]
    a_cl = torch.func.vmap(torch.func.jacfwd(closed_loop))(s.x[:, :4], bias, s.x_ref, s.u_ref)
    f_cl = torch.func.vmap(closed_loop)(s.x[:, :4], bias, s.x_ref, s.u_ref)
    dw = torch.func.vmap(torch.func.jacfwd(model.metric))(s.x[:, :4])  # (n, 4, 4, 4)
    w = model.metric(s.x[:, :4])
    w_dot = (dw * f_cl[:, None, None, :]).sum(-1)
    expected = -w_dot + a_cl @ w + w @ a_cl.transpose(-1, -2) + 2 * rate * w
    torch.testing.assert_close(terms.cl, expected, rtol=1e-10, atol=1e-10)  # float64, rounding only
    # (C1) with the open-loop drift Jacobian, (C2) = B_perp^T dW/d(theta, v) B_perp = 0 by construction
    a = torch.func.vmap(torch.func.jacfwd(lambda x4: car.drift(torch.cat([x4, x4[:1] * 0]))[:4]))(s.x[:, :4])
    bp = torch.tensor(CAR_B_PERP, dtype=F64)
    c1 = bp.T @ (a @ w + w @ a.transpose(-1, -2) + 2 * rate * w) @ bp
    torch.testing.assert_close(terms.c1, c1, rtol=1e-10, atol=1e-10)
    assert float(terms.c2.abs().max()) < 1e-12


def test_c1_cannot_hold_at_standstill():
    """At v = 0 the lateral direction is uncontrollable: B_perp^T (A W + W A^T + 2 lambda W) B_perp has the
    eigenvalue 2 lambda n^T W_pp n > 0 along the lateral unit vector n, for every metric."""
    model = C3MModel(C3MArchitecture(hidden=8, metric_hidden=8, rank=2)).double().requires_grad_(False)
    x = torch.zeros(10, 4, dtype=F64)
    x[:, 2] = torch.linspace(0, 2 * math.pi, 10, dtype=F64)
    terms = car_contraction_terms(model, x, x, x, torch.zeros(10, 2, dtype=F64), 0.5)
    assert bool((max_eigenvalue(terms.c1) > 0).all())


def test_rate_and_divergence_caps_on_a_fast_linear_example():
    # A_cl = -5 I contracts at rate 5 in W = I: generalised eigenvalues of C are 2 (0.5 - 5) = -9 (both)
    a = -5.0 * torch.eye(2, dtype=F64)
    b = torch.tensor([[0.0], [1.0]], dtype=F64)
    terms = _linear_terms(a, b, torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64), rate=0.5)
    terms.a_cl = a[None]
    assert float(contraction_loss(terms).total) == 0.0
    # rate cap 3/s: penalty relu(2 (0.5 - 3) - (-9)) = 4
    capped = contraction_loss(terms, rate=0.5, max_rate=3.0)
    assert capped.rate_cap == pytest.approx(4.0, abs=1e-12) and float(capped.total) == pytest.approx(4.0, abs=1e-12)
    assert float(contraction_loss(terms, rate=0.5, max_rate=6.0).total) == 0.0
    # divergence tr(A_cl) = -10: cap 6/s gives relu(10 - 6) = 4, cap 12/s nothing
    assert contraction_loss(terms, max_divergence=6.0).rate_cap == pytest.approx(4.0, abs=1e-12)
    assert float(contraction_loss(terms, max_divergence=12.0).total) == 0.0
    with pytest.raises(ValueError, match="either max_rate or max_divergence"):
        contraction_loss(terms, rate=0.5, max_rate=3.0, max_divergence=6.0)
    with pytest.raises(ValueError, match="must exceed rate"):
        contraction_loss(terms, rate=0.5, max_rate=0.4)

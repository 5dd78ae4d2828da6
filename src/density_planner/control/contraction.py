"""Contraction conditions of C3M (Sun, Jha, Fan, CoRL 2020), written from the paper's equations.

System ``x' = f(x) + B(x) u`` with a state-feedback tracking controller ``u(x, x_ref, u_ref)``. A
*dual metric* ``W(x) = M(x)^{-1}`` (symmetric, ``W >= w_lb I``) certifies that the closed loop contracts at
rate ``lambda`` [1/s] (every two trajectories approach each other like ``exp(-lambda t)`` in the metric ``M``) if

    C(x) := -W' + A_cl W + W A_cl^T + 2 lambda W  < 0        (negative definite)                     (CL)

with ``A_cl = df/dx + sum_j (db_j/dx) u_j + B du/dx`` the closed-loop Jacobian and ``W' = sum_i (dW/dx_i) x'_i``
the derivative of ``W`` along the closed-loop vector field. (This is ``M' + M A_cl + A_cl^T M + 2 lambda M < 0``
multiplied from both sides by ``W``, using ``W M' W = -W'``.) With ``B_perp`` an annihilator of ``B``
(``B_perp^T B = 0``), the two C3M (CCM) conditions for the directions the input cannot move are

    C1(x) := B_perp^T (-d_f W + df/dx W + W df/dx^T + 2 lambda W) B_perp  < 0                          (C1)
    C2_j(x) := B_perp^T (d_{b_j} W - db_j/dx W - W db_j/dx^T) B_perp = 0,   j = 1..m                    (C2)

where ``d_g W = sum_i (dW/dx_i) g_i`` is the derivative of ``W`` along a vector field ``g``.

Sign convention: a matrix condition "holds" when its largest eigenvalue is negative. The loss penalises
``ReLU(lambda_max + margin)``; with ``normalized=True`` the eigenvalues are the *generalised* ones of
``(C, W)`` (i.e. of ``L^{-1} C L^{-T}`` with ``W = L L^T``): ``-lambda_max / 2`` is then the local contraction
rate in excess of ``lambda`` [1/s], invariant to scaling ``W``. Both forms have the same sign, so "holds" does
not depend on the choice.

For the car (state ``(p_x, p_y, theta, v)``, constant ``B = [e_theta, e_v]``, ``B_perp = [e_px, e_py]``) the
controller sees the biased measurement ``x_hat = x + theta_bias e_theta``: ``du/dx = du/dx_hat`` is evaluated at
``x_hat`` while ``df/dx``, ``W`` and ``W'`` are evaluated at the true state ``x`` (see
:func:`car_contraction_terms`). The conditions use the unclipped control law, as in C3M.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..systems.car import ACC, OMEGA, THETA, V
from .c3m import C3MModel

__all__ = [
    "ContractionTerms",
    "closed_loop_condition",
    "uncontrolled_conditions",
    "max_eigenvalue",
    "eigenvalues",
    "contraction_loss",
    "ContractionLoss",
    "car_drift_jacobian",
    "car_contraction_terms",
    "condition_holds",
    "CAR_B",
    "CAR_B_PERP",
]

#: input matrix of the 4-D car (p_x, p_y, theta, v) and an annihilator (B_perp^T B = 0)
CAR_B = ((0.0, 0.0), (0.0, 0.0), (1.0, 0.0), (0.0, 1.0))
CAR_B_PERP = ((1.0, 0.0), (0.0, 1.0), (0.0, 0.0), (0.0, 0.0))


def _sym(m: Tensor) -> Tensor:
    return m + m.transpose(-1, -2)


def closed_loop_condition(a_cl: Tensor, w: Tensor, w_dot: Tensor, rate: float) -> Tensor:
    """``C = -W' + A_cl W + W A_cl^T + 2 rate W`` (condition (CL)); all inputs ``(*batch, n, n)``, rate [1/s]."""
    return -w_dot + _sym(a_cl @ w) + 2.0 * rate * w


def uncontrolled_conditions(
    a: Tensor,
    w: Tensor,
    dw_f: Tensor,
    dw_b: Tensor,
    b_perp: Tensor,
    rate: float,
    db: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Conditions (C1) and (C2) of C3M.

    Args:
        a: ``df/dx (*batch, n, n)`` (open-loop drift Jacobian).
        w: ``W (*batch, n, n)``.
        dw_f: ``d_f W (*batch, n, n)``, derivative of ``W`` along the drift.
        dw_b: ``d_{b_j} W (m, *batch, n, n)``, derivatives of ``W`` along the input columns.
        b_perp: ``(n, n - m)`` (or batched) annihilator of ``B``.
        rate: contraction rate [1/s].
        db: ``db_j/dx (m, *batch, n, n)``; ``None`` for a constant ``B``.

    Returns:
        ``C1 (*batch, n-m, n-m)`` and ``C2 (m, *batch, n-m, n-m)``.
    """
    bp = b_perp.to(w)
    bpt = bp.transpose(-1, -2)
    c1 = bpt @ (-dw_f + _sym(a @ w) + 2.0 * rate * w) @ bp
    inner = dw_b if db is None else dw_b - _sym(db @ w)
    c2 = bpt @ inner @ bp
    return c1, c2


def eigenvalues(c: Tensor, w: Tensor | None = None) -> Tensor:
    """Ascending eigenvalues of the symmetric ``c (*batch, k, k)``; of the pencil ``(c, w)`` if ``w`` is given
    (those of ``L^{-1} c L^{-T}`` with ``w = L L^T``)."""
    if w is not None:
        el = torch.linalg.cholesky(w)
        tmp = torch.linalg.solve_triangular(el, c, upper=False)
        c = torch.linalg.solve_triangular(el, tmp.transpose(-1, -2), upper=False)
    c = 0.5 * (c + c.transpose(-1, -2))
    return torch.linalg.eigvalsh(c)


def max_eigenvalue(c: Tensor, w: Tensor | None = None) -> Tensor:
    """Largest eigenvalue of the symmetric ``c (*batch, k, k)``; of the pencil ``(c, w)`` if ``w`` is given."""
    return eigenvalues(c, w)[..., -1]


@dataclass
class ContractionTerms:
    """Per-sample matrices of the contraction conditions of one batch.

    Attributes:
        cl: ``C (*b, n, n)`` of condition (CL).
        c1: ``C1 (*b, n-m, n-m)``.
        c2: ``C2 (m, *b, n-m, n-m)`` (zero by construction for the car metric).
        w: ``W (*b, n, n)``.
        w_perp: ``B_perp^T W B_perp (*b, n-m, n-m)`` (for the normalised eigenvalues of ``C1``).
        a_cl: closed-loop Jacobian, when known.
    """

    cl: Tensor
    c1: Tensor
    c2: Tensor
    w: Tensor
    w_perp: Tensor
    #: closed-loop Jacobian ``A_cl (*b, n, n)`` (its trace is the divergence of the closed loop) or ``None``
    a_cl: Tensor | None = None

    def eigenvalues(self, normalized: bool = True) -> tuple[Tensor, Tensor]:
        """Largest eigenvalues of ``C`` and ``C1`` per sample (generalised w.r.t. ``W`` if ``normalized``)."""
        if normalized:
            return max_eigenvalue(self.cl, self.w), max_eigenvalue(self.c1, self.w_perp)
        return max_eigenvalue(self.cl), max_eigenvalue(self.c1)

    def c2_norm(self) -> Tensor:
        """Frobenius norm of ``C2`` per sample, summed over the input channels."""
        return torch.linalg.matrix_norm(self.c2).sum(0)


def condition_holds(terms: ContractionTerms) -> tuple[Tensor, Tensor, Tensor]:
    """Per-sample ``(holds, lambda_max(C), lambda_max(C, W))``: condition (CL) holds where ``lambda_max < 0``."""
    lam = max_eigenvalue(terms.cl)
    lam_n = max_eigenvalue(terms.cl, terms.w)
    return lam < 0, lam, lam_n


@dataclass(frozen=True)
class ContractionLoss:
    """Value and parts of :func:`contraction_loss` (``total`` keeps the graph; the rest are floats)."""

    total: Tensor
    cl: float
    c1: float
    c2: float
    #: fraction of the batch where (CL) holds with the margin
    frac_cl: float
    #: fraction of the batch where (C1) holds with the margin
    frac_c1: float
    #: mean penalty of the rate cap (0 when it is off)
    rate_cap: float = 0.0


def contraction_loss(
    terms: ContractionTerms,
    *,
    margin: float = 0.0,
    margin_c1: float = 0.0,
    weight_c1: float = 1.0,
    weight_c2: float = 1.0,
    normalized: bool = True,
    rate: float = 0.0,
    max_rate: float = 0.0,
    weight_max_rate: float = 1.0,
    max_divergence: float = 0.0,
) -> ContractionLoss:
    """``mean ReLU(lambda_max(C) + margin) + w1 mean ReLU(lambda_max(C1) + margin_c1) + w2 mean |C2|_F``
    ``[+ w3 mean ReLU(2 (rate - max_rate) - lambda_min(C, W))]``.

    Zero exactly when every sample satisfies (CL) and (C1) with the margins and (C2) holds (and, with
    ``max_rate > 0``, the rate cap). The generalised eigenvalues ``mu_i`` of ``(C, W)`` are ``2 (rate - r_i)``
    with ``r_i`` the local contraction rates in the metric; the optional cap asks ``r_i <= max_rate`` [1/s], i.e.
    ``mu_min >= 2 (rate - max_rate)``, which bounds the real parts of the closed-loop eigenvalues (stiffness)
    and the divergence. It needs ``normalized=True`` and the ``rate`` that ``C`` was built with.

    With ``max_divergence > 0`` the term ``w3 mean ReLU(-tr(A_cl) - max_divergence)`` is added instead (needs
    ``terms.a_cl``): the closed loop may compress volume at most at ``max_divergence`` [1/s], which keeps the
    Liouville density growth ``d log rho / dt = -div f`` and the stiffness of the closed loop bounded.
    """
    if max_rate > 0 and max_divergence > 0:
        raise ValueError("contraction_loss: use either max_rate or max_divergence, not both")
    if max_rate > 0 and not normalized:
        raise ValueError("contraction_loss: max_rate needs normalized=True (generalised eigenvalues)")
    if max_rate > 0:
        if max_rate <= rate:
            raise ValueError(f"contraction_loss: max_rate ({max_rate}) must exceed rate ({rate})")
        ev = eigenvalues(terms.cl, terms.w)
        lam, low = ev[..., -1], ev[..., 0]
        lam1 = max_eigenvalue(terms.c1, terms.w_perp)
        p_cap = torch.relu(2.0 * (rate - max_rate) - low)
    else:
        lam, lam1 = terms.eigenvalues(normalized)
        p_cap = torch.zeros_like(lam)
        if max_divergence > 0:
            if terms.a_cl is None:
                raise ValueError("contraction_loss: max_divergence needs the closed-loop Jacobian (terms.a_cl)")
            div = torch.diagonal(terms.a_cl, dim1=-2, dim2=-1).sum(-1)
            p_cap = torch.relu(-div - max_divergence)
    p_cl = torch.relu(lam + margin)
    p_c1 = torch.relu(lam1 + margin_c1)
    c2 = terms.c2_norm()
    total = p_cl.mean() + weight_c1 * p_c1.mean() + weight_c2 * c2.mean() + weight_max_rate * p_cap.mean()
    p_cl, p_c1, c2, p_cap = p_cl.detach(), p_c1.detach(), c2.detach(), p_cap.detach()
    return ContractionLoss(
        total=total,
        cl=float(p_cl.mean()),
        c1=float(p_c1.mean()),
        c2=float(c2.mean()),
        frac_cl=float((p_cl == 0).to(p_cl.dtype).mean()),
        frac_c1=float((p_c1 == 0).to(p_c1.dtype).mean()),
        rate_cap=float(p_cap.mean()),
    )


# ----------------------------------------------------------------------------------------------------- the car
def car_drift_jacobian(x: Tensor) -> Tensor:
    """``da/dx (*batch, 4, 4)`` of the car drift ``a = (v cos theta, v sin theta, 0, 0)`` at ``x (*batch, >=4)``."""
    theta, v = x[..., THETA], x[..., V]
    c, s = torch.cos(theta), torch.sin(theta)
    z = torch.zeros_like(v)
    rows = [
        torch.stack([z, z, -v * s, c], dim=-1),
        torch.stack([z, z, v * c, s], dim=-1),
        torch.stack([z, z, z, z], dim=-1),
        torch.stack([z, z, z, z], dim=-1),
    ]
    return torch.stack(rows, dim=-2)


def car_contraction_terms(
    model: C3MModel, x: Tensor, x_hat: Tensor, x_ref: Tensor, u_ref: Tensor, rate: float
) -> ContractionTerms:
    """Matrices of (CL), (C1), (C2) for the car at true states ``x``, measured ``x_hat``, references ``x_ref, u_ref``.

    ``A_cl = da/dx(x) + B du/dx_hat(x_hat)`` (``dx_hat/dx = I``: the bias is constant), ``W = W(x)`` and
    ``W' = dW/dtheta omega + dW/dv a`` with the unclipped input ``u`` (``theta' = omega``, ``v' = a``; ``W`` does
    not depend on the positions). The drift has no ``theta`` or ``v`` component, so ``d_f W = 0``, and
    ``d_{b_omega} W = dW/dtheta``, ``d_{b_a} W = dW/dv``.
    """
    u, k = model.controller.jacobian(x_hat, x_ref, u_ref)
    w, dw = model.metric.with_derivatives(x)
    a = car_drift_jacobian(x)
    b = torch.as_tensor(CAR_B, dtype=w.dtype, device=w.device)
    a_cl = a + b @ k
    w_dot = dw[0] * u[..., OMEGA, None, None] + dw[1] * u[..., ACC, None, None]
    cl = closed_loop_condition(a_cl, w, w_dot, rate)
    # d_f W = dW/dtheta * a_theta + dW/dv * a_v with a_theta = a_v = 0 for the car drift
    dw_f = torch.zeros_like(w)
    b_perp = torch.as_tensor(CAR_B_PERP, dtype=w.dtype, device=w.device)
    c1, c2 = uncontrolled_conditions(a, w, dw_f, dw, b_perp, rate)
    w_perp = b_perp.T @ w @ b_perp
    return ContractionTerms(cl=cl, c1=c1, c2=c2, w=w, w_perp=w_perp, a_cl=a_cl)

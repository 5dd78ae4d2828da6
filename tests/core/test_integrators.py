"""Butcher tableaux of the integrators: order conditions, the embedded estimates and the continuous extensions."""

from __future__ import annotations

import math

import pytest
import torch

from density_planner.density.integrators import DOPRI5, RK4, RK43, EmbeddedPair


def _conditions(c, a, b):
    """The eight order conditions up to order 4, as (computed, required) pairs."""
    n = len(b)
    A = [[a[i][j] if j < len(a[i]) else 0.0 for j in range(n)] for i in range(n)]
    Ac = [sum(A[i][j] * c[j] for j in range(n)) for i in range(n)]
    Ac2 = [sum(A[i][j] * c[j] ** 2 for j in range(n)) for i in range(n)]
    AAc = [sum(A[i][j] * Ac[j] for j in range(n)) for i in range(n)]
    rows = [
        (sum(b), 1.0),
        (sum(bi * ci for bi, ci in zip(b, c)), 1 / 2),
        (sum(bi * ci ** 2 for bi, ci in zip(b, c)), 1 / 3),
        (sum(bi * x for bi, x in zip(b, Ac)), 1 / 6),
        (sum(bi * ci ** 3 for bi, ci in zip(b, c)), 1 / 4),
        (sum(bi * ci * x for bi, ci, x in zip(b, c, Ac)), 1 / 8),
        (sum(bi * x for bi, x in zip(b, Ac2)), 1 / 12),
        (sum(bi * x for bi, x in zip(b, AAc)), 1 / 24),
    ]
    return rows


@pytest.mark.parametrize("pair,propagated,embedded", [(RK43, 4, 3), (DOPRI5, 4, 4)])
def test_pairs_meet_the_order_conditions(pair: EmbeddedPair, propagated: int, embedded: int):
    """The propagated solution ``b`` and the embedded one ``b - error`` meet the order conditions of their orders
    (up to 4, the conditions written here); the stage times are the row sums of ``a``; the last row of ``a`` is ``b``
    (the last stage is evaluated at the propagated solution and is the next step's first)."""
    n_cond = {3: 4, 4: 8}
    b_hat = tuple(b - e for b, e in zip(pair.b, pair.error))
    for weights, order in ((pair.b, propagated), (b_hat, embedded)):
        for got, want in _conditions(pair.stages, pair.a, weights)[:n_cond[order]]:
            assert got == pytest.approx(want, abs=1e-12)
    for c, row in zip(pair.stages, pair.a):
        assert sum(row) == pytest.approx(c, abs=1e-12)
    assert pair.a[-1] == pair.b[:-1] and pair.b[-1] == 0.0
    # RK43 is RK4 with the stage at the new state appended
    assert RK43.a[:4] == RK4.a and RK43.b[:4] == RK4.b and RK43.stages[:4] == RK4.stages


def _pendulum(t, y):
    return torch.stack([y[..., 1], -torch.sin(y[..., 0]) + 0.3 * torch.cos(2 * t)], -1)


def _step(pair: EmbeddedPair, y0, h, t0=0.0):
    """One step of ``pair`` on the forced pendulum from ``(t0, y0)``: the new state and the stages."""
    ks = []
    for i, c in enumerate(pair.stages):
        yi = y0 + h * sum(a * k for a, k in zip(pair.a[i], ks)) if i else y0
        ks.append(_pendulum(torch.tensor(t0 + c * h, dtype=torch.float64), yi))
    return y0 + h * sum(b * k for b, k in zip(pair.b, ks)), ks


def _fine(y0, t_end, n=400):
    """A converged solution at ``t_end`` (DOPRI5 at ``t_end / n``)."""
    y = y0
    for i in range(n):
        y, _ = _step(DOPRI5, y, t_end / n, i * t_end / n)
    return y


@pytest.mark.parametrize("pair,order", [(DOPRI5, 4), (RK43, 3)])
def test_continuous_extension_has_its_order(pair: EmbeddedPair, order: int):
    """Inside a step the continuous extension errs by ``O(h^(order + 1))``: halving the step divides its error at
    theta = 0.3, 0.5, 0.7 by about ``2^(order + 1)``; at theta = 0 and 1 it is the step's ends."""
    y0 = torch.tensor([1.0, 0.2], dtype=torch.float64)
    errors = []
    for h in (0.4, 0.2, 0.1):
        y1, ks = _step(pair, y0, h)
        hs = torch.tensor([h], dtype=torch.float64)
        e = 0.0
        for theta in (0.3, 0.5, 0.7):
            got = pair.interpolate(y0[None], y1[None], [k[None] for k in ks], hs, torch.tensor([theta]))
            e = max(e, float((got[0] - _fine(y0, theta * h)).abs().max()))
        errors.append(e)
        ends = pair.interpolate(y0[None].expand(2, 2), y1[None].expand(2, 2), [k[None].expand(2, 2) for k in ks],
                                hs.expand(2), torch.tensor([0.0, 1.0]))
        torch.testing.assert_close(ends, torch.stack([y0, y1]), atol=1e-15, rtol=0)
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    expected = 2.0 ** (order + 1)
    assert all(0.7 * expected < r < 1.4 * expected for r in ratios), (errors, ratios)
    assert math.isfinite(errors[-1]) and errors[-1] < 1e-6


def test_midpoint_weights_are_a_continuous_extension_of_order_3():
    """RK43's ``midpoint`` weights (RK4's stage-only extension at theta = 1/2, without the last stage) err by
    ``O(h^4)`` at the step's middle: halving the step divides the error by about 16; the weights sum to 1/2."""
    assert math.isclose(sum(RK43.midpoint), 0.5) and len(RK43.midpoint) == len(RK43.stages) - 1
    assert DOPRI5.midpoint == ()  # its extension needs the last stage: the loop evaluates the middle after it
    y0 = torch.tensor([1.0, 0.2], dtype=torch.float64)
    errors = []
    for h in (0.4, 0.2, 0.1):
        _, ks = _step(RK43, y0, h)
        mid = y0 + h * sum(w * k for w, k in zip(RK43.midpoint, ks))
        errors.append(float((mid - _fine(y0, 0.5 * h)).abs().max()))
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    assert all(0.7 * 16 < r < 1.4 * 16 for r in ratios), (errors, ratios)


def test_scheme_names_are_the_integrators():
    """The one list of scheme names (``systems.base.LiouvilleScheme``, which configurations, the CLI and the systems
    check against) names exactly the fixed steps and the embedded pairs that exist."""
    from typing import get_args

    from density_planner.density.integrators import INTEGRATORS, PAIRS
    from density_planner.systems.base import LiouvilleScheme

    assert set(get_args(LiouvilleScheme)) == set(INTEGRATORS) | set(PAIRS)
    assert not set(INTEGRATORS) & set(PAIRS)

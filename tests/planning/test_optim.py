"""BatchedAdam's backtracking and the density planner's backtracking rule."""

from __future__ import annotations

import math

import pytest
import torch

from density_planner.planners.density_planner import DensityPlannerConfig, _Backtracker
from density_planner.planners.optim import BatchedAdam


def test_backtrack_restores_forgets_and_halves_the_step():
    params = torch.zeros(3, 2, 4)
    opt = BatchedAdam(params, lr=0.01, update_clip=0.02)
    for _ in range(5):
        opt.step(torch.ones(3, 2, 4))
    assert torch.allclose(params, torch.full_like(params, -0.05), atol=1e-6)  # Adam: lr per step on a steady sign
    to = torch.full_like(params, 0.3)
    back = torch.tensor([False, True, False])
    opt.backtrack(back, to)
    assert torch.equal(params[1], to[1]) and torch.allclose(params[0], torch.full_like(params[0], -0.05))
    assert float(opt.t[1]) == 0 and float(opt.m[1].abs().sum()) == 0 and float(opt.v[1].abs().sum()) == 0
    before = params.clone()
    opt.step(-torch.ones(3, 2, 4))
    assert float((params - before)[1].abs().max()) == pytest.approx(0.005, abs=1e-7)  # fresh moments, half step
    opt.backtrack(back, to)
    before = params.clone()
    opt.step(torch.ones(3, 2, 4))
    assert float((params - before)[1].abs().max()) == pytest.approx(0.0025, abs=1e-7)


def test_backtracker_sends_back_what_exceeds_factor_times_best_plus_slack():
    p = torch.zeros(3, 2)
    bt = _Backtracker(p, factor=2.0, slack=0.1)
    back = bt.observe(torch.tensor([1.0, 1.0, math.nan]), p)
    assert not back.any()  # first evaluations set the best (NaN never does)
    p2 = torch.ones(3, 2)
    back = bt.observe(torch.tensor([2.05, 2.2, 5.0]), p2)
    assert back.tolist() == [False, True, False]  # 2.05 <= 2 * 1 + 0.1; 2.2 above; the third has no best yet
    assert torch.equal(bt.best_params[2], p2[2]) and torch.equal(bt.best_params[0], p[0])
    bt.forget(torch.tensor([True, False, False]))
    assert not bt.observe(torch.tensor([50.0, 0.5, 5.0]), p2)[0]  # a new objective: no best to exceed
    assert bt.count == 1
    off = _Backtracker(p, factor=0.0, slack=0.1)
    off.observe(torch.ones(3), p)
    assert not off.observe(torch.full((3,), 100.0), p).any()


@pytest.mark.parametrize("factor", [0.5, 1.0, math.inf, -1.0])
def test_backtrack_factor_is_validated(factor):
    with pytest.raises(ValueError, match="backtrack_factor"):
        DensityPlannerConfig(backtrack_factor=factor)


def test_backtracking_bounds_every_excursion():
    """A fresh Adam next to a stiff wall (the road barrier): its first steps have size lr whatever the gradient, so
    it jumps into the wall. With the planner's rule an iterate worse than twice the best (plus slack) is followed
    by the best point again, and the last iterate is within the slack of the best."""
    def f(x):
        return 1e-3 * (1.0 - x) + 1e4 * torch.relu(x - 0.905) ** 2

    x = torch.full((1, 1), 0.9)
    opt = BatchedAdam(x, lr=0.01, update_clip=0.02)
    bt = _Backtracker(x, factor=2.0, slack=0.01)
    trace, sent_back = [], []
    for _ in range(100):
        xv = x.detach().requires_grad_(True)
        c = f(xv).sum()
        (g,) = torch.autograd.grad(c, xv)
        trace.append(float(c.detach()))
        back = bt.observe(c.detach().reshape(1), x)
        sent_back.append(bool(back.any()))
        if back.any():
            opt.backtrack(back, bt.best_params)
        else:
            opt.step(g)
    assert bt.count >= 1 and max(trace) > 0.2  # the first step jumped into the wall
    for i, b in enumerate(sent_back[:-1]):
        assert b == (trace[i] > 2 * min(trace[: i + 1]) + 0.01)
        if b:
            assert trace[i + 1] == min(trace[: i + 1])  # back at the best point
    assert trace[-1] <= min(trace) + 0.01

"""Cost terms on hand-built trajectories, the desired-position surrogate and gradients."""

from __future__ import annotations

import functools
import math

import pytest
import torch
from helpers import block_scene, empty_scene

from density_planner.cost.composite import CostConfig, WeightedCost, build_cost
from density_planner.cost.terms import BoundsCost, CollisionCost, CostInputs, GoalCost, InputCost, desired_positions
from density_planner.environment.grid import OccupancyGrid


def _inputs(x, w=None, u=None):
    x = torch.as_tensor(x, dtype=torch.float64)
    if w is None:
        w = torch.full(x.shape[:-1], 1.0 / x.shape[-3], dtype=torch.float64)
    if u is None:
        u = torch.zeros(*x.shape[:-3], x.shape[-2] - 1, 2, dtype=torch.float64)
    return CostInputs(x=x, weights=w, u_ref=u, slices=torch.arange(x.shape[-2]))


def test_goal_cost_hand_value():
    x = torch.zeros(2, 3, 5, dtype=torch.float64)  # N = 2 samples, T = 3
    x[0, -1, :2] = torch.tensor([1.0, 2.0])
    x[1, -1, :2] = torch.tensor([4.0, 6.0])
    w = torch.tensor([[0.5, 0.5, 0.25], [0.5, 0.5, 0.75]], dtype=torch.float64)
    j = GoalCost((1.0, 2.0))(_inputs(x, w))
    # only the final positions count: 0.25 * 0 + 0.75 * (3^2 + 4^2)
    assert float(j) == pytest.approx(0.75 * 25)
    # far factor applies above the threshold only
    assert float(GoalCost((1.0, 2.0), far_factor=10, close_threshold=3)(_inputs(x, w))) == pytest.approx(187.5)
    assert float(GoalCost((4.0, 6.0), far_factor=10, close_threshold=30)(_inputs(x, w))) == pytest.approx(6.25)


def test_input_cost_hand_value():
    u = torch.zeros(1, 4, 2, dtype=torch.float64)
    u[0, :, 0] = torch.tensor([1.0, 2.0, 0.0, 0.0])
    u[0, :, 1] = torch.tensor([0.0, 0.0, 3.0, 0.0])
    j = InputCost()(_inputs(torch.zeros(1, 1, 5, 5), u=u))
    assert float(j) == pytest.approx(1 + 4 + 9)


def test_bounds_cost_hand_value():
    x = torch.zeros(1, 2, 5, dtype=torch.float64)
    x[0, 0] = torch.tensor([11.0, 0.0, 0.0, -0.5, 3.0])  # x above 10 by 1, v below 0 by 0.5
    x[0, 1] = torch.tensor([0.0, -12.0, 0.0, 1.0, -3.0])  # y below -10 by 2
    term = BoundsCost((-10.0, -10.0, -1.0, 0.0, -math.inf), (10.0, 10.0, 1.0, 5.0, math.inf))
    w = torch.tensor([[[0.5, 1.0]]], dtype=torch.float64)[0]
    assert float(term(_inputs(x, w))) == pytest.approx(0.5 * (1.0 + 0.25) + 1.0 * 4.0)


def _weighted(term, x, w):
    """``term`` on states ``x (..., N, T, nx)`` with weights ``w``."""
    return term(CostInputs(x=x, weights=w, u_ref=torch.zeros(x.shape[-2] - 1, 2, dtype=x.dtype),
                           slices=torch.arange(x.shape[-2])))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_bounds_cost_gradients_in_closed_form_equal_autograd(dtype):
    """The bounds term's closed-form gradients (states and weights, weights broadcast over a batch of candidates,
    bounds shorter than the state, infinite bounds) equal autograd's through the clamp; float64 passes gradcheck."""
    g = torch.Generator().manual_seed(4)
    x = (6.0 * torch.randn(3, 7, 11, 5, generator=g, dtype=torch.float64)).to(dtype)
    w = torch.rand(1, 7, 11, generator=g, dtype=torch.float64).to(dtype)
    scale = torch.tensor([1.0, -0.5, 2.0], dtype=dtype)
    tol = {"rtol": 1e-5, "atol": 1e-4} if dtype == torch.float32 else {"rtol": 1e-12, "atol": 1e-12}
    for low, high in (((-5.0, -4.0, -1.0, 0.0, -math.inf), (5.0, 4.0, 1.0, 5.0, math.inf)), ((-3.0, -2.0), (3.0, 2.0))):
        term, n = BoundsCost(low, high), len(low)
        lo, hi = torch.tensor(low, dtype=dtype), torch.tensor(high, dtype=dtype)
        xa, wa = x.clone().requires_grad_(True), w.clone().requires_grad_(True)
        ja = _weighted(term, xa, wa)
        xb, wb = x.clone().requires_grad_(True), w.clone().requires_grad_(True)
        jb = (wb * (xb[..., :n] - torch.clamp(xb[..., :n], lo, hi)).square().sum(-1)).sum(dim=(-1, -2))
        assert float(jb.detach().min()) > 0
        torch.testing.assert_close(ja, jb, **tol)
        grads_a = torch.autograd.grad((ja * scale).sum(), (xa, wa))
        grads_b = torch.autograd.grad((jb * scale).sum(), (xb, wb))
        for u, v in zip(grads_a, grads_b):
            assert u.shape == v.shape and u.dtype == v.dtype
            torch.testing.assert_close(u, v, **tol)
        if dtype == torch.float64:
            small = (x[:, :2, :3].clone().requires_grad_(True), w[:, :2, :3].clone().requires_grad_(True))
            assert torch.autograd.gradcheck(functools.partial(_weighted, term), small)
        with torch.no_grad():  # no graph: the plain expression, the same value
            torch.testing.assert_close(_weighted(term, x, w), (w * term.violation(x)).sum(dim=(-1, -2)))


def test_desired_position_moves_down_the_gradient_and_collision_cost_decreases():
    scene = block_scene()
    grid = scene.grid
    # a point on the ramp right of the block: the occupancy falls towards +x
    xy = torch.tensor([[2.0, -6.0]], dtype=torch.float64)
    p_des, p = desired_positions(grid, xy, torch.tensor([0]), beta=100.0)
    assert 0 < float(p) < 0.9 and float(p_des[0, 0]) > 2.0 and abs(float(p_des[0, 1]) + 6.0) < 1e-6
    term = CollisionCost(grid, beta=100.0)
    x = torch.zeros(1, 1, 1, 5, dtype=torch.float64)
    costs = []
    for px in (1.7, 2.0, 2.3):  # moving down the occupancy gradient
        x[..., 0], x[..., 1] = px, -6.0
        costs.append(float(term(_inputs(x.clone(), torch.ones(1, 1, 1, dtype=torch.float64)))))
    assert costs[0] > costs[1] > costs[2] > 0


def test_plateau_cells_use_wider_stencils():
    scene = block_scene(half_width=2.0)
    xy = torch.tensor([[0.6, -6.0]], dtype=torch.float64)  # inside the flat top of the block
    p_des, p = desired_positions(scene.grid, xy, torch.tensor([0]), beta=100.0)
    assert float(p) == pytest.approx(0.9, abs=1e-6)
    assert float(p_des[0, 0]) == pytest.approx(0.6, abs=1e-6)  # plain gradient: no push at all
    p_des, _ = desired_positions(scene.grid, xy, torch.tensor([0]), beta=100.0, plateau_scales=(5, 15, 25))
    # s = 15 cells reaches the ramp on the +x side only: (0.81 - 0.9) / 2 per cell -> 4.5 cells = 0.45 m push to +x
    assert float(p_des[0, 0]) == pytest.approx(0.6 + 0.45, abs=1e-3)


def test_gradient_matches_grid_gradient():
    g = torch.Generator().manual_seed(0)
    probs = torch.rand(2, 30, 20, generator=g)
    grid = OccupancyGrid(probs, origin=(0.0, 0.0), cell_size=0.5)
    xy = torch.tensor([[3.0, 4.0], [7.5, 2.5]], dtype=torch.float64)
    p_des, _ = desired_positions(grid, xy, torch.tensor(1), beta=2.0)
    c = torch.round(xy / 0.5).long()
    G = grid.gradient()[1, c[:, 0], c[:, 1]].double()
    torch.testing.assert_close(p_des, (c.double() - 2.0 * G) * 0.5)


def test_total_cost_gradcheck_small_grid():
    """Gradcheck of the weighted cost w.r.t. the states and the weights (float64).

    J_C treats P_occ and the desired positions as constants (piecewise constant in the positions), so the
    finite differences use a step small enough not to cross a cell boundary.
    """
    g = torch.Generator().manual_seed(0)
    probs = torch.rand(3, 12, 12, generator=g, dtype=torch.float64)
    grid = OccupancyGrid(probs, origin=(-3.0, -3.0), cell_size=0.5)
    terms = [GoalCost((1.0, 1.0)), InputCost(), BoundsCost((-2.0,) * 5, (2.0,) * 5), CollisionCost(grid, beta=3.0)]
    cost = WeightedCost(terms, {"goal": 1.0, "input": 0.1, "bounds": 2.0, "collision": 0.5})
    x0 = torch.tensor([[[0.1, 0.2, 2.3, 0.0, 0.0], [1.12, -0.61, 0.0, 2.4, 0.0], [2.6, 1.1, 0.0, 0.0, 0.0]],
                       [[-0.87, 0.38, 0.0, 0.0, 0.0], [0.66, 1.59, 0.0, 0.0, -2.2], [-2.6, 0.13, 0.0, 0.0, 0.0]]],
                      dtype=torch.float64, requires_grad=True)
    w0 = torch.rand(2, 3, generator=g, dtype=torch.float64).requires_grad_(True)
    u0 = torch.randn(2, 2, generator=g, dtype=torch.float64).requires_grad_(True)

    def f(x, w, u):
        return cost(CostInputs(x, w, u, torch.arange(3))).total

    assert torch.autograd.gradcheck(f, (x0, w0, u0), eps=1e-6, atol=1e-6)


def test_build_cost_uses_scene_box_and_config():
    scene = empty_scene()
    cost = build_cost(scene, CostConfig(), optimisation=False)
    assert set(cost.terms) == {"goal", "input", "bounds", "collision"}
    assert cost.terms["goal"].far_factor == 1.0
    assert float(cost.terms["bounds"].low[0]) == -9.9 and float(cost.terms["bounds"].high[1]) == 9.9
    assert build_cost(scene).terms["goal"].far_factor == 10.0


def test_bounds_come_from_the_system_planning_bounds():
    """Heading and speed bounds are the system's (the paper's X_MIN_MP / X_MAX_MP for its box, 0.1 inside the speed
    range); the road car's 15 m/s is inside its bounds (the cost once capped every system at the paper's 9.9 m/s)."""
    from density_planner.systems.car import KinematicCar, car_domain

    scene = empty_scene()
    for domain, v_hi in (("paper", 9.9), ("road", 39.9)):
        car = KinematicCar(car_domain(domain))
        bounds = build_cost(scene, system=car).terms["bounds"]
        assert float(bounds.low[3]) == pytest.approx(0.1) and float(bounds.high[3]) == pytest.approx(v_hi)
        assert float(bounds.low[0]) == -9.9 and float(bounds.high[1]) == 9.9
        assert float(bounds.low[2]) == car.config.state_min[2] and float(bounds.high[2]) == car.config.state_max[2]
        x = torch.zeros(1, 1, 3, 5)
        x[..., 3] = 15.0
        assert (float(bounds.violation(x).max()) > 0) == (domain == "paper")


def test_inactive_terms_are_zero_and_skipped():
    scene = block_scene()
    cost = build_cost(scene)
    x = torch.zeros(3, 1, 101, 5)
    x[..., 0], x[..., 1] = 0.33, -6.27  # inside the block, off its centre
    inputs = CostInputs(x, torch.ones(3, 1, 101), torch.zeros(3, 100, 2), torch.arange(101))
    mask = torch.tensor([True, False, True])
    out = cost(inputs, active={"collision": mask})
    assert out.terms["collision"][1] == 0 and (out.terms["collision"][mask] > 0).all()
    full = cost(inputs)
    torch.testing.assert_close(out.terms["collision"][mask], full.terms["collision"][mask])


@pytest.mark.parametrize("kwargs", [{"beta": -1.0}, {"plateau_scales": (0,)}, {"goal_far_factor": 0.5}])
def test_bad_cost_config(kwargs):
    with pytest.raises(ValueError):
        CostConfig(**kwargs)


@pytest.mark.parametrize("memo", [True, False])
def test_point_collision_cost_is_the_paper_sum_with_its_gradient(memo):
    """The point vehicle's J_C reads every state at once: its value is ``sum_ik w P_occ ||p - p_des||^2`` and its
    gradient ``2 w P_occ (p - p_des)`` (P_occ, p_des constants), free cells and states off the map included."""
    g = torch.Generator().manual_seed(3)
    probs = torch.rand(4, 30, 20, generator=g) ** 3
    probs[:, 10:20, :] = 0.0  # a free band
    grid = OccupancyGrid(probs, origin=(0.0, 0.0), cell_size=0.5)
    x = torch.zeros(2, 6, 4, 5, dtype=torch.float64)  # (batch, N, T, nx)
    x[..., :2] = torch.rand(2, 6, 4, 2, generator=g, dtype=torch.float64) * torch.tensor([17.0, 12.0]) - 1.0
    w = torch.rand(2, 6, 4, generator=g, dtype=torch.float64)
    term = CollisionCost(grid, beta=2.0, memo=memo)
    xr = x.clone().requires_grad_(True)
    j = term(CostInputs(x=xr, weights=w, u_ref=torch.zeros(2, 3, 2, dtype=torch.float64), slices=torch.arange(4)))
    k = torch.arange(4).expand(2, 6, 4)
    p_des, p_occ = desired_positions(grid, x[..., :2], k, beta=2.0)
    expected = (w * p_occ * (x[..., :2] - p_des).pow(2).sum(-1)).sum(dim=(-1, -2))
    assert float((p_occ == 0).double().mean()) > 0.2 and float((p_occ > 0).double().mean()) > 0.2
    torch.testing.assert_close(j, expected)
    (grad,) = torch.autograd.grad(j.sum(), xr)
    torch.testing.assert_close(grad[..., :2], 2 * (w * p_occ)[..., None] * (x[..., :2] - p_des))
    assert float(grad[..., 2:].abs().max()) == 0.0


def test_body_collision_cost_dense_and_selected_paths_agree():
    """With the memo every disc centre is read at once; without it only the occupied states are evaluated on the
    autograd graph: the same value and gradient (positions and heading), centres off the map included."""
    from density_planner.risk import CollisionModel
    from density_planner.systems.car import CarConfig, KinematicCar

    g = torch.Generator().manual_seed(5)
    probs = torch.rand(4, 60, 40, generator=g) ** 4
    probs[:, 20:40, :] = 0.0
    grid = OccupancyGrid(probs, origin=(0.0, 0.0), cell_size=0.25)
    model = CollisionModel(grid, KinematicCar(CarConfig(length=2.0, width=0.8)))
    x = torch.zeros(2, 8, 4, 5, dtype=torch.float64)
    x[..., :2] = torch.rand(2, 8, 4, 2, generator=g, dtype=torch.float64) * torch.tensor([16.0, 11.0]) - 0.5
    x[..., 2] = torch.rand(2, 8, 4, generator=g, dtype=torch.float64) * 6.3
    w = torch.rand(2, 8, 4, generator=g, dtype=torch.float64)
    out = []
    for memo in (True, False):
        term = CollisionCost(model, beta=2.0, plateau_scales=(3,), memo=memo)
        assert (term._memo is not None) == memo
        xr = x.clone().requires_grad_(True)
        j = term(CostInputs(x=xr, weights=w, u_ref=torch.zeros(2, 3, 2, dtype=torch.float64), slices=torch.arange(4)))
        out.append((j, torch.autograd.grad(j.sum(), xr)[0]))
    assert float(out[0][0].detach().min()) > 0 and float(out[0][1][..., 2].abs().sum()) > 0
    torch.testing.assert_close(out[0][0], out[1][0])
    torch.testing.assert_close(out[0][1], out[1][1])

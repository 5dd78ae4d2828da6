"""Collision: the body on the grid (disc cover, dilation) and the probability estimators ("is" and "paper")."""

from __future__ import annotations

import math

import pytest
import torch
from helpers import empty_scene

from density_planner.environment.grid import OccupancyGrid
from density_planner.risk import CollisionModel, RiskConfig, collision_probability
from density_planner.risk.body import DiscCover, dilate, dilate_sparse, disc_kernel_rows
from density_planner.systems.base import Footprint
from density_planner.systems.car import CarConfig, KinematicCar
from density_planner.systems.linear import LinearSystem


def _grid(values: torch.Tensor, cell: float = 1.0, origin=(0.0, 0.0)) -> OccupancyGrid:
    return OccupancyGrid(values, origin=origin, cell_size=cell, dt=0.1)


def _paper(grid, x, log_rho=None):
    return collision_probability(grid, x, config=RiskConfig(estimator="paper"), log_rho=log_rho)


# ---------------------------------------------------------------- the paper's estimator (point vehicle)
def test_single_sample_gives_cell_occupancy():
    probs = torch.zeros(3, 5, 5)
    probs[1, 2, 3] = 0.37
    x = torch.tensor([[[0.0, 0.0], [2.1, 2.9], [4.0, 4.0]]])
    for est in ("is", "paper"):
        rep = collision_probability(_grid(probs), x, config=RiskConfig(estimator=est))
        torch.testing.assert_close(rep.per_slice, torch.tensor([0.0, 0.37, 0.0]))
        assert float(rep.max) == float(torch.tensor(0.37)) and abs(float(rep.sum) - 0.37) < 1e-7
        assert float(rep.se.abs().max()) == 0.0 and rep.estimator == est


def test_uniform_density_over_region_gives_mean_occupancy():
    g = torch.Generator().manual_seed(0)
    probs = torch.rand(1, 10, 10, generator=g)
    ii, jj = torch.meshgrid(torch.arange(2, 6), torch.arange(3, 8), indexing="ij")
    centres = torch.stack([ii, jj], -1).reshape(-1, 2).float()
    jitter = torch.tensor([[0.2, 0.2], [-0.2, 0.2], [0.2, -0.2], [-0.2, -0.2]])
    pos = (centres[:, None, :] + jitter[None]).reshape(-1, 1, 2)
    expected = probs[0, 2:6, 3:8].mean()
    torch.testing.assert_close(_paper(_grid(probs), pos).per_slice[0], expected)
    torch.testing.assert_close(collision_probability(_grid(probs), pos).per_slice[0], expected)


def test_paper_density_averaged_within_cell_not_summed():
    probs = torch.zeros(1, 4, 4)
    probs[0, 1, 1] = 1.0
    # three samples in the occupied cell with density 1, one in a free cell: averaging gives P_ego = 1/2
    pos = torch.tensor([[[1.0, 1.0]], [[1.1, 0.9]], [[0.9, 1.2]], [[3.0, 3.0]]])
    torch.testing.assert_close(_paper(_grid(probs), pos, torch.zeros(4, 1)).per_slice, torch.tensor([0.5]))
    rep = _paper(_grid(probs), pos, torch.log(torch.tensor([[1.0], [1.0], [1.0], [10.0]])))
    torch.testing.assert_close(rep.per_slice, torch.tensor([1 / 11]))
    # the importance estimator counts samples: 3 of 4 equally weighted samples collide
    torch.testing.assert_close(collision_probability(_grid(probs), pos).per_slice, torch.tensor([0.75]))


def test_invariant_to_sample_order_and_batched():
    scene = empty_scene()
    g = torch.Generator().manual_seed(1)
    grid = scene.grid.with_probs(torch.rand(scene.grid.shape, generator=g))
    pos = torch.randn(3, 50, 101, 2, generator=g) * 3 + torch.tensor([0.0, -10.0])
    lr = torch.randn(3, 50, 101, generator=g)
    l0 = torch.randn(3, 50, generator=g)
    perm = torch.randperm(50, generator=g)
    for est in ("is", "paper"):
        cfg = RiskConfig(estimator=est)
        rep = collision_probability(grid, pos, config=cfg, log_rho=lr, log_rho0=l0)
        rep2 = collision_probability(grid, pos[:, perm], config=cfg, log_rho=lr[:, perm], log_rho0=l0[:, perm])
        torch.testing.assert_close(rep.per_slice, rep2.per_slice)
        single = collision_probability(grid, pos[1], config=cfg, log_rho=lr[1], log_rho0=l0[1])
        torch.testing.assert_close(rep.per_slice[1], single.per_slice)
        assert rep.per_slice.shape == (3, 101) and ((rep.per_slice >= 0) & (rep.per_slice <= 1)).all()
        assert rep.se.shape == (3, 101) and (rep.ess <= 50 + 1e-3).all()


def test_samples_outside_the_map_collide():
    probs = torch.zeros(1, 4, 4)
    pos = torch.tensor([[[1.0, 1.0]], [[50.0, 50.0]]])
    torch.testing.assert_close(_paper(_grid(probs), pos).per_slice, torch.tensor([0.5]))
    torch.testing.assert_close(collision_probability(_grid(probs), pos).per_slice, torch.tensor([0.5]))


# ------------------------------------------------------------------------- estimators with known answers
def test_uniform_law_identity_flow_exact_integral():
    """rho0 uniform on a box of whole cells, samples from a wider uniform proposal, identity flow: the exact
    P_coll is the mean occupancy of the box's cells; the IS estimate agrees within 4 SE."""
    g = torch.Generator().manual_seed(3)
    probs = torch.rand(2, 20, 20, generator=g, dtype=torch.float64)
    grid = _grid(probs, cell=0.5)
    # law: uniform on [2.25, 6.25] x [1.25, 4.25] = cells i 5..12, j 3..8 (cell edges at half-cells)
    lo, hi = torch.tensor([2.25, 1.25], dtype=torch.float64), torch.tensor([6.25, 4.25], dtype=torch.float64)
    exact = probs[:, 5:13, 3:9].mean(dim=(1, 2))
    n = 40_000
    plo, phi = lo - 1.0, hi + 1.0  # proposal: uniform on a box 1 m wider
    x0 = plo + torch.rand(n, 2, generator=g, dtype=torch.float64) * (phi - plo)
    inside = ((x0 >= lo) & (x0 <= hi)).all(-1)
    log_rho0 = torch.where(inside, -torch.log(torch.prod(hi - lo)), torch.tensor(-1e3, dtype=torch.float64))
    log_q0 = torch.full((n,), -float(torch.log(torch.prod(phi - plo))), dtype=torch.float64)
    x = x0[:, None, :].expand(n, 2, 2)  # identity flow, two time slices
    rep = collision_probability(grid, x, log_rho0=log_rho0, log_q0=log_q0)
    z = (rep.per_slice - exact) / rep.se
    assert z.abs().max() < 4, (rep.per_slice, exact, rep.se)
    assert (rep.se < 0.01).all()


def test_linear_gaussian_half_plane_closed_form():
    """x' = A x with a Gaussian initial law: x(t) ~ N(e^{At} m, e^{At} S e^{At}^T); a half-plane obstacle
    P_occ = 1 for cell centres with x >= c: P_coll(t) = 1 - Phi((c - h/2 - mu_x(t)) / sigma_x(t)) (nearest cell)."""
    a = torch.tensor([[-0.3, 0.4], [0.0, -0.1]], dtype=torch.float64)
    system = LinearSystem(a.tolist(), [[1.0], [0.0]])
    h, c = 0.1, 1.0
    xs = torch.arange(-5.0, 5.0 + 1e-9, h, dtype=torch.float64)
    occ = (xs >= c - 1e-9).to(torch.float64)[:, None].expand(len(xs), 201)  # y in [-10, 10]: all samples inside
    grid = _grid(occ[None].expand(5, -1, -1).clone(), cell=h, origin=(-5.0, -10.0))
    m = torch.tensor([0.2, 1.5], dtype=torch.float64)
    s = torch.tensor([[0.3, 0.05], [0.05, 0.1]], dtype=torch.float64)
    times = torch.arange(5, dtype=torch.float64) * 0.5
    g = torch.Generator().manual_seed(4)
    n = 20_000
    # proposal: a Gaussian twice as wide (importance weights are needed)
    sq = 4 * s
    lq = torch.linalg.cholesky(sq)
    x0 = m + torch.randn(n, 2, generator=g, dtype=torch.float64) @ lq.T
    law = torch.distributions.MultivariateNormal(m, s)
    prop = torch.distributions.MultivariateNormal(m, sq)
    flows = torch.linalg.matrix_exp(a[None] * times[:, None, None])  # (T, 2, 2)
    x = torch.einsum("tij,nj->nti", flows, x0)
    rep = collision_probability(grid, x, system=system, log_rho0=law.log_prob(x0), log_q0=prop.log_prob(x0))
    mu = flows @ m
    var = (flows @ s @ flows.transpose(-1, -2))[:, 0, 0]
    normal = torch.distributions.Normal(0.0, 1.0)
    exact = 1 - normal.cdf((c - h / 2 - mu[:, 0]) / var.sqrt())
    z = (rep.per_slice - exact) / rep.se
    assert z.abs().max() < 4, (rep.per_slice, exact, rep.se)


# ------------------------------------------------------------------------------------------ the body
def test_disc_kernel_hand_count():
    assert disc_kernel_rows(0.0) == {0: 0}
    # rho = 0.5: squares within half a cell of the centre square: the 3 x 3 block
    assert sum(2 * a + 1 for a in disc_kernel_rows(0.5).values()) == 9
    # rho = 1.5: rows -2..2; rows 0, +-1 reach |di| <= 2; rows +-2 (gap 1) reach 1 + floor(sqrt(2.25 - 1)) = 2
    assert disc_kernel_rows(1.5) == {-2: 2, -1: 2, 0: 2, 1: 2, 2: 2}
    # rho = 1.0: rows +-2 have gap 1 -> sqrt(0) -> |di| <= 1
    assert disc_kernel_rows(1.0) == {-2: 1, -1: 2, 0: 2, 1: 2, 2: 1}
    probs = torch.zeros(1, 9, 9)
    probs[0, 4, 4] = 0.5
    d = dilate(probs, 1.0)
    assert int((d > 0).sum()) == 5 + 5 + 5 + 3 + 3 and float(d.max()) == 0.5


def test_dilate_matches_brute_force():
    g = torch.Generator().manual_seed(5)
    probs = torch.rand(2, 30, 25, generator=g)
    for rho in (0.7, 2.3, 4.0):
        rows = disc_kernel_rows(rho)
        pad = 8
        p = torch.nn.functional.pad(probs, (pad, pad, pad, pad))
        ref = torch.zeros_like(probs)
        for dj, a in rows.items():
            for di in range(-a, a + 1):
                ref = torch.maximum(ref, p[:, pad + di:pad + di + 30, pad + dj:pad + dj + 25])
        torch.testing.assert_close(dilate(probs, rho), ref)


@pytest.mark.parametrize(("shape", "rho", "tile"), [((3, 70, 45), 2.3, 8), ((2, 33, 64), 7.1, 32),
                                                   ((4, 100, 101), 12.5, 8), ((1, 5, 6), 1.0, 32),
                                                   ((2, 40, 40), 0.0, 16)])
def test_dilate_sparse_equals_dense(shape, rho, tile):
    """Tiles dilated with their halo (strided blocks inside, clamped indices at the border, tiles cut at the
    border, tiles narrower than the reach) give the dense dilation exactly, also quantised to bytes."""
    g = torch.Generator().manual_seed(7)
    probs = torch.rand(shape, generator=g) * (torch.rand(shape, generator=g) < 0.01)
    probs[0, 0, 0], probs[-1, -1, -1] = 1.0, 0.3  # occupied corners: the border paths
    assert torch.equal(dilate_sparse(probs, rho, tile=tile, max_chunk=5000), dilate(probs, rho))
    q = torch.mul(probs, 255).sub_(1e-4).ceil_().clamp_(0, 255).to(torch.uint8)
    assert torch.equal(dilate_sparse(probs, rho, tile=tile, levels=255), dilate(q, rho).float().div_(255))
    assert torch.equal(dilate_sparse(torch.zeros(shape), rho, tile=tile), torch.zeros(shape))
    with pytest.raises(ValueError, match="levels"):
        dilate_sparse(probs, rho, levels=256)
    # ignored cells (a road's off-road cells, at 1.0 in the scene's grid) read as 0: equal to dilating the masked
    # grid, whether a tile is wholly ignored, wholly kept or cut by the mask (also at the border)
    ignore = torch.zeros(shape[1:], dtype=torch.bool)
    ignore[: shape[1] // 3] = True
    ignore[:, -(shape[2] // 4 + 1):] = True
    ignore[shape[1] // 2, 1:3] = True
    walled = probs.masked_fill(ignore, 1.0)
    assert torch.equal(dilate_sparse(walled, rho, tile=tile, max_chunk=5000, ignore=ignore),
                       dilate(probs.masked_fill(ignore, 0.0), rho))
    assert torch.equal(dilate_sparse(walled, rho, tile=tile, levels=255, ignore=ignore),
                       dilate_sparse(walled.masked_fill(ignore, 0.0), rho, tile=tile, levels=255))
    with pytest.raises(ValueError, match="ignore"):
        dilate_sparse(probs, rho, ignore=ignore[1:])


def test_disc_cover_contains_rectangle_and_area_excess():
    fp = Footprint(4.5, 1.8)
    cover = DiscCover.of(fp, has_heading=True)
    assert cover.n == 4 and cover.radius == pytest.approx(math.hypot(4.5 / 8, 0.9))
    assert cover.area_excess() == pytest.approx(0.278, abs=0.002)
    # every point of the rectangle lies in some disc
    g = torch.Generator().manual_seed(6)
    pts = (torch.rand(20000, 2, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([4.5, 1.8], dtype=torch.float64)
    centres = torch.tensor([[s, 0.0] for s in cover.offsets], dtype=torch.float64)
    d = (pts[:, None] - centres[None]).norm(dim=-1).amin(-1)
    assert (d <= cover.radius + 1e-12).all()
    assert DiscCover.of(Footprint(), has_heading=True).radius == 0.0
    assert DiscCover.of(Footprint(2.0, 2.0), has_heading=False).radius == 1.0


def _single_cell_hits(car, pose, n=61, h=0.1):
    """Which cells, when they alone are occupied, make the car at ``pose`` collide: ``(n, n)`` bool."""
    cells = torch.zeros(n * n, n, n)
    cells.view(n * n, -1)[torch.arange(n * n), torch.arange(n * n)] = 1.0
    half = (n - 1) // 2 * h
    grid = OccupancyGrid(cells, origin=(-half, -half), cell_size=h, dt=0.1)
    model = CollisionModel(grid, car)
    # one time per slice: slice k holds cell k alone
    xs = torch.tensor(pose, dtype=torch.float32).expand(1, n * n, 5)
    occ = model.occupancy(xs, torch.arange(n * n))[0]
    return (occ > 0).reshape(n, n), grid


def _rectangle_cells(pose, length, width, grid):
    """Cells whose square intersects the rotated rectangle (separating-axis test), by hand."""
    px, py, th = pose[0], pose[1], pose[2]
    _, nx, ny = grid.shape
    h = grid.cell_size
    ii, jj = torch.meshgrid(torch.arange(nx), torch.arange(ny), indexing="ij")
    cx = grid.origin[0] + ii * h - px
    cy = grid.origin[1] + jj * h - py
    u = torch.tensor([math.cos(th), math.sin(th)])
    v = torch.tensor([-math.sin(th), math.cos(th)])
    ok = torch.ones(nx, ny, dtype=torch.bool)
    # axes of the rectangle
    for ax, half in ((u, length / 2), (v, width / 2)):
        proj = cx * ax[0] + cy * ax[1]
        r = h / 2 * (abs(ax[0]) + abs(ax[1]))
        ok &= (proj - r < half - 1e-9) & (proj + r > -half + 1e-9)
    # axes of the cell
    corners = torch.tensor([[sx * length / 2, sy * width / 2] for sx in (-1, 1) for sy in (-1, 1)])
    world = corners[:, 0:1] * u + corners[:, 1:2] * v  # (4, 2)
    for k in range(2):
        lo, hi = float(world[:, k].min()), float(world[:, k].max())
        c = cx if k == 0 else cy
        ok &= (c - h / 2 < hi - 1e-9) & (c + h / 2 > lo + 1e-9)
    return ok


@pytest.mark.parametrize("theta", [0.0, math.pi / 2, 0.5236, 2.0])
def test_body_occupancy_covers_the_rectangle(theta):
    """A car 2.0 m x 0.8 m on 0.1-m cells: every cell the rotated rectangle covers (hand-counted by separating
    axes) is seen by the body; the cells seen beyond it stay within the disc cover's excess plus one cell."""
    car = KinematicCar(CarConfig(length=2.0, width=0.8))
    pose = (0.0, 0.0, theta, 1.0, 0.0)
    hits, grid = _single_cell_hits(car, pose)
    rect = _rectangle_cells(pose, 2.0, 0.8, grid)
    assert not bool((rect & ~hits).any()), "a cell under the rectangle is not seen"
    cover = DiscCover.of(car.footprint, has_heading=True)
    # area seen <= area of the cover grown by one cell diagonal (snap + cell squares)
    grown = (1 + cover.area_excess()) * 2.0 * 0.8 + 2 * (2.0 + 0.8 + 2 * cover.radius) * 0.15 + 0.1
    assert int(hits.sum()) * 0.01 <= grown
    if theta == 0.0:  # axis-aligned: 20 x 8 cells of the rectangle (cell centres strictly inside) + the rim
        assert int(rect.sum()) == 21 * 9


def test_point_footprint_is_the_paper_lookup():
    probs = torch.rand(3, 6, 7, generator=torch.Generator().manual_seed(7))
    car = KinematicCar(CarConfig(length=0.0, width=0.0))
    x = torch.tensor([[[1.2, 2.6, 0.3, 1.0, 0.0]] * 3])
    a = CollisionModel(_grid(probs), car).occupancy(x)
    b = CollisionModel(_grid(probs), car, RiskConfig(body=False)).occupancy(x)
    torch.testing.assert_close(a, probs[:, 1, 3][None])
    torch.testing.assert_close(a, b)


def test_collision_surrogate_gradcheck_float64_through_the_body():
    """J_C with the car's body is differentiable in the states (positions and heading) in float64: finite
    differences agree with autograd away from cell boundaries (P_occ and p_des are constants per cell)."""
    from density_planner.cost.terms import CollisionCost, CostInputs

    g = torch.Generator().manual_seed(8)
    probs = torch.rand(3, 60, 60, generator=g, dtype=torch.float64) ** 4
    grid = OccupancyGrid(probs, origin=(-3.0, -3.0), cell_size=0.1, dt=0.1)
    car = KinematicCar(CarConfig(length=1.5, width=0.6))
    term = CollisionCost(CollisionModel(grid, car), beta=3.0)
    assert term.collision.cover.n == 4
    x = torch.zeros(2, 3, 3, 5, dtype=torch.float64)  # (batch, N, T, nx)
    x[..., 0:2] = (torch.rand(2, 3, 3, 2, generator=g, dtype=torch.float64) - 0.5) * 2.0
    x[..., 2] = torch.rand(2, 3, 3, generator=g, dtype=torch.float64) * 6.0
    w = torch.softmax(torch.randn(2, 3, 3, generator=g, dtype=torch.float64), dim=1)

    def j(xx):
        return term(CostInputs(x=xx, weights=w, u_ref=torch.zeros(2, 2, 2, dtype=torch.float64),
                               slices=torch.arange(3)))

    xr = x.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(j, (xr,), eps=1e-7, atol=1e-6)
    # the heading gets a gradient (the body turns away from occupancy)
    (grad,) = torch.autograd.grad(j(xr).sum(), xr)
    assert float(grad[..., 2].abs().sum()) > 0


def test_collision_at_some_time_counts_each_execution_once():
    """Two equally likely executions, each in an occupied cell at a different instant: the worst instant reads 0.5,
    collision at some time is certain; a single trajectory reads its own worst instant with SE 0."""
    probs = torch.zeros(3, 10, 10)
    probs[1, 2, 2] = 1.0
    probs[2, 7, 7] = 1.0
    grid = _grid(probs)
    x = torch.tensor([[[2.0, 2.0]] * 3, [[7.0, 7.0]] * 3])  # (N=2, T=3, 2)
    rep = collision_probability(grid, x)
    assert rep.max == pytest.approx(0.5) and rep.any_time == pytest.approx(1.0) and rep.any_time_se == 0
    one = collision_probability(grid, x[:1])
    assert one.any_time == pytest.approx(1.0) and one.any_time_se == 0
    assert collision_probability(grid, x, config=RiskConfig(estimator="paper")).any_time is None
    assert rep.to_dict()["any_time"] == pytest.approx(1.0)


def test_collision_at_some_time_union_bound():
    """The upper bound sum_i w_i min(1, sum_k P_body): one execution that reads 0.3 at one instant and 0.4 at
    another lies in [0.4, 0.7] (the joint law decides where); capped at 1; equal to the lower bound when each
    execution meets occupancy at one instant only."""
    probs = torch.zeros(3, 10, 10)
    probs[1, 2, 2] = 0.3
    probs[2, 2, 2] = 0.4
    probs[0, 7, 7] = 0.9
    probs[2, 7, 7] = 0.8
    grid = _grid(probs)
    x = torch.tensor([[[2.0, 2.0]] * 3, [[7.0, 7.0]] * 3])  # (N=2, T=3, 2)
    one = collision_probability(grid, x[:1])
    assert one.any_time == pytest.approx(0.4) and one.any_time_upper == pytest.approx(0.7)
    assert one.any_time_upper_se == 0
    both = collision_probability(grid, x)  # second execution: 0.9 + 0.8 capped at 1
    assert both.any_time == pytest.approx((0.4 + 0.9) / 2) and both.any_time_upper == pytest.approx((0.7 + 1.0) / 2)
    # SE^2 = sum_i w_i^2 (v_i - m)^2 = 2 * 0.25 * 0.15^2
    assert both.any_time_upper_se == pytest.approx(math.sqrt(2 * 0.25 * 0.15**2), abs=1e-6)
    d = both.to_dict()
    assert d["any_time_upper"] == pytest.approx(0.85) and d["any_time"] <= d["any_time_upper"]
    # hits confined to one instant per execution: the bounds meet
    probs2 = torch.zeros(3, 10, 10)
    probs2[1, 2, 2] = 1.0
    probs2[2, 7, 7] = 0.6
    rep = collision_probability(_grid(probs2), x)
    assert rep.any_time == pytest.approx(rep.any_time_upper) == pytest.approx(0.8)
    assert collision_probability(grid, x, config=RiskConfig(estimator="paper")).any_time_upper is None


def test_collision_at_some_time_importance_weighted_agrees_with_monte_carlo():
    """The importance-weighted P_any from a proposal twice as wide agrees, within its standard errors, with plain
    Monte Carlo from the law itself; and it is never below the worst instant."""
    a = torch.tensor([[-0.3, 0.4], [0.0, -0.1]], dtype=torch.float64)
    system = LinearSystem(a.tolist(), [[1.0], [0.0]])
    h = 0.1
    xs = torch.arange(-5.0, 5.0 + 1e-9, h, dtype=torch.float64)
    # a band x in [0.8, 1.2] occupied at every instant with probability 0.7
    occ = (0.7 * ((xs >= 0.8 - 1e-9) & (xs <= 1.2 + 1e-9)).to(torch.float64))[:, None].expand(len(xs), 201)
    grid = _grid(occ[None].expand(5, -1, -1).clone(), cell=h, origin=(-5.0, -10.0))
    m = torch.tensor([0.2, 1.5], dtype=torch.float64)
    s = torch.tensor([[0.3, 0.05], [0.05, 0.1]], dtype=torch.float64)
    flows = torch.linalg.matrix_exp(a[None] * (torch.arange(5, dtype=torch.float64) * 0.5)[:, None, None])
    law = torch.distributions.MultivariateNormal(m, s)
    prop = torch.distributions.MultivariateNormal(m, 4 * s)
    g = torch.Generator().manual_seed(8)
    x0 = m + torch.randn(20_000, 2, generator=g, dtype=torch.float64) @ torch.linalg.cholesky(4 * s).T
    rep = collision_probability(grid, torch.einsum("tij,nj->nti", flows, x0), system=system,
                                log_rho0=law.log_prob(x0), log_q0=prop.log_prob(x0))
    y0 = m + torch.randn(20_000, 2, generator=g, dtype=torch.float64) @ torch.linalg.cholesky(s).T
    ref = collision_probability(grid, torch.einsum("tij,nj->nti", flows, y0), system=system)
    assert 0.1 < float(ref.any_time) < 0.6 and float(rep.any_time) >= float(rep.max)
    assert abs(float(rep.any_time - ref.any_time)) < 4 * math.hypot(float(rep.any_time_se), float(ref.any_time_se))


def _blobs(T=12, NX=70, NY=60, seed=0):
    """A grid with a few random blobs per slice (values in [0, 1], zeros elsewhere)."""
    g = torch.Generator().manual_seed(seed)
    probs = torch.zeros(T, NX, NY)
    for t in range(T):
        for _ in range(3):
            i, j = int(torch.randint(5, NX - 5, (1,), generator=g)), int(torch.randint(5, NY - 5, (1,), generator=g))
            probs[t, i - 3 : i + 4, j - 2 : j + 3] = torch.rand(7, 5, generator=g)
    return OccupancyGrid(probs, origin=(-3.0, 2.0), cell_size=0.25, dt=0.1, t0=1.0)


@pytest.mark.parametrize("k0,n", [(0, 12), (3, 6), (8, 7), (15, 3)])  # inside, inside, past the end, beyond it
@pytest.mark.parametrize("with_mask", [False, True])
def test_window_reads_the_parents_derived_grids_exactly(k0, n, with_mask, monkeypatch):
    """A window's body grid (and masked grid) are rows of the parent's, equal cell for cell to deriving them from a
    fresh grid of the window's slices; the parent is dilated once for any number of windows."""
    from density_planner.risk import body as body_mod

    grid = _blobs()
    mask = None
    if with_mask:
        mask = torch.zeros(grid.shape[1:], dtype=torch.bool)
        mask[:, :9] = True
        mask[40:47, 20:33] = True
    win = grid.window(k0, n)
    idx = torch.arange(k0, k0 + n).clamp(max=grid.n_slices - 1)
    assert torch.equal(win.probs, grid.probs[idx]) and win.t0 == pytest.approx(grid.t0 + k0 * grid.dt)
    fresh = OccupancyGrid(grid.probs[idx].clone(), grid.origin, grid.cell_size, grid.dt, win.t0)
    calls = []

    class Counting(body_mod.LazyDilatedGrid):
        def __init__(self, *a, **k):
            calls.append(1)
            super().__init__(*a, **k)

    monkeypatch.setattr(body_mod, "LazyDilatedGrid", Counting)
    for radius in (0.0, 1.1):
        got = body_mod.body_grid(win, radius, ignore=mask)
        want = body_mod.body_grid(fresh, radius, ignore=mask)
        assert torch.equal(got.probs, want.probs) and got.t0 == want.t0 and got.shape == want.shape
    n_before = len(calls)  # the parent's dilation and the fresh grid's
    assert n_before == 2
    other = grid.window(max(k0 - 1, 0), n)
    body_mod.body_grid(other, 1.1, ignore=mask)
    win.drop_caches()  # forgets the window's derived grids, not where its slices come from
    assert torch.equal(body_mod.body_grid(win, 1.1, ignore=mask).probs, want.probs)
    assert len(calls) == n_before  # both read from the parent's cached dilation
    # the oracle prediction's windows are such windows
    from density_planner.environment.prediction import OraclePrediction
    from density_planner.environment.scene import Scene

    scene = Scene(grid, (0.0, 5.0, 0.0, 1.0), (10.0, 10.0), (-2.0, 13.0, 3.0, 15.0), name="blobs")
    w = OraclePrediction(scene).window(grid.t0 + 0.2, 0.5)
    assert w._cache[OccupancyGrid.WINDOW_OF][0] is scene.grid and torch.equal(w.probs, grid.probs[2:8])


@pytest.mark.parametrize("with_mask", [False, True])
def test_lazy_body_grid_dilates_what_is_read_and_equals_the_sparse_dilation(with_mask):
    """The body grid dilates a tile when a cell of it is first read; every read (cells, lookups, the whole grid)
    equals dilate_sparse's values (levels of 1/255) cell for cell, and only the tiles read are dilated."""
    from density_planner.risk.body import _LEVELS, LazyDilatedGrid, body_grid

    grid = _blobs(T=9, NX=150, NY=130)
    mask = None
    if with_mask:
        mask = torch.zeros(grid.shape[1:], dtype=torch.bool)
        mask[:, :20] = True
        mask[60:80, 40:90] = True
    rho = 1.1 / grid.cell_size
    want = dilate_sparse(grid.probs, rho, levels=_LEVELS, ignore=mask)
    lazy = body_grid(grid, 1.1, ignore=mask)
    assert isinstance(lazy, LazyDilatedGrid) and body_grid(grid, 1.1, ignore=mask) is lazy  # cached on the grid
    total = lazy.remaining_tiles
    assert lazy.shape == grid.shape and lazy.device == grid.device and lazy.to(grid.device) is lazy
    assert lazy.remaining_tiles == total  # nothing dilated by shape, device or to()
    g = torch.Generator().manual_seed(5)
    k = torch.randint(0, 9, (40,), generator=g)
    i, j = torch.randint(0, 150, (40,), generator=g), torch.randint(0, 130, (40,), generator=g)
    assert torch.equal(lazy.cell_values(k, i, j), want[k, i, j])
    read = total - lazy.remaining_tiles
    assert 0 < read <= 40 and read == len({(int(a), int(b) // 32, int(c) // 32) for a, b, c in zip(k, i, j)})
    xy = grid.cell_to_world(torch.rand(200, 2, generator=g) * torch.tensor([149.0, 129.0]))
    kk = torch.randint(0, 9, (200,), generator=g)
    assert torch.equal(lazy.lookup(xy, kk), OccupancyGrid(want, grid.origin, grid.cell_size, grid.dt, grid.t0)
                       .lookup(xy, kk))
    # a window's body grid reads through the parent: its cells equal the parent's rows, the last one held
    left = lazy.remaining_tiles
    win = body_grid(grid.window(6, 5), 1.1, ignore=mask)
    assert win.shape == (5, 150, 130) and lazy.remaining_tiles == left and win.to(grid.device) is win
    kw = torch.randint(0, 5, (40,), generator=g)
    assert torch.equal(win.cell_values(kw, i, j), want[(kw + 6).clamp(max=8), i, j])
    assert 0 < left - lazy.remaining_tiles <= 40
    assert torch.equal(win.probs, want[torch.tensor([6, 7, 8, 8, 8])])
    assert torch.equal(lazy.probs, want) and lazy.remaining_tiles == 0  # the whole grid on demand
    assert torch.equal(lazy.cell_values(k, i, j), want[k, i, j])
    assert lazy.to(dtype=torch.float64).probs.dtype == torch.float64


def test_window_rejects_bad_ranges():
    grid = _blobs(T=3)
    with pytest.raises(ValueError, match="k0 >= 0 and n >= 1"):
        grid.window(-1, 2)
    with pytest.raises(ValueError, match="k0 >= 0 and n >= 1"):
        grid.window(0, 0)

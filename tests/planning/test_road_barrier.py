"""The road barrier: zero on the road, more than any collision cost off it, a gradient back everywhere, and
consistent with the verdict's on-road test (the rectangle covered by the drivable area)."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import torch
from road_helpers import drivable, lane_graph, road_scene

from density_planner.cost.composite import CostConfig, build_cost
from density_planner.cost.road import RoadBarrierCost, RoadCostConfig, vehicle_outline
from density_planner.cost.terms import CollisionCost, CostInputs
from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.road import GoalRegion
from density_planner.environment.road_sdf import RoadSDF
from density_planner.risk.collision import CollisionModel

ROAD = shapely.box(0, 0, 100, 7)  # two 3.5-m lanes


@pytest.fixture(scope="module")
def barrier() -> RoadBarrierCost:
    sdf = RoadSDF.from_geometry(ROAD, (-20, 120, -20, 27), cell_size=0.2, dtype=torch.float64)
    return RoadBarrierCost(sdf, length=4.5, width=1.8, margin=0.15, spacing=0.5)


def _poses(xy_theta):
    p = torch.as_tensor(xy_theta, dtype=torch.float64).reshape(-1, 3)
    x = torch.zeros(p.shape[0], 5, dtype=torch.float64)
    x[:, :3] = p
    x[:, 3] = 5.0
    return x


def test_outline_has_corners_and_bounded_spacing():
    pts = vehicle_outline(4.5, 1.8, 1.0)
    for c in ([2.25, 0.9], [-2.25, 0.9], [-2.25, -0.9], [2.25, -0.9]):
        assert np.min(np.linalg.norm(pts - np.array(c), axis=1)) < 1e-12
    ring = np.vstack([pts, pts[:1]])
    assert np.linalg.norm(np.diff(ring, axis=0), axis=1).max() <= 1.0 + 1e-12


def test_zero_in_lane_positive_at_the_edge_and_off_road(barrier):
    x = _poses([[50, 1.75, 0.0], [50, 5.25, 0.0], [50, 6.5, 0.0], [50, 12.0, 0.0], [50, 1.75, 1.2]])
    c = barrier.per_state(x)
    assert float(c[0]) == 0.0 and float(c[1]) == 0.0  # centred in either lane
    assert float(c[2]) > 0 and float(c[3]) > float(c[2])  # over the edge, then fully off
    assert float(c[4]) > 0  # turned across the lane: the corners leave the road


def test_margin_weight_splits_the_barrier_between_the_margin_and_the_edge(barrier):
    """mu = margin_weight: inside the road the barrier is mu times the full one (mu = 1; the margin zone priced at mu),
    beyond the edge it is mu phi(sdf + margin) + (1 - mu) phi(sdf) with slope >= 1 per metre (finite differences);
    mu = 1 is the full barrier."""
    full = barrier
    lateral = torch.linspace(4.4, 6.8, 49, dtype=torch.float64)  # the car's left side from 0.26 m inside to 0.9 m out
    x = _poses(torch.stack([torch.full_like(lateral, 50.0), lateral, torch.zeros_like(lateral)], -1))
    d = full._sdf_outline(x)  # (P, n)
    ref = torch.relu(d + full.margin)
    whole = RoadBarrierCost(full.sdf, length=4.5, width=1.8, margin=0.15, spacing=0.5, margin_weight=1.0)
    for mu in (1.0, 0.1, 0.0):
        b = RoadBarrierCost(full.sdf, length=4.5, width=1.8, margin=0.15, spacing=0.5, margin_weight=mu)
        e = torch.relu(d)
        expect = (mu * ref * (1 + ref) + (1 - mu) * e * (1 + e)).sum(0)
        got = b.per_state(x)
        assert torch.allclose(got, expect, atol=1e-12)
        inside = d.amax(0) <= 0
        assert torch.allclose(got[inside], mu * whole.per_state(x)[inside], atol=1e-12)
        out = d.amax(0) > 0.02
        slope = torch.diff(got[out]) / torch.diff(lateral[out])
        assert bool((slope >= 0.99).all())  # at least one outline point's slope of 1 per m, at any mu
    assert full.margin_weight == RoadCostConfig().margin_weight  # the fixture (no margin_weight given): the default
    with pytest.raises(ValueError, match="margin_weight"):
        RoadBarrierCost(full.sdf, margin_weight=1.5)
    with pytest.raises(ValueError, match="margin_weight"):
        RoadCostConfig(margin_weight=-0.1)


def test_off_road_costs_more_than_any_collision(barrier):
    """One state whose rectangle crosses the road's edge costs (weighted) more than the largest collision cost
    one state can have: P_occ = 1 with the steepest occupancy gradient the grid allows (0.5 per cell)."""
    cfg = CostConfig()
    for cell in (0.1, 0.2):
        n = 41
        probs = torch.zeros(1, n, n, dtype=torch.float64)
        probs[0, n // 2 + 1:, :] = 1.0  # a step: gradient 0.5 per cell at the cell next to it
        probs[0, n // 2, :] = 1.0
        grid = OccupancyGrid(probs, origin=(0.0, 0.0), cell_size=cell, dt=0.1)
        coll = CollisionCost(CollisionModel(grid), beta=cfg.beta, plateau_scales=cfg.plateau_scales)
        xs = torch.zeros(n, n, 5, dtype=torch.float64)
        xs[..., 0] = grid.xs[:, None]
        xs[..., 1] = grid.ys[None, :]
        worst = cfg.weights.collision * coll(CostInputs.single(xs.reshape(-1, 1, 5),
                                                               torch.zeros(n * n, 0, 2, dtype=torch.float64),
                                                               torch.zeros(1, dtype=torch.long))).max()
        assert float(worst) > 0
        # the car 0.05 m over the edge with one corner
        edge = _poses([[50, 7.0 - 0.9 + 0.05, 0.0]])
        assert float(cfg.road.weight * barrier.per_state(edge)[0]) > float(worst)


def test_gradient_points_back_to_the_road_everywhere_off_it(barrier):
    for y in (8.0, 15.0, 40.0, 200.0):  # beyond the edge, deep off the road, outside the SDF's lattice
        x = _poses([[50, y, 0.0]]).requires_grad_(True)
        (g,) = torch.autograd.grad(barrier.per_state(x).sum(), x)
        assert float(g[0, 1]) > 1.0, y  # descending moves the car towards the road (-y)


def test_consistent_with_the_verdicts_on_road():
    """Where every outline point is at least the margin inside the road the rectangle is on the road (shapely
    ``covers``); where the largest outline SDF is positive it is not."""
    graph = lane_graph()
    area = drivable(graph)
    sdf = RoadSDF.from_geometry(area, (-10, 160, -30, 20), cell_size=0.2, dtype=torch.float64)
    barrier = RoadBarrierCost(sdf, length=4.5, width=1.8, margin=0.15, spacing=0.5)
    gen = np.random.default_rng(1)
    poses = np.column_stack([gen.uniform(0, 150, 3000), gen.uniform(-25, 10, 3000), gen.uniform(-np.pi, np.pi, 3000)])
    x = _poses(poses)
    pen = barrier.penetration(x).numpy()
    hl, hw = 2.25, 0.9
    corners = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    px = poses[:, None, 0] + c[:, None] * corners[:, 0] - s[:, None] * corners[:, 1]
    py = poses[:, None, 1] + s[:, None] * corners[:, 0] + c[:, None] * corners[:, 1]
    on_road = shapely.covers(area, shapely.polygons(np.stack([px, py], axis=-1)))
    assert (pen <= -0.15).sum() > 100 and (pen > 0).sum() > 100  # both kinds are tested
    assert on_road[pen <= -0.15].all()
    assert not on_road[pen > 0.05].any()


def test_build_cost_barrier_on_road_scene():
    goal = GoalRegion(shapely.box(85, 0.5, 95, 3.0), (9.0, 10.0))
    cost = build_cost(road_scene(goal), CostConfig())
    x = _poses([[20, 1.75, 0.0], [20, 12.0, 0.0]]).float()
    inp = CostInputs.single(x[:, None, :].expand(2, 11, 5).contiguous(), torch.zeros(2, 10, 2))
    out = cost(inp)
    assert float(out.terms["road"][0]) == 0.0 and float(out.terms["road"][1]) > 0
    assert cost.weights["road"] == CostConfig().road.weight


def test_density_planner_weighs_the_sample_cloud_with_the_sample_weight():
    """Stage 2 and the reported cost read the cloud's barrier at ``cost.road.sample_weight``; the reference keeps
    ``cost.road.weight`` (times ``reference_weight``); ``None`` keeps one weight for both."""
    from dataclasses import replace

    from density_planner.planners.density_planner import DensityPlanner, DensityPlannerConfig

    goal = GoalRegion(shapely.box(85, 0.5, 95, 3.0), (9.0, 10.0))
    cost = build_cost(road_scene(goal), CostConfig())
    x = _poses([[20, 1.75, 0.0], [20, 12.0, 0.0]]).float()
    inp = CostInputs.single(x[:, None, :].expand(2, 11, 5).contiguous(), torch.zeros(2, 10, 2))
    for sample_weight in (7.0, None):
        cfg = DensityPlannerConfig(cost=replace(CostConfig(), road=RoadCostConfig(sample_weight=sample_weight)))
        on_samples = DensityPlanner(predictor=None, config=cfg)._sample_objective(cost)  # type: ignore[arg-type]
        w = cost.weights["road"] if sample_weight is None else sample_weight
        assert on_samples.weights["road"] == w and cost.weights["road"] == RoadCostConfig().weight
        a, b = on_samples(inp), cost(inp)
        torch.testing.assert_close(a.total - b.total, (w - cost.weights["road"]) * b.terms["road"])
    with pytest.raises(ValueError, match="sample_weight"):
        RoadCostConfig(sample_weight=-1.0)


def test_active_subset_call_equals_the_dense_sum_with_gradients():
    """J_R evaluates only the states near the edge on the autograd graph: same value and gradients as the dense
    sum over every state (x and the weights)."""
    road = shapely.union(shapely.box(0, 0, 40, 4), shapely.box(36, 0, 40, 30))
    sdf = RoadSDF.from_geometry(road, (-10, 50, -10, 40), cell_size=0.2, dtype=torch.float64)
    barrier = RoadBarrierCost(sdf, length=4.5, width=1.8, margin=0.15, spacing=0.5)
    gen = torch.Generator().manual_seed(3)
    x = torch.zeros(2, 40, 30, 5, dtype=torch.float64)
    x[..., 0] = torch.rand(2, 40, 30, generator=gen, dtype=torch.float64) * 36 + 2
    x[..., 1] = 2 + 0.5 * torch.randn(2, 40, 30, generator=gen, dtype=torch.float64)
    x[..., 2] = 0.1 * torch.randn(2, 40, 30, generator=gen, dtype=torch.float64)
    w = torch.rand(2, 40, 30, generator=gen, dtype=torch.float64)
    x.requires_grad_(True)
    w.requires_grad_(True)
    got = barrier(CostInputs(x, w, None, None))
    dense = (w * barrier.per_state(x)).sum(dim=(-1, -2))
    active = (barrier.penetration(x.detach()) + 0.15 > 0).double().mean()
    assert 0.05 < float(active) < 0.95  # both kinds of states present
    assert torch.allclose(got, dense, rtol=1e-12)
    g_got = torch.autograd.grad(got.sum(), (x, w))
    g_dense = torch.autograd.grad(dense.sum(), (x, w))
    for a, b in zip(g_got, g_dense):
        assert torch.allclose(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("cell", [0.2, 0.5])
def test_centre_pretest_skips_deep_states_only(cell):
    """The centre test skips states deep inside a wide road (most of them here) and never one whose outline comes
    within the margin of the edge (a curved, cornered road; coarse and fine lattices); value and gradients stay
    those of the dense sum."""
    road = shapely.union_all([shapely.box(0, 0, 60, 14), shapely.Point(60, 30).buffer(22).difference(
        shapely.Point(60, 30).buffer(10)), shapely.box(50, 40, 64, 90)])
    sdf = RoadSDF.from_geometry(road, (-10, 100, -10, 100), cell_size=cell, dtype=torch.float64)
    barrier = RoadBarrierCost(sdf, length=4.5, width=1.8, margin=0.15, spacing=0.5)
    gen = torch.Generator().manual_seed(4)
    x = torch.zeros(20000, 5, dtype=torch.float64)
    x[:, :2] = torch.rand(20000, 2, generator=gen, dtype=torch.float64) * 90
    x[:, 2] = torch.rand(20000, generator=gen, dtype=torch.float64) * 6.3
    maybe = barrier._possibly_active(x)
    deep = barrier.penetration(x[~maybe]) + barrier.margin
    assert 0.05 < float((~maybe).double().mean()) and bool((deep < 0).all())
    x = x.reshape(2, 100, 100, 5).requires_grad_(True)
    w = torch.rand(2, 100, 100, generator=gen, dtype=torch.float64)
    got = barrier(CostInputs(x, w, None, None))
    dense = (w * barrier.per_state(x)).sum(dim=(-1, -2))
    assert torch.allclose(got, dense, rtol=1e-12)
    assert torch.allclose(torch.autograd.grad(got.sum(), x)[0], torch.autograd.grad(dense.sum(), x)[0],
                          rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------ the road's edge in collision (risk.road_edge)
def _edge_scene():
    """The hand-made road whose grid marks the off-road cells occupied (as the CommonRoad importer does) and one
    parked car on the right lane at x = 60."""
    from dataclasses import replace

    from density_planner.environment.commonroad import offroad_cells

    scene = road_scene(GoalRegion(shapely.box(140, 0, 150, 3.5), (0.0, 10.0)))
    g = scene.grid
    _, nx, ny = g.shape
    probs = torch.from_numpy(offroad_cells(scene.road.drivable, g.origin, g.cell_size, (nx, ny)).astype(np.float32))
    probs = probs.expand(g.n_slices, nx, ny).clone()
    i0, j0 = int((58 - g.origin[0]) / g.cell_size), int((1.0 - g.origin[1]) / g.cell_size)
    probs[:, i0:i0 + 18, j0:j0 + 7] = 1.0  # 4.5 m x 1.75 m
    return replace(scene, grid=g.with_probs(probs))


def test_road_edge_barrier_reads_road_users_only_and_occupied_reads_the_edge():
    from density_planner.risk.collision import RiskConfig, collision_grid

    scene = _edge_scene()
    barrier_grid = collision_grid(scene, RiskConfig())
    assert collision_grid(scene, RiskConfig(road_edge="occupied")) is scene.grid
    assert collision_grid(scene, RiskConfig()) is barrier_grid  # cached
    g = scene.grid
    on_road = ~torch.from_numpy(np.asarray(
        shapely.intersects_xy(scene.road.drivable.buffer(g.cell_size * 0.7072),
                              *np.meshgrid(g.xs.numpy(), g.ys.numpy(), indexing="ij"))))
    assert float(barrier_grid.probs[:, on_road].max()) == 0.0  # every off-road cell reads 0
    assert torch.equal(barrier_grid.probs[:, ~on_road], g.probs[:, ~on_road])  # the road users are kept
    assert float(barrier_grid.probs.sum()) > 0

    # a car on the road, its side 0.15 m from the edge: the disc cover and its dilation reach off-road cells
    from density_planner.systems.car import KinematicCar

    car = KinematicCar()
    on_edge = torch.tensor([[[20.0, 1.05, 0.0, 5.0, 0.0]]])  # (1 sample, 1 time, state); side 0.15 m inside
    behind = torch.tensor([[[57.0, 1.75, 0.0, 5.0, 0.0]]])  # front bumper 0.75 m into the parked car
    k = torch.tensor([0])
    occupied = CollisionModel(scene.grid, car, RiskConfig(road_edge="occupied"))
    users = CollisionModel(barrier_grid, car, RiskConfig())
    assert float(occupied.probability(on_edge, k).max) == 1.0
    assert float(users.probability(on_edge, k).max) == 0.0
    assert float(users.probability(behind, k).max) == 1.0


def test_initial_law_conditioned_on_the_body_on_the_road():
    """A start 0.7 m from the kerb (the body's side 0.2 m from it) with a +-0.5-m position error: the scene's
    initial law puts every draw, and the planner's every proposal sample, with the body inside the drivable area;
    without the prior a good part of the law lies off the road."""
    from dataclasses import replace

    from density_planner.density.distributions import Conditioned
    from density_planner.environment.road import BodyOnRoad
    from density_planner.planners.density_planner import sample_initial_states
    from density_planner.planners.problem import PlanningProblem

    scene = road_scene(GoalRegion(shapely.box(140, 0, 150, 3.5), (0.0, 10.0)), start=(10.0, 1.1, 0.0, 6.0))
    scene = replace(scene, meta={"initial_on_road": True, "initial_error": {"position": 0.5, "heading": 0.05,
                                                                              "speed": 0.3}})
    problem = PlanningProblem.from_scene(scene)
    law = problem.initial_distribution
    assert isinstance(law, Conditioned) and 0.2 < law.acceptance < 0.95
    on_road = BodyOnRoad(scene.road.drivable, scene.road.vehicle_length, scene.road.vehicle_width)
    gen = torch.Generator().manual_seed(0)
    assert on_road(law.sample(2000, gen, dtype=torch.float64)).all()
    assert not on_road(law.base.sample(2000, gen, dtype=torch.float64)).all()
    x0, log_rho0, log_q0 = sample_initial_states(problem, 500, gen, dtype=torch.float64)
    assert on_road(x0).all() and torch.isfinite(log_rho0).all() and torch.isfinite(log_q0).all()
    assert float(law.mean[1]) > 1.1  # the prior moves the mean away from the kerb
    # off: the paper's law
    plain = PlanningProblem.from_scene(replace(scene, meta={**scene.meta, "initial_on_road": False}))
    assert not isinstance(plain.initial_distribution, Conditioned)

"""Goal region in time: zero inside the region during its interval, growing with the distance in space and time,
velocity / orientation intervals, alternatives, exact polygon distances and finite-difference gradients."""

from __future__ import annotations

import math

import pytest
import shapely
import torch
from helpers import empty_scene
from road_helpers import road_scene

from density_planner.cost.composite import CostConfig, build_cost
from density_planner.cost.goal_region import GoalRegionCost, distance_to_polygons, polygon_edges
from density_planner.cost.terms import CostInputs, GoalCost
from density_planner.environment.road import GoalRegion

BOX = shapely.box(10.0, -1.0, 14.0, 1.0)  # 4 m x 2 m


def _inputs(x: torch.Tensor) -> CostInputs:
    """Single trajectories ``x (B, T, nx)`` on slices 0..T-1 (t = 0.1 k s)."""
    return CostInputs.single(x, torch.zeros(*x.shape[:-2], x.shape[-2] - 1, 2, dtype=x.dtype))


def _traj(xs, v=5.0, theta=0.0, dtype=torch.float64):
    """Straight trajectories along y = 0 through the given x positions (one per time step)."""
    xs = torch.as_tensor(xs, dtype=dtype)
    x = torch.zeros(*xs.shape, 5, dtype=dtype)
    x[..., 0] = xs
    x[..., 2] = theta
    x[..., 3] = v
    return x


def test_polygon_distance_is_exact_and_zero_inside():
    edges = torch.as_tensor(polygon_edges(BOX))
    pts = torch.tensor([[12.0, 0.0], [9.0, 0.0], [12.0, 3.0], [16.0, 4.0], [10.0, 0.5]], dtype=torch.float64)
    d = distance_to_polygons(pts, edges)
    ref = shapely.distance(BOX, shapely.points(pts.numpy()))
    assert torch.allclose(d, torch.as_tensor(ref), atol=1e-9)
    # a polygon with a hole: inside the hole is outside the region
    ring = shapely.box(0, 0, 10, 10).difference(shapely.box(4, 4, 6, 6))
    d2 = distance_to_polygons(torch.tensor([[5.0, 5.0], [2.0, 2.0]], dtype=torch.float64),
                              torch.as_tensor(polygon_edges(ring)))
    assert d2.tolist() == pytest.approx([1.0, 0.0])


def test_zero_inside_the_region_during_the_interval_positive_outside_in_space_and_time():
    goal = GoalRegion(BOX, (0.5, 0.8))  # steps 5..8
    term = GoalRegionCost(goal, t0=0.0, dt=0.1)
    xs = torch.linspace(0.0, 20.0, 11)  # 2 m per step: x = 10, 12, 14, 16 at steps 5..8
    assert float(term(_inputs(_traj(xs)[None]))[0]) == 0.0
    # in the region only before the interval (too early): positive, and equal to the squared distance at the
    # closest state of the interval
    early = torch.linspace(0.0, 40.0, 11)  # x = 20.. at steps 5..8
    j = float(term(_inputs(_traj(early)[None]))[0])
    assert j == pytest.approx((20.0 - 14.0) ** 2)
    # in space: a trajectory 3 m beside the region
    beside = _traj(xs)
    beside[:, 1] = 4.0
    assert float(term(_inputs(beside[None]))[0]) == pytest.approx(9.0)
    # farther costs more
    far = beside.clone()
    far[:, 1] = 6.0
    assert float(term(_inputs(far[None]))[0]) > float(term(_inputs(beside[None]))[0])


def test_interval_after_the_horizon_uses_the_last_step_and_reached_goal_may_hold():
    goal = GoalRegion(BOX, (5.0, 6.0))  # after the 1-s horizon of these inputs
    term = GoalRegionCost(goal, t0=0.0, dt=0.1)
    hold = _traj(torch.tensor([0.0, 4, 8, 11, 12, 12, 12, 12, 12, 12, 12]), v=0.0)  # reaches, stops, holds
    assert float(term(_inputs(hold[None]))[0]) == 0.0
    short = _traj(torch.linspace(0.0, 8.0, 11))
    assert float(term(_inputs(short[None]))[0]) == pytest.approx(4.0)


def test_velocity_and_orientation_intervals():
    goal = GoalRegion(BOX, (0.0, 1.0), velocity=(2.0, 4.0), orientation=(-0.1, 0.1))
    term = GoalRegionCost(goal, t0=0.0, dt=0.1, velocity_weight=1.0, orientation_weight=25.0)
    x = _traj(torch.full((11,), 12.0), v=3.0)
    assert float(term(_inputs(x[None]))[0]) == 0.0
    fast = _traj(torch.full((11,), 12.0), v=6.0)
    assert float(term(_inputs(fast[None]))[0]) == pytest.approx(4.0)  # (6 - 4)^2
    turned = _traj(torch.full((11,), 12.0), v=3.0, theta=0.3 + 2 * math.pi)  # modulo 2 pi
    assert float(term(_inputs(turned[None]))[0]) == pytest.approx(25.0 * 0.2**2)


def test_alternatives_take_the_best_and_samples_are_weighted():
    other = shapely.box(10.0, 9.0, 14.0, 11.0)
    goal = GoalRegion(shapely.union(BOX, other), (0.0, 1.0),
                      alternatives=(GoalRegion(BOX, (0.0, 0.1)), GoalRegion(other, (0.0, 1.0))))
    term = GoalRegionCost(goal, t0=0.0, dt=0.1)
    x = _traj(torch.full((11,), 12.0))
    x[:, 1] = 10.0
    assert float(term(_inputs(x[None]))[0]) == 0.0  # in the second alternative
    # two samples, one in the region and one 2 m beside it, weights 0.25 / 0.75
    xs = torch.stack([_traj(torch.full((11,), 12.0)), _traj(torch.full((11,), 12.0))])
    xs[1, :, 1] = 3.0
    w = torch.tensor([0.25, 0.75], dtype=torch.float64)[:, None].expand(2, 11)
    single = GoalRegionCost(GoalRegion(BOX, (0.0, 1.0)), t0=0.0, dt=0.1)
    inp = CostInputs(xs[None], w[None], torch.zeros(1, 10, 2, dtype=torch.float64), torch.arange(11))
    assert float(single(inp)[0]) == pytest.approx(0.75 * 4.0)


def test_gradient_matches_finite_differences():
    goal = GoalRegion(BOX, (0.3, 0.7), velocity=(2.0, 4.0), orientation=(-0.1, 0.1))
    term = GoalRegionCost(goal, t0=0.0, dt=0.1)
    gen = torch.Generator().manual_seed(0)
    x = _traj(torch.linspace(0.0, 8.0, 11))
    x = x + 0.3 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
    x[..., 3] = 5.5
    x[..., 2] = 0.4
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda z: term(_inputs(z[None])), (x,), eps=1e-6, atol=1e-5)


def test_build_cost_uses_the_region_on_road_scenes_and_the_point_elsewhere():
    goal = GoalRegion(shapely.box(85, 0.5, 95, 3.0), (9.0, 10.0))
    road = build_cost(road_scene(goal), CostConfig())
    assert isinstance(road.terms["goal"], GoalRegionCost) and "road" in road.terms
    plain = build_cost(empty_scene(), CostConfig())
    assert isinstance(plain.terms["goal"], GoalCost) and set(plain.terms) == {"goal", "input", "bounds", "collision"}
    from density_planner.cost.road import RoadCostConfig

    off = build_cost(road_scene(goal), CostConfig(road=RoadCostConfig(goal_region=False, barrier=False)))
    assert isinstance(off.terms["goal"], GoalCost) and "road" not in off.terms


def test_margin_keeps_plans_off_the_regions_edge():
    goal = GoalRegion(BOX, (0.0, 1.0), velocity=(2.0, 6.0))
    term = GoalRegionCost(goal, t0=0.0, dt=0.1, margin=0.5)
    on_edge = _traj(torch.full((11,), 10.1), v=4.0)  # inside the true region, 0.1 m from its edge
    assert float(term(_inputs(on_edge[None]))[0]) == pytest.approx(0.4**2, rel=1e-4)
    centre = _traj(torch.full((11,), 12.0), v=4.0)
    assert float(term(_inputs(centre[None]))[0]) == 0.0
    slow = _traj(torch.full((11,), 12.0), v=2.2)  # inside the speed interval, within its margin (0.5 m/s)
    assert float(term(_inputs(slow[None]))[0]) == pytest.approx(0.3**2, rel=1e-4)
    # a region too thin for the full margin keeps a core
    thin = GoalRegionCost(GoalRegion(shapely.box(0, 0, 10, 0.6), (0.0, 1.0)), t0=0.0, dt=0.1, margin=0.5)
    mid = _traj(torch.full((11,), 5.0))
    mid[:, 1] = 0.3
    assert float(thin(_inputs(mid[None]))[0]) == 0.0


def test_time_margin_keeps_plans_off_the_intervals_ends():
    goal = GoalRegion(BOX, (0.4, 0.8))  # steps 4..8; with a 0.1-s margin 5..7
    strict = GoalRegionCost(goal, t0=0.0, dt=0.1)
    term = GoalRegionCost(goal, t0=0.0, dt=0.1, time_margin=0.1)
    # in the region only at step 8 (the interval's last instant): zero without the margin, positive with it
    late = _traj(torch.tensor([0.0, 1, 2, 3, 4, 5, 6, 7, 10.5, 20, 30]))
    assert float(strict(_inputs(late[None]))[0]) == 0.0
    assert float(term(_inputs(late[None]))[0]) == pytest.approx((10.0 - 7.0) ** 2)
    # inside in the middle of the interval: zero with the margin too
    mid = _traj(torch.tensor([0.0, 1, 2, 3, 4, 11, 12, 13, 20, 30, 40]))
    assert float(term(_inputs(mid[None]))[0]) == 0.0
    # the margin is at most a quarter of the interval's width, and an instant stays an instant
    wide = GoalRegionCost(goal, t0=0.0, dt=0.1, time_margin=5.0)
    assert wide._alts[0][1] == pytest.approx((0.5, 0.7))
    instant = GoalRegionCost(GoalRegion(BOX, (0.6, 0.6)), t0=0.0, dt=0.1, time_margin=0.3)
    assert instant._alts[0][1] == pytest.approx((0.6, 0.6))
    with pytest.raises(ValueError, match="time_margin must be a finite number >= 0"):
        GoalRegionCost(goal, t0=0.0, dt=0.1, time_margin=-1.0)


def test_stage_two_adds_the_references_own_cost_on_road_scenes_only():
    """``reference_weight`` w: stage 2's cost becomes cost + w sum_n alpha_n J_n(reference) over goal, collision,
    road and bounds on a road scene (with its gradient through the reference), and stays the paper's cost on a
    random scene or with w = 0."""
    from density_planner.control.reference import make_reference
    from density_planner.planners.density_planner import DensityPlanner, DensityPlannerConfig
    from density_planner.planners.problem import PlanningProblem

    goal = GoalRegion(shapely.box(85, 0.5, 95, 3.0), (9.0, 10.0))
    for scene, expect in ((road_scene(goal, start=(40.0, 1.75, 0.0, 6.0)), True), (empty_scene(), False)):
        problem = PlanningProblem.from_scene(scene)
        planner = DensityPlanner(predictor=None, config=DensityPlannerConfig(reference_weight=10.0))
        objective = build_cost(scene, CostConfig(), system=problem.system)
        slices = problem.slices()
        params = torch.zeros(problem.system.nu, problem.parameterization.n_segments)
        params[1, :3] = 1.0  # accelerate for 3 s: it ends past the goal region
        params.requires_grad_(True)
        ref = make_reference(problem.system, problem.reference_start(), params.unsqueeze(0), problem.parameterization)
        base = objective(CostInputs.single(ref.x_plan[0].unsqueeze(0), ref.u_plan[0].unsqueeze(0), slices))
        out = planner._with_reference(problem, objective, ref, slices, base)
        if not expect:
            assert out is base
            continue
        own = objective(CostInputs.single(ref.x_plan, ref.u_plan, slices))
        added = sum(10.0 * objective.weights[n] * float(own.terms[n].detach()) for n in ("goal", "collision", "road",
                                                                                       "bounds"))
        assert float(own.terms["goal"].detach()) > 1.0  # it ends past the region
        assert float(out.total.detach()) == pytest.approx(float(base.total.detach()) + added, rel=1e-6)
        for n in ("goal", "collision", "road", "bounds"):
            assert float(out.terms[f"reference_{n}"].detach()) == pytest.approx(float(own.terms[n].detach()))
        assert "reference_input" not in out.terms
        (grad,) = torch.autograd.grad(out.total.sum(), params)
        assert grad.abs().sum() > 0
        off = DensityPlanner(predictor=None, config=DensityPlannerConfig(reference_weight=0.0))
        assert off._with_reference(problem, objective, ref, slices, base) is base
    with pytest.raises(ValueError, match="reference_weight"):
        DensityPlannerConfig(reference_weight=-1.0)

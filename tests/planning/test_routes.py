"""Route search on a hand-made lane map, route paths, speed profiles and the fit through the reference roll-out."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
import torch
from helpers import empty_scene
from road_helpers import lane_graph, road_scene

from density_planner.control.reference import PiecewiseConstantInputs, plan_grid_reference
from density_planner.environment.lanes import Lane, LaneGraph
from density_planner.environment.road import GoalRegion
from density_planner.planners.density_planner import DensityPlanner, DensityPlannerConfig
from density_planner.planners.problem import PlanningProblem
from density_planner.planners.routes import (
    RouteSeedConfig,
    cap_profiles,
    find_routes,
    first_distinct_rows,
    fit_reference_parameters,
    path_points,
    path_speed_limit,
    profile_family,
    risk_aware_profiles,
    route_seed_parameters,
    speed_profiles,
)
from density_planner.systems.car import KinematicCar


def _box(x0, x1, y0, y1):
    return shapely.box(x0, y0, x1, y1)


def test_straight_route_follows_successors():
    routes = find_routes(lane_graph(), (10.0, 1.75), 0.0, _box(85, 95, 0.5, 3.0))
    assert routes[0].lane_ids == (1, 2) and routes[0].kinds == ("successor",)
    path = routes[0].path
    assert np.allclose(path[:, 1], 1.75, atol=1e-9)  # on the right lane's centre line
    assert path[0, 0] == pytest.approx(10.0, abs=0.5) and path[-1, 0] == pytest.approx(100.0)


def test_lane_change_route_ends_in_the_left_lane():
    routes = find_routes(lane_graph(), (10.0, 1.75), 0.0, _box(85, 95, 4.0, 6.5), max_routes=3)
    best = routes[0]
    assert best.lane_ids[-1] == 4 and best.n_changes == 1
    path = best.path
    assert path[-1, 1] == pytest.approx(1.75 + 3.5, abs=1e-6)  # blended onto lane 4's centre line
    # the blend is smooth: lateral steps between 0.5-m path points stay small
    assert np.abs(np.diff(path[:, 1])).max() < 0.2
    # without a lane change no route exists, so every route makes one
    assert all(r.n_changes >= 1 for r in routes)


def test_junction_route_takes_the_right_turn():
    goal = _box(110.5, 113.0, -10.5, -8.5)  # on the turn's exit, heading -y
    routes = find_routes(lane_graph(), (10.0, 1.75), 0.0, goal)
    assert routes[0].lane_ids == (1, 2, 6)
    end = routes[0].path[-1]
    assert end == pytest.approx([100.0 + 11.75, -10.0], abs=1e-6)
    straight = find_routes(lane_graph(), (10.0, 1.75), 0.0, _box(140, 148, 0.5, 3.0))
    assert straight[0].lane_ids == (1, 2, 5)


def test_routes_continue_straight_past_the_goal_lane_until_the_map_ends():
    goal = _box(85, 95, 0.5, 3.0)  # on lane 2, whose successors are 5 (straight on) and 6 (the right turn)
    routes = find_routes(lane_graph(), (10.0, 1.75), 0.0, goal, continue_for=30.0)
    assert routes[0].lane_ids == (1, 2, 5) and routes[0].kinds == ("successor", "successor")
    assert routes[0].path[-1] == pytest.approx([150.0, 1.75], abs=1e-6)
    # lane 5 has no successor: the continuation stops there however long it is asked to be
    assert find_routes(lane_graph(), (10.0, 1.75), 0.0, goal, continue_for=500.0)[0].lane_ids == (1, 2, 5)
    # the turn's exit continues along its only successor
    turn = find_routes(lane_graph(), (10.0, 1.75), 0.0, _box(110.5, 113.0, -10.5, -8.5), continue_for=5.0)
    assert turn[0].lane_ids == (1, 2, 6, 7)


def _profile_arcs(v, tau):
    return np.concatenate([np.zeros((v.shape[0], 1)), np.cumsum(0.5 * (v[:, 1:] + v[:, :-1]) * np.diff(tau), axis=1)],
                          axis=1)


def test_profiles_stop_before_the_end_of_the_lanes():
    tau = np.arange(0, 10.01, 0.1)
    path = np.array([[0.0, 0.0], [70.0, 0.0]])
    limit = path_speed_limit(path, 15.0, lateral_acceleration=3.0, deceleration=3.0, s_end=60.0)
    v = np.stack([np.full_like(tau, 12.0), np.full_like(tau, 2.0)])  # the first would drive 120 m, the second 20
    s2, v2 = cap_profiles(v, tau, limit, acceleration=3.0, deceleration=3.0, v_lo=0.0)
    assert s2[0].max() <= 60.0 + 0.5 and v2[0, -1] == 0.0  # stands (within one step's travel) at the end
    assert s2[0, -1] >= 60.0 - 1.5  # and not far short of it
    assert np.diff(v2[0]).min() >= -3.0 * 0.1 - 1e-9  # braking at the given rate
    assert np.array_equal(v2[1], v[1]) and np.allclose(s2[1], _profile_arcs(v[1:], tau)[0])  # slow: unchanged
    # with the end given as a stop, a profile that does not reach it within the horizon keeps its speed: 4 s at
    # 12 m/s end at 48 m, before the end at 60 m, although braking from 12 m/s takes 24 m
    free = path_speed_limit(path, 15.0, lateral_acceleration=3.0, deceleration=3.0)
    short = tau[:41]
    s3, v3 = cap_profiles(v[:, :41], short, free, acceleration=3.0, deceleration=3.0, v_lo=0.0, stop=(60.0, limit))
    assert np.array_equal(v3, v[:, :41]) and s3[0, -1] == pytest.approx(48.0)
    s4, v4 = cap_profiles(v, tau, free, acceleration=3.0, deceleration=3.0, v_lo=0.0, stop=(60.0, limit))
    assert np.allclose(v4, v2) and np.allclose(s4, s2)  # one that would pass it stops as before


def test_profiles_slow_down_for_the_turn_and_speed_up_after_it():
    graph = lane_graph()
    route = find_routes(graph, (60.0, 1.75), 0.0, _box(110.5, 113.0, -26.0, -20.0))[0]  # lanes 2, 6, 7
    limit = path_speed_limit(route.path, 15.0, lateral_acceleration=3.0, deceleration=3.0, turn_rate=0.9)
    s_grid, v_lim = limit
    # lane 6 is a quarter circle of radius 10 m (centre line 11.75 m): v <= sqrt(3 * 11.75) = 5.9 m/s inside it
    mid = np.argmin(np.abs(s_grid - (40.0 + 0.25 * math.pi * 11.75)))
    assert v_lim[mid] == pytest.approx(math.sqrt(3.0 * 11.75), rel=0.1)
    assert v_lim[0] == pytest.approx(15.0) and v_lim[-1] == pytest.approx(15.0)  # straight: the speed bound
    assert np.all(np.diff(v_lim**2) >= -2 * 3.0 * 0.5 - 1e-6)  # v^2 falls by <= 2 a ds per 0.5-m step: a <= 3
    tau = np.arange(0, 10.01, 0.1)
    s, v = cap_profiles(np.full((1, tau.size), 12.0), tau, limit, acceleration=2.0, deceleration=3.0, v_lo=0.0)
    assert np.all(v[0] <= np.interp(s[0], s_grid, v_lim) + 3.0 * 0.1 + 1e-9)  # under the limit (one step's lag)
    assert v[0, -1] > 10.0  # and back to speed after the turn


def test_lane_map_noise_does_not_limit_highway_speed_but_a_curve_does():
    """A straight lane whose vertices zigzag by +-0.05 m every 5 m (0.04-rad kinks as on recorded maps, curvature 0.01
    1/m over 4 m, a 3 m/s^2 limit of 17 m/s if read at 4 m) allows 35 m/s; an arc of radius 200 m is held to
    sqrt(3 * 200) = 24.5 m/s; a 5-m hairpin to the turn-rate bound."""
    x = np.arange(0.0, 400.01, 5.0)
    noisy = np.stack([x, 0.05 * (-1.0) ** np.arange(x.size)], axis=1)
    s_grid, v_lim = path_speed_limit(noisy, 35.0, lateral_acceleration=3.0, deceleration=3.0, turn_rate=0.9)
    assert v_lim.min() == pytest.approx(35.0)
    phi = np.linspace(0.0, 400.0 / 200.0, 801)
    arc = 200.0 * np.stack([np.sin(phi), 1.0 - np.cos(phi)], axis=1)
    s_grid, v_lim = path_speed_limit(arc, 35.0, lateral_acceleration=3.0, deceleration=3.0, turn_rate=0.9)
    mid = (s_grid > 100.0) & (s_grid < 300.0)
    assert np.allclose(v_lim[mid], math.sqrt(3.0 * 200.0), rtol=0.02)
    # the turn-rate bound: a 5-m radius needs v <= 0.9 * 5 = 4.5 m/s whatever the window
    phi = np.linspace(0.0, math.pi, 201)
    hairpin = np.concatenate([np.stack([np.linspace(-30.0, 0.0, 61), np.full(61, -5.0)], axis=1)[:-1],
                              5.0 * np.stack([np.sin(phi), -np.cos(phi)], axis=1),
                              np.stack([np.linspace(0.0, -30.0, 61), np.full(61, 5.0)], axis=1)[1:]])
    s_grid, v_lim = path_speed_limit(hairpin, 35.0, lateral_acceleration=8.0, deceleration=3.0, turn_rate=0.9)
    bend = (s_grid > 32.0) & (s_grid < 43.0)
    assert v_lim[bend].max() <= 0.9 * 5.0 * 1.05


def test_targeted_profiles_reach_the_goal_in_time_through_a_curve():
    """With the road's cap passed in, the profiles aimed at the goal are chosen among capped ones: the slow-down
    in the turn does not make them late (without it, the profile capped afterwards misses the interval)."""
    route = find_routes(lane_graph(), (60.0, 1.75), 0.0, _box(110.0, 113.5, -27.0, -24.0))[0]
    path = route.path
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    inside = shapely.contains_xy(_box(110.0, 113.5, -27.0, -24.0), path[:, 0], path[:, 1])
    goal_arc = (float(cum[inside].min()), float(cum[inside].max()))
    tau = np.arange(0, 10.01, 0.1)  # from 8 m/s, in the goal during [9, 10] s: through the turn at <= 5.9 m/s
    limit = path_speed_limit(path, 15.0, lateral_acceleration=3.0, deceleration=3.0, turn_rate=0.9)

    def cap(v):
        return cap_profiles(v, tau, limit, acceleration=3.0, deceleration=5.0, v_lo=0.0)

    def in_time(s):
        during = tau >= 9.0 - 1e-9
        return ((s[:, during] >= goal_arc[0]) & (s[:, during] <= goal_arc[1])).any(axis=1)

    kw = dict(v_limits=(0.0, 15.0), acceleration=1.5, max_acceleration=3.0)
    s_free, v_free, _ = speed_profiles(0.0, 8.0, tau, goal_arc, (9.0, 10.0), **kw)
    s_late, _ = cap(v_free)
    s_cap, v_cap, _ = speed_profiles(0.0, 8.0, tau, goal_arc, (9.0, 10.0), cap=cap, **kw)
    assert np.allclose(cap(v_cap)[0][1:], s_cap[1:])  # the targeted ones are already under the cap
    assert in_time(s_free)[1:6].all() and not in_time(s_late)[1:6].all()  # capped afterwards: some are late
    assert in_time(s_cap)[1:6].all()  # chosen among capped ones: all five on time


def test_no_route_against_the_driving_direction_or_off_the_map():
    assert find_routes(lane_graph(), (10.0, 1.75), math.pi, _box(85, 95, 0.5, 3.0)) == []  # wrong heading
    assert find_routes(lane_graph(), (10.0, 60.0), 0.0, _box(85, 95, 0.5, 3.0)) == []  # start off the lanes
    assert find_routes(lane_graph(), (60.0, 1.75), 0.0, _box(10, 20, 0.5, 3.0)) == []  # goal behind


def test_goal_without_position_follows_the_lanes_ahead():
    routes = find_routes(lane_graph(), (10.0, 1.75), 0.0, None, reach=120.0, max_routes=8)
    ids = {r.lane_ids for r in routes}
    assert (1, 2, 5) in ids and any(r[:3] == (1, 2, 6) for r in ids)


def test_lane_graph_validates_and_drops_unknown_neighbours():
    with pytest.raises(ValueError, match="polyline"):
        Lane(1, [[0, 0]], [[0, 1]])
    g = LaneGraph([Lane(1, [[0, 3.5], [10, 3.5]], [[0, 0], [10, 0]], successors=(7,), left_same=8)])
    assert g[1].successors == () and g[1].left_same is None


def test_speed_profiles_reach_the_goal_in_its_time_interval():
    tau = np.arange(101) * 0.1
    s, v, labels = speed_profiles(0.0, 6.0, tau, (40.0, 50.0), (8.0, 9.0), v_limits=(0.0, 10.0), acceleration=1.5)
    assert set(labels) >= {"keep", "stop"} and s.shape == v.shape == (len(labels), 101)
    assert np.all(np.diff(s, axis=1) >= -1e-9)  # never backwards
    assert np.all((v >= -1e-9) & (v <= 10.0 + 1e-9))
    assert np.abs(np.diff(v, axis=1)).max() <= 1.5 * 0.1 + 1e-9  # within the ramp rate
    k8 = 80
    reach = [i for i, lab in enumerate(labels) if lab != "keep"]
    # every targeted profile is inside the goal arc at some time of the goal interval
    for i in reach:
        assert ((s[i, k8:91] >= 40.0 - 1.0) & (s[i, k8:91] <= 50.0 + 1.0)).any(), labels[i]
    stop = labels.index("stop")
    assert v[stop, -1] == pytest.approx(0.0, abs=1e-9) and 40.0 <= s[stop, -1] <= 50.0
    # a goal out of reach at the comfortable rate is reached with the harder one
    s2, _, lab2 = speed_profiles(0.0, 0.0, tau, (90.0, 95.0), (9.0, 10.0), v_limits=(0.0, 12.0),
                                 acceleration=1.0, max_acceleration=3.0)
    assert (s2[lab2.index("accelerate"), 90:] >= 89.0).any()


def test_profile_family_ramps_within_its_rates_and_limits():
    tau = np.arange(101) * 0.1
    v = profile_family(8.0, tau, v_limits=(0.0, 12.0), rates=(1.5, 6.0), n_speeds=5, switch_times=(2.0, 5.0))
    assert v.shape[1] == 101 and v.shape[0] == 2 * 5 + 2 * 2 * 2 * 25  # one-phase + (rate, switch, rate) x 5 x 5
    assert np.all(v[:, 0] == 8.0) and np.all((v >= 0.0) & (v <= 12.0))
    assert np.abs(np.diff(v, axis=1)).max() <= 6.0 * 0.1 + 1e-9
    assert np.isclose(v[:, -1], 0.0).any() and np.isclose(v[:, -1], 12.0).any()
    # an (accelerate, brake) pair: the car brakes at 5 m/s^2 but speeds up at 2 at most
    v = profile_family(8.0, tau, v_limits=(0.0, 12.0), rates=((2.0, 5.0),), n_speeds=5, switch_times=(2.0,))
    dv = np.diff(v, axis=1)
    assert dv.max() == pytest.approx(2.0 * 0.1) and dv.min() == pytest.approx(-5.0 * 0.1)


def test_first_distinct_rows_equals_numpy_unique():
    """The first occurrence of each distinct row, as np.unique(axis=0) finds it: random rows with repeats and
    signed zeros (equal as floats), and the speed-profile family that the risk-aware seeds thin out."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        base = np.round(rng.normal(size=(int(rng.integers(1, 30)), int(rng.integers(1, 8)))), 1)
        a = base[rng.integers(0, len(base), size=int(rng.integers(1, 60)))]
        a[rng.random(a.shape) < 0.1] *= -0.0  # -0.0 == 0.0
        ref = np.sort(np.unique(a, axis=0, return_index=True)[1])
        np.testing.assert_array_equal(first_distinct_rows(a), ref)
    tau = np.arange(101) * 0.1
    v = np.round(profile_family(6.0, tau, v_limits=(0.0, 40.0), rates=((2.0, 4.0), (1.0, 2.0)), n_speeds=25,
                                switch_times=(1.0, 2.0, 4.0, 6.0, 8.0)), 9)
    first = first_distinct_rows(v)
    np.testing.assert_array_equal(first, np.sort(np.unique(v, axis=0, return_index=True)[1]))
    assert 100 < first.size < v.shape[0]  # the family does repeat profiles
    assert first_distinct_rows(np.zeros((0, 3))).size == 0 and first_distinct_rows(np.ones((1, 3))).tolist() == [0]


def test_risk_aware_profiles_stop_behind_a_standing_car_and_reach_a_goal_in_time():
    """A straight path along x; a car stands at x in [40, 45] (the body's 2.25 m half-length included): starting
    at 10 m/s, the kept profile stops short of it, while "keep" would hit it at t ~ 4 s. Without the car, the kept
    profile is inside the goal arc [70, 75] m during the goal interval [6, 7] s."""
    tau = np.arange(101) * 0.1
    path = np.array([[0.0, 0.0], [200.0, 0.0]])

    def blocked(xy, heading, speed):
        return ((xy[..., 0] + 2.25 >= 40.0) & (xy[..., 0] - 2.25 <= 45.0)).astype(float)

    kw = dict(v_limits=(0.0, 15.0), rates=(1.5, 6.0), n_speeds=13, switch_times=(1.0, 2.0, 4.0), n_keep=3,
              risk_weight=1.0e4, effort_weight=0.05)
    s, v, cost = risk_aware_profiles(blocked, path, 10.0, tau, (100.0, 110.0), (9.0, 10.0), **kw)
    assert s.shape == v.shape == (3, 101) and np.all(np.diff(cost) >= 0)
    assert s[0].max() + 2.25 < 40.0  # no collision
    assert np.sqrt(np.mean((v[1] - v[0]) ** 2)) >= 1.0  # diverse
    free = lambda xy, heading, speed: np.zeros(heading.shape)  # noqa: E731
    s, v, cost = risk_aware_profiles(free, path, 10.0, tau, (70.0, 75.0), (6.0, 7.0), **kw)
    assert cost[0] < 5.0 and ((s[0, 60:71] >= 70.0 - 1e-6) & (s[0, 60:71] <= 75.0 + 1e-6)).any()
    # a goal speed interval: the best profile is inside the arc during the interval at a speed inside it
    s, v, cost = risk_aware_profiles(free, path, 10.0, tau, (70.0, 75.0), (6.0, 7.0), goal_speed=(12.0, 15.0), **kw)
    at = (s[0, 60:71] >= 70.0 - 1e-6) & (s[0, 60:71] <= 75.0 + 1e-6) & (v[0, 60:71] >= 12.0 - 1e-6)
    assert cost[0] < 5.0 and at.any()


@pytest.mark.parametrize("route_goal, speed", [((110.5, 113.0, -10.5, -8.5), 8.0), ((85, 95, 4.0, 6.5), 6.0)])
def test_fit_reproduces_the_route(route_goal, speed):
    """The batched least-squares fit puts the roll-out within 0.1 m RMS (0.3 m worst point) of turn and
    lane-change targets (measured 0.044 / 0.14 m and 0.009 / 0.03 m; the residual comes from the 1-s constant turn
    rate that cannot follow a curvature step exactly), well below the 0.35 m a 1.8-m car has on a 2.5-m lane."""
    graph = lane_graph()
    start = (40.0, 1.75) if route_goal[0] > 100 else (10.0, 1.75)
    route = find_routes(graph, start, 0.0, _box(route_goal[0], route_goal[1], route_goal[2], route_goal[3]),
                        lane_change_length=25.0)[0]
    par = PiecewiseConstantInputs()
    tau = np.arange(par.n_plan) * par.plan_dt
    s, v, _ = speed_profiles(0.0, speed, tau, None, (10.0, 10.0), v_limits=(0.0, 10.0), acceleration=1.5)
    s, v = s[:1], v[:1]  # keep the speed
    xy = path_points(route.path, s)
    car = KinematicCar()
    x0 = torch.tensor([start[0], start[1], 0.0, speed, 0.0], dtype=torch.float64)
    targets, speeds = torch.tensor(xy), torch.tensor(v)
    params, rms = fit_reference_parameters(car, x0, par, targets, speeds)
    lo, hi = car.input_bounds
    assert params.shape == (1, 2, 10)
    assert bool((params[:, 0] >= lo[0]).all() and (params[:, 0] <= hi[0]).all())
    assert bool((params[:, 1] >= lo[1]).all() and (params[:, 1] <= hi[1]).all())
    x, _ = plan_grid_reference(car, x0, params, par)
    err = (x[..., :2] - targets).norm(dim=-1)
    assert float(rms[0]) < 0.1 and float(err.max()) < 0.3, (float(rms[0]), float(err.max()))


def test_route_seeds_for_a_problem_and_none_without_lanes():
    goal = GoalRegion(_box(110.5, 113.0, -10.5, -8.5), (9.0, 10.0))
    scene = road_scene(goal, start=(40.0, 1.75, 0.0, 6.0))
    problem = PlanningProblem.from_scene(scene)
    seeds = route_seed_parameters(problem, RouteSeedConfig(max_routes=2), lane_graph=lane_graph(),
                                  v_limits=(0.1, 9.9), dtype=torch.float64)
    assert seeds is not None and seeds.params.shape[1:] == (2, 10)
    assert seeds.routes[0].lane_ids == (1, 2, 6, 7)  # continued past the goal lane
    assert float(seeds.fit_rms.median()) < 1.0
    # a targeted candidate ends in the goal region at the end of the horizon
    ends = seeds.targets[:, -1].numpy()
    assert shapely.contains_xy(goal.shapes, ends[:, 0], ends[:, 1]).any()
    # no lanes (the paper's random scenes): no seeds, the planner keeps its random candidates only
    plain = PlanningProblem.from_scene(empty_scene())
    assert route_seed_parameters(plain) is None
    assert DensityPlanner(predictor=None, config=DensityPlannerConfig()).seed_candidates(plain) is None
    assert route_seed_parameters(problem, RouteSeedConfig(enabled=False), lane_graph=lane_graph()) is None


def test_route_seed_config_rejects_bad_values():
    with pytest.raises(ValueError, match="routes.max_routes"):
        RouteSeedConfig(max_routes=0)
    with pytest.raises(ValueError, match="routes.acceleration"):
        RouteSeedConfig(acceleration=float("nan"))
    with pytest.raises(ValueError, match="routes.risk_aware"):
        RouteSeedConfig(risk_aware=-1)
    with pytest.raises(ValueError, match="routes.profile_switch_times"):
        RouteSeedConfig(profile_switch_times=(0.0,))


def test_stage_one_with_route_seeds_turns_at_the_junction_and_stays_on_the_road():
    """Stage 1 on the hand-made junction (goal on the right turn's exit in 9-10 s): the kept candidate is a route
    seed, its reference reaches the goal region inside the interval, and its rectangle never leaves the road."""
    goal = GoalRegion(_box(110.5, 113.0, -14.0, -8.5), (9.0, 10.0))
    scene = road_scene(goal, start=(40.0, 1.75, 0.0, 6.0))
    problem = PlanningProblem.from_scene(scene)
    graph = lane_graph()
    cfg = DensityPlannerConfig(n_candidates=10, epochs_init=20)
    planner = DensityPlanner(
        predictor=None, config=cfg,
        candidate_seeds=lambda pr: route_seed_parameters(pr, cfg.routes, lane_graph=graph, v_limits=(0.1, 9.9)).params,
    )
    params, history, _ = planner.initialise(problem, torch.Generator().manual_seed(0))
    assert history["best_is_seed"] == [1.0] and history["seed_candidates"][0] >= 1
    x, _ = plan_grid_reference(problem.system, problem.reference_start(), params[None], problem.parameterization)
    x = x[0].double().numpy()
    t = np.arange(x.shape[0]) * problem.parameterization.plan_dt
    assert scene.road.goal.contains(x[:, :2], t).any()
    assert scene.road.on_road(scene.road.vehicle_polygons(x[:, :3])).all()

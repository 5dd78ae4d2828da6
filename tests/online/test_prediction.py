"""The prediction layer: observed-only occupancy uses no observation after the replanning time, propagates the
last observed state with the documented motion models, and matches the importer's footprints at zero prediction
time."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.prediction import (
    ObservedPrediction,
    OraclePrediction,
    PredictionConfig,
    make_prediction,
)
from density_planner.environment.road import GoalRegion, ObstacleTrack, RoadScene
from density_planner.environment.scene import Scene

shapely = pytest.importorskip("shapely")

DATA = Path(__file__).resolve().parents[2] / "src" / "density_planner" / "data" / "commonroad"


def _synthetic(tracks, *, t_end: float = 6.0) -> Scene:
    """A 100 m x 40 m road (drivable everywhere on the map) with the given road users, 0.5-m cells."""
    n = int(round(t_end / 0.1)) + 1
    grid = OccupancyGrid(torch.zeros(n, 201, 81), (0.0, -20.0), 0.5, 0.1, 0.0)
    road = RoadScene(shapely.box(-1.0, -21.0, 101.0, 21.0), tuple(tracks),
                     GoalRegion(shapely.box(90, -5, 99, 5), (0.0, t_end)), 0.1, 0.0, "synthetic")
    return Scene(grid, (5.0, 0.0, 0.0, 5.0), (95.0, 0.0), (0.0, 100.0, -20.0, 20.0), name="synthetic",
                 road=road)


def _user(v: float = 10.0, omega: float = 0.0, x0: float = 20.0, t_end: float = 6.0, oid: int = 1) -> ObstacleTrack:
    t = np.arange(0.0, t_end + 1e-9, 0.1)
    th = omega * t
    if omega == 0:
        x, y = x0 + v * t, np.zeros_like(t)
    else:
        x, y = x0 + v / omega * np.sin(th), -v / omega * (np.cos(th) - 1.0)
    return ObstacleTrack(oid, "car", 4.0, 1.8, t, np.column_stack([x, y, th]), speeds=np.full(t.size, v))


def test_constant_velocity_propagates_the_last_observed_state():
    scene = _synthetic([_user(v=10.0)])
    pred = ObservedPrediction(scene, PredictionConfig(motion_model="cv"))
    times = 2.0 + 0.1 * np.arange(31)
    tr = pred.tracks(2.0, times)
    # observed at t = 2 s at x = 40 m with 10 m/s: x(t) = 40 + 10 (t - 2), y = 0; tau = t - 2
    np.testing.assert_allclose(tr.x[0], 40.0 + 10.0 * (times - 2.0), atol=1e-9)
    np.testing.assert_allclose(tr.y[0], 0.0, atol=1e-9)
    np.testing.assert_allclose(tr.predicted_for[0], times - 2.0, atol=1e-12)


def test_constant_turn_rate_stays_on_the_circle():
    v, omega = 8.0, 0.2
    scene = _synthetic([_user(v=v, omega=omega)])
    pred = ObservedPrediction(scene, PredictionConfig(motion_model="ctrv"))
    times = 1.0 + 0.1 * np.arange(21)
    tr = pred.tracks(1.0, times)
    # the recorded motion is itself a circle of radius v / omega around (20, v / omega): CTRV reproduces it
    # (turn rate from the last two headings: exact for a constant turn rate, up to float round-off)
    r = np.hypot(tr.x[0] - 20.0, tr.y[0] - v / omega)
    np.testing.assert_allclose(r, v / omega, rtol=1e-6)
    th_true = omega * times
    np.testing.assert_allclose(tr.heading[0], th_true, atol=1e-6)


def test_prediction_at_t_uses_no_observation_after_t():
    user = _user(v=10.0)
    scene = _synthetic([user, _user(v=5.0, x0=60.0, oid=2)])
    t = 2.0
    before = ObservedPrediction(scene).window(t, 3.0).probs.clone()
    # rewrite the recording after t: the first user turns hard and the second stops
    def changed(tr: ObstacleTrack, shift: float) -> ObstacleTrack:
        poses = tr.poses.copy()
        later = tr.times > t + 1e-9
        poses[later, 1] += shift * (tr.times[later] - t)
        speeds = tr.speeds.copy()
        speeds[later] = 0.0
        return dataclasses.replace(tr, poses=poses, speeds=speeds)

    road2 = dataclasses.replace(scene.road, obstacles=(changed(scene.road.obstacles[0], 5.0),
                                                       changed(scene.road.obstacles[1], -3.0)))
    after = ObservedPrediction(dataclasses.replace(scene, road=road2)).window(t, 3.0).probs
    assert torch.equal(before, after)
    # ... while a change at or before t does change it (the test can fail)
    road3 = dataclasses.replace(scene.road, obstacles=(dataclasses.replace(user, poses=user.poses + [0.0, 2.0, 0.0]),
                                                       scene.road.obstacles[1]))
    moved = ObservedPrediction(dataclasses.replace(scene, road=road3)).window(t, 3.0).probs
    assert not torch.equal(before, moved)


def test_unobserved_and_stale_users_are_absent():
    late = ObstacleTrack(3, "car", 4.0, 1.8, np.arange(3.0, 6.0, 0.1), np.tile([50.0, 10.0, 0.0], (30, 1)))
    gone = ObstacleTrack(4, "car", 4.0, 1.8, np.arange(0.0, 1.0, 0.1), np.tile([30.0, -10.0, 0.0], (10, 1)))
    scene = _synthetic([late, gone])
    obs = ObservedPrediction(scene, PredictionConfig(max_observation_age=0.5)).observe(2.0)
    assert obs.ids.size == 0  # 3 not seen yet, 4 last seen 1.1 s ago
    assert ObservedPrediction(scene).observe(3.0).ids.tolist() == [3]


def test_uncertainty_grows_with_prediction_time():
    scene = _synthetic([_user(v=10.0)])
    w = ObservedPrediction(scene, PredictionConfig(std_rate_along=2.0, std_rate_across=1.0)).window(1.0, 3.0)
    peak = w.probs.amax(dim=(1, 2))
    # the footprint's peak drops by prod s / sqrt(s^2 + e^2) as e = rate * tau grows (module docstring)
    assert bool((peak[1:] <= peak[:-1] + 1e-6).all())
    assert float(peak[-1]) < 0.6 * float(peak[0])


def test_observed_equals_importer_at_zero_prediction_time():
    pytest.importorskip("commonroad")
    from density_planner.environment.commonroad import load_commonroad_scene

    scene = load_commonroad_scene(DATA / "USA_US101-3_3_T-1.xml")
    obs = ObservedPrediction(scene).window(scene.t_start, 1.0)
    orc = OraclePrediction(scene).window(scene.t_start, 1.0)
    assert obs.shape == orc.shape and obs.t0 == orc.t0 == scene.t_start
    # slice 0: the same footprints of the same observed states (float32 rasterisation)
    assert float((obs.probs[0] - orc.probs[0]).abs().max()) < 1e-5


def test_scenes_without_road_data_keep_their_model():
    from density_planner.environment.random_scene import random_scene

    scene = random_scene(0)
    pred = make_prediction(scene, PredictionConfig(kind="observed"))
    assert pred.name == "oracle"
    w = pred.window(1.0, 2.0)
    assert torch.equal(w.probs, scene.grid.probs[10:31]) and math.isclose(w.t0, 1.0)
    with pytest.raises(ValueError, match="no road data"):
        ObservedPrediction(scene)


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="kind"):
        PredictionConfig(kind="magic")
    with pytest.raises(ValueError, match="std_rate_along"):
        PredictionConfig(std_rate_along=-1.0)


def test_a_drive_first_plan_reads_only_what_was_observed_at_the_start():
    """With the observed-only prediction the drive's first plan reads the prediction's window at the start (no
    observation after it: rewriting the recording later leaves its grid unchanged), not the scene's recorded
    future; with the oracle it is the offline problem itself."""
    from density_planner.evaluation.online import initial_problem
    from density_planner.planners.problem import PlanningConfig, PlanningProblem

    observed, recorded = [], []
    for drift in (0.0, 3.0):  # after the start the road user drifts sideways at `drift` m/s
        user = _user(v=10.0)
        scene = _synthetic([dataclasses.replace(user, poses=user.poses + np.outer(user.times, [0.0, drift, 0.0]))])
        problem = PlanningProblem.from_scene(scene, planning=PlanningConfig(horizon=5.0))
        first = initial_problem(problem, ObservedPrediction(scene))
        assert first.scene.grid is not scene.grid and first.t_start == problem.t_start
        assert first.initial_distribution is problem.initial_distribution
        assert first.parameterization == problem.parameterization and first.scene.start == problem.scene.start
        assert initial_problem(problem, OraclePrediction(scene)) is problem
        observed.append(first.scene.grid.probs.clone())
        recorded.append(ObservedPrediction(scene).window(2.0, 3.0).probs.clone())  # seen 2 s later
    assert not torch.equal(recorded[0], recorded[1])  # the recordings differ after the start ...
    assert torch.equal(observed[0], observed[1])  # ... what was observed at the start does not


# -- the lane-following motion model ------------------------------------------------------------------------
def _fork_graph():
    """A 3.5-m lane along y = 0 from x = 0 to 50 that forks into a straight lane (x 50 -> 100) and a quarter circle
    of radius 20 m turning left (centre (50, 20))."""
    from density_planner.environment.lanes import Lane, LaneGraph

    def straight(x0, x1):
        xs = np.linspace(x0, x1, 11)
        return np.column_stack([xs, np.full(11, 1.75)]), np.column_stack([xs, np.full(11, -1.75)])

    phi = np.linspace(-math.pi / 2, 0.0, 91)
    arc = lambda r: np.column_stack([50.0 + r * np.cos(phi), 20.0 + r * np.sin(phi)])  # noqa: E731
    l1, r1 = straight(0.0, 50.0)
    l2, r2 = straight(50.0, 100.0)
    return LaneGraph([Lane(1, l1, r1, successors=(2, 3)), Lane(2, l2, r2), Lane(3, arc(18.25), arc(21.75))])


def test_follow_splits_at_a_fork_and_stays_on_the_centre_lines():
    graph = _fork_graph()
    d = np.array([0.0, 10.0, 30.0, 45.0, 120.0])
    paths = graph.follow((30.0, 0.5), 0.05, d)
    assert sorted(p.lanes for p in paths) == [(1, 2), (1, 3)]
    assert math.isclose(sum(p.weight for p in paths), 1.0) and all(math.isclose(p.weight, 0.5) for p in paths)
    for p in paths:
        assert math.isclose(p.offset, 0.5, abs_tol=1e-9)  # left of the centre line
        np.testing.assert_allclose(p.xy[:2], [[30.0, 0.0], [40.0, 0.0]], atol=1e-9)
    straight = next(p for p in paths if p.lanes == (1, 2))
    np.testing.assert_allclose(straight.xy[2:], [[60.0, 0.0], [75.0, 0.0], [150.0, 0.0]], atol=1e-9)  # 150: past
    turn = next(p for p in paths if p.lanes == (1, 3))
    # 25 m past the fork on the arc of radius 20 (polyline of 1-degree chords: ~1e-4 relative)
    ang = -math.pi / 2 + 25.0 / 20.0
    np.testing.assert_allclose(turn.xy[3], [50.0 + 20 * math.cos(ang), 20.0 + 20 * math.sin(ang)], atol=0.05)
    np.testing.assert_allclose(turn.heading[3], ang + math.pi / 2, atol=0.02)
    # past the end of the arc (a polyline of 90 chords): on the line continuing its last chord (heading 89.5 deg)
    chords = 90 * 2 * 20.0 * math.sin(math.radians(0.5))
    h = math.radians(89.5)
    past = 100.0 - chords
    np.testing.assert_allclose(turn.xy[4], [70.0 + past * math.cos(h), 20.0 + past * math.sin(h)], atol=1e-6)
    # one branch at most: the straightest successor; the wrong heading or a far point: no path
    assert [p.lanes for p in graph.follow((30.0, 0.5), 0.0, d, max_branches=1)] == [(1, 2)]
    assert graph.follow((30.0, 0.5), math.pi, d) == []
    assert graph.follow((30.0, 9.0), 0.0, d) == []


def test_lane_model_predicts_a_mixture_along_the_lanes_and_keeps_other_users_straight():
    car = _user(v=10.0, x0=0.0)  # on the lane (y = 0), at x = 20 m at t = 2 s
    walker = dataclasses.replace(_user(v=1.0, x0=30.0, oid=2), kind="pedestrian")
    scene = _synthetic([car, walker])
    pred = ObservedPrediction(scene, PredictionConfig(motion_model="lane"), lane_graph=_fork_graph())
    times = 2.0 + 0.1 * np.arange(61)
    tr = pred.tracks(2.0, times)
    assert list(tr.ids) == [1, 1, 2] and np.allclose(tr.weight, [0.5, 0.5, 1.0])
    end = tr.x[:2, -1], tr.y[:2, -1]  # 60 m later: 30 m past the fork, straight or on the turn
    assert np.isclose(end[0].max(), 80.0, atol=1e-6) and np.isclose(end[1][np.argmax(end[0])], 0.0, atol=1e-6)
    assert end[1].max() > 5.0
    np.testing.assert_allclose(tr.x[2], 32.0 + (times - 2.0), atol=1e-9)  # the pedestrian: constant velocity
    # the occupancy of the two branches sums to the car's footprint: half on each past the fork, all before it
    probs = pred.window(2.0, 6.0).probs
    cv = ObservedPrediction(scene, PredictionConfig(motion_model="cv")).window(2.0, 6.0).probs
    k = 10  # 1 s: 30 m, before the fork: both branches on the same spot, the same as constant velocity
    torch.testing.assert_close(probs[k], cv[k], atol=1e-5, rtol=0)
    k = 60  # 6 s: 80 m along; the straight branch's peak is half the constant-velocity peak at the same place
    assert math.isclose(float(probs[k].max()), 0.5 * float(cv[k].max()), rel_tol=0.02)


def test_lane_model_offset_from_the_centre_line_is_kept_or_decays():
    car = _user(v=10.0, x0=0.0)
    car = dataclasses.replace(car, poses=car.poses + np.array([0.0, 0.8, 0.0]))  # 0.8 m left of the centre line
    scene = _synthetic([car])
    times = 1.0 + np.array([0.0, 1.0, 2.0])
    kept = ObservedPrediction(scene, PredictionConfig(motion_model="lane"), lane_graph=_fork_graph())
    np.testing.assert_allclose(kept.tracks(1.0, times).y[0], 0.8, atol=1e-9)  # 10-30 m along: before the fork
    decays = ObservedPrediction(scene, PredictionConfig(motion_model="lane", lane_offset_time=1.0),
                                lane_graph=_fork_graph())
    np.testing.assert_allclose(decays.tracks(1.0, times).y[0], 0.8 * np.exp(-(times - 1.0)), atol=1e-9)
    # its heading relative to the lane (0.1 rad) likewise: the observed heading at tau = 0
    turned = _synthetic([dataclasses.replace(car, poses=car.poses + np.array([0.0, 0.0, 0.1]))])
    for offset_time, expect in ((0.0, np.full(3, 0.1)), (1.0, 0.1 * np.exp(-(times - 1.0)))):
        tr = ObservedPrediction(turned, PredictionConfig(motion_model="lane", lane_offset_time=offset_time),
                                lane_graph=_fork_graph()).tracks(1.0, times)
        np.testing.assert_allclose(tr.heading[0], expect, atol=1e-9)


def test_lane_model_with_car_following_stops_behind_a_stopped_car_and_is_constant_speed_on_a_free_road():
    follower = _user(v=10.0, x0=0.0)  # at x = 10 m at t = 1 s, on the lane
    stopped = _user(v=0.0, x0=45.0, oid=2)  # 35 m ahead, standing on the lane before the fork
    times = 1.0 + 0.1 * np.arange(51)
    idm = PredictionConfig(motion_model="lane", lane_speed="idm")
    const = PredictionConfig(motion_model="lane", lane_speed="constant")
    # alone on the road: the same mixture as at constant speed (both branches)
    alone = _synthetic([follower])
    a = ObservedPrediction(alone, idm, lane_graph=_fork_graph()).tracks(1.0, times)
    b = ObservedPrediction(alone, const, lane_graph=_fork_graph()).tracks(1.0, times)
    assert list(a.ids) == list(b.ids) == [1, 1]
    np.testing.assert_allclose(a.x, b.x, atol=1e-6)
    np.testing.assert_allclose(a.y, b.y, atol=1e-6)
    np.testing.assert_allclose(a.speed, b.speed, atol=1e-9)
    # behind the stopped car: at constant speed it drives through it; with car following it stops behind it
    scene = _synthetic([follower, stopped])
    tr = ObservedPrediction(scene, idm, lane_graph=_fork_graph()).tracks(1.0, times)
    through = ObservedPrediction(scene, const, lane_graph=_fork_graph()).tracks(1.0, times)
    rows = tr.ids == 1
    assert through.x[through.ids == 1, -1].max() > 55.0
    bumper_gap = 45.0 - tr.x[rows] - 4.0  # both 4 m long
    assert bumper_gap.min() > 2.0 and tr.speed[rows, -1].max() < 2.0  # nearly at rest, s0 = 2 m behind or more
    np.testing.assert_allclose(tr.x[tr.ids == 2], 45.0, atol=1e-9)  # the stopped car stays
    assert np.all(np.diff(tr.x[rows], axis=1) >= -1e-9)


def test_lane_speed_config_is_checked():
    with pytest.raises(ValueError, match="lane_speed"):
        PredictionConfig(lane_speed="fast")
    with pytest.raises(ValueError, match="online.prediction.idm.min_gap"):
        PredictionConfig(idm=dataclasses.replace(PredictionConfig().idm, min_gap=-2.0))


def test_the_observed_acceleration_is_the_recent_speed_change_and_braking_cars_are_predicted_to_stop():
    t = np.arange(0.0, 6.0 + 1e-9, 0.1)
    v = np.maximum(10.0 - 2.0 * t, 0.0)  # braking at 2 m/s^2 from 10 m/s: stops at 5 s
    x = np.where(t <= 5.0, 20.0 + 10.0 * t - t**2, 45.0)
    braking = ObstacleTrack(1, "car", 4.0, 1.8, t, np.column_stack([x, np.zeros_like(t), np.zeros_like(t)]),
                            speeds=v)
    scene = _synthetic([braking])
    cfg = PredictionConfig(motion_model="lane", lane_speed="idm", accel_hold=3.0, accel_window=1.0)
    pred = ObservedPrediction(scene, cfg, lane_graph=_fork_graph())
    obs = pred.observe(2.0)
    assert obs.accel[0] == pytest.approx(-2.0, abs=1e-9)  # (6 - 8) / 1 s
    # also from positions alone (no recorded speeds): the same up to the finite differences' lag
    no_speed = dataclasses.replace(braking, speeds=None)
    obs_p = ObservedPrediction(_synthetic([no_speed]), cfg, lane_graph=_fork_graph()).observe(2.0)
    assert obs_p.accel[0] == pytest.approx(-2.0, abs=0.05)
    # at 2 s (x = 36 m, 6 m/s) kept braking for 3 s: it stops at x = 36 + 6^2 / (2 * 2) = 45 m, as recorded
    times = 2.0 + 0.1 * np.arange(41)
    tr = pred.tracks(2.0, times)
    np.testing.assert_allclose(tr.x[:, -1], 45.0, atol=1e-6)
    np.testing.assert_allclose(tr.x[0], np.interp(times, t, x), atol=1e-6)
    # the observed speed kept (accel_hold = 0): it drives on through x = 45 m
    kept = ObservedPrediction(scene, dataclasses.replace(cfg, accel_hold=0.0), lane_graph=_fork_graph())
    assert kept.tracks(2.0, times).x[:, -1].min() > 55.0

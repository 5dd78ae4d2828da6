"""The car-following model of the lane prediction: constant speed on a free road and at an observed steady gap,
braking behind slower road users without running into them, and leaders found on the path only."""

from __future__ import annotations

import math

import numpy as np
import pytest

from density_planner.environment.car_following import DT, IDMConfig, find_leaders, idm_distances

CFG = IDMConfig()


def test_a_free_road_keeps_the_observed_speed_exactly():
    tau = np.linspace(0.0, 9.0, 37)
    v0 = np.array([0.0, 3.0, 14.0])
    s, v = idm_distances(tau, v0, np.ones(3, bool), np.full(3, -1), np.full(3, np.inf), CFG)
    np.testing.assert_allclose(s, v0[:, None] * tau[None], atol=1e-9)
    np.testing.assert_allclose(v, np.broadcast_to(v0[:, None], v.shape), atol=1e-12)


def test_a_follower_at_its_observed_steady_gap_keeps_it():
    # leader at 12 m/s on a free road, follower 20 m behind at 12 m/s: headway (20 - 2) / 12 = 1.5 s, in range
    tau = np.linspace(0.0, 8.0, 81)
    s, v = idm_distances(tau, np.array([12.0, 12.0]), np.ones(2, bool), np.array([-1, 0]),
                         np.array([np.inf, 20.0]), CFG)
    np.testing.assert_allclose(s[1], 12.0 * tau, atol=1e-9)
    np.testing.assert_allclose(v[1], 12.0, atol=1e-12)


def test_a_follower_brakes_behind_a_stopped_car_and_stops_short_of_it():
    # a car stopped 60 m ahead (not moving), the follower at 15 m/s
    tau = np.arange(0.0, 30.0 + 1e-9, DT)
    gap0 = 60.0
    s, v = idm_distances(tau, np.array([0.0, 15.0]), np.array([False, True]), np.array([-1, 0]),
                         np.array([np.inf, gap0]), CFG)
    gap = gap0 + s[0] - s[1]
    assert np.all(s[0] == 0.0)
    assert gap.min() > 0.5 * CFG.min_gap  # never into it
    assert v[1, -1] < 0.05 and abs(gap[-1] - CFG.min_gap) < 0.5  # at rest about s0 behind it (IDM's standstill)
    assert np.all(np.diff(s[1]) >= -1e-12) and np.all(v >= 0) and np.all(v[1] <= 15.0 + 1e-12)
    assert np.all(np.diff(v[1]) / DT >= -CFG.max_decel - 1e-9)
    # it starts braking before it is close: after 3 s it is slower than its observed speed by more than 2 m/s
    assert v[1, 30] < 13.0


def test_a_queue_is_integrated_jointly_in_any_row_order():
    # a stopped car, a car approaching it, a car following that one at its steady gap: the third brakes only
    # because the second does, and nobody runs into anybody; the rows given in two orders give the same answer
    tau = np.arange(0.0, 15.0 + 1e-9, DT)
    speed = np.array([0.0, 12.0, 12.0])
    moving = np.array([False, True, True])
    leader, gap = np.array([-1, 0, 1]), np.array([np.inf, 50.0, 20.0])
    s, v = idm_distances(tau, speed, moving, leader, gap, CFG)
    order = np.array([2, 0, 1])  # row r of the permuted problem is row order[r] of the first
    inv = np.argsort(order)
    s_p, v_p = idm_distances(tau, speed[order], moving[order], np.where(leader[order] >= 0, inv[leader[order]], -1),
                             gap[order], CFG)
    np.testing.assert_allclose(s_p, s[order], atol=1e-12)
    np.testing.assert_allclose(v_p, v[order], atol=1e-12)
    for r in (1, 2):
        assert np.min(gap[r] + s[leader[r]] - s[r]) > 0.5 * CFG.min_gap
    assert v[2, -1] < 1.0  # the whole queue stops


def test_distances_at_each_rows_own_times():
    tau = np.array([[0.0, 0.05, 1.0], [0.3, 0.35, 2.0]])
    s, _ = idm_distances(tau, np.array([10.0, 5.0]), np.ones(2, bool), np.full(2, -1), np.full(2, np.inf), CFG)
    np.testing.assert_allclose(s, np.array([[10.0], [5.0]]) * tau, atol=1e-9)


def test_leaders_are_the_nearest_road_users_ahead_on_the_path():
    step = 0.5
    path = np.column_stack([np.arange(0.0, 50.0 + 1e-9, step), np.zeros(101)])[None]  # along +x from the origin
    xy = np.array([[0.0, 0.0],      # 0: the follower itself
                   [20.0, 0.5],     # 1: ahead, 0.5 m off the centre line, same direction: a leader at 20 m
                   [10.0, 3.5],     # 2: the next lane
                   [5.0, 0.0],      # 3: oncoming (heading pi, moving): not a leader
                   [3.0, 0.2],      # 4: a pedestrian: never a leader
                   [-6.0, 0.0]])    # 5: behind
    heading = np.array([0.0, 0.1, 0.0, math.pi, 0.0, 0.0])
    speed = np.array([10.0, 8.0, 9.0, 7.0, 1.0, 9.0])
    candidate = np.array([True, True, True, True, False, True])
    leader, ahead = find_leaders(path, step, np.array([0]), xy, heading, speed, candidate, CFG)
    assert leader.tolist() == [1] and ahead[0] == pytest.approx(20.0, abs=1e-9)
    # a car standing across the lane 12 m ahead leads whatever its heading
    xy2 = np.vstack([xy, [[12.0, -0.8]]])
    leader, ahead = find_leaders(path, step, np.array([0]), xy2, np.append(heading, 1.4), np.append(speed, 0.0),
                                 np.append(candidate, True), CFG)
    assert leader.tolist() == [6] and ahead[0] == pytest.approx(12.0, abs=1e-9)
    # nobody ahead (or a path of one point): no leader
    leader, ahead = find_leaders(path, step, np.array([0]), xy[[0, 2, 5]], heading[[0, 2, 5]], speed[[0, 2, 5]],
                                 candidate[[0, 2, 5]], CFG)
    assert leader.tolist() == [-1] and np.isinf(ahead[0])
    leader, _ = find_leaders(path[:, :1], step, np.array([0]), xy, heading, speed, candidate, CFG)
    assert leader.tolist() == [-1]


@pytest.mark.parametrize("change", [{"max_accel": 0.0}, {"min_gap": -1.0}, {"min_headway": 3.0},
                                    {"max_decel": float("nan")}, {"leader_offset": True}])
def test_config_rejects_bad_values(change):
    with pytest.raises(ValueError, match="online.prediction.idm"):
        IDMConfig(**change)


def test_an_observed_acceleration_is_kept_for_the_hold_then_the_speed():
    """Free road: v(tau) = v0 + a min(tau, hold), never below 0; the distances are its integral."""
    tau = np.arange(0.0, 4.0 + 1e-9, DT)
    v0, a = np.array([6.0, 2.0, 0.2, 10.0]), np.array([-3.0, -4.0, 1.5, 0.0])
    s, v = idm_distances(tau, v0, np.ones(4, bool), np.full(4, -1), np.full(4, np.inf), CFG, accel=a,
                         accel_hold=1.0)
    v_expected = np.maximum(v0[:, None] + a[:, None] * np.minimum(tau, 1.0)[None], 0.0)
    np.testing.assert_allclose(v, v_expected, atol=1e-9)
    # braking 6 -> 3 m/s in 1 s then 3 m/s; 2 m/s at -4 m/s^2 stops after 0.5 m; 0.2 -> 1.7 m/s; 10 m/s kept
    s_expected = np.stack([np.where(tau <= 1, 6 * tau - 1.5 * tau**2, 4.5 + 3 * (tau - 1)),
                           np.where(tau <= 0.5, 2 * tau - 2 * tau**2, 0.5),
                           np.where(tau <= 1, 0.2 * tau + 0.75 * tau**2, 0.95 + 1.7 * (tau - 1)),
                           10 * tau])
    np.testing.assert_allclose(s, s_expected, atol=1e-9)
    # no acceleration given, or a hold of 0: the observed speed is kept
    s0, _ = idm_distances(tau, v0, np.ones(4, bool), np.full(4, -1), np.full(4, np.inf), CFG, accel=a,
                          accel_hold=0.0)
    np.testing.assert_allclose(s0, v0[:, None] * tau[None], atol=1e-9)


def test_a_follower_of_a_braking_leader_brakes_too():
    """The leader observed braking to a stop 30 m ahead: its follower (same speed, steady gap) brakes behind it and
    stops short of it; with the leader's acceleration ignored neither brakes."""
    tau = np.arange(0.0, 10.0 + 1e-9, DT)
    speed, leader, gap = np.array([8.0, 8.0]), np.array([-1, 0]), np.array([np.inf, 30.0])
    s, v = idm_distances(tau, speed, np.ones(2, bool), leader, gap, CFG, accel=np.array([-4.0, 0.0]), accel_hold=2.0)
    assert v[0, 20] == pytest.approx(0.0, abs=1e-9) and s[0, -1] == pytest.approx(8.0, abs=1e-6)  # 8^2 / (2 * 4)
    assert np.min(gap[1] + s[0] - s[1]) > 0.5 * CFG.min_gap and v[1, -1] < 0.5
    s_c, _ = idm_distances(tau, speed, np.ones(2, bool), leader, gap, CFG)
    np.testing.assert_allclose(s_c, 8.0 * tau[None].repeat(2, 0), atol=1e-9)

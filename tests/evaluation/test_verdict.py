"""The verdict on hand-made plans: through an obstacle, off the road, in the goal too early, in time."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
import torch

from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.road import GoalRegion, ObstacleTrack, RoadScene
from density_planner.environment.scene import Scene
from density_planner.evaluation.verdict import VerdictConfig, judge, vehicle_footprints
from density_planner.systems.car import KinematicCar

DT = 0.1
CAR = KinematicCar()


def straight(v: float = 5.0, n: int = 101, y: float = 0.0, x0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Driving along +x at constant speed from (x0, y); states (n, 5) and zero inputs (n - 1, 2)."""
    t = DT * np.arange(n)
    x = np.zeros((n, 5))
    x[:, 0] = x0 + v * t
    x[:, 1] = y
    x[:, 3] = v
    return x, np.zeros((n - 1, 2))


def road_scene(*, obstacles=(), goal_time=(8.0, 12.0), goal_box=(40.0, 55.0, -2.0, 2.0), velocity=None,
               t_start: float = 2.0) -> Scene:
    """A straight 4-m road y in [-2, 2] (x in [-10, 100]) in a scenario whose planning problem starts at
    absolute time ``t_start``; goal times are relative to the start."""
    drivable = shapely.box(-10.0, -2.0, 100.0, 2.0)
    gx0, gx1, gy0, gy1 = goal_box
    goal = GoalRegion(shapely.box(gx0, gy0, gx1, gy1), (t_start + goal_time[0], t_start + goal_time[1]),
                      velocity=velocity)
    road = RoadScene(drivable, tuple(obstacles), goal, dt=0.1, t_start=t_start, source="hand-made",
                     vehicle_length=4.0, vehicle_width=1.6)
    grid = OccupancyGrid(torch.zeros(101, 23, 9), (-10.0, -20.0), 5.0, 0.1, 0.0)
    return Scene(grid, (0.0, 0.0, 0.0, 5.0), (47.5, 0.0), (-10.0, 100.0, -20.0, 20.0), name="hand", road=road)


def test_footprint_is_the_rotated_rectangle():
    boxes = vehicle_footprints(np.array([[1.0, 2.0], [0.0, 0.0]]), np.array([0.0, math.pi / 2]), 4.0, 2.0)
    assert shapely.area(boxes) == pytest.approx([8.0, 8.0])
    np.testing.assert_allclose(shapely.bounds(boxes), [[-1.0, 1.0, 3.0, 3.0], [-1.0, -2.0, 1.0, 2.0]], atol=1e-12)


def test_plan_reaching_the_goal_in_time_succeeds():
    x, u = straight()  # in the goal box x in [40, 55] for t in [8, 10] s, inside the interval [8, 12] s
    v = judge(road_scene(), x, u, system=CAR, dt=DT, p_coll_max=0.01)
    assert v.ok and v.status == "success" and v.reasons == ()
    assert v.basis == "road"
    assert v.details["goal_reached_at"] == pytest.approx(8.0)
    assert v.details["vehicle_length"] == 4.0  # the scenario's vehicle, not the default
    d = v.to_dict()
    assert d["status"] == "success" and d["p_coll_max"] == pytest.approx(0.01)


def test_plan_in_the_goal_too_early_fails():
    x, u = straight()  # in the goal box x in [40, 55] during t in [8, 10] s; the interval starts at 10.5 s
    v = judge(road_scene(goal_time=(10.5, 14.0)), x, u, system=CAR, dt=DT)
    assert not v.goal_reached and v.collision_free and v.on_road and v.within_model
    assert v.status == "failed" and v.reasons[0] == (
        "goal: in the goal area at t = 8.0-10.0 s but never during its time interval [10.5, 14.0] s")
    # the same plan with the interval in reach succeeds: the time is what failed
    assert judge(road_scene(goal_time=(9.5, 14.0)), x, u, system=CAR, dt=DT).ok


def test_goal_velocity_interval_is_checked():
    x, u = straight(v=5.0)
    v = judge(road_scene(velocity=(0.0, 3.0)), x, u, system=CAR, dt=DT)
    assert not v.goal_reached
    assert v.reasons[0] == ("goal: in the goal area during its time interval [8.0, 12.0] s but with speed "
                            "5.00-5.00 m/s outside [0.00, 3.00]")
    assert judge(road_scene(velocity=(4.0, 6.0)), x, u, system=CAR, dt=DT).goal_reached


def test_plan_through_an_obstacle_fails_with_its_id_and_time():
    # a parked car (4 x 2 m) at x = 25 in the lane: the ego front reaches it at x_ego = 25 - 2 - 2 = 21 m, t = 4.2 s
    parked = ObstacleTrack(7, "car", 4.0, 2.0, times=[0.0], poses=[[25.0, 0.0, 0.0]], static=True)
    v = judge(road_scene(obstacles=[parked]), *straight(), system=CAR, dt=DT)
    assert not v.collision_free and v.goal_reached and v.on_road
    assert v.details["first_collision_obstacle"] == 7
    assert v.details["first_collision_time"] == pytest.approx(4.2, abs=DT + 1e-9)
    # a car ahead driving at the same speed never touches the ego; its shape moves with absolute time
    ahead = ObstacleTrack(8, "car", 4.0, 2.0, times=[2.0, 14.0], poses=[[10.0, 0.0, 0.0], [70.0, 0.0, 0.0]])
    assert judge(road_scene(obstacles=[ahead]), *straight(), system=CAR, dt=DT).collision_free
    # ... but a slower one is hit
    slow = ObstacleTrack(9, "car", 4.0, 2.0, times=[2.0, 14.0], poses=[[10.0, 0.0, 0.0], [34.0, 0.0, 0.0]])
    assert not judge(road_scene(obstacles=[slow]), *straight(), system=CAR, dt=DT).collision_free


def test_obstacle_outside_its_recorded_times_is_absent():
    # present only from absolute 12 s (10 s after the start): the ego has passed x = 25 by then
    late = ObstacleTrack(3, "car", 4.0, 2.0, times=[12.0, 13.0], poses=[[25.0, 0.0, 0.0], [25.0, 0.0, 0.0]])
    assert judge(road_scene(obstacles=[late]), *straight(), system=CAR, dt=DT).collision_free


def test_plan_off_the_road_fails():
    x, u = straight(y=1.0)  # the 1.6-m wide rectangle reaches y = 1.8 < 2: on the road
    assert judge(road_scene(), x, u, system=CAR, dt=DT).on_road
    x, u = straight(y=1.5)  # reaches y = 2.3: 0.3 m over the edge, beyond the 0.05-m tolerance
    v = judge(road_scene(), x, u, system=CAR, dt=DT)
    assert not v.on_road and v.goal_reached and v.collision_free
    assert v.details["off_road_steps"] == 101 and "drivable area" in v.reasons[0]
    # how much and how far beyond the edge (the tolerance not subtracted): a 4 x 0.3-m strip, corners 0.3 m out
    assert v.details["off_road_max_depth"] == pytest.approx(0.3, abs=1e-9)
    assert v.details["off_road_max_area"] == pytest.approx(4.0 * 0.3, abs=1e-9)
    assert v.reasons[0].endswith("(101 of 101 steps, up to 1.2 m^2 and 0.3 m beyond the road's edge)")
    # a tolerance that covers the overhang accepts it
    assert judge(road_scene(), x, u, system=CAR, dt=DT, config=VerdictConfig(road_tolerance=0.35)).on_road


def test_outside_the_model_fails():
    x, u = straight(v=12.0)  # the car model covers v <= 10 m/s
    v = judge(road_scene(goal_time=(3.0, 5.0)), x, u, system=CAR, dt=DT)
    assert not v.within_model and "v = 12" in v.reasons[-1]
    x, u = straight()
    u[3, 1] = 4.0  # acceleration bound 3 m/s^2
    v = judge(road_scene(), x, u, system=CAR, dt=DT)
    assert not v.within_model and "input a" in v.reasons[-1]


def test_non_finite_trajectory_fails_every_part():
    x, u = straight()
    x[5, 0] = np.nan
    v = judge(road_scene(), x, u, system=CAR, dt=DT)
    assert not (v.goal_reached or v.collision_free or v.on_road or v.within_model)


def test_scene_without_road_uses_goal_tolerance_occupancy_and_map():
    probs = torch.zeros(101, 31, 21)
    probs[:, 24:27, 9:12] = 1.0  # an obstacle around (15, 0) on a 1-m grid over x in [-10, 20], y in [-10, 10]
    grid = OccupancyGrid(probs, (-10.0, -10.0), 1.0, 0.1, 0.0)
    scene = Scene(grid, (0.0, 0.0, 0.0, 1.0), (8.0, 0.0), (-9.0, 9.0, -9.0, 9.0), name="grid-only")
    x, u = straight(v=0.5)  # ends at (5, 0): 3 m from the goal, inside the paper's 4.5 m
    v = judge(scene, x, u, system=CAR, dt=DT)
    assert v.ok and v.basis == "occupancy"
    v = judge(scene, *straight(v=0.3), system=CAR, dt=DT)  # ends at (3, 0): 5 m short
    assert not v.goal_reached and v.collision_free
    v = judge(scene, *straight(v=2.5), system=CAR, dt=DT)  # through the obstacle and off the map (x = 25)
    assert not v.collision_free and not v.on_road


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="states must have shape"):
        judge(road_scene(), np.zeros((10, 3)), None, system=CAR, dt=DT)
    with pytest.raises(ValueError, match="dt"):
        judge(road_scene(), np.zeros((10, 5)), None, system=CAR, dt=0.0)


def test_within_model_judges_applied_inputs_against_the_actuators():
    # road domain: the controller saturates smoothly up to the actuator box, wider than the reference box
    from density_planner.control.registry import model_set
    from density_planner.evaluation.verdict import judge
    from density_planner.systems.car import KinematicCar

    car = KinematicCar(model_set("road").car)
    (alo, ahi), (rlo, rhi) = car.applied_input_bounds, car.input_bounds
    assert ahi[1] > rhi[1] and alo[1] < rlo[1]
    x = np.zeros((3, 5))
    x[:, 0] = [0.0, 0.5, 1.0]
    x[:, 3] = 5.0
    from density_planner.environment.random_scene import random_scene

    scene = random_scene(0)
    x[:, :2] += np.asarray(scene.start[:2])
    inside = np.array([[0.0, 0.5 * (rhi[1] + ahi[1])]] * 2)  # beyond the reference box, inside the actuators
    outside = np.array([[0.0, ahi[1] + 1.0]] * 2)
    v_in = judge(scene, x, inside, system=car, dt=0.1)
    v_out = judge(scene, x, outside, system=car, dt=0.1)
    assert v_in.within_model and not v_out.within_model


def test_goal_miss_names_every_visit_of_the_goal_area():
    from density_planner.evaluation.verdict import _spans

    t = np.arange(60) * 0.1
    mask = np.zeros(60, dtype=bool)
    mask[0:15] = mask[33:59] = True  # leaves the goal area at 1.5 s, back from 3.3 s: misses an interval at 3.0 s
    assert _spans(mask, t) == "0.0-1.4, 3.3-5.8"
    mask[:] = False
    mask[[1, 3, 5, 7, 59]] = True
    assert _spans(mask, t) == "0.1-0.1, 0.3-0.3, 0.5-0.5 and 2 more"

"""RoadScene geometry (environment/road.py): goal regions in position, time, velocity and orientation; obstacle
tracks as true shapes over time; JSON round trip; Scene save/load keeps the road."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
import torch

from density_planner.environment import OccupancyGrid, Scene, load_scene, save_scene
from density_planner.environment.road import GoalRegion, ObstacleTrack, RoadScene, angle_in_interval


def test_goal_contains_position_time_velocity_orientation():
    goal = GoalRegion(shapely.box(0, 0, 2, 2), (1.0, 2.0), velocity=(0.0, 5.0), orientation=(-0.5, 0.5))
    xy = np.array([[1, 1], [3, 3], [2, 2], [1, 1], [1, 1], [1, 1]], dtype=float)
    t = np.array([1.5, 1.5, 2.0, 2.5, 1.5, 1.5])
    v = np.array([1, 1, 1, 1, 6, 1], dtype=float)
    th = np.array([0.1, 0.1, -0.5, 0.1, 0.1, 2 * math.pi + 0.4])
    # inside / outside position / on the corner (boundary counts) / too late / too fast / heading wrapped
    np.testing.assert_array_equal(goal.contains(xy, t, v, th), [True, False, True, False, False, True])
    with pytest.raises(ValueError, match="pass v"):
        goal.contains(xy, t)


def test_goal_without_position_is_time_only():
    goal = GoalRegion(None, (3.0, 4.0))
    np.testing.assert_array_equal(goal.contains(np.array([[1e3, -1e3], [0, 0]]), np.array([3.5, 5.0])), [1, 0])
    np.testing.assert_array_equal(goal.distance(np.array([[1e3, 5.0]])), [0.0])
    assert goal.representative_point() is None


def test_goal_distance_is_euclidean_to_the_shape():
    goal = GoalRegion(shapely.Point(0, 0).buffer(1.0, quad_segs=64), (0, 1))
    d = goal.distance(np.array([[0.2, 0.1], [3.0, 4.0]]))
    assert d[0] == 0.0
    assert d[1] == pytest.approx(4.0, abs=1e-3)  # 5 - radius 1 (polygonised circle)
    x, y = goal.representative_point()
    assert math.hypot(x, y) < 1.0


def test_goal_alternatives_need_one_alternative_fully():
    a = GoalRegion(shapely.box(0, 0, 1, 1), (0.0, 1.0))
    b = GoalRegion(shapely.box(10, 0, 11, 1), (5.0, 6.0))
    goal = GoalRegion(shapely.union_all([a.shapes, b.shapes]), (0.0, 6.0), alternatives=(a, b))
    xy = np.array([[0.5, 0.5], [0.5, 0.5], [10.5, 0.5], [10.5, 0.5]])
    t = np.array([0.5, 5.5, 5.5, 0.5])
    np.testing.assert_array_equal(goal.contains(xy, t), [True, False, True, False])
    back = GoalRegion.from_json_dict(goal.to_json_dict())
    np.testing.assert_array_equal(back.contains(xy, t), [True, False, True, False])


@pytest.mark.parametrize(
    ("interval", "theta", "expected"),
    [
        ((3.0, -3.0), [3.1, -3.1, 0.0, math.pi], [1, 1, 0, 1]),  # wraps through pi
        ((-0.1, 0.1), [0.0, 2 * math.pi, -2 * math.pi + 0.05, 0.2], [1, 1, 1, 0]),
        ((-4.0, 4.0), [0.0, math.pi, 10.0], [1, 1, 1]),  # wider than 2 pi: every heading
    ],
)
def test_angle_interval_wraps(interval, theta, expected):
    np.testing.assert_array_equal(angle_in_interval(np.array(theta), interval), np.array(expected, bool))


def test_track_polygons_follow_the_poses_and_vanish_outside_their_times():
    track = ObstacleTrack(3, "car", 4.0, 2.0, [1.0, 2.0], [[0, 0, 0], [10, 0, math.pi / 2]])
    polys = track.polygons_at(np.array([0.5, 1.0, 1.5, 2.0, 2.5]))
    assert polys[0] is None and polys[4] is None
    assert polys[1].area == pytest.approx(8.0)
    assert polys[1].bounds == pytest.approx((-2, -1, 2, 1))
    assert polys[3].bounds == pytest.approx((9, -2, 11, 2))  # turned by 90 deg
    c = polys[2].centroid
    assert (c.x, c.y) == pytest.approx((5.0, 0.0))
    # predicted poses: included by default, excluded on request
    pred = ObstacleTrack(4, "car", 4, 2, [0, 1, 2], np.zeros((3, 3)), predicted=[False, False, True])
    assert pred.t_last_recorded == 1.0
    assert pred.polygons_at(np.array([1.5]))[0] is not None
    assert pred.polygons_at(np.array([1.5]), include_predicted=False)[0] is None


def test_track_custom_shape_and_static_and_sets():
    tri = shapely.Polygon([(1, 0), (-1, 1), (-1, -1)])
    track = ObstacleTrack(1, "x", 2, 2, [0.0], [[5, 5, math.pi]], shape=tri, static=True)
    poly = track.polygons_at(np.array([-100.0, 100.0]))
    assert poly[0].equals(poly[1])
    assert poly[0].area == pytest.approx(tri.area)
    assert poly[0].bounds == pytest.approx((4, 4, 6, 6))
    occ = np.array([shapely.box(0, 0, 1, 1), shapely.box(5, 0, 6, 1)], dtype=object)
    sets = ObstacleTrack(2, "car", 1, 1, [0.0, 1.0], [[0.5, 0.5, 0], [5.5, 0.5, 0]], occupancies=occ)
    got = sets.polygons_at(np.array([0.2, 0.8, 1.0]))
    assert got[0].equals(occ[0]) and got[1].equals(occ[1]) and got[2].equals(occ[1])


def test_track_validation():
    with pytest.raises(ValueError, match="strictly increasing"):
        ObstacleTrack(1, "car", 4, 2, [1.0, 1.0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="finite"):
        ObstacleTrack(1, "car", 4, 2, [1.0], [[np.nan, 0, 0]])


def _road() -> RoadScene:
    goal = GoalRegion(shapely.box(15, -1, 19, 1), (2.0, 3.0), velocity=(0.0, 4.0))
    track = ObstacleTrack(7, "car", 4.0, 2.0, [0.0, 1.0], [[5, 0, 0], [6, 0, 0]])
    return RoadScene(shapely.box(-5, -3, 20, 3), (track,), goal, 0.1, 0.5, "toy.xml (ZAM_Toy-1)")


def test_roadscene_vehicle_on_road_and_json_round_trip():
    road = _road()
    ego = road.vehicle_polygons(np.array([[0, 0, 0], [0, 2.5, 0], [0, 1.5, math.pi / 2]]))
    np.testing.assert_array_equal(road.on_road(ego), [True, False, False])
    back = RoadScene.from_json_dict(road.to_json_dict())
    assert back.drivable.equals(road.drivable)
    assert back.goal.shapes.equals(road.goal.shapes) and back.goal.velocity == (0.0, 4.0)
    a, b = road.obstacle_polygons(np.array([0.5])), back.obstacle_polygons(np.array([0.5]))
    assert a.shape == (1, 1) and a[0, 0].equals(b[0, 0])


def test_scene_save_load_keeps_the_road(tmp_path):
    grid = OccupancyGrid(torch.zeros(3, 10, 10), (-5.0, -5.0), 3.0, 0.1, 0.5)
    road = _road()
    scene = Scene(grid, (0, 0, 0, 1), road.goal.representative_point(), (-5, 25, -5, 25), road=road)
    back = load_scene(save_scene(scene, tmp_path / "s.npz"))
    assert back.road is not None and back.road.source == road.source
    assert back.road.goal.time_interval == (2.0, 3.0)
    plain = load_scene(save_scene(Scene(grid, (0, 0, 0, 1), (1, 1), (-5, 25, -5, 25)), tmp_path / "p.npz"))
    assert plain.road is None

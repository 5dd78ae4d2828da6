"""Calibration of the occupancy model against true shapes: hits by hand-placed rectangles, the binning, pooling,
the road-users-only occupancy, and the ``validate risk`` report on a recorded scene."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import shapely

from density_planner.environment.road import GoalRegion, ObstacleTrack, RoadScene
from density_planner.evaluation.calibration import CalibrationResult, bin_pairs, road_user_hits

SHIPPED = Path(__file__).resolve().parents[2] / "src" / "density_planner" / "data" / "commonroad"


def _road(obstacles) -> RoadScene:
    goal = GoalRegion(shapely.box(40, -2, 50, 2), (0.0, 10.0))
    return RoadScene(shapely.box(-10, -4, 100, 4), tuple(obstacles), goal, dt=0.1, t_start=0.0, source="hand",
                     vehicle_length=4.0, vehicle_width=2.0)


def test_hits_of_rectangles_against_a_moving_road_user():
    # a 4 x 2 road user at x = 10 + 5 t on y = 0, recorded for t in [0, 1] s
    times = np.arange(11) * 0.1
    other = ObstacleTrack(7, "car", 4.0, 2.0, times.tolist(), [[10 + 5 * t, 0.0, 0.0] for t in times])
    road = _road([other])
    poses = np.zeros((3, 11, 3))
    poses[0, :, 0] = 10 + 5 * times - 3.9   # rear-end overlap of 0.1 m: always a hit
    poses[1, :, 0] = 10 + 5 * times - 4.1   # 0.1 m gap: never
    poses[2, :, 0] = 10 + 5 * times         # beside it, turned 90 deg: y in [1.1, 5.1], a 0.1-m gap to y <= 1
    poses[2, :, 1] = 3.1
    poses[2, :, 2] = math.pi / 2
    hits = road_user_hits(road, poses, times)
    assert hits[0].all() and not hits[1].any()
    assert not hits[2].any()
    poses[2, :, 1] = 2.9  # y in [0.9, 4.9]: overlaps the other's side y <= 1 by 0.1 m
    assert road_user_hits(road, poses, times)[2].all()


def test_hits_only_while_the_road_user_is_present():
    times = np.arange(11) * 0.1
    other = ObstacleTrack(3, "car", 4.0, 2.0, [0.5, 0.6], [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    poses = np.zeros((1, 11, 3))
    hits = road_user_hits(_road([other]), poses, times)
    present = other.present(times)
    assert present.any() and not present.all()
    np.testing.assert_array_equal(hits[0], present)


def test_hits_count_recorded_shapes_only_by_default():
    # recorded at 0 and 0.5 s, extrapolated at 1 s: the ego sits where it is at 1 s
    other = ObstacleTrack(5, "car", 4.0, 2.0, [0.0, 0.5, 1.0], [[0, 0, 0], [2.5, 0, 0], [5.0, 0, 0]],
                          predicted=[False, False, True], position_std=[0.0, 0.0, 0.5])
    poses = np.zeros((1, 1, 3))
    poses[0, 0, 0] = 5.0
    t = np.array([1.0])
    assert not road_user_hits(_road([other]), poses, t)[0, 0]
    assert road_user_hits(_road([other]), poses, t, include_predicted=True)[0, 0]


def test_hits_reject_bad_shapes():
    with pytest.raises(ValueError, match=r"\(M, T, 3\)"):
        road_user_hits(_road([]), np.zeros((4, 3)), np.zeros(4))
    with pytest.raises(ValueError, match="one per pose column"):
        road_user_hits(_road([]), np.zeros((1, 4, 3)), np.zeros(5))


def test_bins_count_pairs_predictions_and_hits():
    edges = np.linspace(0, 1, 5)  # (0, .25], (.25, .5], (.5, .75], (.75, 1]
    p = np.array([0.0, 0.25, 0.26, 0.5, 0.9, 1.0])
    hit = np.array([False, True, False, True, True, False])
    count, psum, hits = bin_pairs(p, hit, edges)
    np.testing.assert_array_equal(count, [2, 2, 0, 2])
    np.testing.assert_allclose(psum, [0.25, 0.76, 0.0, 1.9])
    np.testing.assert_array_equal(hits, [1, 1, 0, 1])
    with pytest.raises(ValueError, match="same number"):
        bin_pairs(p, hit[:3], edges)


def test_pooling_adds_bins_and_round_trips():
    edges = np.linspace(0, 1, 3)
    a = CalibrationResult(np.arange(2.0), np.array([0.1, 0.2]), np.array([0.0, 0.5]), 10, edges,
                          np.array([15, 5]), np.array([1.5, 4.0]), np.array([1, 4]))
    b = CalibrationResult.from_dict(json.loads(json.dumps(a.to_dict())))
    np.testing.assert_allclose(b.bin_predicted, a.bin_predicted)
    pool = CalibrationResult.pooled([a, b])
    np.testing.assert_array_equal(pool.bin_count, [30, 10])
    assert pool.total_observed == pytest.approx(10 / 40)
    assert pool.total_predicted == pytest.approx(11.0 / 40)
    bins = pool.bins()
    assert bins[1]["observed"] == pytest.approx(0.8) and bins[1]["predicted"] == pytest.approx(0.8)
    with pytest.raises(ValueError, match="bin edges"):
        CalibrationResult.pooled([a, CalibrationResult(a.times, a.predicted, a.observed, 1, np.linspace(0, 1, 4),
                                                       np.zeros(3), np.zeros(3), np.zeros(3))])


def test_road_users_only_occupancy_leaves_the_road_edge_free():
    from density_planner.control.registry import model_set_for_scene
    from density_planner.environment.commonroad import CommonRoadSceneConfig, load_commonroad_scene
    from density_planner.systems.car import KinematicCar

    f = SHIPPED / "USA_Lanker-1_1_T-1.xml"
    car = KinematicCar(model_set_for_scene("commonroad", None).car)
    full = load_commonroad_scene(f, system=car)
    users = load_commonroad_scene(f, CommonRoadSceneConfig(offroad_occupied=False), system=car)
    assert full.grid.probs.shape == users.grid.probs.shape and full.grid.origin == users.grid.origin
    margin = full.grid.cell_size * np.sqrt(0.5)  # commonroad.offroad_margin: half a cell diagonal outside the road
    off = ~np.asarray(shapely.contains_xy(full.road.drivable.buffer(margin + 1e-6), *np.meshgrid(
        full.grid.origin[0] + full.grid.cell_size * np.arange(full.grid.probs.shape[1]),
        full.grid.origin[1] + full.grid.cell_size * np.arange(full.grid.probs.shape[2]), indexing="ij")))
    assert off.any()
    assert float(full.grid.probs[0][off].min()) == 1.0  # beyond the road's edge is occupied by default
    assert float(users.grid.probs[0][off].mean()) < 0.05  # only road users (and static obstacles) remain
    assert bool((users.grid.probs <= full.grid.probs + 1e-6).all())


@pytest.mark.slow
def test_validate_risk_reports_the_calibration_on_a_recorded_scene(tmp_path):
    from density_planner.cli import main

    out = tmp_path / "v"
    rc = main(["validate", "risk", "--env", "commonroad", "--file", str(SHIPPED / "USA_Lanker-1_1_T-1.xml"),
               "--samples", "200", "--calibration-samples", "100", "-q", "--out", str(out),
               "--set", "density_planner.n_candidates=8", "--set", "density_planner.epochs_init=5",
               "--set", "density_planner.epochs_density=3", "--set", "density_planner.n_samples=50",
               "--set", "density_planner.evaluation_samples=50"])
    assert rc in (0, 1)
    report = json.loads((out / "risk_report.json").read_text())
    cal = report["calibration"]
    assert cal["n"] == 100 and sum(cal["bin_count"]) == 100 * len(cal["times"])
    assert 0.0 <= cal["mean_observed"] <= 1.0 and 0.0 <= cal["mean_predicted"] <= 1.0
    assert report["reported_by"] in ("exact", None) or isinstance(report["reported_by"], str)
    assert (out / "calibration.png").stat().st_size > 10_000


def test_validate_risk_rejects_one_calibration_sample(tmp_path):
    from density_planner.cli import main

    rc = main(["validate", "risk", "--env", "random", "--calibration-samples", "1", "-q", "--out",
               str(tmp_path / "x")])
    assert rc == 2
    assert not (tmp_path / "x").exists()

"""CommonRoad importer (environment/commonroad.py): the shipped BSD scenarios and hand-made XML files
(tests/environment/cr_testdata.py) for every rule of the module docstring (issue 13 items 1-8, issue 18)."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch

pytest.importorskip("commonroad", reason="commonroad-io (extra 'commonroad') is not installed")
shapely = pytest.importorskip("shapely")

from cr_testdata import write_scenario  # noqa: E402

from density_planner.environment import CommonRoadSceneConfig, load_commonroad_scene  # noqa: E402
from density_planner.environment.commonroad import (  # noqa: E402
    drivable_area,
    reach_distance,
    read_commonroad,
    static_map,
)
from density_planner.environment.scene import load_scene, save_scene  # noqa: E402
from density_planner.errors import DataError  # noqa: E402

NGSIM = ["USA_US101-4_1_T-1.xml", "USA_Peach-4_8_T-1.xml"]
#: a coarse grid keeps the hand-made scenes fast; the rules under test do not depend on the cell size
FAST = {"cell_size": 0.25}


def _cfg(**kw) -> CommonRoadSceneConfig:
    return CommonRoadSceneConfig(**{**FAST, **kw})


def _lookup(scene, x, y, k):
    return float(scene.grid.lookup(torch.tensor([x, y], dtype=torch.float64), k))


def _centre_points(scenario):
    pts = [
        0.5 * (np.asarray(ll.left_vertices) + np.asarray(ll.right_vertices))[1:-1]
        for ll in scenario.lanelet_network.lanelets
    ]
    return np.concatenate(pts)


# ------------------------------------------------------------------------------------------ shipped files
@pytest.mark.parametrize("name", NGSIM)
def test_shipped_ngsim_scenarios_load_with_their_planning_problem(commonroad_dir, name):
    scene = load_commonroad_scene(commonroad_dir / name, _cfg())
    scenario, problems = read_commonroad(commonroad_dir / name)
    problem = next(iter(problems.planning_problem_dict.values()))
    st = problem.initial_state
    assert scene.start[:2] == pytest.approx(tuple(st.position))
    assert math.cos(scene.start[2]) == pytest.approx(math.cos(st.orientation))
    assert scene.start[3] == pytest.approx(st.velocity) and len(scene.start) == 4
    assert scene.name == name  # the file (its XML id is the same here)
    assert scene.road is not None and scene.road.source == name
    assert scene.grid.t0 == pytest.approx(st.time_step * scenario.dt)
    xmin, xmax, ymin, ymax = scene.grid.bounds
    assert xmin <= scene.goal[0] <= xmax and ymin <= scene.goal[1] <= ymax
    # the planners' goal point lies in the goal region
    assert scene.road.goal.distance(np.array([scene.goal]))[0] == 0.0
    # the horizon follows the goal's time interval (capped at max_horizon)
    assert scene.meta["horizon"] == pytest.approx(
        min(scene.road.goal.t_end - scene.road.t_start, CommonRoadSceneConfig().max_horizon))
    assert scene.grid.n_slices >= round(scene.meta["horizon"] / scene.grid.dt) + 1


def test_us101_goal_rectangle_and_time(commonroad_dir):
    scene = load_commonroad_scene(commonroad_dir / NGSIM[0], _cfg())
    _, problems = read_commonroad(commonroad_dir / NGSIM[0])
    st = next(iter(problems.planning_problem_dict.values())).goal.state_list[0]
    goal = scene.road.goal
    # US101-4_1: one rectangle centred at (17.836, -17.218); time steps of 0.1 s -> absolute seconds
    assert goal.representative_point() == pytest.approx((17.836, -17.2178), abs=1e-3)
    assert goal.time_interval == pytest.approx((st.time_step.start * 0.1, st.time_step.end * 0.1))
    t_mid = np.array([sum(goal.time_interval) / 2])
    v = None if goal.velocity is None else np.array([sum(goal.velocity) / 2])
    th = None if goal.orientation is None else np.array([sum(goal.orientation) / 2])
    assert goal.contains(np.array([[17.836, -17.2178]]), t_mid, v, th)[0]
    assert not goal.contains(np.array([[17.836, -17.2178]]), t_mid - 10.0, v, th)[0]


@pytest.mark.parametrize("name", NGSIM)
def test_lanelets_are_free_and_far_off_cells_occupied(commonroad_dir, name):
    scenario, _ = read_commonroad(commonroad_dir / name)
    origin, h, size = (-60.0, -60.0), 0.25, (481, 481)
    static, _ = static_map(scenario, origin, h, size, CommonRoadSceneConfig())
    xs = origin[0] + h * np.arange(size[0])
    ys = origin[1] + h * np.arange(size[1])
    pts = _centre_points(scenario)
    inside = (pts[:, 0] > xs[0]) & (pts[:, 0] < xs[-1]) & (pts[:, 1] > ys[0]) & (pts[:, 1] < ys[-1])
    pts = pts[inside]
    assert len(pts) > 10
    i = np.rint((pts[:, 0] - origin[0]) / h).astype(int)
    j = np.rint((pts[:, 1] - origin[1]) / h).astype(int)
    assert static[i, j].max() == 0.0
    union = shapely.union_all([
        shapely.Polygon(np.vstack([ll.left_vertices, ll.right_vertices[::-1]])).buffer(0)
        for ll in scenario.lanelet_network.lanelets
    ])
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    far = shapely.distance(union, shapely.points(gx.ravel(), gy.ravel())).reshape(gx.shape) > 2.0
    assert far.any() and static[far].min() == 1.0


@pytest.mark.parametrize("block", [1, 3, 16])
@pytest.mark.parametrize("strict", [False, True])
def test_lattice_in_is_the_point_test_of_every_point(commonroad_dir, block, strict):
    """lattice_in (the static map's and the distance field's point test by blocks) answers exactly as
    shapely.intersects_xy (closed geometry) or, strict, contains_xy (interior) point by point: on a shipped road
    network (drivable area buffered as the off-road mask does) and on shapes with holes, a multipolygon, a line,
    points on edges and lattices whose size is no multiple of the block."""
    from density_planner.environment.road import lattice_in

    def direct(geom, origin, h, size):
        gx, gy = np.meshgrid(origin[0] + h * np.arange(size[0]), origin[1] + h * np.arange(size[1]), indexing="ij")
        return (shapely.contains_xy if strict else shapely.intersects_xy)(geom, gx, gy)

    scenario, _ = read_commonroad(commonroad_dir / NGSIM[1])
    road, _ = drivable_area(scenario, CommonRoadSceneConfig())
    x0, y0, x1, y1 = road.bounds
    ring = shapely.Polygon([(0, 0), (10, 0), (10, 10), (0, 10)], holes=[[(3, 3), (7, 3), (7, 7), (3, 7)]])
    shapes = [
        (road.buffer(0.35, quad_segs=2), (x0 - 3.0, y0 - 3.0), 0.5,
         (int((x1 - x0) / 0.5) + 13, int((y1 - y0) / 0.5) + 7)),
        (ring, (-1.0, -1.0), 0.25, (53, 47)),  # edges on lattice points (x = 0, 3, 7, 10)
        (shapely.MultiPolygon([ring, shapely.box(20, 0, 20.6, 30)]), (-2.0, -3.0), 0.2, (121, 171)),
        (shapely.LineString([(0, 0), (5, 5)]), (-1.0, -1.0), 0.5, (17, 18)),
    ]
    for geom, origin, h, size in shapes:
        got = lattice_in(geom, origin, h, size, strict=strict, block=block)
        want = direct(geom, origin, h, size)
        assert got.shape == tuple(size) and got.dtype == bool
        assert np.array_equal(got, want) and not want.all()
        assert want.any() or (strict and geom.area == 0)  # a line has no interior


def test_the_scenes_offroad_mask_is_the_one_its_static_map_used(commonroad_dir):
    """The import computes the off-road cells once: offroad_mask (what collision reads) is that array, equal to a
    fresh offroad_cells of the same geometry, and the grid holds 1 there."""
    from density_planner.environment.commonroad import offroad_cells, offroad_mask

    scene = load_commonroad_scene(commonroad_dir / NGSIM[0], _cfg())
    g = scene.grid
    _, nx, ny = g.shape
    mask = offroad_mask(scene)
    fresh = offroad_cells(scene.road.drivable, g.origin, g.cell_size, (nx, ny), scene.meta["config"]["offroad_margin"])
    assert mask.dtype == torch.bool and torch.equal(mask, torch.from_numpy(fresh)) and bool(mask.any())
    assert offroad_mask(scene) is mask
    assert bool((g.probs[:, mask] == 1.0).all())


def test_dynamic_obstacles_are_drawn_and_kept_as_true_shapes(commonroad_dir):
    scene = load_commonroad_scene(commonroad_dir / NGSIM[0], _cfg())
    scenario, _ = read_commonroad(commonroad_dir / NGSIM[0])
    xmin, xmax, ymin, ymax = scene.grid.bounds
    seen = 0
    for obs in scenario.dynamic_obstacles:
        x, y = obs.initial_state.position
        if xmin + 1 < x < xmax - 1 and ymin + 1 < y < ymax - 1:
            assert _lookup(scene, x, y, 0) >= 0.95
            seen += 1
    assert seen >= 3
    dropped = 0 if scene.meta["dropped_ego"] is None else 1
    n_dyn = len([t for t in scene.road.obstacles if not t.static and t.kind != "red_light"])
    assert n_dyn == len(scenario.dynamic_obstacles) - dropped


@pytest.mark.parametrize("name", ["DEU_A9-3_1_T-1.xml", "USA_Lanker-1_1_T-1.xml", "USA_US101-3_3_T-1.xml",
                                  "ARG_Carcarana-4_5_T-1.xml", "FRA_Anglet-1_1_T-1.xml",
                                  "ZAM_Tutorial-1_1_T-1.xml", "ZAM_Tutorial-1_2_T-1.xml",
                                  "DEU_Starnberg-1_1_T-1.xml"])
def test_every_additional_shipped_scenario_imports_or_is_refused_in_one_line(commonroad_dir, name):
    """The 8 BSD scenarios added to the package: each gives a scene or one clear DataError (issue 13)."""
    try:
        scene = load_commonroad_scene(commonroad_dir / name, _cfg())
    except DataError as exc:
        text = str(exc)
        assert "\n" not in text and name in text
        assert ("outside the KinematicCar model's domain" in text) or ("no planning problem" in text)
        return
    assert scene.road is not None and scene.name.startswith(name)
    assert scene.grid.probs.isfinite().all()


def test_map_without_planning_problem_is_refused_unless_sampling(commonroad_dir):
    with pytest.raises(DataError, match=r"no planning problem.*commonroad\.sample_start_goal=true"):
        load_commonroad_scene(commonroad_dir / "DEU_Starnberg-1_1_T-1.xml", _cfg())
    scene = load_commonroad_scene(commonroad_dir / "USA_US101-3_3_T-1.xml",
                                  _cfg(sample_start_goal=True, seed=3, cell_size=0.5))
    assert scene.meta["start_goal_sampled"]
    assert 10 <= math.hypot(scene.goal[0] - scene.start[0], scene.goal[1] - scene.start[1]) <= 70
    assert scene.road.goal.distance(np.array([scene.goal]))[0] == 0.0


def test_traffic_lights_of_the_shipped_peachtree_block_stop_lines(commonroad_dir):
    scene = load_commonroad_scene(commonroad_dir / NGSIM[1], _cfg())
    red = [t for t in scene.road.obstacles if t.kind == "red_light"]
    assert red and scene.meta["n_red_light_phases"] == len(red)
    t = red[0]
    poly = t.polygons_at(np.array([t.times[0]]))[0]
    k = int(round((t.times[0] - scene.grid.t0) / scene.grid.dt))
    c = poly.centroid
    if scene.grid.bounds[0] < c.x < scene.grid.bounds[1] and scene.grid.bounds[2] < c.y < scene.grid.bounds[3]:
        assert _lookup(scene, c.x, c.y, k) >= 0.99
    ignored = load_commonroad_scene(commonroad_dir / NGSIM[1], _cfg(traffic_lights=False))
    assert not [t for t in ignored.road.obstacles if t.kind == "red_light"]
    assert any("traffic lights are ignored" in n for n in ignored.meta["simplifications"])


# ------------------------------------------------------------------------------------------ hand-made files
def test_recorded_ego_is_dropped_and_recorded(tmp_path):
    path = write_scenario(tmp_path / "ego.xml")
    scene = load_commonroad_scene(path, _cfg())
    assert scene.meta["dropped_ego"] == {"id": 10, "distance_m": pytest.approx(0.0)}
    assert 10 not in [t.obstacle_id for t in scene.road.obstacles]
    assert any("recorded ego" in n for n in scene.meta["simplifications"])
    # the start is free (it read ~1 with the ego drawn as an obstacle)
    assert _lookup(scene, 10.0, 1.75, 0) < 0.05
    kept = load_commonroad_scene(path, _cfg(drop_ego=False))
    assert _lookup(kept, 10.0, 1.75, 0) > 0.95
    # a recording elsewhere is not the ego: tolerance 1 m
    far = load_commonroad_scene(write_scenario(tmp_path / "far.xml", start_x="12.0"), _cfg())
    assert far.meta["dropped_ego"] is None


def test_exclude_obstacles(tmp_path):
    path = write_scenario(tmp_path / "s.xml")
    scene = load_commonroad_scene(path, _cfg(exclude_obstacles=(11, 20)))
    ids = {t.obstacle_id for t in scene.road.obstacles}
    assert 11 not in ids and 20 not in ids and 12 in ids
    assert scene.meta["excluded_obstacles"] == [11, 20]
    assert _lookup(scene, 30.0, 5.25, 0) < 0.05  # obstacle 11's initial position is free
    with pytest.raises(DataError, match=r"s\.xml \(ZAM_Handmade-1_1_T-1\): commonroad\.exclude_obstacles.*\[999\]"):
        load_commonroad_scene(path, _cfg(exclude_obstacles=(999,)))


def test_road_user_is_predicted_past_its_last_state(tmp_path):
    """Obstacle 11 (5 m/s along +x from x = 30) is recorded for 2 s only; at 6 s it is predicted at x = 60."""
    scene = load_commonroad_scene(write_scenario(tmp_path / "s.xml", n_recorded=20), _cfg())
    track = next(t for t in scene.road.obstacles if t.obstacle_id == 11)
    assert track.t_last_recorded == pytest.approx(2.0)
    assert track.predicted.any() and track.times[-1] == pytest.approx(scene.grid.t0 + 10.0)
    poly = track.polygons_at(np.array([6.0]))[0]
    assert (poly.centroid.x, poly.centroid.y) == pytest.approx((60.0, 5.25), abs=1e-6)
    assert track.position_std[-1] > track.position_std[track.times.size // 2] > 0
    k = 60
    # the shape model (default): the chance that the 4 m x 2 m rectangle covers its predicted centre, with the
    # position error sqrt(0.2^2 + (rate * 4 s)^2) along (rate 1 m/s) and across (0.3 m/s) after 4 s of prediction
    s_u, s_w = math.hypot(0.2, 4.0), math.hypot(0.2, 1.2)
    expected = math.erf(2.0 / s_u / math.sqrt(2)) * math.erf(1.0 / s_w / math.sqrt(2))
    assert _lookup(scene, 60.0, 5.25, k) == pytest.approx(expected, abs=0.02)  # still there, with a lower peak
    assert _lookup(scene, 60.0, 5.25, k) < _lookup(scene, 30.0, 5.25, 0)
    info = next(d for d in scene.meta["dynamic_obstacles"] if d["id"] == 11)
    assert info["predicted_after_s"] == pytest.approx(2.0)
    assert excluded_free(scene)


def excluded_free(scene) -> bool:
    return bool(torch.isfinite(scene.grid.probs).all())


def test_set_based_prediction_is_used_over_every_step(tmp_path):
    """Obstacle 12: boxes centred at x = 60 + k (k = 1..5 steps of 0.1 s), then moving on at its 10 m/s."""
    scene = load_commonroad_scene(write_scenario(tmp_path / "s.xml"), _cfg())
    for k in range(1, 6):
        assert _lookup(scene, 60.0 + k, 1.75, k) == pytest.approx(1.0)
    # beyond its sets: continued at the initial velocity (10 m/s) from the last set
    assert _lookup(scene, 65.0 + 10.0 * 0.5, 1.75, 10) == pytest.approx(1.0)
    track = next(t for t in scene.road.obstacles if t.obstacle_id == 12)
    assert track.occupancies is not None and track.t_last_recorded == pytest.approx(0.5)


def test_start_time_step_sets_the_grid_origin_in_time(tmp_path):
    scene = load_commonroad_scene(write_scenario(tmp_path / "s.xml", start_step=20, start_x="20.0"), _cfg())
    assert scene.grid.t0 == pytest.approx(2.0) and scene.road.t_start == pytest.approx(2.0)
    assert scene.meta["horizon"] == pytest.approx(10.0 - 2.0)
    # obstacle 11 is at x = 30 + 5 * 2 = 40 at the first slice
    assert _lookup(scene, 40.0, 5.25, 0) > 0.9
    # the ego (recorded at x = 20 at step 20) is recognised at the initial time step
    assert scene.meta["dropped_ego"]["id"] == 10


def test_goal_with_time_only_keeps_the_scenario_start(tmp_path):
    goal = "<time><intervalStart>30</intervalStart><intervalEnd>50</intervalEnd></time>"
    scene = load_commonroad_scene(write_scenario(tmp_path / "s.xml", goal=goal), _cfg())
    assert scene.start[:2] == (10.0, 1.75) and not scene.meta["start_goal_sampled"]
    assert scene.road.goal.shapes is None and scene.road.goal.time_interval == pytest.approx((3.0, 5.0))
    assert scene.meta["horizon"] == pytest.approx(5.0)
    # the planners' point: 5 m/s x 5 s = 25 m ahead along the lane
    assert scene.goal == pytest.approx((35.0, 1.75), abs=0.05)
    assert scene.road.goal.contains(np.array([[500.0, 500.0]]), np.array([4.0]))[0]


def test_goal_velocity_orientation_circle_polygon_and_alternatives(tmp_path):
    goal = ("<position><circle><radius>3</radius><center><x>70</x><y>1.75</y></center></circle></position>"
            "<time><intervalStart>50</intervalStart><intervalEnd>70</intervalEnd></time>"
            "<orientation><intervalStart>-0.2</intervalStart><intervalEnd>0.2</intervalEnd></orientation>"
            "<velocity><intervalStart>2</intervalStart><intervalEnd>6</intervalEnd></velocity></goalState>"
            "<goalState><position><polygon><point><x>90</x><y>0</y></point><point><x>100</x><y>0</y></point>"
            "<point><x>100</x><y>3.5</y></point></polygon></position>"
            "<time><intervalStart>80</intervalStart><intervalEnd>90</intervalEnd></time>")
    scene = load_commonroad_scene(write_scenario(tmp_path / "s.xml", goal=goal), _cfg())
    g = scene.road.goal
    assert len(g.alternatives) == 2 and g.time_interval == pytest.approx((5.0, 9.0))
    xy = np.array([[70.0, 1.75], [70.0, 1.75], [70.0, 1.75], [99.0, 1.0], [99.0, 1.0]])
    t = np.array([6.0, 6.0, 8.5, 8.5, 6.0])
    v = np.array([4.0, 8.0, 4.0, 20.0, 4.0])
    th = np.array([0.1, 0.1, 0.1, 3.0, 0.1])
    np.testing.assert_array_equal(g.contains(xy, t, v, th), [True, False, False, True, False])
    assert scene.meta["horizon"] == pytest.approx(9.0)


def test_goal_lanelet(tmp_path):
    goal = ("<position><lanelet ref=\"2\"/></position>"
            "<time><intervalStart>40</intervalStart><intervalEnd>60</intervalEnd></time>")
    scene = load_commonroad_scene(write_scenario(tmp_path / "s.xml", goal=goal), _cfg())
    g = scene.road.goal
    assert g.contains(np.array([[100.0, 5.25], [100.0, 1.75]]), np.array([5.0, 5.0])).tolist() == [True, False]
    assert g.shapes.area == pytest.approx(200.0 * 3.5, rel=1e-6)


def test_horizon_is_capped(tmp_path):
    goal = "<time><intervalStart>10</intervalStart><intervalEnd>400</intervalEnd></time>"
    scene = load_commonroad_scene(write_scenario(tmp_path / "s.xml", goal=goal), _cfg(max_horizon=12.0))
    assert scene.meta["horizon"] == 12.0 and scene.grid.n_slices == 121
    assert any("capped" in n for n in scene.meta["simplifications"])


def test_sidewalks_are_not_drivable_and_small_gaps_close(tmp_path):
    """Lanelets 1 and 2 with a 0.2-m gap form one surface without a wall; a 1-m gap stays a wall; the sidewalk
    lanelet 3 is off the road unless configured."""
    scenario, _ = read_commonroad(write_scenario(tmp_path / "g.xml", gap=0.2))
    drivable, notes = drivable_area(scenario, CommonRoadSceneConfig())
    assert drivable.geom_type == "Polygon" and not drivable.interiors
    assert notes["gap_area_closed_m2"] == pytest.approx(200 * 0.2, rel=1e-3)
    assert drivable.area == pytest.approx(200 * 7.2, rel=1e-3)  # the outer boundary did not grow
    assert drivable.intersects(shapely.Point(100, 3.6))  # inside the former gap
    assert not drivable.intersects(shapely.Point(100, -1.0))  # the sidewalk
    assert notes["non_drivable_lanelets"] == [3]
    # without closing, the gap is a wall inside the road
    raw, raw_notes = drivable_area(scenario, CommonRoadSceneConfig(gap_close=0.0))
    assert raw.geom_type == "MultiPolygon" and raw_notes["gap_area_closed_m2"] == 0.0
    wide, _ = drivable_area(read_commonroad(write_scenario(tmp_path / "w.xml", gap=1.0))[0])
    assert wide.geom_type == "MultiPolygon"
    sidewalk_ok, _ = drivable_area(scenario, CommonRoadSceneConfig(non_drivable_lanelet_types=()))
    assert sidewalk_ok.intersects(shapely.Point(100, -1.0))


def test_red_light_blocks_the_stop_line_while_red(tmp_path):
    """Light 300 on lanelet 1: green for steps 0-19, red for 20-49 (5-s cycle); stop line at x = 100."""
    scene = load_commonroad_scene(write_scenario(tmp_path / "s.xml", traffic_light=True), _cfg())
    assert _lookup(scene, 100.0, 1.75, 10) < 0.05  # green
    assert _lookup(scene, 100.0, 1.75, 30) == pytest.approx(1.0)  # red
    assert _lookup(scene, 100.0, 1.75, 60) < 0.05  # green again (steps 50-69)
    assert _lookup(scene, 100.0, 5.25, 30) < 0.05  # lanelet 2 has no light
    red = [t for t in scene.road.obstacles if t.kind == "red_light"]
    assert len(red) == 2 and red[0].times[0] == pytest.approx(2.0)


def test_start_outside_the_model_domain_is_refused(tmp_path):
    from density_planner.systems.car import CarConfig, KinematicCar

    path = write_scenario(tmp_path / "fast.xml", start_speed=25.0)
    with pytest.raises(DataError, match=r"fast\.xml \(ZAM_Handmade-1_1_T-1\): start speed 25\.00 m/s is outside "
                                        r"the KinematicCar model's domain \(0 <= v <= 10 m/s"):
        load_commonroad_scene(path, _cfg())
    # the limit is read from the system, not a constant of the importer
    wide = KinematicCar(CarConfig(state_max=(50.0, 50.0, 3 * math.pi - 0.2, 30.0, math.pi / 8)))
    scene = load_commonroad_scene(path, _cfg(), system=wide)
    assert scene.start[3] == 25.0 and scene.meta["model_domain"]["v_max"] == 30.0


def test_map_region_is_the_reachable_part_and_the_cell_fits_the_budget(tmp_path):
    path = write_scenario(tmp_path / "s.xml")
    scene = load_commonroad_scene(path, CommonRoadSceneConfig())
    area = scene.meta["map"]["area"]
    reach = reach_distance(5.0, 10.0, 3.0, 10.0)
    assert reach == pytest.approx(5.0 * 5 / 3 + 0.5 * 3 * (5 / 3) ** 2 + 10 * (10 - 5 / 3))
    assert area[1] <= 10.0 + reach + 2 * 10.0 + 1.0 < 200.0  # not the whole 200-m road
    T, NX, NY = scene.grid.shape
    assert T * NX * NY * 4 <= CommonRoadSceneConfig().memory_budget_gib * 2**30
    assert scene.meta["map"]["cell_size"] == scene.grid.cell_size
    small = load_commonroad_scene(path, CommonRoadSceneConfig(memory_budget_gib=0.01))
    assert small.grid.cell_size > scene.grid.cell_size
    assert math.prod(small.grid.shape) * 4 <= 0.01 * 2**30
    with pytest.raises(DataError, match=r"--set commonroad\.memory_budget_gib="):
        load_commonroad_scene(path, CommonRoadSceneConfig(memory_budget_gib=0.0001, max_cell_size=0.2))


def test_scene_with_road_round_trips_through_npz(tmp_path):
    scene = load_commonroad_scene(write_scenario(tmp_path / "s.xml", traffic_light=True), _cfg())
    back = load_scene(save_scene(scene, tmp_path / "scene.npz"))
    assert back.road is not None and len(back.road.obstacles) == len(scene.road.obstacles)
    assert back.road.drivable.equals(scene.road.drivable)
    t = np.array([3.0])
    for a, b in zip(scene.road.obstacle_polygons(t)[:, 0], back.road.obstacle_polygons(t)[:, 0]):
        assert (a is None and b is None) or a.equals_exact(b, 1e-9)


# ------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"lanelet_x": "nan"}, r"lanelet 4 has non-finite vertices"),
        ({"start_x": "nan"}, r"initial state must have a finite position"),
        ({"planning_problem": False}, r"no planning problem"),
    ],
)
def test_bad_scenarios_give_one_clear_line(tmp_path, options, match):
    path = write_scenario(tmp_path / "bad.xml", **options)
    with pytest.raises(DataError, match=match) as info:
        load_commonroad_scene(path, _cfg())
    assert "\n" not in str(info.value) and "bad.xml" in str(info.value)


def test_without_lanelets_and_truncated(tmp_path):
    path = write_scenario(tmp_path / "s.xml")
    root = ET.parse(path).getroot()
    for ll in root.findall("lanelet"):
        root.remove(ll)
    empty = tmp_path / "nolanelets.xml"
    ET.ElementTree(root).write(empty)
    with pytest.raises(DataError, match=r"nolanelets\.xml.*(no lanelets|cannot read)"):
        load_commonroad_scene(empty, _cfg())
    text = path.read_text()
    cut = tmp_path / "truncated.xml"
    cut.write_text(text[: len(text) // 2])
    with pytest.raises(DataError, match=r"truncated\.xml is not a CommonRoad scenario \(not valid XML"):
        load_commonroad_scene(cut, _cfg())


def test_not_a_commonroad_file(tmp_path):
    bad = tmp_path / "other.xml"
    bad.write_text("<?xml version='1.0'?><osm><node id='1'/></osm>")
    with pytest.raises(DataError, match="not a CommonRoad scenario.*<osm>"):
        load_commonroad_scene(bad)
    text = tmp_path / "text.xml"
    text.write_text("this is not xml")
    with pytest.raises(DataError, match="not a CommonRoad scenario.*not valid XML"):
        load_commonroad_scene(text)
    with pytest.raises(DataError, match="not found"):
        load_commonroad_scene(tmp_path / "missing.xml")


def test_goal_velocity_outside_the_model_domain_is_refused(tmp_path):
    goal = ("<position>" + "<rectangle><length>10</length><width>3.5</width><orientation>0</orientation>"
            "<center><x>80</x><y>1.75</y></center></rectangle></position>"
            "<time><intervalStart>80</intervalStart><intervalEnd>100</intervalEnd></time>"
            "<velocity><intervalStart>12.5</intervalStart><intervalEnd>18</intervalEnd></velocity>")
    with pytest.raises(DataError, match=r"goal's velocity interval \[12\.50, 18\.00\] m/s lies outside the "
                                        r"KinematicCar model's domain \(0 <= v <= 10 m/s"):
        load_commonroad_scene(write_scenario(tmp_path / "g.xml", goal=goal), _cfg())


def test_far_coordinates_are_translated_to_a_local_frame(tmp_path):
    """UTM-like coordinates (float32 resolution 0.5 m at 5e6 m) are moved by a multiple of 100 m, recorded."""
    path = write_scenario(tmp_path / "s.xml")
    root = ET.parse(path).getroot()
    for tag, off in (("x", 686000.0), ("y", 5334000.0)):
        for el in root.iter(tag):
            el.text = str(float(el.text) + off)
    far = tmp_path / "utm.xml"
    ET.ElementTree(root).write(far)
    scene = load_commonroad_scene(far, _cfg())
    assert scene.meta["frame_offset"] == [686000.0, 5334000.0]
    assert scene.start[:2] == pytest.approx((10.0, 1.75), abs=1e-6)
    near = load_commonroad_scene(path, _cfg())
    assert scene.goal == pytest.approx(near.goal, abs=1e-6)
    assert scene.road.goal.shapes.equals_exact(near.road.goal.shapes, 1e-6)
    assert near.meta["frame_offset"] == [0.0, 0.0]
    # the lanes the route seeds follow are in the scene's frame too (they were in the file's, 5e6 m away)
    from density_planner.environment.lanes import scene_lane_graph

    lanes, lanes_near = scene_lane_graph(scene), scene_lane_graph(near)
    assert lanes is not None and lanes_near is not None and lanes.ids == lanes_near.ids
    for i in lanes.ids:
        assert np.allclose(lanes[i].center, lanes_near[i].center, atol=1e-6)
    assert lanes.lanes_at(scene.start[:2], scene.start[2]) == lanes_near.lanes_at(near.start[:2], near.start[2]) != []


def test_a_start_the_road_car_could_drive_out_of_its_position_box_from_is_translated(tmp_path):
    """A start 5.9 km out (below recenter_above, but the road car's positions are bounded by +-1 km: DEU_A9-3_1)
    is moved by a multiple of 100 m to within 50 m of the origin, so the problem built on it is inside the model;
    the same scenario near the origin is not moved."""
    from density_planner.planners import PlanningProblem
    from density_planner.systems.registry import make_system

    car = make_system("car", "road")
    path = write_scenario(tmp_path / "s.xml")
    root = ET.parse(path).getroot()
    for tag, off in (("x", 331.0), ("y", -5863.0)):
        for el in root.iter(tag):
            el.text = str(float(el.text) + off)
    far = tmp_path / "far.xml"
    ET.ElementTree(root).write(far)
    scene = load_commonroad_scene(far, _cfg(), system=car)
    assert scene.meta["frame_offset"] == [300.0, -5900.0]
    assert scene.start[:2] == pytest.approx((41.0, 38.75), abs=1e-6)
    assert max(abs(c) for c in scene.start[:2]) <= 50.0
    PlanningProblem.from_scene(scene, system=car)  # refused before: "the start is outside the model's state box"
    assert load_commonroad_scene(path, _cfg(), system=car).meta["frame_offset"] == [0.0, 0.0]


def test_the_ego_size_is_the_systems_body(commonroad_dir):
    """One owner of the vehicle's size: the road scene (road barrier, verdict) takes the system's footprint; the
    import's vehicle_length/width only serve a point system."""
    from density_planner.systems.linear import LinearSystem
    from density_planner.systems.registry import make_system

    path = commonroad_dir / "USA_Peach-4_8_T-1.xml"
    for system in (make_system("car", "road"), make_system("ks", "road")):
        road = load_commonroad_scene(path, _cfg(), system=system).road
        assert (road.vehicle_length, road.vehicle_width) == (system.footprint.length, system.footprint.width)
    point = LinearSystem([[0, 0, 1, 0], [0, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0]], [[0, 0], [0, 0], [1, 0], [0, 1]])
    assert point.footprint.is_point
    # a point has no speed state and no acceleration input: the importer says which fact is missing
    with pytest.raises(ValueError, match="no speed state"):
        load_commonroad_scene(path, _cfg(vehicle_length=3.0), system=point)


def test_offroad_margin_offsets_the_grid_quantisation():
    """A cell is off the road when its centre lies more than ``offroad_margin`` outside the drivable area (default:
    half the cell diagonal, 0.71 m at 1-m cells); 0 marks every centre outside."""
    import shapely

    from density_planner.environment.commonroad import static_map

    road = shapely.box(0.0, 0.0, 10.0, 3.0)
    args = dict(drivable=road, static_polygons=[])
    # cell centres at x = -2.5 .. 12.5, y = -1.5 .. 4.5 (origin (-2.5, -1.5), 1-m cells)
    auto, _ = static_map(None, (-2.5, -1.5), 1.0, (16, 7), CommonRoadSceneConfig(), **args)
    exact, _ = static_map(None, (-2.5, -1.5), 1.0, (16, 7), CommonRoadSceneConfig(offroad_margin=0.0), **args)
    # centre (5.5, -0.5): 0.5 m outside the road; (5.5, -1.5): 1.5 m outside; (5.5, 1.5): on the road
    assert exact[8, 1] == 1.0 and auto[8, 1] == 0.0
    assert exact[8, 0] == 1.0 and auto[8, 0] == 1.0
    assert exact[8, 3] == 0.0 and auto[8, 3] == 0.0
    assert auto.sum() < exact.sum()
    with pytest.raises(ValueError, match="offroad_margin"):
        CommonRoadSceneConfig(offroad_margin=-1.0)


def test_scene_gives_the_planners_initial_uncertainty(tmp_path):
    """``commonroad.initial_error`` (position, heading, speed half-widths) replaces those entries of the system's XE0
    box in the planner's initial law; the hidden heading bias keeps the system's; None: the system's box."""
    from density_planner.environment.random_scene import random_scene
    from density_planner.planners.problem import PlanningProblem, initial_error_box
    from density_planner.systems.car import KinematicCar, car_domain

    car = KinematicCar(car_domain("road"))
    scene = load_commonroad_scene(write_scenario(tmp_path / "s.xml"), _cfg())
    assert scene.meta["initial_error"] == {"position": 0.5, "heading": 0.05, "speed": 0.3}
    box = initial_error_box(scene, car)
    assert box == pytest.approx((0.5, 0.5, 0.05, 0.3, car.initial_error_max[4]))
    law = PlanningProblem.from_scene(scene, system=car).initial_distribution
    lo, hi = law.support
    assert (hi - lo).tolist() == pytest.approx([2 * b for b in box])
    paper = load_commonroad_scene(write_scenario(tmp_path / "p.xml"), _cfg(initial_error=None))
    assert initial_error_box(paper, car) == tuple(car.initial_error_max)
    assert initial_error_box(random_scene(0), car) == tuple(car.initial_error_max)
    with pytest.raises(ValueError, match="initial_error"):
        CommonRoadSceneConfig(initial_error=(0.5, 0.0, 0.3))


def test_positions_given_as_shapes_read_as_their_centres(commonroad_dir):
    """CommonRoad states may give an uncertain position as a shape (DEU_A9-3_1: RectOccupancy, whose centre is a
    shapely point): the importer reads its centre, not a traceback; with the default configuration (the recorded
    ego's duplicate looked for at the start) the file loads."""
    from commonroad.geometry.occupancy.circle_occupancy import CircleOccupancy
    from commonroad.geometry.occupancy.rect_occupancy import RectOccupancy

    from density_planner.environment.commonroad import _point

    assert np.allclose(_point(np.array([1.0, 2.0])), [1.0, 2.0])
    assert np.allclose(_point(RectOccupancy(shapely.Point(3.0, -1.0), 2.0, 4.0, 0.3)), [3.0, -1.0])
    assert np.allclose(_point(CircleOccupancy(1.5, shapely.Point(-2.0, 5.0))), [-2.0, 5.0])

    class _Polygon:  # a shape without a centre attribute: its centroid
        shapely_object = shapely.box(0.0, 0.0, 2.0, 4.0)

    assert np.allclose(_point(_Polygon()), [1.0, 2.0])
    assert _point(None) is None and _point("a b") is None and _point([1.0, 2.0, 3.0]) is None
    from density_planner.systems.registry import make_system

    scene = load_commonroad_scene(commonroad_dir / "DEU_A9-3_1_T-1.xml", system=make_system("car", "road"))
    assert scene.road is not None and len(scene.road.obstacles) > 0

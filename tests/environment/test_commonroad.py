"""CommonRoad importer on the two shipped NGSIM scenarios (skipped without commonroad-io or the shared
data)."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch

pytest.importorskip("commonroad", reason="commonroad-io (extra 'commonroad') is not installed")
shapely = pytest.importorskip("shapely")

from density_planner.environment import CommonRoadSceneConfig, load_commonroad_scene  # noqa: E402
from density_planner.environment.commonroad import read_commonroad, static_map  # noqa: E402
from density_planner.errors import DataError  # noqa: E402

SCENARIOS = ["USA_US101-4_1_T-1.xml", "USA_Peach-4_8_T-1.xml"]


def _centre_points(scenario):
    """Points on the lanelet centre lines (mean of left and right bound vertices), without the first and last
    ones (they lie on the lanelet's end edges, at a dead end on the map's border)."""
    pts = [
        0.5 * (np.asarray(ll.left_vertices) + np.asarray(ll.right_vertices))[1:-1]
        for ll in scenario.lanelet_network.lanelets
    ]
    return np.concatenate(pts)


@pytest.mark.parametrize("name", SCENARIOS)
def test_loads_with_planning_problem(commonroad_dir, name):
    scene = load_commonroad_scene(commonroad_dir / name)
    grid = scene.grid
    assert grid.n_slices == 101 and grid.dt == 0.1 and grid.cell_size == 0.1
    scenario, problems = read_commonroad(commonroad_dir / name)
    problem = next(iter(problems.planning_problem_dict.values()))
    st = problem.initial_state
    assert scene.start[:2] == pytest.approx(tuple(st.position))
    assert math.cos(scene.start[2]) == pytest.approx(math.cos(st.orientation))
    assert scene.start[3] == pytest.approx(st.velocity) and scene.start[4] == 0.0
    assert not scene.meta["start_goal_sampled"]
    xmin, xmax, ymin, ymax = grid.bounds
    assert xmin <= scene.goal[0] <= xmax and ymin <= scene.goal[1] <= ymax
    assert scene.planning_box == pytest.approx((xmin + 0.1, xmax - 0.1, ymin + 0.1, ymax - 0.1))


def test_goal_is_the_centre_of_the_goal_region(commonroad_dir):
    scene = load_commonroad_scene(commonroad_dir / SCENARIOS[0])
    # US101: the goal is one rectangle centred at (17.836, -17.218)
    assert scene.goal == pytest.approx((17.836, -17.2178), abs=1e-3)


@pytest.mark.parametrize("name", SCENARIOS)
def test_lanelets_are_free_and_far_off_cells_occupied(commonroad_dir, name):
    scenario, _ = read_commonroad(commonroad_dir / name)
    cfg = CommonRoadSceneConfig()
    origin, h, size = (-60.0, -60.0), 0.25, (481, 481)  # 120 m x 120 m around the origin
    static, _ = static_map(scenario, origin, h, size, cfg)
    xs = origin[0] + h * np.arange(size[0])
    ys = origin[1] + h * np.arange(size[1])
    pts = _centre_points(scenario)
    inside = (pts[:, 0] > xs[0]) & (pts[:, 0] < xs[-1]) & (pts[:, 1] > ys[0]) & (pts[:, 1] < ys[-1])
    pts = pts[inside]
    assert len(pts) > 10
    i = np.rint((pts[:, 0] - origin[0]) / h).astype(int)
    j = np.rint((pts[:, 1] - origin[1]) / h).astype(int)
    # nearest cell centre of a centre-line point is within 0.18 m of it: inside any lane wider than 0.4 m
    assert static[i, j].max() == 0.0
    # cells more than 2 m from every lanelet are occupied
    union = shapely.union_all(
        [
            shapely.Polygon(np.vstack([ll.left_vertices, ll.right_vertices[::-1]])).buffer(0)
            for ll in scenario.lanelet_network.lanelets
        ]
    )
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    far = shapely.distance(union, shapely.points(gx.ravel(), gy.ravel())).reshape(gx.shape) > 2.0
    assert far.any() and static[far].min() == 1.0


def test_far_off_cells_occupied_in_every_slice(commonroad_dir):
    scene = load_commonroad_scene(commonroad_dir / SCENARIOS[1])
    # Peach: the corner (x_max, y_min) is off the road network
    xmin, xmax, ymin, ymax = scene.grid.bounds
    corner = torch.tensor([xmax - 1.0, ymin + 1.0], dtype=torch.float64)
    for k in (0, 50, 100):
        assert float(scene.grid.lookup(corner, k)) == 1.0


def test_dynamic_obstacles_are_drawn(commonroad_dir):
    scene = load_commonroad_scene(commonroad_dir / SCENARIOS[0])
    scenario, _ = read_commonroad(commonroad_dir / SCENARIOS[0])
    xmin, xmax, ymin, ymax = scene.grid.bounds
    seen = 0
    for obs in scenario.dynamic_obstacles:
        x, y = obs.initial_state.position
        if xmin + 1 < x < xmax - 1 and ymin + 1 < y < ymax - 1:
            # the obstacle's centre is the footprint's peak: 1 (clamped sum; coarse lattice ~1 %)
            assert float(scene.grid.lookup(torch.tensor([x, y], dtype=torch.float64), 0)) >= 0.98
            seen += 1
    assert seen >= 3
    assert len(scene.meta["dynamic_obstacles"]) == len(scenario.dynamic_obstacles)


def test_without_planning_problem_the_sampler_is_used(commonroad_dir, tmp_path):
    tree = ET.parse(commonroad_dir / SCENARIOS[0])
    root = tree.getroot()
    for pp in root.findall("planningProblem"):
        root.remove(pp)
    path = tmp_path / "no_problem.xml"
    tree.write(path)
    scene = load_commonroad_scene(path, CommonRoadSceneConfig(cell_size=0.5, seed=3))
    assert scene.meta["start_goal_sampled"] and scene.meta["planning_problem"] is None
    assert 10 <= math.hypot(scene.goal[0] - scene.start[0], scene.goal[1] - scene.start[1]) <= 70


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

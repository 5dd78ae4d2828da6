"""Per-run metrics and their aggregation, on hand-built trajectories and hand-made records."""

from __future__ import annotations

import math

import pytest
import torch
from eval_testdata import record

from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.scene import Scene
from density_planner.evaluation.config import EvaluationConfig
from density_planner.evaluation.metrics import (
    cost_increase,
    evaluation_box,
    failure_flags,
    monte_carlo_metrics,
    run_metrics,
    summarise,
)
from density_planner.systems.car import CarConfig

CAR = CarConfig()


def _scene(p_block: float = 0.0) -> Scene:
    """24 m x 40 m map; optionally a block of occupancy ``p_block`` for x in [-1, 1], y in [-5, -3] (all times)."""
    probs = torch.zeros(101, 241, 401)
    if p_block:
        probs[:, 110:131, 250:271] = p_block
    grid = OccupancyGrid(probs, origin=(-12.0, -30.0), cell_size=0.1, dt=0.1)
    return Scene(grid, (0.0, -20.0, math.pi / 2, 3.0), (0.0, 5.0), (-9.9, 9.9, -29.9, 9.9))


def _straight(x: float = 0.0, y0: float = -20.0, y1: float = 5.0, T: int = 101) -> torch.Tensor:
    s = torch.zeros(T, 5)
    s[:, 0] = x
    s[:, 1] = torch.linspace(y0, y1, T)
    s[:, 2] = math.pi / 2
    s[:, 3] = 2.5
    return s


def _box(scene):
    return evaluation_box(scene, CAR.state_min, CAR.state_max)


def test_straight_line_to_the_goal_in_free_space():
    scene = _scene()
    u = torch.full((100, 2), 0.5)
    m = run_metrics(scene, _straight(), u, u, box=_box(scene))
    assert m["goal_cost"] == pytest.approx(0.0, abs=1e-8)
    assert m["final_distance"] == pytest.approx(0.0, abs=1e-4)
    assert m["input_cost"] == pytest.approx(100 * 2 * 0.25)  # sum over 100 steps of ||u||^2
    assert m["bounds_cost"] == 0.0 and m["collision_cost"] == 0.0
    assert m["collision_probability_max"] == 0.0 and len(m["collision_probability"]) == 101
    assert m["steps"] == 100


def test_final_distance_and_goal_cost():
    scene = _scene()
    m = run_metrics(scene, _straight(x=3.0, y1=1.0), torch.zeros(100, 2), box=_box(scene))
    assert m["goal_cost"] == pytest.approx(9.0 + 16.0, rel=1e-5)  # (3, 1) vs goal (0, 5)
    assert m["final_distance"] == pytest.approx(5.0, rel=1e-5)
    assert math.isnan(m["input_cost_applied"])


def test_collision_probability_and_cost_through_a_block():
    scene = _scene(p_block=0.8)
    m = run_metrics(scene, _straight(), torch.zeros(100, 2), box=_box(scene))
    # the occupancy of the cell met: exactly the block's value while inside it
    assert m["collision_probability_max"] == pytest.approx(0.8)
    inside = sum(1 for p in m["collision_probability"] if p > 0)
    assert 6 <= inside <= 10  # 2 m of 25 m at 0.25 m per step
    assert m["collision_probability_sum"] == pytest.approx(0.8 * inside, rel=1e-5)
    assert m["collision_cost"] > 0


def test_bounds_of_the_evaluation_box():
    scene = _scene()
    s = _straight()
    s[50:, 3] = 10.5  # 0.5 m/s above v_max = 10 for 51 steps
    m = run_metrics(scene, s, torch.zeros(100, 2), box=_box(scene))
    assert m["bounds_cost"] == pytest.approx(51 * 0.25, rel=1e-5)
    # the planning box (+-9.9 m) is not the evaluation box: x = 11 is inside the map and the car's box
    m2 = run_metrics(scene, _straight(x=11.0), torch.zeros(100, 2), box=_box(scene))
    assert m2["bounds_cost"] == 0.0


def test_evaluation_box_positions():
    scene = _scene()
    low, high = evaluation_box(scene, CAR.state_min, CAR.state_max, "auto")
    assert (low[0], high[0], low[1], high[1]) == (-50.0, 50.0, -50.0, 50.0)  # the map lies inside: the car box
    low, high = evaluation_box(scene, CAR.state_min, CAR.state_max, "map")
    assert (low[0], high[0], low[1], high[1]) == pytest.approx((-12.0, 12.0, -30.0, 10.0))
    # a map reaching beyond +-50 m: "auto" uses the map
    probs = torch.zeros(101, 10, 10)
    far = Scene(OccupancyGrid(probs, origin=(-80.0, 0.0), cell_size=0.1, dt=0.1), (-79.5, 0.5, 0.0, 1.0),
                (-79.2, 0.6), (-80.0, -79.1, 0.0, 0.9))
    low, _ = evaluation_box(far, CAR.state_min, CAR.state_max, "auto")
    assert low[0] == pytest.approx(-80.0)
    with pytest.raises(ValueError, match="position_bounds"):
        evaluation_box(scene, CAR.state_min, CAR.state_max, "nowhere")


def test_monte_carlo_frequency():
    scene = _scene(p_block=0.8)
    through = _straight()
    beside = _straight(x=5.0)
    m = monte_carlo_metrics(scene, [through, beside, beside, beside], threshold=0.5)
    assert m["mc_samples"] == 4
    assert m["mc_collision_frequency"] == pytest.approx(0.25)
    assert m["mc_collision_mean"] == pytest.approx(0.8 / 4)
    assert m["mc_final_distance_mean"] == pytest.approx((0 + 3 * 5) / 4, rel=1e-5)
    # trajectories of different lengths (an MPC stopping early) are handled one by one
    m2 = monte_carlo_metrics(scene, [through, beside[:50]], threshold=0.5)
    assert m2["mc_samples"] == 2 and m2["mc_collision_frequency"] == pytest.approx(0.5)
    # threshold above the block: no sample counts as colliding
    assert monte_carlo_metrics(scene, [through], threshold=0.9)["mc_collision_frequency"] == 0.0
    empty = monte_carlo_metrics(scene, [])
    assert empty["mc_samples"] == 0 and empty["mc_collision_frequency"] is None


@pytest.mark.parametrize(
    ("metrics", "solved", "reason"),
    [
        ({"collision_cost": 1.0, "final_distance": 1.0, "bounds_cost": 0.0}, True, ""),
        ({"collision_cost": 11.0, "final_distance": 1.0, "bounds_cost": 0.0}, True, "collision"),
        ({"collision_cost": 1.0, "final_distance": 4.6, "bounds_cost": 0.0}, True, "goal"),
        ({"collision_cost": 1.0, "final_distance": 4.4, "bounds_cost": 2e-4}, True, "bounds"),
        ({"collision_cost": 12.0, "final_distance": 5.0, "bounds_cost": 0.0}, False, "no_solution+collision+goal"),
        ({"collision_cost": float("nan"), "final_distance": 1.0, "bounds_cost": 0.0}, True, "collision"),
        (None, True, "no_solution+collision+goal+bounds"),
    ],
)
def test_failure_flags(metrics, solved, reason):
    flags, got = failure_flags(metrics, solved, EvaluationConfig())
    assert got == reason
    assert flags["no_solution"] == (not solved or metrics is None)


def test_failure_flags_without_cost_thresholds():
    flags, reason = failure_flags({"collision_cost": 50.0, "final_distance": 9.0, "bounds_cost": 1.0}, True,
                                  EvaluationConfig(), cost_thresholds=False)
    assert reason == "" and not any(flags.values())


def test_cost_increase_against_the_best_valid_method():
    recs = [
        # env a: A best on collision (1), B 3, C failed with collision 0 -> ignored
        record("a", "A", collision=1.0, goal=4.0), record("a", "B", collision=3.0, goal=1.0),
        record("a", "C", collision=0.0, goal=0.0, failed=True),
        # env b: only B valid -> it is its own best (increase 0)
        record("b", "A", failed=True), record("b", "B", collision=5.0, goal=2.0),
        record("b", "C", failed=True),
    ]
    cri = cost_increase(recs, "collision_cost")
    gci = cost_increase(recs, "goal_cost")
    assert cri[("artificial", "A", "unbiased")] == pytest.approx(0.0)
    assert cri[("artificial", "B", "unbiased")] == pytest.approx((2.0 + 0.0) / 2)
    assert math.isnan(cri[("artificial", "C", "unbiased")])  # never valid
    assert gci[("artificial", "A", "unbiased")] == pytest.approx(3.0)
    assert gci[("artificial", "B", "unbiased")] == pytest.approx(0.0)


def test_variants_are_methods_and_settings_separate():
    recs = [
        record("a", "A", "unbiased", collision=1.0), record("a", "A", "biased", collision=2.0),
        record("a", "A", "unbiased", collision=7.0, setting="real"),
        record("a", "B", "unbiased", collision=9.0, setting="real"),
    ]
    cri = cost_increase(recs, "collision_cost")
    assert cri[("artificial", "A", "biased")] == pytest.approx(1.0)
    assert cri[("real", "A", "unbiased")] == pytest.approx(0.0)
    assert cri[("real", "B", "unbiased")] == pytest.approx(2.0)


def test_summary_failure_rate_and_times_over_valid_runs_only():
    recs = [
        record("a", "A", offline=10.0, online=0.02, mc=0.5),
        record("b", "A", offline=1000.0, online=5.0, failed=True, mc=1.0),  # must not enter the time means
        record("c", "A", offline=20.0, online=0.04, mc=None),
        record("a", "B", failed=True, status="error", reason="no_solution"),
        record("b", "B", failed=True, reason="collision+goal"),
        record("c", "B", offline=3.0, goal=9.0),
    ]
    rows = {s.planner: s for s in summarise(recs)}
    a, b = rows["A"], rows["B"]
    assert (a.runs, a.valid, a.failures) == (3, 2, 1)
    assert a.failure_rate == pytest.approx(1 / 3)
    assert a.offline_time == pytest.approx(15.0)
    assert a.online_time == pytest.approx(0.03)
    assert a.mc_collision_frequency == pytest.approx(0.75) and a.mc_runs == 2  # MC over all runs that have it
    assert b.failure_rate == pytest.approx(2 / 3) and b.errors == 1
    assert b.failure_reasons == {"no_solution": 1, "collision": 1, "goal": 1}
    assert b.final_distance == pytest.approx(3.0)
    assert a.gci == pytest.approx(0.0) and b.gci == pytest.approx(9.0)  # env c: A has goal 0, B 9


def test_summary_of_a_method_that_always_fails():
    rows = summarise([record("a", "A", failed=True), record("b", "A", failed=True)])
    assert rows[0].failure_rate == 1.0
    assert math.isnan(rows[0].cri) and math.isnan(rows[0].offline_time)

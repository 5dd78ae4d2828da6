"""``bench commonroad``: every scenario of a folder, refused ones as records, the verdict in every record, resumable;
``solution.xml`` round trip through commonroad-io's reader."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from eval_testdata import TINY_DP

from density_planner.cli import main
from density_planner.evaluation.commonroad_bench import commonroad_summary, summary_markdown
from density_planner.evaluation.environments import shipped_commonroad_dir
from density_planner.io.commonroad_solution import SolutionConfig, read_solution, write_solution

TINY = [f"--set=density_planner.{k}={v}" for k, v in TINY_DP.items()] + ["--set=evaluation.mc_samples_tracked=2"]
SHIPPED = shipped_commonroad_dir() / "USA_US101-4_1_T-1.xml"


def _folder(tmp_path):
    d = tmp_path / "scenarios"
    d.mkdir()
    shutil.copy(SHIPPED, d / SHIPPED.name)
    text = SHIPPED.read_text()
    (d / "broken.xml").write_text(text[: len(text) // 3])  # truncated: refused with one line
    return d


@pytest.mark.slow
def test_bench_commonroad_records_verdicts_and_refusals(tmp_path, capsys):
    scen = _folder(tmp_path)
    out = tmp_path / "out"
    args = ["bench", "commonroad", "--scenarios", str(scen), "--planners", "density", "--workers", "1",
            "--no-progress", "--plot-envs", "0", *TINY, "--out", str(out)]
    assert main(args) == 0
    printed = capsys.readouterr().out
    recs = {p.name.split("__")[0]: json.loads(p.read_text()) for p in (out / "records" / "commonroad").glob("*.json")}
    assert set(recs) == {"cr-broken", "cr-USA_US101-4_1_T-1"}
    refused = recs["cr-broken"]
    assert refused["status"] == "refused" and refused["verdict"] is None and "\n" not in refused["message"]
    planned = recs["cr-USA_US101-4_1_T-1"]
    v = planned["verdict"]
    assert v["status"] in ("success", "failed")
    assert all(isinstance(v[k], bool) for k in ("goal_reached", "collision_free", "on_road", "within_model"))
    assert v["details"]["n_states"] == len(planned["trajectory"])
    # the record's failure is the verdict's (not the paper's goal-point thresholds)
    assert planned["failed"] == (v["status"] != "success")
    parts = {"goal": "goal_reached", "collision": "collision_free", "off_road": "on_road",
             "outside_model": "within_model"}
    assert set(filter(None, planned["failure_reason"].split("+"))) == {r for r, k in parts.items() if not v[k]}
    table = (out / "summary_commonroad.md").read_text()
    assert "| density | 2 | 1 | 1 (0) |" in table and "Refused scenarios" in table and table in printed
    # resumable: nothing left to do
    assert main(args) == 0
    assert "2 already done, 0 written" in capsys.readouterr().out


def test_summary_counts_parts_and_refusals():
    def rec(env, status, verdict=None, msg=""):
        return {"setting": "commonroad", "planner": "density", "env": env, "status": status, "verdict": verdict,
                "message": msg, "timings": {"offline": 2.0}}

    ok = {"status": "success", "goal_reached": True, "collision_free": True, "on_road": True, "within_model": True,
          "p_coll_max": 0.1, "details": {"final_goal_distance": 0.0}}
    bad = dict(ok, status="failed", on_road=False, p_coll_max=0.3, details={"final_goal_distance": 2.0})
    s = commonroad_summary([rec("a", "success", ok), rec("b", "success", bad),
                            rec("c", "refused", msg="c.xml (C): start speed 42.0 m/s > 10 m/s"),
                            rec("d", "refused", msg="d.xml (D): start speed 30.5 m/s > 10 m/s")])
    row = s["rows"][0]
    assert row["scenarios"] == 4 and row["refused"] == 2 and row["planned"] == 2 and row["success"] == 1
    assert row["success_rate"] == 0.25 and row["success_rate_planned"] == 0.5
    assert row["on_road_rate"] == 0.5 and row["goal_reached_rate"] == 1.0
    assert row["p_coll_max_mean"] == pytest.approx(0.2) and row["final_goal_distance_median"] == pytest.approx(1.0)
    assert sum(s["refusals"]["density"].values()) == 2 and len(s["refusals"]["density"]) == 1  # one reason
    assert "2 x c: c.xml" in summary_markdown(s).replace("cr-", "")


def test_bench_commonroad_needs_scenarios(tmp_path, capsys):
    assert main(["bench", "commonroad", "--out", str(tmp_path)]) == 2
    assert "needs --scenarios DIR" in capsys.readouterr().err
    assert main(["bench", "commonroad", "--scenarios", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "holds no CommonRoad scenarios" in capsys.readouterr().err


@pytest.mark.parametrize("model", ["KS", "ST", "PM"])
def test_solution_round_trips_through_commonroad_reader(tmp_path, model):
    t = 0.1 * np.arange(31)
    x = np.stack([3.0 * t, 0.5 * t**2, 0.2 * t, 3.0 + 0 * t, 0 * t], axis=1)  # turning at 0.2 rad/s, 3 m/s
    u = np.tile([0.2, 0.0], (30, 1))
    path = write_solution(tmp_path / "solution.xml", x, u, 0.1, scenario_id="USA_US101-4_1_T-1",
                          planning_problem_id=458, scenario_dt=0.1, initial_time_step=5,
                          config=SolutionConfig(vehicle_model=model, cost_function="WX1" if model == "PM" else "SM1"),
                          computation_time=1.5)
    sol = read_solution(path)
    assert str(sol.scenario_id) == "USA_US101-4_1_T-1"
    pps = sol.planning_problem_solutions[0]
    assert pps.planning_problem_id == 458 and pps.vehicle_model.name == model
    states = pps.trajectory.state_list
    assert [s.time_step for s in states] == list(range(5, 36))
    np.testing.assert_allclose([s.position for s in states], x[:, :2], atol=1e-9)
    if model == "PM":
        np.testing.assert_allclose([s.velocity for s in states], 3.0 * np.cos(x[:, 2]), atol=1e-9)
    else:
        np.testing.assert_allclose([s.orientation for s in states], x[:, 2], atol=1e-9)
        # kinematic single-track: theta' = v / l_wb tan(delta) reproduces the car's yaw rate
        wheelbase = 1.1561957064 + 1.4227170936  # BMW 320i (vehicle type 2)
        np.testing.assert_allclose([3.0 / wheelbase * np.tan(s.steering_angle) for s in states], 0.2, atol=1e-9)


def test_solution_resamples_to_the_scenario_time_step(tmp_path):
    t = 0.1 * np.arange(21)
    x = np.stack([2.0 * t, 0 * t, 0 * t, 2.0 + 0 * t, 0 * t], axis=1)
    path = write_solution(tmp_path / "s.xml", x, None, 0.1, scenario_id="ZAM_Test-1_1_T-1", planning_problem_id=1,
                          scenario_dt=0.04, initial_time_step=0)
    states = read_solution(path).planning_problem_solutions[0].trajectory.state_list
    assert len(states) == 51  # 0 .. 2.0 s every 0.04 s
    np.testing.assert_allclose([s.position[0] for s in states], 2.0 * 0.04 * np.arange(51), atol=1e-9)


def test_solution_is_written_in_the_file_frame(tmp_path):
    # the importer moves far (UTM) coordinates to a local frame; the solution goes back to the file's frame
    x = np.stack([np.linspace(0, 3, 11), np.zeros(11), np.zeros(11), 3.0 + np.zeros(11), np.zeros(11)], axis=1)
    path = write_solution(tmp_path / "s.xml", x, None, 0.1, scenario_id="ZAM_Test-1_1_T-1", planning_problem_id=1,
                          scenario_dt=0.1, initial_time_step=0, frame_offset=(692000.0, 5339000.0))
    states = read_solution(path).planning_problem_solutions[0].trajectory.state_list
    np.testing.assert_allclose([s.position for s in states], x[:, :2] + [692000.0, 5339000.0], atol=1e-6)
    assert x[0, 0] == 0.0  # the caller's array is not modified


def test_solution_config_rejects_unknown_names():
    with pytest.raises(ValueError, match="vehicle_model"):
        SolutionConfig(vehicle_model="XX")
    with pytest.raises(ValueError, match="cost_function"):
        SolutionConfig(cost_function="NOPE")
    with pytest.raises(ValueError, match="for vehicle model PM"):
        SolutionConfig(vehicle_model="PM", cost_function="SM1")


def test_solution_config_default_pair_is_supported_by_commonroad():
    """The default vehicle model and cost function are not checked against commonroad-io at construction (the
    import costs ~0.1 s of every command): they must be a pair it supports."""
    from commonroad.common.solution import SupportedCostFunctions

    default = SolutionConfig()
    assert default.cost_function in [c.name for c in SupportedCostFunctions[default.vehicle_model].value]


@pytest.mark.slow
def test_plan_commonroad_writes_verdict_and_solution(tmp_path, capsys):
    out = tmp_path / "p"
    rc = main(["plan", "--env", "commonroad", "--file", str(SHIPPED), *TINY, "--no-progress", "--no-gif",
               "--out", str(out)])
    data = json.loads((out / "plan.json").read_text())
    v = data["verdict"]
    assert v["basis"] == "road" and data["status"] == v["status"]
    assert rc == (0 if v["status"] == "success" else 3)  # a failed verdict still writes every file
    for name in ("plan.json", "config.toml", "plan.png", "solution.xml"):
        assert (out / name).stat().st_size > 0
    sol = read_solution(out / "solution.xml")
    states = sol.planning_problem_solutions[0].trajectory.state_list
    planned = np.asarray(data["states"])
    np.testing.assert_allclose([s.position for s in states[: len(planned)]], planned[: len(states), :2], atol=1e-4)
    assert v["status"] in capsys.readouterr().out


def test_verdict_failure_follows_the_road_verdict_only():
    from density_planner.evaluation.verdict import verdict_failure

    ok = {"status": "success", "goal_reached": True, "collision_free": True, "on_road": True, "within_model": True,
          "basis": "road"}
    assert verdict_failure(ok, True) == ({"no_solution": False, "goal": False, "collision": False,
                                          "off_road": False, "outside_model": False}, "")
    flags, reason = verdict_failure(dict(ok, status="failed", goal_reached=False, on_road=False), True)
    assert reason == "goal+off_road" and flags["off_road"] and not flags["collision"]
    assert verdict_failure(dict(ok, status="error"), True)[1] == "no_solution"
    assert verdict_failure(ok, False)[1] == "no_solution"
    assert verdict_failure(dict(ok, basis="occupancy"), True) is None  # the paper's scenes keep their thresholds
    assert verdict_failure(None, True) is None


def test_risk_calibration_counts_agreement_within_standard_errors():
    from density_planner.evaluation.commonroad_bench import risk_calibration, summary_markdown

    def rec(env, p, p_se, q, q_se):
        return {"env": env, "plan": {"collision_probability_any": p, "collision_probability_any_se": p_se},
                "metrics": {"mc_collision_mean": q, "mc_collision_se": q_se}}

    recs = [rec("a", 0.50, 0.03, 0.55, 0.04),  # |d| = 0.05 <= 3 * 0.05
            rec("b", 0.10, 0.01, 0.65, 0.05),  # far apart
            rec("c", 0.0, 0.0, 0.005, 0.0),  # the 0.01 floor
            {"env": "d", "plan": {"collision_probability_any": None}, "metrics": {}}]  # not checked
    cal = risk_calibration(recs)
    assert cal["calibration_checked"] == 3 and cal["calibrated"] == 2
    assert cal["p_any_mean"] == pytest.approx(0.2) and cal["mc_collision_mean"] == pytest.approx(1.205 / 3)
    assert cal["calibration_worst"][0] == ("b", 0.1, 0.65)
    assert cal["learned_checked"] == 0
    recs[1]["plan"]["collision_probability_any_predictor"] = 0.4  # the learned estimate, 0.25 off
    recs[0]["plan"]["collision_probability_any_predictor"] = 0.5
    cal = risk_calibration(recs)
    assert cal["learned_checked"] == 2 and cal["learned_off_by_0_1"] == 1
    row = {"planner": "density", "scenarios": 4, "refused": 0, "planned": 4, "errors": 0, "success": 1,
           "success_rate": 0.25, "success_rate_planned": 0.25, "p_coll_max_mean": 0.1,
           "final_goal_distance_median": 1.0, "planning_time_median": 2.0,
           **{f"{p}_rate": 1.0 for p in ("goal_reached", "collision_free", "on_road", "within_model")}, **cal}
    text = summary_markdown({"rows": [row], "failed_parts": {}, "refusals": {}})
    assert "within 3 standard errors (at least 0.01) on 2 of 3 scenarios" in text and "b 0.10 vs 0.65" in text
    assert "off Monte Carlo by more than 0.1 on 1 of 2 scenarios" in text


def test_monte_carlo_metrics_report_the_standard_error():
    """Two closed loops, one through an occupied cell and one clear: mean 0.5, standard error std / sqrt(2) = 0.5."""
    from density_planner.environment.grid import OccupancyGrid
    from density_planner.environment.scene import Scene
    from density_planner.evaluation.metrics import monte_carlo_metrics
    from density_planner.risk.collision import CollisionModel

    probs = torch.zeros(3, 10, 10)
    probs[:, 2, 2] = 1.0
    scene = Scene(OccupancyGrid(probs, origin=(0.0, 0.0), cell_size=1.0, dt=0.1), (2.0, 2.0, 0.0, 1.0),
                  (7.0, 7.0), (0.5, 8.5, 0.5, 8.5), name="two-cells")
    runs = [torch.tensor([[2.0, 2.0, 0.0, 1.0, 0.0]] * 3), torch.tensor([[7.0, 7.0, 0.0, 1.0, 0.0]] * 3)]
    m = monte_carlo_metrics(scene, runs, collision=CollisionModel(scene.grid))
    assert m["mc_collision_mean"] == pytest.approx(0.5) and m["mc_collision_se"] == pytest.approx(0.5)
    assert monte_carlo_metrics(scene, runs[:1], collision=CollisionModel(scene.grid))["mc_collision_se"] == 0.0


def test_a_scenarios_initial_law_does_not_depend_on_its_folder(tmp_path):
    """The initial law's seed comes from the file's name, not from its sorted position in the folder."""
    from density_planner.evaluation.commonroad_bench import commonroad_envs

    alone, crowded = tmp_path / "alone", tmp_path / "crowded"
    alone.mkdir()
    crowded.mkdir()
    shutil.copy(SHIPPED, alone / SHIPPED.name)
    shutil.copy(SHIPPED, crowded / SHIPPED.name)
    shutil.copy(SHIPPED, crowded / ("AAA_" + SHIPPED.name))  # sorts first: shifts the index
    a = commonroad_envs(alone)[0]
    b = [e for e in commonroad_envs(crowded) if e.name == a.name][0]
    assert (a.index, b.index) == (0, 1) and a.law_seed == b.law_seed != commonroad_envs(crowded)[0].law_seed

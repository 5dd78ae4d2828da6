"""The kinematic single-track model through the pipeline: ``solution.xml`` with KS states read back by commonroad-io,
and ``density-planner plan --system ks`` on a random and a CommonRoad scene."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from density_planner.cli import main
from density_planner.errors import ConfigError
from density_planner.io.commonroad_solution import SolutionConfig, read_solution, write_solution
from density_planner.systems.ks import KinematicSingleTrack, KSConfig

TINY = ["--set", "density_planner.n_candidates=4", "--set", "density_planner.epochs_init=3",
        "--set", "density_planner.epochs_density=2", "--set", "density_planner.n_samples=16",
        "--set", "density_planner.evaluation_samples=16"]


def _trajectory(ks: KinematicSingleTrack) -> np.ndarray:
    x0 = torch.tensor([1.0, 2.0, 0.0, 6.0, 0.4], dtype=torch.float64)
    u = torch.tensor([[0.1, 0.5]], dtype=torch.float64).expand(300, 2)  # steering ramp, accelerating
    return ks.rollout(x0, u, 0.01)[::10].numpy()  # 0.1-s grid, 31 states


@pytest.mark.parametrize("model", ["KS", "ST"])
def test_ks_solution_round_trips_through_commonroad_reader(tmp_path, model):
    pytest.importorskip("commonroad")
    ks = KinematicSingleTrack()
    x = _trajectory(ks)
    path = write_solution(tmp_path / "solution.xml", x, None, 0.1, scenario_id="USA_US101-4_1_T-1",
                          planning_problem_id=458, scenario_dt=0.1, initial_time_step=5,
                          config=SolutionConfig(vehicle_model=model), state_names=ks.state_names, system=ks)
    pps = read_solution(path).planning_problem_solutions[0]
    assert pps.vehicle_model.name == model and pps.vehicle_type.name == "BMW_320i"
    states = pps.trajectory.state_list
    assert [s.time_step for s in states] == list(range(5, 36))
    np.testing.assert_allclose([s.position for s in states], x[:, :2], atol=1e-9)
    # the KS state is written as it is: steering angle, speed and yaw angle
    np.testing.assert_allclose([s.steering_angle for s in states], x[:, 2], atol=1e-9)
    np.testing.assert_allclose([s.velocity for s in states], x[:, 3], atol=1e-9)
    np.testing.assert_allclose([s.orientation for s in states], x[:, 4], atol=1e-9)
    if model == "ST":
        np.testing.assert_allclose([s.yaw_rate for s in states], x[:, 3] * np.tan(x[:, 2]) / ks.wheelbase,
                                   atol=1e-9)


def test_ks_solution_names_the_systems_vehicle(tmp_path):
    ks = KinematicSingleTrack()
    with pytest.raises(ConfigError, match="models the BMW_320i"):
        write_solution(tmp_path / "s.xml", _trajectory(ks), None, 0.1, scenario_id="ZAM_Test-1_1_T-1",
                       planning_problem_id=1, scenario_dt=0.1, initial_time_step=0,
                       config=SolutionConfig(vehicle_type="FORD_ESCORT"), system=ks)
    ford = KinematicSingleTrack(KSConfig(vehicle="FORD_ESCORT"))
    path = write_solution(tmp_path / "s.xml", _trajectory(ford), None, 0.1, scenario_id="ZAM_Test-1_1_T-1",
                          planning_problem_id=1, scenario_dt=0.1, initial_time_step=0,
                          config=SolutionConfig(vehicle_type="FORD_ESCORT"), system=ford)
    assert read_solution(path).planning_problem_solutions[0].vehicle_type.name == "FORD_ESCORT"


def test_plan_random_scene_with_ks(tmp_path):
    out = tmp_path / "p"
    rc = main(["plan", "--system", "ks", "--env", "random", "--seed", "1", "--density", "exact", *TINY, "-q",
               "--no-gif", "--out", str(out)])
    data = json.loads((out / "plan.json").read_text())
    assert rc == (0 if data["status"] == "success" else 3) and data["planner_status"] == "success"
    assert data["config"]["system"]["name"] == "ks" and data["controller"] == "KSTrackingController"
    assert data["models"] == "ks"
    states = np.asarray(data["states"])
    assert states.shape[1] == 5
    # the plan starts at the mean of the initial law around the scene's pose (inside the XE0 box), and its steering
    # stays inside the vehicle's range
    start, xe0 = data["scene"]["start"], KinematicSingleTrack().initial_error_max
    assert np.all(np.abs(states[0, [0, 1, 3]] - [start[0], start[1], start[3]]) <= [xe0[0], xe0[1], xe0[3]])
    assert abs(math.remainder(states[0, 4] - start[2], 2 * math.pi)) <= xe0[4]
    assert abs(states[0, 2]) <= xe0[2]
    assert np.abs(states[:, 2]).max() <= 1.066
    assert "config.toml" in [p.name for p in out.iterdir()]
    assert 'name = "ks"' in (out / "config.toml").read_text()


@pytest.mark.slow
def test_plan_commonroad_with_ks_writes_ks_solution(tmp_path):
    from density_planner.evaluation.environments import shipped_commonroad_dir

    out = tmp_path / "p"
    rc = main(["plan", "--system", "ks", "--env", "commonroad", "--file",
               str(shipped_commonroad_dir() / "USA_US101-4_1_T-1.xml"), "--density", "exact", *TINY, "-q",
               "--no-gif", "--out", str(out)])
    data = json.loads((out / "plan.json").read_text())
    assert rc == (0 if data["status"] == "success" else 3) and data["verdict"]["basis"] == "road"
    pps = read_solution(out / "solution.xml").planning_problem_solutions[0]
    assert pps.vehicle_model.name == "KS"
    states = pps.trajectory.state_list
    planned = np.asarray(data["states"])
    np.testing.assert_allclose([s.steering_angle for s in states[:len(planned)]], planned[:len(states), 2],
                               atol=1e-4)

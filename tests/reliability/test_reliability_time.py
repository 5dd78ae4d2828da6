"""Issue 18's time-offset bug: one owner of "time of a slice" (absolute times on the grid's clock), plans that start
after the grid's t0, and the horizon as configuration (issue 13 item 4)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import torch

from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.scene import Scene, load_scene, save_scene
from density_planner.planners.problem import PlanningConfig, PlanningProblem

# a 1.0-m blob moving along +x at SPEED m/s on a 60 m x 20 m map, slices of 0.1 s from t = 0 to 15 s
SPEED, X0, Y = 2.0, 5.0, 0.0
CELL, DT, T = 0.5, 0.1, 151


def obstacle_x(t: float | np.ndarray) -> float | np.ndarray:
    return X0 + SPEED * t


def moving_grid(t0: float = 0.0, n: int = T) -> OccupancyGrid:
    xs = np.arange(0.0, 60.0 + CELL / 2, CELL)
    ys = np.arange(-10.0, 10.0 + CELL / 2, CELL)
    times = t0 + DT * np.arange(n)
    cx = obstacle_x(times)[:, None, None]
    probs = ((np.abs(xs[None, :, None] - cx) <= 1.0) & (np.abs(ys[None, None, :] - Y) <= 1.0)).astype(np.float32)
    return OccupancyGrid(torch.from_numpy(probs), (0.0, -10.0), CELL, DT, t0)


def scene_at(t_start: float, grid: OccupancyGrid | None = None, **meta) -> Scene:
    grid = grid or moving_grid()
    return Scene(grid, (50.0, 8.0, 0.0, 0.0), (55.0, 8.0), (0.0, 60.0, -10.0, 10.0), name="moving",
                 meta=meta, t_start=t_start)


# ----------------------------------------------------------------------------------------------- the grid API
def test_slice_index_is_absolute_and_refuses_times_outside_the_grid():
    grid = moving_grid(t0=2.0, n=51)  # 2 .. 7 s
    assert int(grid.slice_index(2.0)) == 0 and int(grid.slice_index(4.53)) == 25
    assert grid.t_end == pytest.approx(7.0)
    with pytest.raises(ValueError, match=r"outside the occupancy grid's time span \[2, 7\] s"):
        grid.slice_index(1.0)
    with pytest.raises(ValueError, match="outside the occupancy grid's time span"):
        grid.slice_index(torch.tensor([3.0, 7.2]))
    assert int(grid.slice_index(100.0, clamp=True)) == 50  # explicit look-ahead past the end only
    assert grid.slices_for(3.0, 0.1, 5).tolist() == [10, 11, 12, 13, 14]
    with pytest.raises(ValueError, match=r"planning from 5 s over 10 s needs occupancy for \[5, 15\] s.*\[2, 7\] s"):
        grid.slices_for(5.0, 0.1, 101)


def test_scene_t_start_defaults_to_grid_t0_and_survives_save_load(tmp_path):
    grid = moving_grid(t0=3.0, n=120)
    assert scene_at(None, grid).t_start == 3.0  # type: ignore[arg-type]
    scene = scene_at(5.0, grid)
    assert scene.to_json_dict()["t_start"] == 5.0
    back = load_scene(save_scene(scene, tmp_path / "s.npz"))
    assert back.t_start == 5.0
    with pytest.raises(ValueError, match=r"Scene.t_start = 20 s lies outside the occupancy grid's time span \[3, "):
        scene_at(20.0, grid)


# ------------------------------------------------------------------------------------ planning from t0 = 5 s
def test_plan_from_5s_reads_the_moving_obstacle_at_absolute_times():
    problem = PlanningProblem.from_scene(scene_at(5.0))
    slices = problem.slices()
    assert slices.tolist() == list(range(50, 151))  # t = 5 .. 15 s, never frozen at slice 0
    # a trajectory sitting on the obstacle at every planning time meets it at every time (P_occ = 1) ...
    from density_planner.cost.composite import CostConfig
    from density_planner.planners._report import evaluate_trajectory

    t = 5.0 + DT * np.arange(101)
    states = torch.zeros(101, 5, dtype=torch.float64)
    states[:, 0] = torch.from_numpy(obstacle_x(t))
    states[:, 1] = Y
    _, coll = evaluate_trajectory(problem, states, torch.zeros(100, 2, dtype=torch.float64),
                                  cost_config=CostConfig())
    assert float(coll.per_slice.min()) == pytest.approx(1.0)
    # ... and the obstacle moves: where it was at t = 5 s it is gone at t = 10 s
    pos5 = torch.tensor([obstacle_x(5.0), Y], dtype=torch.float64)
    k = problem.slices()
    assert float(problem.scene.grid.lookup(pos5, k[0])) == 1.0
    assert float(problem.scene.grid.lookup(pos5, k[50])) == 0.0


def test_metrics_and_mpc_objective_use_the_plan_start():
    from density_planner.cost.composite import CostConfig
    from density_planner.evaluation.metrics import run_metrics
    from density_planner.planners.mpc import MPCWeights, mpc_objective

    scene = scene_at(5.0)
    t = 5.0 + DT * np.arange(101)
    states = torch.zeros(101, 5, dtype=torch.float64)
    states[:, 0] = torch.from_numpy(obstacle_x(t))
    u = torch.zeros(100, 2, dtype=torch.float64)
    m = run_metrics(scene, states, u, u, box=([-1e9] * 5, [1e9] * 5), cost_config=CostConfig(), plan_dt=DT)
    assert min(m["collision_probability"]) == pytest.approx(1.0)
    obj = mpc_objective(scene.grid, states, u, scene.goal, MPCWeights(), dt=DT, t_start=5.0)
    assert obj["collision"] == pytest.approx(101.0)
    assert mpc_objective(scene.grid, states, u, scene.goal, MPCWeights(), dt=DT)["collision"] < 20


def test_horizon_check_fails_when_the_grid_ends_before_t_start_plus_horizon():
    grid = moving_grid(t0=5.0, n=51)  # covers 5 .. 10 s only
    with pytest.raises(ValueError, match=r"needs occupancy for \[5, 15\] s, but the occupancy grid covers \[5, 10\]"):
        PlanningProblem.from_scene(scene_at(5.0, grid))
    grid = moving_grid(t0=0.0, n=101)  # 0 .. 10 s: a plan from 5 s over 10 s does not fit either
    with pytest.raises(ValueError, match="planning.horizon"):
        PlanningProblem.from_scene(scene_at(5.0, grid))
    # a 5-s horizon fits
    problem = PlanningProblem.from_scene(scene_at(5.0, grid), planning=PlanningConfig(horizon=5.0))
    assert problem.slices().tolist() == list(range(50, 101))


def test_mpc_binds_the_slices_of_the_plan_start():
    pytest.importorskip("casadi")
    from density_planner.planners.mpc import MPCConfig, MPCPlanner

    problem = PlanningProblem.from_scene(scene_at(5.0))
    mpc = MPCPlanner(MPCConfig())
    mpc.reset(problem)
    slices = mpc._bound.slices
    assert slices[0] == 50 and slices[100] == 150 and slices[-1] == 150  # look-ahead holds the last slice


def test_ind_start_time_5_cli(tmp_path):
    """``--env ind --start-time 5``: the scene starts at 5 s on the recording's clock and the planner reads the
    slices of 5 .. 15 s (a plan is made)."""
    from density_planner.cli import main
    from density_planner.environment.ind import IndSceneConfig, load_ind_scene
    from ind_testdata import write_ind_recording

    f = np.arange(500)  # 20 s at 25 Hz
    tt = f / 25.0
    car = {"id": 1, "class": "car", "length": 4.5, "width": 1.8, "frames": f, "x": 10.0 + 3.0 * tt,
           "y": np.full(f.size, -20.0), "heading": np.zeros(f.size), "vx": np.full(f.size, 3.0),
           "vy": np.zeros(f.size)}
    write_ind_recording(tmp_path, 7, [car])
    scene = load_ind_scene(tmp_path, 7, IndSceneConfig(start_time=5.0))
    assert scene.t_start == pytest.approx(5.0) and scene.grid.t0 == pytest.approx(5.0)
    problem = PlanningProblem.from_scene(scene)
    assert problem.slices().tolist() == list(range(101))
    out = tmp_path / "plan"
    rc = main(["plan", "--env", "ind", "--data-dir", str(tmp_path), "--recording", "7", "--start-time", "5",
               "--controller", "analytic", "--density", "exact", "--set", "density_planner.n_candidates=4",
               "--set", "density_planner.epochs_init=3", "--set", "density_planner.epochs_density=2",
               "--set", "density_planner.n_samples=10",
               "--set", "density_planner.evaluation_samples=10", "-q", "--no-gif", "--out", str(out)])
    assert rc in (0, 1, 3)  # a plan (success, failed planning, or a plan that failed its verdict) with its files
    data = json.loads((out / "plan.json").read_text())
    assert data["scene"]["t_start"] == pytest.approx(5.0)


# ------------------------------------------------------------------------------------- horizon configuration
def test_horizon_configuration_and_scene_suggestion():
    scene = scene_at(0.0)  # 15 s of occupancy
    assert PlanningConfig().parameterization(scene).horizon == 10.0
    assert PlanningConfig(horizon=5.0).parameterization(scene).n_segments == 5
    par = PlanningConfig(horizon=6.0, segment_duration=0.5).parameterization(scene)
    assert par.n_segments == 12 and par.n_plan == 61
    # default: the scene's suggestion in whole segments (a plan ends with the goal's time interval), at most 20 s
    # and the scene's span (the learned predictors pad or chain windows of their 10 s)
    assert PlanningConfig().parameterization(scene_at(0.0, horizon=7.3)).horizon == 8.0
    assert PlanningConfig().parameterization(scene_at(0.0, horizon=0.4)).horizon == 1.0  # one segment at least
    assert PlanningConfig().parameterization(scene_at(0.0, horizon=12.2)).horizon == 13.0
    assert PlanningConfig().parameterization(scene_at(0.0, horizon=40.0)).horizon == 15.0  # the scene's span
    assert PlanningConfig(min_horizon=10.0).parameterization(scene_at(0.0, horizon=7.3)).horizon == 10.0
    assert PlanningConfig(max_horizon=12.0).parameterization(scene_at(0.0, horizon=40.0)).horizon == 12.0
    assert PlanningConfig(max_horizon=40.0).parameterization(scene_at(0.0, horizon=40.0)).horizon == 15.0  # span
    assert PlanningConfig(horizon=4.0).parameterization(scene_at(0.0, horizon=7.3)).horizon == 4.0  # explicit wins
    with pytest.raises(ValueError, match="whole number of segments"):
        PlanningConfig(horizon=2.5)
    with pytest.raises(ValueError, match="planning.horizon must be a finite number > 0"):
        PlanningConfig(horizon=-1.0)


def test_planning_section_in_the_run_configuration():
    from density_planner.config import apply_overrides
    from density_planner.settings import RunConfig

    cfg = apply_overrides(RunConfig(), ["planning.horizon=6", "planning.segment_duration=2"])
    assert cfg.planning.parameterization(scene_at(0.0)).n_segments == 3


def test_learned_predictor_refused_or_replaced_for_other_horizons(caplog):
    from density_planner.control.registry import load_controller
    from density_planner.density.liouville import ExactLiouville
    from density_planner.density.registry import load_predictor
    from density_planner.systems.car import KinematicCar

    car, ctrl = KinematicCar(), load_controller("c3m")
    # a shorter horizon of whole 1-s segments is served (one padded window), another segment length is not
    assert not isinstance(load_predictor(None, car, ctrl, parameterization=PlanningConfig(horizon=5.0)
                                         .parameterization()), ExactLiouville)
    par = PlanningConfig(horizon=5.0, segment_duration=0.5).parameterization()
    with pytest.raises(ValueError, match=r"trained for a 10-s horizon.*this plan has 5 s.*--density exact"):
        load_predictor("trajectory", car, ctrl, parameterization=par)
    with caplog.at_level(logging.WARNING):
        pred = load_predictor(None, car, ctrl, parameterization=par)
    assert isinstance(pred, ExactLiouville) and "using exact Liouville" in caplog.text
    default = load_predictor(None, car, ctrl, parameterization=PlanningConfig().parameterization())
    assert not isinstance(default, ExactLiouville)
    # the planner itself refuses a learned predictor for another horizon (no silent extrapolation)
    from density_planner.planners.density_planner import DensityPlanner

    problem = PlanningProblem.from_scene(scene_at(0.0), planning=PlanningConfig(horizon=5.0, segment_duration=0.5))
    with pytest.raises(ValueError, match="trained for a 10-s horizon"):
        DensityPlanner(default).plan(problem)

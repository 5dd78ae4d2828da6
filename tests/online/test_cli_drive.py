"""``density-planner drive`` from the command line: files written, exit codes, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from density_planner.cli import main

DATA = Path(__file__).resolve().parents[2] / "src" / "density_planner" / "data" / "commonroad"

TINY = ["--set", "density_planner.n_candidates=5", "--set", "density_planner.epochs_init=3", "--set",
        "density_planner.epochs_density=3", "--set", "density_planner.n_samples=20",
        "--set", "density_planner.evaluation_samples=20", "--set",
        "online.replan_epochs=1", "--set", "online.replan_samples=20", "--set", "online.overrun=use"]


@pytest.mark.parametrize("argv, needle", [
    (["--env", "random", "--period", "-1"], "period"),
    (["--env", "commonroad"], "--file"),
    (["--env", "random", "--planner", "mpc"], "step by step"),
    (["--env", "random", "--set", "online.prediction.kind=psychic"], "psychic"),
])
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, argv, needle):
    out = tmp_path / "run"
    assert main(["drive", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]
    assert not out.exists()


def test_drive_random_scene(tmp_path, capsys):
    out = tmp_path / "run"
    code = main(["drive", "--env", "random", "--seed", "3", *TINY, "--set", "online.duration=2.0", "--no-gif",
                 "--out", str(out)])
    assert code in (0, 3)
    run = json.loads((out / "run.json").read_text())
    assert [r["t"] for r in run["replans"]] == [0.0, 1.0]  # the default period: one input segment
    assert run["replans"][0]["status"] == "initial" and run["prediction"] == "oracle"
    assert run["status"] == ("success" if code == 0 else "failed")
    assert len(run["states"]) == 21
    assert (out / "run.png").stat().st_size > 10_000 and (out / "config.toml").exists()
    assert "replan_epochs = 1" in (out / "config.toml").read_text()
    assert "online (oracle prediction)" in capsys.readouterr().out


def test_drive_reports_replans_tracked_late(tmp_path, capsys):
    """With the default ``online.overrun = "delay"`` a replan over its budget is tracked late, and the line says so."""
    out = tmp_path / "run"
    code = main(["drive", "--env", "random", "--seed", "3", *TINY, "--set", "online.overrun=delay", "--set",
                 "online.time_budget=1e-9", "--set", "online.duration=3.0", "--no-gif", "--out", str(out)])
    assert code in (0, 3)
    run = json.loads((out / "run.json").read_text())
    late = [r for r in run["replans"][1:] if r["t_effective"] is not None and r["t_effective"] > r["t"]]
    assert late and all(r["status"] == "overrun" for r in late)
    assert f"{len(late)} tracked late (online.overrun = delay)" in capsys.readouterr().out


@pytest.mark.slow
def test_drive_commonroad_observed(tmp_path):
    pytest.importorskip("commonroad")
    out = tmp_path / "run"
    code = main(["drive", "--env", "commonroad", "--file", str(DATA / "ZAM_Tutorial-1_2_T-1.xml"), *TINY,
                 "--set", "online.max_duration=1.5", "--out", str(out)])
    assert code in (0, 3)
    run = json.loads((out / "run.json").read_text())
    assert run["prediction"] == "observed"
    assert run["verdict"]["basis"] == "road"
    assert len(run["replans"]) == 2  # initial, 1.0 s
    # the observed window of the replan is built from the observations (timed), the summary gives its median
    assert run["replans"][1]["prediction_time"] > 0
    assert run["prediction_time_median"] == pytest.approx(run["replans"][1]["prediction_time"])
    assert (out / "run.gif").stat().st_size > 1_000


def test_bench_mode_online_adds_the_online_planners():
    import argparse

    from density_planner.cli.bench import _mode_planners

    cr = argparse.Namespace(mode="online", setting="commonroad")
    assert _mode_planners(cr, ("density",)) == ("density", "density_online", "density_online_oracle", "mpc")
    art = argparse.Namespace(mode="online", setting="artificial")
    assert _mode_planners(art, ("density", "mpc")) == ("density", "density_online", "mpc")
    off = argparse.Namespace(mode="offline", setting="artificial")
    assert _mode_planners(off, ("density", "mpc")) == ("density", "mpc")


@pytest.mark.parametrize("shrink", [True, False])
def test_oracle_scene_covers_the_goal_or_the_run_plus_a_horizon(shrink):
    """Replans that end with the goal (``online.shrink_horizon``) read the scene's own grid, which covers the goal's
    time interval; full-horizon replans need the grid to cover the run plus one horizon (longer, so coarser)."""
    pytest.importorskip("commonroad")
    import math

    from density_planner.api import build_scene, drive_config
    from density_planner.config import apply_overrides
    from density_planner.settings import RunConfig

    cfg = apply_overrides(RunConfig(), ["online.prediction.kind=oracle", "online.max_duration=5",
                                        f"online.shrink_horizon={'true' if shrink else 'false'}"])
    cfg = drive_config(cfg, "commonroad")
    scene = build_scene("commonroad", cfg, file=DATA / "USA_Lanker-1_1_T-1.xml")
    goal_end = scene.road.goal.time_interval[1] - scene.t_start  # 4.0 s
    span = scene.grid.t_end - scene.t_start
    if shrink:
        assert span == pytest.approx(math.ceil(goal_end))
    else:
        assert span >= 5.0 + 10.0 - 1e-6  # the run (max_duration) plus one 10-s horizon

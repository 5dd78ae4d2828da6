"""``density-planner plan``: outputs on a random scene, effective config round trip, one-line errors."""

from __future__ import annotations

import json

import pytest

from density_planner.cli import main

FAST = ["--set", "density_planner.n_candidates=8", "--set", "density_planner.epochs_init=20",
        "--set", "density_planner.epochs_density=2", "--set", "density_planner.n_samples=20",
        "--set", "density_planner.evaluation_samples=20"]


def test_plan_writes_outputs_and_config(tmp_path, capsys):
    out = tmp_path / "p"
    rc = main(["plan", "--env", "random", "--seed", "1", "--controller", "analytic", "--density", "exact",
               *FAST, "-q", "--out", str(out)])
    data = json.loads((out / "plan.json").read_text())
    # the status is the verdict's (this short optimisation need not pass it): exit 0 on success, 3 on failure
    verdict = data["verdict"]
    assert data["status"] == verdict["status"] and rc == (0 if verdict["status"] == "success" else 3)
    assert data["planner_status"] == "success" and verdict["basis"] == "occupancy"
    assert all(isinstance(verdict[k], bool) for k in ("goal_reached", "collision_free", "on_road", "within_model"))
    assert (verdict["status"] == "success") == (verdict["reasons"] == [])
    assert len(data["params"]) == 2 and len(data["params"][0]) == 10
    assert set(data["cost"]) >= {"goal", "input", "bounds", "collision", "total"}
    assert 0.0 <= data["collision_probability"]["max"] <= 1.0
    assert data["config"]["density_planner"]["n_candidates"] == 8
    assert data["versions"]["torch"] and data["scene"]["name"] == "random-1"
    for name in ("plan.png", "plan.gif", "costs.png", "config.toml"):
        assert (out / name).stat().st_size > 0
    assert verdict["status"] in capsys.readouterr().out
    from density_planner.density.split import prediction_processes

    assert prediction_processes() == 1  # the command's execution setting does not outlive it
    # the effective configuration, [system] included (the flags wrote it), reproduces the run on its own
    assert data["config"]["system"] == {"name": "car", "models": "auto", "controller": "analytic", "density": "exact"}
    out2 = tmp_path / "p2"
    assert main(["plan", "--env", "random", "--seed", "1", "--config", str(out / "config.toml"), "-q", "--no-gif",
                 "--out", str(out2)]) == rc
    data2 = json.loads((out2 / "plan.json").read_text())
    assert data2["params"] == data["params"]


def test_console_script_exits_fast_with_every_file_written(tmp_path):
    """``python -m density_planner plan`` (the console path) ends with ``os._exit`` after ``plan``: the exit code,
    the printed line and every file (the figures of the child process included) are still there."""
    import subprocess
    import sys

    out = tmp_path / "p"
    proc = subprocess.run([sys.executable, "-m", "density_planner", "plan", "--env", "random", "--seed", "1",
                           "--controller", "analytic", "--density", "exact", *FAST, "--no-progress",
                           "--out", str(out)], capture_output=True, text=True)
    data = json.loads((out / "plan.json").read_text())
    assert proc.returncode == (0 if data["status"] == "success" else 3), proc.stderr
    assert f"{data['status']}" in proc.stdout and str(out / "costs.png") in proc.stdout
    # solution.xml and the figures came from the process forked before planning (it drew plan.png, its own child
    # the GIF)
    assert "outputs" in data["command_timings"]
    assert {"plan_png", "child_wait"} <= set(data["output_process_timings"])
    for name in ("plan.png", "plan.gif", "costs.png", "config.toml", "plan.json"):
        assert (out / name).stat().st_size > 0
    # an error still exits normally with its code and one line
    bad = subprocess.run([sys.executable, "-m", "density_planner", "plan", "--env", "random", "--planner", "magic",
                          "--out", str(tmp_path / "q")], capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "unknown planner" in bad.stderr


def test_plan_output_process_failure_and_fallback(tmp_path, capsys, monkeypatch):
    """A failure in the process that draws the figures is one line naming it (exit 1), no process is left behind;
    a planner error ends that process too; without fork the files are written here, in turn."""
    import multiprocessing as mp

    import density_planner.viz.plan as viz_plan
    from density_planner.cli import plan as plan_cli
    from density_planner.planners.density_planner import DensityPlanner

    args = ["plan", "--env", "random", "--seed", "1", "--controller", "analytic", "--density", "exact", *FAST, "-q"]
    before = set(mp.active_children())  # pools of earlier tests may live on

    def _new_children(before: set) -> list:
        return [p for p in mp.active_children() if p not in before]

    def broken(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(viz_plan, "plot_plan", broken)  # inherited by the forked process
    assert main([*args, "--no-gif", "--out", str(tmp_path / "a")]) == 1
    err = capsys.readouterr().err
    assert "writing the figures and solution of the plan failed (OSError: disk full)" in err and err.count("\n") == 1
    assert _new_children(before) == []
    monkeypatch.undo()

    monkeypatch.setattr(DensityPlanner, "plan", broken)
    assert main([*args, "--out", str(tmp_path / "b")]) == 1
    assert "disk full" in capsys.readouterr().err and _new_children(before) == []
    monkeypatch.undo()

    from density_planner.planners.base import PlanResult, PlanStatus

    monkeypatch.setattr(DensityPlanner, "plan", lambda self, problem: PlanResult(
        "density", PlanStatus.FAILED, message="no finite cost"))  # no plan: nothing to draw, the process ends
    assert main([*args, "--out", str(tmp_path / "n")]) == 1
    assert "no finite cost" in capsys.readouterr().out and _new_children(before) == []
    monkeypatch.undo()

    monkeypatch.setattr(plan_cli._OutputProcess, "start", classmethod(lambda cls, *a, **k: None))
    assert main([*args, "--out", str(tmp_path / "c")]) in (0, 3)
    data = json.loads((tmp_path / "c" / "plan.json").read_text())
    assert "plan_png" in data["command_timings"] and "output_process_timings" not in data
    for name in ("plan.png", "plan.gif", "costs.png"):
        assert (tmp_path / "c" / name).stat().st_size > 0


@pytest.mark.parametrize(
    "args,match",
    [
        (["--env", "random", "--planner", "magic"], "unknown planner 'magic'"),
        (["--env", "random", "--density", "magic"], "unknown density predictor 'magic'"),
        (["--env", "random", "--set", "density_planner.n_candidatez=3"], "unknown key(s) ['n_candidatez']"),
        (["--env", "random", "--set", "density_planner.n_candidates=0"], "n_candidates must be a positive"),
        (["--env", "ind"], "needs --data-dir D and --recording N"),
        (["--env", "file"], "needs --file"),
        (["--env", "random", "--config", "missing.toml"], "config file not found"),
        (["--env", "random", "--device", "cuda:7"], "cuda"),
        (["--env", "random", "--system", "boat"], "unknown system 'boat'; valid choices: car"),
        (["--env", "random", "--models", "moon"], "unknown model set 'moon'"),
        (["--env", "random", "--set", "system.name=boat"], "unknown system 'boat'"),
    ],
)
def test_plan_errors_are_one_line(tmp_path, capsys, monkeypatch, args, match):
    monkeypatch.chdir(tmp_path)
    rc = main(["plan", *args, "--controller", "analytic", "-q", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and match in err and err.count("\n") == 1 and "Traceback" not in err


def test_plan_on_saved_scene_file(tmp_path):
    assert main(["env", "--kind", "random", "--seed", "2", "--no-gif", "--out", str(tmp_path / "e")]) == 0
    rc = main(["plan", "--env", "file", "--file", str(tmp_path / "e" / "occupancy.npz"), "--controller", "analytic",
               "--density", "exact", *FAST, "-q", "--no-gif", "--out", str(tmp_path / "p")])
    assert rc in (0, 3)
    assert json.loads((tmp_path / "p" / "plan.json").read_text())["scene"]["name"] == "random-2"

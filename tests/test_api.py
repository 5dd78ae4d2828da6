"""``density_planner.api``: one call plans a scene as ``density-planner plan`` does (the same plan from the same
arguments), writes the command's files, and rejects bad arguments with one clear error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from density_planner.api import PlanOutcome, drive_scene, load_run_config, plan_scene
from density_planner.cli import main

SHIPPED = Path(__file__).resolve().parents[1] / "src" / "density_planner" / "data" / "commonroad"
LANKER = SHIPPED / "USA_Lanker-1_1_T-1.xml"
FAST = ["density_planner.n_candidates=8", "density_planner.epochs_init=20", "density_planner.epochs_density=3",
        "density_planner.n_samples=20", "density_planner.evaluation_samples=20"]


def _cli_args(fast: list[str]) -> list[str]:
    return [a for kv in fast for a in ("--set", kv)]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_plan_scene_equals_the_plan_command_on_a_commonroad_scenario(tmp_path):
    """The API and the command line, same file and settings: the same parameters, verdict and risk; the files
    the API writes are the command's (solution.xml included) and its config.toml reproduces the run."""
    outcome = plan_scene("commonroad", file=LANKER, overrides=FAST)
    assert isinstance(outcome, PlanOutcome) and type(outcome.problem.system).__name__ == "KinematicCar"
    assert outcome.setup.context.controller is not None and outcome.summary()["models"] == "road"
    out = tmp_path / "cli"
    rc = main(["plan", "--env", "commonroad", "--file", str(LANKER), *_cli_args(FAST), "-q", "--no-gif",
               "--out", str(out)])
    cli = json.loads((out / "plan.json").read_text())
    assert rc == (0 if outcome.ok else 3) and cli["status"] == outcome.status
    params = outcome.result.params.detach().double().cpu()
    assert torch.allclose(torch.tensor(cli["params"], dtype=torch.float64), params, atol=1e-6)
    assert cli["verdict"] == outcome.verdict.to_dict()
    assert cli["collision_probability"]["max"] == pytest.approx(float(outcome.result.collision.max), abs=1e-6)

    written = outcome.write(tmp_path / "api")
    assert {p.name for p in written} == {"plan.json", "config.toml", "solution.xml", "plan.png", "costs.png"}
    assert all(p.stat().st_size > 0 for p in written)
    api = json.loads((tmp_path / "api" / "plan.json").read_text())
    assert api["verdict"] == cli["verdict"] and api["config"] == cli["config"]
    assert (tmp_path / "api" / "solution.xml").read_text().count("<trajectory") == \
        (out / "solution.xml").read_text().count("<trajectory")
    again = plan_scene("commonroad", file=LANKER, config=tmp_path / "api" / "config.toml")
    assert torch.equal(again.result.params, outcome.result.params)


def test_plan_scene_on_a_random_scene_with_system_choices():
    outcome = plan_scene("random", seed=1, controller="analytic", density="exact", overrides=FAST)
    assert outcome.verdict is not None and outcome.verdict.to_dict()["basis"] == "occupancy"
    assert outcome.setup.distribution_seed == 1  # the scene's seed, as the command
    assert outcome.setup.run_config.system.controller == "analytic"
    with pytest.raises(ValueError, match="needs a CommonRoad scene"):
        outcome.write_solution("x.xml")


def test_load_run_config_layers_file_overrides_and_system():
    cfg = load_run_config("paper", ["density_planner.n_candidates=7"], models="road")
    assert cfg.density_planner.n_candidates == 7 and cfg.system.models == "road"
    assert cfg.density_planner.n_samples == 500  # the preset's


@pytest.mark.parametrize("kwargs, error, match", [
    ({"env": "moon"}, ValueError, "unknown scene kind 'moon'"),
    ({"env": "commonroad"}, ValueError, "needs --file F.xml"),
    ({"env": "random", "file": "x.xml"}, ValueError, "--file is not used with --env random"),
    ({"env": "random", "overrides": "density_planner.n_candidates=3"}, TypeError, "not one string"),
    ({"env": "random", "overrides": ["density_planner.n_candidatez=3"]}, Exception, "n_candidatez"),
    ({"env": "random", "run_config": load_run_config(), "config": "paper"}, ValueError, "not both"),
    ({"env": "random", "planner": "teleport"}, ValueError, "teleport"),
    ({"env": "random", "seed": -1}, ValueError, "seed"),
])
def test_plan_scene_rejects_bad_arguments(kwargs, error, match):
    with pytest.raises(error, match=match):
        plan_scene(**kwargs)


TINY_DRIVE = ["density_planner.n_candidates=5", "density_planner.epochs_init=3", "density_planner.epochs_density=3",
              "density_planner.n_samples=20", "density_planner.evaluation_samples=20", "online.replan_epochs=1",
              "online.replan_samples=20", "online.overrun=use", "online.duration=2.0"]


def test_drive_scene_equals_the_drive_command(tmp_path):
    """``drive_scene`` and ``density-planner drive``, same scene and settings: the same executed states, replans
    and verdict (``overrun = "use"``: the run does not depend on the machine's speed); the files it writes."""
    outcome = drive_scene("random", seed=3, overrides=TINY_DRIVE)
    out = tmp_path / "cli"
    rc = main(["drive", "--env", "random", "--seed", "3", *_cli_args(TINY_DRIVE), "-q", "--no-gif",
               "--out", str(out)])
    cli = json.loads((out / "run.json").read_text())
    assert rc == (0 if outcome.ok else 3) and cli["status"] == outcome.status
    assert [r["t"] for r in cli["replans"]] == [0.0, 1.0] == [r.t for r in outcome.result.replans]
    assert np.allclose(np.asarray(cli["states"]), np.asarray(outcome.result.states), atol=1e-6)
    written = outcome.write(tmp_path / "api")
    assert {p.name for p in written} == {"run.json", "config.toml", "run.png"}
    api = json.loads((tmp_path / "api" / "run.json").read_text())
    assert api["verdict"] == cli["verdict"] and api["config"] == cli["config"] and api["planner"] == "density"


def test_drive_scene_refuses_a_step_by_step_planner():
    with pytest.raises(ValueError, match="step by step"):
        drive_scene("random", planner="mpc")

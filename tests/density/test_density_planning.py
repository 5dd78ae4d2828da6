"""Learned predictors in the planner: both architectures plug into stage 2; the plan is re-checked with exact
Liouville and both figures are reported (library and ``plan`` command)."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from density_planner.cli import main
from density_planner.control.analytic import CarTrackingController
from density_planner.density.liouville import ExactLiouville
from density_planner.density.network import (
    DensityNetArchitecture,
    DensityNetwork,
    LearnedDensity,
    controller_fingerprint,
    save_density_model,
)
from density_planner.density.split import using_prediction_processes
from density_planner.environment import random_scene
from density_planner.planners.base import PlanStatus
from density_planner.planners.density_planner import DensityPlanner, DensityPlannerConfig
from density_planner.planners.problem import PlanningProblem
from density_planner.systems.car import KinematicCar

FAST = DensityPlannerConfig(n_candidates=6, epochs_init=15, epochs_density=4, n_samples=30, evaluation_samples=30)


def untrained(arch: str) -> DensityNetwork:
    torch.manual_seed(0)
    net = DensityNetwork(DensityNetArchitecture(arch=arch, hidden=16, layers=2))
    with torch.no_grad():
        net.last.weight.normal_(0, 0.01)
    return net


@pytest.mark.parametrize("arch", ["trajectory", "pointwise"])
def test_learned_predictor_in_density_planner(arch):
    car, ctrl = KinematicCar(), CarTrackingController()
    scene = random_scene(1)
    problem = PlanningProblem.from_scene(scene, seed=1)
    planner = DensityPlanner(LearnedDensity(untrained(arch)), FAST, exact_check=ExactLiouville(car, ctrl))
    result = planner.plan(problem)
    assert result.status == PlanStatus.SUCCESS
    assert result.extras["predictor"] == arch
    check = result.extras["exact_check"]
    assert check["predictor"] == "exact"
    assert set(check["cost"]) >= {"goal", "collision", "total"}
    assert 0.0 <= check["collision_probability_max"] <= 1.0
    assert result.samples.x.shape == (FAST.n_samples, 101, 5)
    # the reported risk is the exact propagation of the evaluation samples, the learned estimate kept beside it
    assert result.extras["reported_by"] == "exact"
    assert float(result.collision.max) == pytest.approx(check["collision_probability_max"], abs=1e-7)
    assert result.cost["total"] == pytest.approx(check["cost"]["total"], rel=1e-6)
    assert result.extras["predictor_estimate"]["predictor"] == arch
    # stage 2 changed the parameters: the prediction is differentiable w.r.t. them
    assert len(result.cost_history["stage2"]["total"]) == FAST.epochs_density


@pytest.mark.parametrize("processes", [1, 2])
def test_exact_check_of_states_reports_what_the_exact_log_densities_report(processes):
    """The exact check propagates only the states by default (``exact_log_density = False``): the reported cost and
    collision probability are those with the exact log-densities integrated too, bit for bit (importance weights
    and "mass" cost weights read no log-density along the trajectories), and the cloud's log-densities are the
    planning predictor's for the same samples."""
    car, ctrl = KinematicCar(), CarTrackingController()
    problem = PlanningProblem.from_scene(random_scene(1), seed=1)
    results = {}
    with using_prediction_processes(processes):
        for exact_density in (False, True):
            cfg = dataclasses.replace(FAST, exact_log_density=exact_density)
            results[exact_density] = DensityPlanner(LearnedDensity(untrained("trajectory")), cfg,
                                                    exact_check=ExactLiouville(car, ctrl)).plan(problem)
    fast, full = results[False], results[True]
    assert fast.extras["exact_check"]["log_density"] == "trajectory"
    assert full.extras["exact_check"]["log_density"] == "exact"
    assert torch.equal(fast.samples.x, full.samples.x)
    assert float(fast.collision.max) == float(full.collision.max)
    assert fast.collision.to_dict() == full.collision.to_dict()
    assert fast.cost == full.cost
    # the cloud's log-densities: the network's for the same samples (what it reports without report_exact), not
    # the exact ones
    cfg = dataclasses.replace(FAST, report_exact=False)
    learned = DensityPlanner(LearnedDensity(untrained("trajectory")), cfg, exact_check=ExactLiouville(car, ctrl)
                             ).plan(problem)
    assert torch.equal(fast.samples.log_rho, learned.samples.log_rho)
    assert not torch.allclose(fast.samples.log_rho, full.samples.log_rho)


def test_report_exact_false_keeps_the_learned_estimate():
    car, ctrl = KinematicCar(), CarTrackingController()
    problem = PlanningProblem.from_scene(random_scene(1), seed=1)
    cfg = dataclasses.replace(FAST, report_exact=False)
    result = DensityPlanner(LearnedDensity(untrained("trajectory")), cfg, exact_check=ExactLiouville(car, ctrl)
                            ).plan(problem)
    assert result.extras["reported_by"] == "trajectory"
    assert "predictor_estimate" not in result.extras
    assert "exact_check" in result.extras


@pytest.mark.slow
def test_plan_command_with_learned_predictor_reports_exact_check(tmp_path):
    ctrl = CarTrackingController()
    save_density_model(tmp_path / "w", untrained("trajectory"),
                       extra={"controller": {"spec": "analytic", "fingerprint": controller_fingerprint(ctrl)}})
    fast = ["--set", "density_planner.n_candidates=6", "--set", "density_planner.epochs_init=15",
            "--set", "density_planner.epochs_density=3", "--set", "density_planner.n_samples=20",
            "--set", "density_planner.evaluation_samples=20"]
    rc = main(["plan", "--env", "random", "--seed", "1", "--controller", "analytic", "--density",
               str(tmp_path / "w.pt"), *fast, "-q", "--no-gif", "--out", str(tmp_path / "p")])
    assert rc in (0, 3)  # a plan was made (3: its verdict failed; this short optimisation need not pass it)
    data = json.loads((tmp_path / "p" / "plan.json").read_text())
    assert data["density_predictor"] == "trajectory"
    assert data["extras"]["predictor"] == "trajectory"
    assert data["extras"]["exact_check"]["predictor"] == "exact"
    assert "collision_probability_max" in data["extras"]["exact_check"]
    assert data["collision_probability"]["max"] is not None


@pytest.mark.slow
def test_plan_command_default_falls_back_to_exact_for_other_controller(tmp_path):
    fast = ["--set", "density_planner.n_candidates=4", "--set", "density_planner.epochs_init=5",
            "--set", "density_planner.epochs_density=2", "--set", "density_planner.n_samples=10",
            "--set", "density_planner.evaluation_samples=10"]
    rc = main(["plan", "--env", "random", "--seed", "1", "--controller", "analytic", *fast, "-q", "--no-gif",
               "--out", str(tmp_path / "p")])
    assert rc in (0, 3)  # a plan was made (3: its verdict failed; this short optimisation need not pass it)
    data = json.loads((tmp_path / "p" / "plan.json").read_text())
    assert data["extras"]["predictor"] == "exact"
    assert "exact_check" not in data["extras"]  # no second exact propagation of the same plan


def test_plan_command_learned_predictor_for_wrong_controller_is_a_clear_error(tmp_path, capsys):
    save_density_model(tmp_path / "w", untrained("trajectory"),
                       extra={"controller": {"spec": "c3m", "fingerprint": "0123456789abcdef"}})
    rc = main(["plan", "--env", "random", "--seed", "1", "--controller", "analytic", "--density",
               str(tmp_path / "w.pt"), "-q", "--out", str(tmp_path / "p")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "was trained for the controller 'c3m'" in err and "--density exact" in err

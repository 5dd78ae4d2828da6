"""The baselines are registered, configurable from the run configuration, and CasADi is optional."""

from __future__ import annotations

import sys

import pytest

from density_planner.config import apply_overrides, from_dict
from density_planner.control.analytic import CarTrackingController
from density_planner.density.liouville import ExactLiouville
from density_planner.errors import OptionalDependencyError
from density_planner.planners.registry import PlannerContext, make_planner, planner_help, planner_names
from density_planner.settings import RunConfig
from density_planner.systems.car import KinematicCar

BASELINES = ("mpc", "tube_mpc", "tube_mpc_0.3", "tube_mpc_0.5", "tube_mpc_1.0", "oracle", "search", "sampling")
NEEDS_CASADI = ("mpc", "tube_mpc", "tube_mpc_0.3", "tube_mpc_0.5", "tube_mpc_1.0", "oracle")


def _context(config: RunConfig | None = None) -> PlannerContext:
    car, ctrl = KinematicCar(), CarTrackingController()
    return PlannerContext(car, ctrl, config or RunConfig(), predictor_factory=lambda: ExactLiouville(car, ctrl))


def test_names_and_help():
    names = planner_names()
    for name in BASELINES:
        assert name in names
        assert planner_help()[name]


def test_config_sections():
    cfg = from_dict(RunConfig, {"mpc": {"max_iter": 50, "weights": {"collision": 0.5}},
                                "search": {"time_limit": 10.0}, "sampling": {"batch_size": 5},
                                "oracle": {"restarts": 2}, "tube_mpc": {"tube_radius": 0.7}})
    assert cfg.mpc.max_iter == 50 and cfg.mpc.weights.collision == 0.5
    assert cfg.tube_mpc.max_iter == 10 and cfg.tube_mpc.tube_radius == 0.7
    assert cfg.search.time_limit == 10.0 and cfg.search.cost.weights.collision == 10.0
    assert cfg.sampling.cost.weights.goal == 0.1 and not cfg.sampling.include_input_cost
    cfg = apply_overrides(cfg, ["oracle.max_iter=100", "mpc.goal_weight_growth=false"])
    assert cfg.oracle.max_iter == 100 and not cfg.mpc.goal_weight_growth


@pytest.mark.parametrize("name", ["search", "sampling"])
def test_make_tree_planners(name):
    planner = make_planner(name, _context())
    assert planner.name == name


@pytest.mark.parametrize("name", NEEDS_CASADI)
def test_make_casadi_planners(name):
    pytest.importorskip("casadi", reason="the MPC baselines and the oracle need the optional 'mpc' extra")
    cfg = from_dict(RunConfig, {"tube_mpc": {"tube_radius": 0.7}})
    planner = make_planner(name, _context(cfg))
    expected = {"tube_mpc": "tube_mpc_0.7"}.get(name, name)
    assert planner.name == expected
    if name.startswith("tube_mpc_"):
        assert planner.config.tube_radius == float(name.rsplit("_", 1)[1]) and planner.config.max_iter == 10
    if name == "mpc":
        assert planner.config.tube_radius == 0.0 and planner.config.max_iter == 300


@pytest.mark.parametrize("name", NEEDS_CASADI)
def test_missing_casadi_names_the_extra(monkeypatch, name):
    monkeypatch.setitem(sys.modules, "casadi", None)  # import casadi -> ImportError
    assert name in planner_names()  # listing the planners does not need casadi
    with pytest.raises(OptionalDependencyError, match=r"density-planner\[mpc\]"):
        make_planner(name, _context())


def test_cli_names_the_extra_when_casadi_is_missing(monkeypatch, tmp_path, capsys):
    from density_planner.cli import main

    monkeypatch.setitem(sys.modules, "casadi", None)
    rc = main(["plan", "--env", "random", "--seed", "0", "--planner", "mpc", "-q", "--no-gif",
               "--out", str(tmp_path / "p")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "casadi" in err and "density-planner[mpc]" in err and len(err.strip().splitlines()) == 1


def test_cli_plans_with_a_baseline(tmp_path, capsys):
    """The plan command runs a baseline end to end (M0 here: writes plan.json with the per-step record)."""
    pytest.importorskip("casadi", reason="the MPC baselines need the optional 'mpc' extra (casadi)")
    import json

    from density_planner.cli import main

    out = tmp_path / "mpc"
    rc = main(["plan", "--env", "random", "--seed", "1", "--planner", "mpc", "--set", "mpc.n_steps=5",
               "--set", "mpc.max_cpu_time=inf", "-q", "--no-gif", "--out", str(out)])
    data = json.loads((out / "plan.json").read_text())
    # 5 steps (0.5 s) cannot reach the goal: the verdict fails (exit 3), the planner itself succeeded
    assert rc == 3 and data["status"] == "failed" and not data["verdict"]["goal_reached"]
    assert data["planner"] == "mpc" and data["planner_status"] == "success"
    assert len(data["extras"]["step_times"]) == 5 and len(data["states"]) == 6
    assert (out / "plan.png").stat().st_size > 0

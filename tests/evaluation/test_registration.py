"""One registration per planner and per scene source: everything else reads it.

A planner registered with one ``register_planner`` call (in this file only) runs in a benchmark sweep with the
execution mode, variants and configuration section of its registration, and appears in the summary tables and the
figures under its label and colour. A scene source registered with one ``register_scene_source`` call is offered by
the command line; the command line and the benchmarks build the same scenes through the same builders.
"""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch
from eval_testdata import tiny_run_config

from density_planner.config import update
from density_planner.evaluation.benchmark import BenchmarkSpec, config_hash, run_benchmark
from density_planner.evaluation.environments import EnvSpec, artificial_envs, build_scene, shipped_commonroad_dir
from density_planner.evaluation.records import load_records
from density_planner.planners import registry
from density_planner.planners.base import Planner, PlanResult, PlanStatus


class _Straight(Planner):
    """Drives straight on at the start speed: zero inputs (a reference planner, tracked by the controller)."""

    name = "test_straight"

    def plan(self, problem):
        from density_planner.control.reference import make_reference

        par = problem.parameterization
        params = torch.zeros(problem.system.nu, par.n_segments)
        ref = make_reference(problem.system, problem.reference_start(), params, par)
        return PlanResult(self.name, PlanStatus.SUCCESS, params=params, reference=ref, states=ref.x_plan,
                          timings={"total": 0.01})


class _KnowsTheTruth(Planner):
    """Plans from the true state and applies zero inputs open loop (an oracle-like planner)."""

    name = "test_truth"

    def plan(self, problem):  # pragma: no cover - executed through plan_from only
        raise NotImplementedError

    def plan_from(self, problem, true_state):
        par = problem.parameterization
        u = torch.zeros(par.n_plan - 1, problem.system.nu)
        states = problem.system.rollout(true_state.to(torch.float32), u, par.plan_dt)
        return PlanResult(self.name, PlanStatus.SUCCESS, states=states, timings={"total": 0.02})


@pytest.fixture
def registered(monkeypatch):
    """Two planners registered with one call each, removed again after the test."""
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    registry.register_planner("test_straight", "test: straight on", section="search", label="ST",
                              colour="tab:pink")(lambda ctx: _Straight())
    registry.register_planner("test_truth", "test: open loop from the true state", execution="open_loop",
                              plans_from_true_state=True, label="TT", colour="gold")(lambda ctx: _KnowsTheTruth())


def test_the_registration_carries_every_fact(registered):
    info = registry.planner_info("test_straight")
    assert (info.label, info.colour, info.section, info.execution) == ("ST", "tab:pink", "search",
                                                                       registry.ExecutionMode.TRACK)
    assert not info.plans_from_true_state and "test_straight" in registry.planner_names()
    truth = registry.planner_info("test_truth")
    assert truth.execution == registry.ExecutionMode.OPEN_LOOP and truth.plans_from_true_state
    with pytest.raises(ValueError, match="unknown planner 'nope'; valid choices: .*test_truth"):
        registry.planner_info("nope")
    assert registry.planner_info("nope", default=True).label == "nope"  # records of unregistered planners
    with pytest.raises(ValueError, match="registered twice"):
        registry.register_planner("test_straight", "again")(lambda ctx: _Straight())
    # the paper's planners: labels, colours, sections and execution modes all come from their registrations
    assert [registry.planner_info(n).label for n in ("density", "mpc", "tube_mpc_0.5", "oracle")] == [
        "DP", "M0", "M2", "O"]
    assert registry.planner_info("tube_mpc_1.0").section == "tube_mpc"
    assert registry.planner_info("oracle").execution == registry.ExecutionMode.OPEN_LOOP


def test_a_registered_planner_runs_in_sweeps_reports_and_figures(registered, tmp_path, monkeypatch):
    from matplotlib.axes import Axes

    from density_planner.cli.bench import write_report

    spec = BenchmarkSpec("artificial", artificial_envs((0,)), ("test_straight", "test_truth"), ("unbiased", "biased"),
                         tiny_run_config())
    assert spec.variants_of("test_truth") == ("unbiased",)  # open loop: the heading bias cannot matter
    rep = run_benchmark(spec, tmp_path, workers=1)
    assert (rep.written, rep.errors) == (3, 0)
    records = {(r["planner"], r["variant"]): r for r in load_records(tmp_path)}
    assert set(records) == {("test_straight", "unbiased"), ("test_straight", "biased"), ("test_truth", "unbiased")}
    straight, truth = records["test_straight", "unbiased"], records["test_truth", "unbiased"]
    assert straight["execution"] == "track" and truth["execution"] == "open_loop"
    assert straight["status"] == truth["status"] == "success"
    assert len(straight["reference"]) == 101 and "reference" not in truth
    assert straight["config_hash"] == config_hash(spec, "test_straight")
    # its section is part of its configuration hash; another planner's section is not
    other = BenchmarkSpec("artificial", spec.envs, spec.planners, spec.variants,
                          update(spec.run_config, {"search": {"time_limit": 1.0}, "sampling": {"time_limit": 1.0}}))
    assert config_hash(other, "test_straight") != config_hash(spec, "test_straight")
    assert config_hash(other, "test_truth") == config_hash(spec, "test_truth")

    colours: list = []
    bar = Axes.bar

    def spy(self, *args, **kwargs):
        colours.append(kwargs.get("color"))
        return bar(self, *args, **kwargs)

    monkeypatch.setattr(Axes, "bar", spy)
    paths = write_report(tmp_path, plot_envs=1)
    table = (tmp_path / "summary.md").read_text()
    assert "| ST |" in table and "| ST-b |" in table and "| TT |" in table
    assert {"tab:pink", "gold"} <= set(colours)
    assert any(p.name == "plans_artificial_random-0.png" for p in paths)


def test_execution_settings_do_not_change_the_configuration_hash():
    base = BenchmarkSpec("artificial", artificial_envs((0, 1)), ("density", "mpc", "oracle"), ("unbiased",),
                         tiny_run_config())
    threads = BenchmarkSpec("artificial", base.envs, base.planners, base.variants,
                            update(base.run_config, {"evaluation": {"threads_per_worker": 4}}))
    samples = BenchmarkSpec("artificial", base.envs, base.planners, base.variants,
                            update(base.run_config, {"evaluation": {"mc_samples_tracked": 9}}))
    for planner in (*base.planners, None):
        assert config_hash(threads, planner) == config_hash(base, planner)
        assert config_hash(samples, planner) != config_hash(base, planner)
    # the [system] section: another controller changes what the density planner's records depend on, not MPC's
    analytic = BenchmarkSpec("artificial", base.envs, base.planners, base.variants,
                             update(base.run_config, {"system": {"controller": "analytic"}}))
    assert config_hash(analytic, "density") != config_hash(base, "density")
    assert config_hash(analytic, "mpc") == config_hash(base, "mpc")
    road = BenchmarkSpec("artificial", base.envs, base.planners, base.variants,
                         update(base.run_config, {"system": {"models": "road"}}))
    assert config_hash(road, "mpc") != config_hash(base, "mpc")


def test_more_threads_keep_existing_records(tmp_path):
    spec = BenchmarkSpec("artificial", artificial_envs((0,)), ("density",), ("unbiased",), tiny_run_config())
    run_benchmark(spec, tmp_path, workers=1)
    more = BenchmarkSpec("artificial", spec.envs, spec.planners, spec.variants,
                         update(spec.run_config, {"evaluation": {"threads_per_worker": 2}}))
    rep = run_benchmark(more, tmp_path, workers=1)  # not refused as "a different configuration"
    assert (rep.skipped, rep.written) == (1, 0)


# ------------------------------------------------------------------------------------------------ scene sources
def _args(**kw):
    base = {"seed": None, "file": None, "data_dir": None, "recording": None, "start_time": None, "models": None}
    return argparse.Namespace(**{**base, **kw})


def test_cli_and_benchmark_build_the_same_scenes():
    from density_planner.cli._scenes import scene_from_args
    from density_planner.settings import RunConfig

    cfg = RunConfig()
    cli = scene_from_args(_args(kind="random", seed=3), cfg)
    bench = build_scene(artificial_envs((3,))[0], cfg)
    assert torch.equal(cli.grid.probs, bench.grid.probs) and cli.start == bench.start and cli.goal == bench.goal
    pytest.importorskip("commonroad")
    file = shipped_commonroad_dir() / "USA_Peach-4_8_T-1.xml"
    cli = scene_from_args(_args(kind="commonroad", file=file), cfg)
    bench = build_scene(EnvSpec("commonroad", 0, 0, "cr", file=str(file)), cfg)
    assert torch.equal(cli.grid.probs, bench.grid.probs)
    np.testing.assert_array_equal(np.asarray(cli.start), np.asarray(bench.start))


def test_a_registered_scene_source_is_offered_by_the_command_line(monkeypatch):
    from density_planner.cli._scenes import add_scene_args, scene_from_args
    from density_planner.environment import sources
    from density_planner.environment.random_scene import random_scene
    from density_planner.settings import RunConfig

    monkeypatch.setattr(sources, "_SOURCES", dict(sources._SOURCES))
    calls = []

    @sources.register_scene_source("test_mirror", "test: a random scene, mirrored", uses=("seed", "recording"),
                                   requires=("recording",), requires_text="--recording N")
    def _mirror(request, run_config, system):
        calls.append((request.seed, request.recording, system.speed_max))
        return random_scene(request.seed or 0, run_config.random_scene)

    assert "test_mirror" in sources.scene_kinds()
    p = argparse.ArgumentParser()
    add_scene_args(p)
    args = p.parse_args(["--env", "test_mirror", "--seed", "2", "--recording", "5"])
    scene = scene_from_args(args, update(RunConfig(), {"system": {"models": "road"}}))
    assert calls == [(2, 5, 40.0)]  # the run's system (the car in the road set's domain, 0-40 m/s) is passed
    assert scene.grid.probs.shape == random_scene(2).grid.probs.shape
    with pytest.raises(ValueError, match="--env test_mirror needs --recording N"):
        scene_from_args(p.parse_args(["--env", "test_mirror"]), RunConfig())
    with pytest.raises(ValueError, match="--file is not used with --env test_mirror"):
        scene_from_args(p.parse_args(["--env", "test_mirror", "--recording", "1", "--file", "x.xml"]), RunConfig())
    with pytest.raises(ValueError, match="unknown scene kind 'nope'; valid choices: random, .*test_mirror"):
        sources.scene_source("nope")


def test_the_context_loads_the_predictor_when_asked(monkeypatch):
    from density_planner.density import registry as density_registry
    from density_planner.planners.context import build_context, run_system
    from density_planner.settings import RunConfig

    loads = []
    real = density_registry.load_predictor

    def counting(*args, **kwargs):
        loads.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(density_registry, "load_predictor", counting)
    lazy = build_context(RunConfig(), kind="random", controller="analytic", density="exact", lazy=True)
    assert loads == [] and lazy.system.speed_max == run_system(RunConfig(), "random").speed_max == 10.0
    assert lazy.predictor() is lazy.predictor() and loads == ["exact"]
    assert lazy.exact() is None  # the predictor is exact already: no re-check
    cfg = update(RunConfig(), {"system": {"controller": "analytic", "density": "exact"}})
    eager = build_context(cfg, kind="commonroad")  # the [system] section names controller and predictor
    assert loads == ["exact", "exact"] and eager.system.speed_max == 40.0

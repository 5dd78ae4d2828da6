"""Benchmark sweeps: records, resume, determinism across executors, failures recorded instead of raised."""

from __future__ import annotations

import json
import math

import pytest
from eval_testdata import run_job_with_test_planners, tiny_run_config

from density_planner.config import update
from density_planner.evaluation.benchmark import BenchmarkSpec, config_hash, make_jobs, run_benchmark
from density_planner.evaluation.environments import EnvSpec, artificial_envs, real_envs, stable_seed
from density_planner.evaluation.records import identity_view, load_records, load_scene_map, record_path
from density_planner.evaluation.report import summary_rows

TIME_COLUMNS = ("offline_time", "online_time")


def _spec(setting="artificial", planners=("density",), variants=("unbiased", "biased"), envs=(0,), **cfg):
    return BenchmarkSpec(setting, artificial_envs(envs), planners, variants, tiny_run_config(**cfg))


def _identity(out):
    return {(r["env"], r["planner"], r["variant"]): identity_view(r) for r in load_records(out)}


def _rows_without_times(records):
    return [{k: v for k, v in r.items() if k not in TIME_COLUMNS} for r in summary_rows(records)]


def test_records_resume_and_summary(tmp_path):
    spec = _spec()
    rep = run_benchmark(spec, tmp_path, workers=1)
    assert (rep.total, rep.written, rep.skipped) == (2, 2, 0)
    records = load_records(tmp_path)
    assert [(r["planner"], r["variant"]) for r in records] == [("density", "biased"), ("density", "unbiased")]
    for r in records:
        assert r["status"] == "success" and r["config_hash"] == config_hash(spec, "density")
        assert r["error"] is None and r["execution"] == "track"
        assert len(r["trajectory"]) == 101 and len(r["reference"]) == 101
        assert r["metrics"]["mc_samples"] == 8
        assert r["timings"]["offline"] > 0 and r["timings"]["online_per_step"] > 0
        assert r["failed"] == bool(r["failure_reason"])
    by_variant = {r["variant"]: r for r in records}
    # one plan, executed twice: same offline plan, same true state apart from the bias
    assert by_variant["biased"]["plan"] == by_variant["unbiased"]["plan"]
    assert by_variant["unbiased"]["true_state"][4] == 0.0
    assert by_variant["biased"]["true_state"][:4] == by_variant["unbiased"]["true_state"][:4]
    assert load_scene_map(tmp_path, "artificial", "random-0")["occupancy_u8"].shape == (241, 401)
    first = _identity(tmp_path)
    rows = _rows_without_times(records)

    # nothing to do on a re-run
    assert run_benchmark(spec, tmp_path, workers=1).written == 0
    # a lost record is recomputed identically
    record_path(tmp_path, "artificial", "random-0", "density", "biased").unlink()
    rep = run_benchmark(spec, tmp_path, workers=1)
    assert (rep.written, rep.skipped) == (1, 1)
    assert _identity(tmp_path) == first
    assert _rows_without_times(load_records(tmp_path)) == rows


def test_a_different_configuration_is_refused(tmp_path):
    run_benchmark(_spec(), tmp_path, workers=1)
    other = _spec(evaluation={"max_goal_distance": 3.0})
    assert config_hash(other) != config_hash(_spec())
    with pytest.raises(ValueError, match="different configuration"):
        run_benchmark(other, tmp_path, workers=1)
    rep = run_benchmark(other, tmp_path, workers=1, redo_stale=True)
    assert rep.written == 2
    assert {r["config_hash"] for r in load_records(tmp_path)} == {config_hash(other, "density")}


def test_mpc_records_do_not_depend_on_the_learned_components():
    from dataclasses import replace

    spec = _spec(planners=("density", "mpc"))
    new = replace(spec, controller="c3m", components="0123")
    assert config_hash(new, "mpc") == config_hash(spec, "mpc")
    assert config_hash(new, "oracle") == config_hash(spec, "oracle")
    assert config_hash(new, "density") != config_hash(spec, "density")
    assert config_hash(new) != config_hash(spec)
    tweaked = replace(spec, run_config=tiny_run_config(mpc={"max_iter": 7}))
    assert config_hash(tweaked, "mpc") != config_hash(spec, "mpc")
    assert config_hash(tweaked, "density") == config_hash(spec, "density")


def test_records_depend_on_the_scene_sections_of_their_setting_only():
    """A CommonRoad or inD setting cannot change the numbers of random scenes, and vice versa."""
    from dataclasses import replace

    spec = _spec(planners=("density", "mpc"))
    cr = replace(spec, run_config=update(spec.run_config, {"commonroad": {"footprint": {"model": "gaussian"}}}))
    rnd = replace(spec, run_config=update(spec.run_config, {"random_scene": {"n_static": (5, 7)}}))
    for planner in ("density", "mpc"):
        assert config_hash(cr, planner) == config_hash(spec, planner)
        assert config_hash(rnd, planner) != config_hash(spec, planner)
        cr_setting, default_setting = replace(cr, setting="commonroad"), replace(spec, setting="commonroad")
        assert config_hash(cr_setting, planner) != config_hash(default_setting, planner)


def test_planner_exception_becomes_a_recorded_failure(tmp_path):
    spec = _spec(planners=("test_crash", "density"), variants=("unbiased",))
    rep = run_benchmark(spec, tmp_path, workers=1, job_fn=run_job_with_test_planners)
    assert rep.written == 2 and rep.errors == 1
    crash = json.loads(record_path(tmp_path, "artificial", "random-0", "test_crash", "unbiased").read_text())
    assert crash["status"] == "error" and crash["failed"] and crash["failure_reason"] == "no_solution"
    assert "fails on purpose" in crash["error"] and "planning failed" in crash["message"]
    ok = json.loads(record_path(tmp_path, "artificial", "random-0", "density", "unbiased").read_text())
    assert ok["status"] == "success"
    # --retry-errors runs the failed record again (it fails again, the successful one is kept)
    rep = run_benchmark(spec, tmp_path, workers=1, retry_errors=True, job_fn=run_job_with_test_planners)
    assert rep.written == 1 and rep.errors == 1


def test_ablation_compares_planned_references(tmp_path):
    spec = _spec("ablation", variants=("nominal",), evaluation={"plan_time_limit": 1e-6})
    run_benchmark(spec, tmp_path, workers=1)
    (r,) = load_records(tmp_path)
    assert r["execution"] == "planned" and r["status"] == "timeout"
    assert r["failed"] and r["failure_reason"] == "no_solution" and "took" in r["message"]
    assert r["metrics"]["final_distance"] >= 0 and r["metrics"]["mc_samples"] == 8


def test_jobs_group_variants_of_offline_planners_only():
    spec = BenchmarkSpec("artificial", artificial_envs([0, 1]), ("density", "mpc", "oracle"), ("unbiased", "biased"),
                         tiny_run_config())
    jobs = make_jobs(spec)
    assert [(j.env.name, j.planner, j.variants) for j in jobs] == [
        ("random-0", "density", ("unbiased", "biased")), ("random-0", "mpc", ("unbiased",)),
        ("random-0", "mpc", ("biased",)), ("random-0", "oracle", ("unbiased",)),
        ("random-1", "density", ("unbiased", "biased")), ("random-1", "mpc", ("unbiased",)),
        ("random-1", "mpc", ("biased",)), ("random-1", "oracle", ("unbiased",)),
    ]
    assert [j.want_map for j in jobs] == [True, False, False, False] * 2
    done = {("random-0", "density", "biased"), ("random-0", "mpc", "unbiased")}
    jobs = make_jobs(spec, done, maps_done={"random-0"})
    assert [(j.planner, j.variants) for j in jobs][:3] == [("density", ("unbiased",)), ("mpc", ("biased",)),
                                                            ("oracle", ("unbiased",))]
    assert not jobs[0].want_map and jobs[3].want_map


def test_stable_seeds_and_spec_validation():
    assert stable_seed("a", 1) == stable_seed("a", 1) != stable_seed("a", 2)
    assert 0 <= stable_seed("x") < 2**31
    with pytest.raises(ValueError, match="setting"):
        BenchmarkSpec("nope", artificial_envs([0]), ("density",), ("unbiased",), tiny_run_config())
    with pytest.raises(ValueError, match="variant"):
        BenchmarkSpec("artificial", artificial_envs([0]), ("density",), ("sideways",), tiny_run_config())
    with pytest.raises(ValueError, match="unique"):
        BenchmarkSpec("artificial", artificial_envs([0, 0]), ("density",), ("unbiased",), tiny_run_config())


def test_real_environments_from_the_shipped_commonroad_scenarios():
    envs = real_envs(range(5))
    assert [e.kind for e in envs] == ["commonroad"] * 5
    assert [e.seed for e in envs] == [0, 0, 1, 1, 2]  # seed 0: the scenario's planning problem
    assert len({e.file for e in envs}) == 2 and all(e.file.startswith("<shipped>/") for e in envs)
    assert len({e.name for e in envs}) == 5


def test_real_environments_from_ind_recordings(tmp_path):
    import numpy as np

    from ind_testdata import write_ind_recording

    f = np.arange(1000)  # 40 s at 25 Hz
    car = {"id": 1, "class": "car", "length": 4.5, "width": 1.8, "frames": f, "x": 0.2 * f, "y": np.zeros(f.size),
           "heading": np.zeros(f.size), "vx": np.full(f.size, 5.0), "vy": np.zeros(f.size)}
    for rec in (3, 7):
        write_ind_recording(tmp_path, rec, [car], duration=40.0)
    envs = real_envs(range(4), tmp_path)
    assert [e.kind for e in envs] == ["ind"] * 4
    assert [e.recording for e in envs] == [3, 7, 3, 7]
    assert all(0 <= e.start_time <= 30.0 for e in envs)  # a 10-s window inside the 40-s recording
    assert real_envs(range(4), tmp_path) == envs  # seeded
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="neither"):
        real_envs(range(2), tmp_path / "empty")


@pytest.mark.slow
def test_real_commonroad_scene_with_sampled_start_goal():
    from density_planner.evaluation.environments import build_scene

    env = real_envs(range(4))[3]  # US101, start/goal seed 1
    scene = build_scene(env, tiny_run_config())
    assert scene.name == env.name and scene.meta["start_goal_sampled"]
    first = build_scene(real_envs(range(2))[1], tiny_run_config())
    assert first.start != scene.start


def test_serial_and_dask_give_identical_records(tmp_path):
    """A real Dask scheduler and worker (in this process, over TCP on 127.0.0.1) against the serial run."""
    distributed = pytest.importorskip("distributed")
    spec = _spec(variants=("unbiased",))
    run_benchmark(spec, tmp_path / "serial", workers=1)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        run_benchmark(spec, tmp_path / "dask", scheduler=cluster.scheduler_address)
    assert _identity(tmp_path / "dask") == _identity(tmp_path / "serial")


@pytest.mark.slow
def test_serial_joblib_and_dask_processes_give_identical_records(tmp_path):
    """Serial, two joblib workers and a Dask cluster of two worker processes on 127.0.0.1: identical records,
    including a deterministic MPC (no CPU-time limit) and the oracle."""
    distributed = pytest.importorskip("distributed")
    pytest.importorskip("casadi")
    spec = BenchmarkSpec("artificial", artificial_envs([0, 1]), ("density", "mpc", "oracle"), ("unbiased", "biased"),
                         update(tiny_run_config(), {"mpc": {"n_steps": 20}}))
    run_benchmark(spec, tmp_path / "serial", workers=1)
    run_benchmark(spec, tmp_path / "joblib", workers=2)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        run_benchmark(spec, tmp_path / "dask", scheduler=cluster.scheduler_address)
    serial = _identity(tmp_path / "serial")
    assert len(serial) == 10
    assert all(r["status"] != "error" for r in serial.values()), [r["error"] for r in serial.values()]
    assert _identity(tmp_path / "joblib") == serial
    assert _identity(tmp_path / "dask") == serial


@pytest.mark.slow
def test_killed_worker_becomes_a_recorded_failure(tmp_path):
    spec = BenchmarkSpec("artificial", artificial_envs([0]), ("test_kill", "density"), ("unbiased",),
                         tiny_run_config())
    rep = run_benchmark(spec, tmp_path, workers=2, job_fn=run_job_with_test_planners)
    assert rep.written == 2
    killed = json.loads(record_path(tmp_path, "artificial", "random-0", "test_kill", "unbiased").read_text())
    assert killed["status"] == "error" and killed["failed"] and "WorkerDied" in killed["error"]
    other = json.loads(record_path(tmp_path, "artificial", "random-0", "density", "unbiased").read_text())
    # the density job either finished before the crash or was in flight with it (then it failed too)
    assert other["status"] in ("success", "error")
    if other["status"] == "error":
        assert "WorkerDied" in other["error"]


@pytest.mark.slow
def test_killed_dask_worker_becomes_a_recorded_failure(tmp_path):
    distributed = pytest.importorskip("distributed")
    spec = BenchmarkSpec("artificial", artificial_envs([0]), ("test_kill",), ("unbiased",), tiny_run_config())
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        rep = run_benchmark(spec, tmp_path, scheduler=cluster.scheduler_address, job_fn=run_job_with_test_planners)
    assert rep.written == 1 and rep.errors == 1
    (r,) = load_records(tmp_path)
    assert r["failed"] and "KilledWorker" in r["error"]


def test_env_spec_roundtrip():
    env = EnvSpec("random", 3, 3, "random-3")
    assert env.as_dict() == {"kind": "random", "index": 3, "seed": 3, "name": "random-3"}
    assert math.isfinite(stable_seed(env.name))


def test_component_digest_tracks_weights():
    import torch

    from density_planner.control.analytic import CarTrackingController
    from density_planner.density.liouville import ExactLiouville
    from density_planner.evaluation.benchmark import component_digest
    from density_planner.systems.car import KinematicCar

    ctrl = CarTrackingController()
    # the exact predictor holds the same controller: counted once
    assert component_digest(ctrl, ExactLiouville(KinematicCar(), ctrl)) == component_digest(ctrl)
    assert component_digest(object()) == ""
    net = torch.nn.Linear(3, 2)
    d1 = component_digest(ctrl, net)
    assert d1 and component_digest(ctrl, net) == d1

    class Holder:
        def __init__(self, module):
            self.network = module

    assert component_digest(Holder(net)) == component_digest(net)
    with torch.no_grad():
        net.weight.add_(1.0)
    assert component_digest(net) != d1
    spec = _spec()
    from dataclasses import replace

    assert config_hash(replace(spec, components="abc")) != config_hash(spec)


@pytest.mark.slow
def test_real_setting_on_a_shipped_commonroad_scenario(tmp_path):
    spec = BenchmarkSpec("real", real_envs([1]), ("density",), ("unbiased",), tiny_run_config())
    run_benchmark(spec, tmp_path, workers=1)
    (r,) = load_records(tmp_path)
    assert r["env"] == "cr-USA_US101-4_1_T-1-s0" and r["status"] == "success", r["error"]
    assert r["env_spec"]["kind"] == "commonroad" and r["env_spec"]["file"].startswith("<shipped>/")
    assert len(r["trajectory"]) == 101

"""Issue 18's catalogue of bad inputs: each gives one line naming the problem (exit 2), never a traceback, never
silently changed data, and leaves no empty ``--out`` behind. Exit codes: 2 bad input, 1 internal failure."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from density_planner.cli import EXIT_BAD_INPUT, EXIT_FAILURE, classify_error, main
from density_planner.errors import CheckpointError, DataError


def run_cli(capsys, args: list[str]) -> tuple[int, str]:
    rc = main(args)
    err = capsys.readouterr().err.strip()
    return rc, err


def assert_one_line(rc: int, err: str, match: str, code: int = EXIT_BAD_INPUT) -> None:
    assert rc == code, err
    lines = [ln for ln in err.splitlines() if ln.startswith("density-planner: error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert match in lines[0], lines[0]


@pytest.fixture
def small_scene_file(tmp_path) -> Path:
    from density_planner.environment.random_scene import random_scene
    from density_planner.environment.scene import save_scene

    return save_scene(random_scene(0), tmp_path / "scene.npz")


@pytest.fixture
def memory_limit(monkeypatch):
    """A fixed memory budget (1 GiB): the estimates are checked against it, whatever the test machine has."""
    monkeypatch.setenv("DENSITY_PLANNER_MEMORY_LIMIT", "1G")


# ------------------------------------------------------------------------------------------------- scene files
def test_truncated_npz(tmp_path, capsys, small_scene_file):
    bad = tmp_path / "trunc.npz"
    data = small_scene_file.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    out = tmp_path / "out"
    rc, err = run_cli(capsys, ["plan", "--env", "file", "--file", str(bad), "--out", str(out)])
    assert_one_line(rc, err, "not a readable .npz file (truncated or corrupt")
    assert not out.exists()


def test_zip_bomb_npz_refused_before_loading(tmp_path, capsys):
    import numpy.lib.format as fmt

    bomb = tmp_path / "bomb.npz"
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        with zf.open("probs.npy", "w", force_zip64=True) as fh:
            fmt.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False, "shape": (101, 3000, 3000)})
            fh.write(bytes(2**20))  # the header declares 3.4 GiB; the test writes only 1 MiB of it
    assert bomb.stat().st_size < 100_000
    rc, err = run_cli(capsys, ["plan", "--env", "file", "--file", str(bomb), "--out", str(tmp_path / "o")])
    assert_one_line(rc, err, "declares 3.39 GiB of arrays (largest: probs 101 x 3000 x 3000 float32)")
    assert "DENSITY_PLANNER_MAX_FILE_BYTES" in err


def test_object_array_npz_refused(tmp_path):
    from density_planner.io.npz import read_npz

    path = tmp_path / "obj.npz"
    np.savez(path, probs=np.array([{"a": 1}], dtype=object))
    with pytest.raises(DataError, match="object array"):
        read_npz(path)


# ---------------------------------------------------------------------------------------- memory estimates
def test_random_scene_cell_size_memory(tmp_path, capsys, memory_limit):
    out = tmp_path / "o"
    rc, err = run_cli(capsys, ["env", "--kind", "random", "--set", "random_scene.cell_size=0.001", "--out", str(out)])
    assert_one_line(rc, err, "raise random_scene.cell_size")
    assert "101 x 24001 x 40001 cells needs about" in err and not out.exists()


def test_bench_envs_memory(tmp_path, capsys, memory_limit):
    rc, err = run_cli(capsys, ["bench", "artificial", "--envs", "1000000000", "--out", str(tmp_path / "o")])
    assert_one_line(rc, err, "lower --envs")
    assert not (tmp_path / "o").exists()


def test_density_samples_memory(tmp_path, capsys, memory_limit):
    rc, err = run_cli(capsys, ["density", "--samples", "1000000000", "--out", str(tmp_path / "o")])
    assert_one_line(rc, err, "lower --samples")
    assert "--samples 1000000000 needs about" in err and not (tmp_path / "o").exists()


def test_memory_limit_variable_is_checked(monkeypatch):
    from density_planner.memory import check_memory

    monkeypatch.setenv("DENSITY_PLANNER_MEMORY_LIMIT", "lots")
    with pytest.raises(ValueError, match="DENSITY_PLANNER_MEMORY_LIMIT='lots' is not a size"):
        check_memory(1, "x", "y")
    monkeypatch.setenv("DENSITY_PLANNER_MEMORY_LIMIT", "512M")
    check_memory(2**20, "x", "y")
    with pytest.raises(ValueError, match="needs about 1 GiB of memory, more than the 512 MiB"):
        check_memory(2**30, "x", "lower y")


# ------------------------------------------------------------------------------------------ benchmark records
def _record(env: str, planner: str = "density", variant: str = "unbiased", failed: bool = False) -> dict:
    return {"setting": "artificial", "env": env, "planner": planner, "variant": variant, "status": "success",
            "failed": failed, "failure_reason": "goal" if failed else "",
            "metrics": {"collision_cost": 0.0, "goal_cost": 1.0, "input_cost": 1.0, "final_distance": 1.0,
                        "collision_probability_max": 0.1},
            "timings": {"offline": 1.0, "online_per_step": 0.0}, "env_spec": {"index": int(env.split("-")[1])}}


@pytest.mark.parametrize("content", ["42", '{"setting": "artificial"}', "TRUNCATED",
                                     "METRICS_STRING", '["a", "b"]'])
def test_report_counts_bad_records_as_missing_runs(tmp_path, capsys, content):
    d = tmp_path / "records" / "artificial"
    d.mkdir(parents=True)
    for i in range(3):
        (d / f"random-{i}__density__unbiased.json").write_text(json.dumps(_record(f"random-{i}")))
    bad = d / "random-3__density__unbiased.json"
    if content == "TRUNCATED":
        bad.write_text(json.dumps(_record("random-3"))[:40])
    elif content == "METRICS_STRING":
        bad.write_text(json.dumps({**_record("random-3"), "metrics": "oops"}))
    else:
        bad.write_text(content)
    rc = main(["report", str(tmp_path), "--plot-envs", "0"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "1 record file(s) are not usable and count as missing runs" in captured.err
    assert "Traceback" not in captured.err
    text = (tmp_path / "summary.md").read_text()
    assert "| DP | 3 (1 missing) |" in text and "**Missing runs**" in text and "DP 1" in text
    import csv

    with open(tmp_path / "summary.csv") as fh:
        (row,) = list(csv.DictReader(fh))
    assert row["runs"] == "3" and row["missing"] == "1"


def test_report_counts_runs_the_sweep_expects(tmp_path):
    from density_planner.evaluation.report import write_tables

    d = tmp_path / "records" / "artificial"
    d.mkdir(parents=True)
    (d / "random-0__density__unbiased.json").write_text(json.dumps(_record("random-0")))
    sweep = {"setting": "artificial", "planners": ["density"], "variants": ["unbiased"],
             "envs": [{"name": "random-0"}, {"name": "random-1"}]}
    (tmp_path / "sweep_artificial.json").write_text(json.dumps(sweep))
    _, rows, _ = write_tables(tmp_path)
    assert rows[0]["runs"] == 1 and rows[0]["missing"] == 1


def test_resumed_bench_recomputes_bad_records(tmp_path):
    from density_planner.evaluation.benchmark import BenchmarkSpec, _existing
    from density_planner.evaluation.environments import artificial_envs
    from density_planner.settings import RunConfig

    spec = BenchmarkSpec("ablation", artificial_envs(range(2)), ("density",), ("nominal",), RunConfig())
    d = tmp_path / "records" / "ablation"
    d.mkdir(parents=True)
    (d / "random-0__density__nominal.json").write_text("42")
    (d / "random-1__density__nominal.json").write_text('{"planner": 3}')
    done, _ = _existing(tmp_path, spec, False, False)
    assert done == set()


def test_unreachable_scheduler_leaves_no_sweep_file(tmp_path, monkeypatch):
    import density_planner.evaluation.benchmark as bm
    from density_planner.settings import RunConfig

    def refuse(*args, **kwargs):
        raise ValueError("cannot connect to the Dask scheduler at 'tcp://127.0.0.1:1'")
        yield  # pragma: no cover

    monkeypatch.setattr(bm, "run_tasks", refuse)
    from density_planner.evaluation.environments import artificial_envs

    spec = bm.BenchmarkSpec("ablation", artificial_envs(range(1)), ("density",), ("nominal",), RunConfig())
    with pytest.raises(ValueError, match="cannot connect"):
        bm.run_benchmark(spec, tmp_path, scheduler="tcp://127.0.0.1:1")
    assert not list(tmp_path.glob("sweep_*.json"))


# --------------------------------------------------------------------------------------------------- inD files
def _ind(tmp_path) -> Path:
    from ind_testdata import write_ind_recording

    f = np.arange(300)
    car = {"id": 1, "class": "car", "length": 4.5, "width": 1.8, "frames": f, "x": 10.0 + 0.2 * f,
           "y": np.full(f.size, -20.0), "heading": np.zeros(f.size), "vx": np.full(f.size, 5.0),
           "vy": np.zeros(f.size)}
    write_ind_recording(tmp_path, 7, [car])
    return tmp_path


def test_ind_row_with_an_extra_field(tmp_path):
    from density_planner.environment.ind import load_ind_scene

    d = _ind(tmp_path)
    path = d / "07_tracks.csv"
    lines = path.read_text().splitlines()
    lines[10] = lines[10] + ",99.0"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match="line 11 has .* fields, the header has"):
        load_ind_scene(d, 7)


@pytest.mark.parametrize("column", ["width", "length"])
def test_ind_negative_size(tmp_path, column):
    from density_planner.environment.ind import load_ind_scene

    d = _ind(tmp_path)
    path = d / "07_tracksMeta.csv"
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    row = lines[1].split(",")
    row[header.index(column)] = "-1.8"
    lines[1] = ",".join(row)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=f"column '{column}' must be >= 0 m, got -1.8 on line 2"):
        load_ind_scene(d, 7)


# ------------------------------------------------------------------------------------------------ weights files
def _copy_weights(tmp_path: Path, name: str) -> Path:
    from importlib.resources import files

    src = Path(str(files("density_planner") / "weights" / name))
    for suffix in (".pt", ".json"):
        shutil.copy(src.with_suffix(suffix), tmp_path / (src.stem + suffix))
    return tmp_path / (src.stem + ".pt")


def _poison(pt: Path) -> None:
    state = torch.load(pt, weights_only=True)
    key = next(k for k, v in state.items() if v.is_floating_point())
    state[key] = state[key].clone()
    state[key].view(-1)[0] = float("nan")
    torch.save(state, pt)


def test_nan_controller_weights_refused_on_load(tmp_path, capsys):
    from density_planner.control.registry import load_controller

    pt = _copy_weights(tmp_path, "controller_c3m.pt")
    _poison(pt)
    with pytest.raises(CheckpointError, match="NaN or infinite value"):
        load_controller(pt)
    out = tmp_path / "o"
    rc, err = run_cli(capsys, ["plan", "--env", "random", "--controller", str(pt), "--out", str(out)])
    assert_one_line(rc, err, "holds 1 NaN or infinite value(s); the weights are corrupt")
    assert not out.exists()  # no plan.json full of nulls


def test_nan_density_weights_refused_on_load(tmp_path):
    from density_planner.density.registry import load_learned_predictor

    pt = _copy_weights(tmp_path, "density_trajectory.pt")
    _poison(pt)
    with pytest.raises(CheckpointError, match="NaN or infinite value"):
        load_learned_predictor(pt)


# ------------------------------------------------------------------------------------------------------ seeds
@pytest.mark.parametrize("args,name", [
    (["--distribution-seed", "-1"], "--distribution-seed"),
    (["--seed", "-1"], "--seed"),
    (["--set", "density_planner.seed=-1"], "seed"),
    (["--distribution-seed", str(2**64)], "--distribution-seed"),
    (["--seed", str(2**70)], "--seed"),
])
def test_one_rule_for_all_seeds(tmp_path, capsys, args, name):
    out = tmp_path / "o"
    rc, err = run_cli(capsys, ["plan", "--env", "random", *args, "--out", str(out)])
    assert_one_line(rc, err, f"{name} must be an integer in [0, 2^63 - 1]")
    assert "Overflow" not in err and not out.exists()


def test_seed_rule_in_the_api():
    from density_planner.checks import MAX_SEED, check_seed
    from density_planner.planners.density_planner import DensityPlannerConfig

    assert check_seed("s", MAX_SEED) == MAX_SEED
    for bad in (-1, MAX_SEED + 1, 1.5, True):
        with pytest.raises(ValueError, match=r"s must be an integer in \[0, 2\^63 - 1\]"):
            check_seed("s", bad)
    with pytest.raises(ValueError, match="seed must be an integer"):
        DensityPlannerConfig(seed=-1)


# ----------------------------------------------------------------------------------------------- API checks
def test_make_reference_refuses_inputs_outside_the_bounds():
    from density_planner.control.reference import make_reference
    from density_planner.systems.car import KinematicCar

    car = KinematicCar()
    params = torch.zeros(2, 10)
    params[0, 3] = 1e6
    with pytest.raises(ValueError, match=r"params must lie within the input bounds of KinematicCar"):
        make_reference(car, torch.zeros(5), params)
    params[0, 3] = 3.0  # on the bound is fine
    assert make_reference(car, torch.zeros(5), params).x.shape == (1001, 5)


# ------------------------------------------------------------------------------------------- messages, --out
def test_ragged_params_file_names_option_and_file(tmp_path, capsys):
    params = tmp_path / "p.json"
    params.write_text(json.dumps([[0.0] * 10, [0.0] * 9]))
    out = tmp_path / "o"
    rc, err = run_cli(capsys, ["density", "--params", str(params), "--samples", "5", "--out", str(out)])
    assert_one_line(rc, err, f"--params {params}: cannot read reference parameters (the rows have different lengths")
    assert not out.exists()


@pytest.mark.parametrize("args", [
    ["plan", "--env", "random", "--planner", "magic"],
    ["plan", "--env", "random", "--set", "density_planner.bogus=1"],
    ["env", "--kind", "random", "--set", "random_scene.walls=3"],
    ["bench", "artificial", "--planners", "magic"],
    ["density", "--samples", "0"],
])
def test_rejected_commands_leave_no_out_directory(tmp_path, capsys, args):
    out = tmp_path / "nested" / "o"
    rc = main([*args, "--out", str(out)])
    capsys.readouterr()
    assert rc == EXIT_BAD_INPUT
    assert not out.exists()


def test_exit_code_rule(capsys, monkeypatch):
    assert classify_error(ValueError("x")) == EXIT_BAD_INPUT
    assert classify_error(FileNotFoundError("x")) == EXIT_BAD_INPUT
    assert classify_error(RuntimeError("x")) == EXIT_FAILURE
    assert classify_error(OSError(28, "No space left on device")) == EXIT_FAILURE
    assert classify_error(KeyError("x")) == EXIT_FAILURE
    import density_planner.cli.env as env_cmd

    def boom(*args, **kwargs):
        raise KeyError("internal")

    monkeypatch.setattr(env_cmd, "scene_from_args", boom)
    rc, err = run_cli(capsys, ["env", "--kind", "random", "--out", "/nonexistent-dir-for-test/o"])
    assert_one_line(rc, err, "internal error: KeyError", code=EXIT_FAILURE)
    assert "--debug" in err

"""Bad input to the core API gives ValueErrors naming the argument; the CLI prints one line and exits non-zero."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from density_planner.cli import main
from density_planner.control.analytic import CarTrackingController
from density_planner.control.reference import make_reference
from density_planner.density.liouville import LiouvilleConfig, propagate_density
from density_planner.io.atomic import atomic_write_bytes
from density_planner.systems.car import KinematicCar


@pytest.fixture
def car_ref():
    car = KinematicCar()
    ref = make_reference(car, torch.tensor([0.0, 0.0, 0.0, 2.0, 0.0]), torch.zeros(2, 10))
    return car, CarTrackingController(), ref


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"dt": 0.0}, "dt must be > 0"),
        ({"dt": -0.1}, "dt must be > 0"),
        ({"integrator": "rk45"}, "unknown integrator 'rk45'; valid choices: euler, rk4"),
        ({"divergence": "fd"}, "unknown divergence"),
        ({"dt": 0.03}, "output_dt"),
    ],
)
def test_bad_liouville_config(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LiouvilleConfig(**kwargs)


def test_bad_propagation_inputs(car_ref):
    car, ctrl, ref = car_ref
    with pytest.raises(ValueError, match="x0 must have trailing shape"):
        propagate_density(car, ctrl, torch.zeros(10, 4), ref)
    with pytest.raises(ValueError, match="x0 must have trailing shape"):
        propagate_density(car, ctrl, torch.zeros(5), ref)
    x0 = torch.zeros(3, 5)
    x0[1, 2] = float("nan")
    with pytest.raises(ValueError, match="x0 contains 1 NaN"):
        propagate_density(car, ctrl, x0, ref)
    with pytest.raises(ValueError, match="log_rho0"):
        propagate_density(car, ctrl, torch.zeros(3, 5), ref, log_rho0=torch.zeros(4))
    with pytest.raises(ValueError, match="log_rho0 contains"):
        propagate_density(car, ctrl, torch.zeros(3, 5), ref, log_rho0=torch.tensor([0.0, float("inf"), 0.0]))
    with pytest.raises(ValueError, match="reference must be a Reference"):
        propagate_density(car, ctrl, torch.zeros(3, 5), ref.x)
    with pytest.raises(ValueError, match="batch shape of x0"):
        refs = make_reference(car, torch.zeros(5), torch.zeros(2, 2, 10))
        propagate_density(car, ctrl, torch.zeros(3, 4, 5), refs)


def test_density_cli_writes_outputs(tmp_path, capsys):
    rc = main(["density", "--samples", "40", "--seed", "1", "--out", str(tmp_path)])
    assert rc == 0
    with np.load(tmp_path / "density.npz") as z:
        assert z["x"].shape == (40, 101, 5) and z["log_rho"].shape == (40, 101) and z["x_ref"].shape == (101, 5)
        assert np.isfinite(z["log_rho"]).all()
    assert (tmp_path / "density.png").stat().st_size > 10_000
    assert "wrote" in capsys.readouterr().out


def test_density_cli_names_the_scheme(tmp_path, capsys):
    """The road domain integrates with the error-controlled rk43 and the command says so; the paper's box with
    RK4 at 0.1 s; ``--integrator`` / ``--tolerance`` choose."""
    assert main(["density", "--models", "road", "--start", "0", "0", "0", "30", "--samples", "4", "--params",
                 str(_zero_params(tmp_path)), "--out", str(tmp_path / "fast")]) == 0
    assert "rk43 (error-controlled, tolerance 0.003, steps <= 0.1 s, saturation step 2)" in capsys.readouterr().out
    assert main(["density", "--samples", "4", "--out", str(tmp_path / "slow")]) == 0
    assert "(rk4 at 0.1 s)" in capsys.readouterr().out
    assert main(["density", "--samples", "4", "--integrator", "dopri5", "--tolerance", "1e-6",
                 "--out", str(tmp_path / "tol")]) == 0
    assert "tolerance 1e-06" in capsys.readouterr().out


def _zero_params(tmp_path):
    path = tmp_path / "zero.json"
    path.write_text(json.dumps({"params": np.zeros((2, 10)).tolist()}))
    return path


def test_density_cli_params_file(tmp_path):
    params = np.zeros((2, 10))
    params[1, :3] = 1.0
    (tmp_path / "p.json").write_text(json.dumps({"params": params.tolist()}))
    assert main(["density", "--samples", "5", "--params", str(tmp_path / "p.json"), "--out", str(tmp_path)]) == 0
    with np.load(tmp_path / "density.npz") as z:
        np.testing.assert_allclose(z["params"], params)


@pytest.mark.parametrize(
    "args,match",
    [
        (["--samples", "0"], "--samples must be >= 1"),
        (["--integrator", "euler", "--dt", "0"], "dt must be > 0"),
        (["--params", "missing.json"], "parameter file not found"),
        (["--params", "bad.json"], "cannot read reference parameters"),
        (["--params", "shape.json"], "must have shape (2, 10)"),
        (["--params", "nan.json"], "NaN"),
        (["--params", "big.json"], "input bounds"),
        (["--controller", "nonsense"], "unknown controller"),
        (["--start", "0", "0", "nan", "1"], "--start contains NaN"),
    ],
)
def test_density_cli_errors_are_one_line(tmp_path, capsys, monkeypatch, args, match):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "shape.json").write_text(json.dumps([[0.0] * 9] * 2))
    (tmp_path / "nan.json").write_text('[[NaN, 0, 0, 0, 0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 0, 0, 0, 0, 0, 0]]')
    (tmp_path / "big.json").write_text(json.dumps([[5.0] * 10, [0.0] * 10]))
    rc = main(["density", *args, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2
    assert match in err and err.count("\n") == 1 and "Traceback" not in err


def test_console_script_exit_code(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "density_planner.cli", "density", "--samples", "-3", "--out",
                           str(tmp_path)], capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and "--samples" in proc.stderr


def test_core_modules_do_not_import_matplotlib():
    code = ("import sys, density_planner, density_planner.density, density_planner.control, "
            "density_planner.systems, density_planner.config; "
            "print('matplotlib' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_atomic_write_leaves_no_partial_file(tmp_path):
    target = tmp_path / "result.bin"
    atomic_write_bytes(target, b"old")

    class Boom(Exception):
        pass

    from density_planner.io import atomic

    def bad_writer(fh):
        fh.write(b"partial")
        raise Boom

    with pytest.raises(Boom):
        atomic._atomic(target, bad_writer)
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["result.bin"]

"""``data density``, ``train density`` and ``validate density`` end to end on a tiny data set (analytic
controller), and one-line errors for bad input."""

from __future__ import annotations

import json

import pytest

from density_planner.cli import main


@pytest.mark.slow
def test_data_train_validate_commands(tmp_path, capsys):
    data = tmp_path / "data"
    rc = main(["data", "density", "--references", "16", "--samples", "4", "--controller", "analytic",
               "--set", "references_per_shard=4", "--workers", "1", "--quiet", "--out", str(data)])
    assert rc == 0
    manifest = json.loads((data / "manifest.json").read_text())
    assert manifest["complete"] and manifest["sizes"]["references_val"] == 4
    assert manifest["command"].startswith("density-planner data density")

    for arch in ("trajectory", "pointwise"):
        out = tmp_path / f"train_{arch}"
        rc = main(["train", "density", "--arch", arch, "--data", str(data), "--epochs", "2", "--set", "hidden=16",
                   "--set", "layers=2", "--threads", "1", "--quiet", "--export", str(tmp_path / f"exp_{arch}.pt"),
                   "--out", str(out)])
        assert rc == 0
        meta = json.loads((out / f"density_{arch}.json").read_text())
        assert meta["kind"] == "density_predictor" and meta["architecture"]["arch"] == arch
        assert meta["controller"]["spec"] == "analytic" and meta["controller"]["fingerprint"]
        assert meta["data"]["sizes"]["references_train"] == 12
        assert meta["training"]["wall_time_s"] > 0
        fresh = meta["diagnostics"]["fresh_references"]
        assert {"error_state_mse", "log_density_rmse", "position_error_m"} <= set(fresh)
        assert meta["commands"]["train"].startswith("density-planner train density")
        assert (out / "history.json").is_file() and (out / "checkpoint.pt").is_file()
        assert (tmp_path / f"exp_{arch}.pt").is_file() and (tmp_path / f"exp_{arch}.json").is_file()

    val = tmp_path / "val"
    rc = main(["validate", "density", "--density", f"{tmp_path / 'exp_trajectory.pt'},{tmp_path / 'exp_pointwise.pt'}",
               "--references", "3", "--samples", "5", "--figure-samples", "200", "--threads", "1",
               "--out", str(val)])
    assert rc == 0
    report = json.loads((val / "density_report.json").read_text())
    assert report["controller"] == "analytic" and len(report["predictors"]) == 2
    for s in report["predictors"].values():
        assert len(s["position_error_m"]["per_time"]["median"]) == 101
        assert s["position_error_m"]["per_time"]["median"][0] == 0.0  # t = 0 is exact
    assert (val / "density_errors.png").stat().st_size > 10_000
    assert (val / "density_heatmaps.png").stat().st_size > 10_000
    assert "wrote" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, message",
    [
        (["train", "density", "--data", "{tmp}/nothing"], "not a density data directory"),
        (["validate", "density", "--density", "{tmp}/missing.pt"], "not found"),
        (["data", "density", "--references", "0"], "references must be a positive integer"),
        (["train", "density", "--data", "{tmp}", "--set", "epochz=3"], "unknown key"),
    ],
)
def test_cli_errors_are_one_line(tmp_path, capsys, argv, message):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    rc = main([*argv, "--out", str(tmp_path / "o")])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1

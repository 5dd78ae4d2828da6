"""``train controller`` and ``validate controller`` end to end on tiny settings."""

from __future__ import annotations

import json

import pytest

from density_planner.cli import main
from density_planner.control.c3m import load_c3m_model

TINY = ["--set", "epochs=1", "--set", "steps_per_epoch=3", "--set", "batch_size=64", "--set", "eval_samples=100",
        "--set", "architecture.hidden=8", "--set", "architecture.metric_hidden=8", "--set", "architecture.rank=2",
        "--check-samples", "300", "--check-references", "4", "--quiet"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    out = tmp_path_factory.mktemp("train")
    assert main(["train", "controller", "--out", str(out), "--export", str(out / "export" / "c.pt"), *TINY]) == 0
    return out


def test_train_controller_writes_weights_with_diagnostics(trained):
    model, meta = load_c3m_model(trained / "controller_c3m.pt")
    assert meta["command"].startswith(f"density-planner train controller --out {trained}")
    assert "--set epochs=1" in meta["command"]
    d = meta["diagnostics"]
    assert set(d["tracking"]) == {"c3m", "analytic"} and d["tracking"]["c3m"]["unbiased"]["t"] == [0, 1, 5, 10]
    assert "frac_holds" in d["contraction"] and "met" in d["targets"]["frac_holds_v_ge_0.5"]
    assert (trained / "export" / "c.pt").is_file() and (trained / "export" / "c.json").is_file()
    assert json.loads((trained / "export" / "c.json").read_text())["diagnostics"] == d


def test_validate_controller_writes_report_and_figures(trained, tmp_path, capsys):
    out = tmp_path / "val"
    rc = main(["validate", "controller", "--controller", str(trained / "controller_c3m.pt"), "--samples", "400",
               "--references", "5", "--out", str(out)])
    assert rc == 0
    report = json.loads((out / "controller_report.json").read_text())
    assert report["contraction"]["n_samples"] == 400
    for name in ("c3m", "analytic"):
        for variant in ("unbiased", "biased"):
            s = report["tracking"][name][variant]
            assert len(s["median"]) == 4 and len(s["p95"]) == 4
    # identical initial errors for both controllers: equal errors at t = 0
    assert report["tracking"]["c3m"]["biased"]["median"][0] == report["tracking"]["analytic"]["biased"]["median"][0]
    for png in ("error_decay.png", "trajectories.png", "eigenvalues.png"):
        assert (out / png).stat().st_size > 10_000
    assert "wrote" in capsys.readouterr().out


def test_validate_analytic_controller(tmp_path):
    assert main(["validate", "controller", "--controller", "analytic", "--references", "3", "--out",
                 str(tmp_path)]) == 0
    report = json.loads((tmp_path / "controller_report.json").read_text())
    assert report["contraction"] is None and set(report["tracking"]) == {"analytic"}
    assert not (tmp_path / "eigenvalues.png").exists()


@pytest.mark.parametrize(
    "args,match",
    [
        (["validate", "controller", "--controller", "nope.pt"], "weights file not found"),
        (["validate", "controller", "--samples", "0"], "--samples and --references must be >= 1"),
        (["train", "controller", "--epochs", "0"], "--epochs must be >= 1"),
        (["train", "controller", "--set", "lr=-1"], "lr must be > 0"),
        (["train", "controller", "--set", "nonsense=1"], "unknown key"),
    ],
)
def test_cli_errors_are_one_line(tmp_path, capsys, args, match):
    rc = main([*args, "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and match in err and err.count("\n") == 1

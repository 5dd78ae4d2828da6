"""``density-planner bench`` and ``density-planner report``: a tiny sweep end to end, and one-line errors."""

from __future__ import annotations

import builtins

import pytest
from eval_testdata import TINY_DP

from density_planner.cli import main

TINY = [f"--set=density_planner.{k}={v}" for k, v in TINY_DP.items()] + ["--set=evaluation.mc_samples_tracked=4"]


def _bench(tmp_path, *extra):
    return main(["bench", "artificial", "--envs", "1", "--planners", "density", "--workers", "1", "-q",
                 "--plot-envs", "1", *TINY, *extra, "--out", str(tmp_path)])


@pytest.mark.slow
def test_bench_then_report_regenerates_the_same_tables(tmp_path, capsys):
    assert _bench(tmp_path) == 0
    out = capsys.readouterr().out
    assert "bench artificial: 2 runs (0 already done, 2 written" in out
    summary = (tmp_path / "summary.md").read_text()
    csv_text = (tmp_path / "summary.csv").read_text()
    assert "| DP |" in summary and "| DP-b |" in summary
    assert csv_text.splitlines()[0].startswith("setting,method,planner,variant,runs")
    figures = sorted(p.name for p in (tmp_path / "figures").glob("*.png"))
    assert "artificial_summary.png" in figures and "plans_artificial_random-0.png" in figures
    assert {f"artificial_{m}.png" for m in ("failure_rate", "cri", "gci", "ici", "offline_time", "online_time")} <= set(
        figures)
    for name in ("summary.md", "summary.csv"):
        (tmp_path / name).unlink()
    assert main(["report", str(tmp_path)]) == 0
    assert (tmp_path / "summary.md").read_text() == summary
    assert (tmp_path / "summary.csv").read_text() == csv_text
    # resuming a finished sweep does nothing
    assert _bench(tmp_path) == 0
    assert "2 already done, 0 written" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--planners", "density,teleport"], "unknown planner 'teleport'"),
        (["--seeds", "5:2"], "--seeds must be A:B with 0 <= A < B"),
        (["--seeds", "x"], "--seeds must be A:B"),
        (["--seeds", "0:2", "--envs", "2"], "either --envs N or --seeds A:B"),
        (["--envs", "0"], "--envs must be >= 1"),
        (["--variants", "sideways"], "unknown variant 'sideways'"),
        (["--data-dir", "."], "only used by the real setting"),
        (["--workers", "0"], "--workers must be >= 1"),
        (["--set", "evaluation.mc_samples_tracked=-1"], "mc_samples_tracked"),
        (["--controller", "nonsense"], "unknown controller"),
        (["--planners", "density,density"], "lists an entry twice"),
    ],
)
def test_bench_errors(tmp_path, capsys, args, message):
    assert main(["bench", "artificial", *args, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("density-planner: error:") and message in err and len(err.strip().splitlines()) == 1


def test_missing_data_dir(tmp_path, capsys):
    assert main(["bench", "real", "--data-dir", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_scheduler_without_dask(tmp_path, capsys, monkeypatch):
    real_import = builtins.__import__

    def no_dask(name, *args, **kwargs):
        if name == "distributed" or name.startswith("distributed."):
            raise ImportError("no distributed here")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_dask)
    assert main(["bench", "artificial", "--scheduler", "tcp://127.0.0.1:1", "--out", str(tmp_path / "o")]) == 2
    assert "pip install 'density-planner[dask]'" in capsys.readouterr().err


def test_report_errors(tmp_path, capsys):
    assert main(["report", str(tmp_path / "nowhere")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["report", str(tmp_path)]) == 2
    assert "no benchmark records" in capsys.readouterr().err


@pytest.mark.parametrize("system,expected", [("car", ("unbiased", "biased")), ("ks", ("unbiased",))])
def test_biased_variant_only_for_systems_with_a_hidden_state(system, expected):
    """The biased variant draws the car's hidden heading bias; a system without hidden states (ks) would only
    repeat the unbiased runs, so its sweeps leave it out unless --variants names it."""
    from density_planner.cli import build_parser
    from density_planner.cli._common import apply_system_args
    from density_planner.cli.bench import spec_from_args
    from density_planner.config import load_config
    from density_planner.settings import RunConfig

    args = build_parser().parse_args(["bench", "artificial", "--envs", "1", "--system", system, "--out", "unused"])
    spec = spec_from_args(args, apply_system_args(args, load_config(RunConfig)))
    assert spec.variants == expected

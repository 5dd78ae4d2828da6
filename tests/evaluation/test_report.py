"""Tables and figures from records alone."""

from __future__ import annotations

import csv
import math

from eval_testdata import record

from density_planner.evaluation.report import method_label, summary_markdown, summary_rows, write_tables
from density_planner.io.atomic import atomic_write_json


def _records():
    recs = [
        record("random-0", "density", "unbiased", collision=2.0, goal=0.25, inputs=10.0, offline=100.0, online=1e-3,
               mc=0.1),
        record("random-0", "density", "biased", collision=1.0, goal=1.0, inputs=10.0, offline=100.0, online=1e-3),
        record("random-0", "mpc", "unbiased", failed=True, reason="goal"),
        record("random-0", "oracle", "unbiased", collision=0.5, goal=0.0, inputs=30.0, offline=900.0, online=0.0),
        record("random-1", "density", "unbiased", failed=True, reason="collision"),
        record("random-1", "mpc", "unbiased", collision=0.0, goal=4.0, inputs=50.0, offline=0.0, online=0.08),
    ]
    for r in recs:
        r["env_spec"] = {"index": int(r["env"].split("-")[1])}
    return recs


def test_rows_are_in_the_paper_order_with_labels():
    rows = summary_rows(_records())
    assert [r["method"] for r in rows] == ["DP", "DP-b", "M0", "O"]
    dp, dpb, m0, o = rows
    assert dp["failure_rate"] == 0.5 and dp["runs"] == 2 and dp["failure_reasons"] == "collision 1"
    assert dp["cri"] == 1.5 and dp["gci"] == 0.25  # env 0: best valid collision 0.5 (oracle), goal 0 (oracle)
    assert o["cri"] == 0.0 and o["ici"] == 20.0  # inputs 30 vs 10 (density) in env 0
    assert m0["gci"] == 0.0 and m0["online_time"] == 0.08  # env 1: M0 is the only valid method
    assert dp["offline_time"] == 100.0  # the failed run of env 1 is not in the mean
    assert math.isnan(dpb["mc_collision_frequency"]) and dp["mc_collision_frequency"] == 0.1
    assert method_label("tube_mpc_0.5", "biased") == "M2-b" and method_label("custom", "unbiased") == "custom"


def test_markdown_table():
    text = summary_markdown(summary_rows(_records()), _records())
    assert "## artificial" in text and "2 environments" in text
    line = next(ln for ln in text.splitlines() if ln.startswith("| DP |"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[1:4] == ["2", "50 %", "1.5"]
    assert cells[8] == "1"  # online time 1 ms
    assert "| O |" in text and "–" in next(ln for ln in text.splitlines() if ln.startswith("| DP-b |"))


def test_write_tables_from_record_files(tmp_path):
    for r in _records():
        atomic_write_json(tmp_path / "records" / "artificial" / f"{r['env']}__{r['planner']}__{r['variant']}.json", r)
    records, rows, paths = write_tables(tmp_path)
    assert len(records) == 6 and len(rows) == 4
    with open(tmp_path / "summary.csv") as fh:
        table = list(csv.DictReader(fh))
    assert [t["method"] for t in table] == ["DP", "DP-b", "M0", "O"]
    assert table[0]["failure_rate"] == "0.5" and table[1]["mc_collision_frequency"] == ""


def test_bar_chart_and_trajectory_figures(tmp_path):
    import numpy as np

    from density_planner.viz.benchmark import plot_env_trajectories, plot_metric_bars

    rows = summary_rows(_records())
    for metric in ("failure_rate", "online_time"):
        path = plot_metric_bars(rows, metric, tmp_path / f"{metric}.png")
        assert path.stat().st_size > 1000
    states = np.stack([np.zeros(11), np.linspace(0, 10, 11)], axis=1)
    smap = {"occupancy_u8": np.zeros((20, 30), dtype=np.uint8), "origin": np.array([-1.0, -1.0]),
            "cell_size": np.float64(0.5), "start": np.array([0.0, 0.0, 1.5, 1.0, 0.0]), "goal": np.array([0.0, 10.0]),
            "planning_box": np.array([-1.0, 8.0, -1.0, 13.0])}
    path = plot_env_trajectories(smap, {"DP": ("density", False, states), "DP-b": ("density", True, states + 0.5)},
                                 tmp_path / "plans.png", references={"DP reference": states})
    assert path.stat().st_size > 1000

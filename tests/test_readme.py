"""The README's Python example runs as written (with the shipped weights) and prints what it says."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks, "README has no python example"
    threads = torch.get_num_threads()
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            exec(compile(blocks[0], str(README), "exec"), {"__name__": "readme_example"})
    finally:
        torch.set_num_threads(threads)
    lines = out.getvalue().splitlines()
    assert lines[0] == "torch.Size([500, 101, 5]) torch.Size([500, 101])"
    assert lines[1].startswith("PlanStatus.SUCCESS")
    assert lines[2].split()[0] in ("success", "failed")  # the verdict
    float(lines[3].split("(")[1].split(")")[0])  # the standard error of the collision probability
    float(lines[4].split("(")[1].split(")")[0])  # the occupancy seen by the body


def test_readme_commonroad_api_example_runs(tmp_path, monkeypatch):
    """The second Python example (a CommonRoad scenario through ``density_planner.api``) runs as written, from the
    repository root, and writes the files it names."""
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert len(blocks) >= 2 and "plan_scene" in blocks[1]
    (tmp_path / "src").symlink_to(README.parent / "src")
    monkeypatch.chdir(tmp_path)
    threads = torch.get_num_threads()
    out = io.StringIO()
    try:
        torch.set_num_threads(1)
        with contextlib.redirect_stdout(out):
            exec(compile(blocks[1], str(README), "exec"), {"__name__": "readme_example"})
    finally:
        torch.set_num_threads(threads)
    status = out.getvalue().split()[0]
    assert status in ("success", "failed")
    written = {p.name for p in (tmp_path / "results" / "api-lanker").iterdir()}
    assert written == {"plan.json", "config.toml", "solution.xml", "plan.png", "costs.png"}

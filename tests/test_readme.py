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

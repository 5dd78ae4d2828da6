"""Progress bars only on a terminal: ``--progress/--no-progress``, default from stderr."""

from __future__ import annotations

import argparse
import io
import sys

import pytest

from density_planner.cli._common import add_progress, show_progress


class _Stream(io.StringIO):
    def __init__(self, tty: bool):
        super().__init__()
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


def _parse(*argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_progress(p)
    return p.parse_args(list(argv))


@pytest.mark.parametrize(("tty", "argv", "expected"), [
    (True, (), True), (False, (), False),  # default: only on a terminal
    (False, ("--progress",), True), (True, ("--no-progress",), False), (True, ("-q",), False),
    (True, ("--progress", "-q"), False),
])
def test_progress_switch(monkeypatch, tty, argv, expected):
    monkeypatch.setattr(sys, "stderr", _Stream(tty))
    assert show_progress(_parse(*argv)) is expected


def test_every_long_command_has_the_switch():
    from density_planner.cli import build_parser

    parser = build_parser()
    for argv in (["plan", "--env", "random", "--out", "x"], ["bench", "artificial", "--out", "x"],
                 ["train", "controller", "--out", "x"], ["data", "density", "--out", "x"],
                 ["train", "density", "--data", "d", "--out", "x"], ["drive", "--env", "random", "--out", "x"],
                 ["bench", "commonroad", "--scenarios", "d", "--out", "x"],
                 ["validate", "risk", "--env", "random", "--out", "x"]):
        assert parser.parse_args([*argv, "--no-progress"]).progress is False

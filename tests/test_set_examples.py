"""Every ``--set KEY=VALUE`` example in the help texts, the README and the docs applies to the configuration of
the command it is given to; the help of ``data density`` states the dataclass's defaults."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from density_planner.cli import build_parser
from density_planner.config import load_config

REPO = Path(__file__).resolve().parents[1]
SET = re.compile(r"--set[ =]([a-z_][\w.]*)=([^\s`\"')]+)")  # KEY=VALUE (the metavar) is no example
COMMAND = re.compile(r"density-planner\s+(train|data|validate)?\s*(\w+)")


def _config_classes() -> dict[str, type]:
    from density_planner.control.c3m_training import C3MTrainConfig
    from density_planner.density.data import DensityDataConfig
    from density_planner.density.train import DensityTrainConfig
    from density_planner.settings import RunConfig

    return {"train density": DensityTrainConfig, "data density": DensityDataConfig,
            "train controller": C3MTrainConfig, "run": RunConfig}


def _command_of(line: str) -> str:
    m = COMMAND.search(line)
    if m and m.group(1):
        return f"{m.group(1)} {m.group(2)}"
    return "run"  # plan, bench, env and prose: the run configuration


def _help_texts() -> list[tuple[str, str]]:
    """(command, help text) of every sub-command of the CLI."""
    out = []

    def walk(parser: argparse.ArgumentParser, name: str) -> None:
        out.append((name, parser.format_help()))
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub_name, sub in action.choices.items():
                    walk(sub, f"{name} {sub_name}".strip())

    walk(build_parser(), "")
    return out


def _examples() -> list[tuple[str, str, str]]:
    """(where, config kind, 'key=value') of every example."""
    found = []
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        lines = path.read_text().splitlines()
        for i, line in enumerate(lines, 1):
            j = i - 1  # a shell command continued with a backslash: the command is on an earlier line
            while j > 0 and lines[j - 1].rstrip().endswith("\\"):
                j -= 1
                line = lines[j] + " " + line
            for key, value in SET.findall(lines[i - 1]):
                if key == "key" or key.endswith("section.key") or not value.strip(".,;") or value.isupper():
                    continue  # the syntax's placeholders (key=value, KEY=..., KEY=N)
                found.append((f"{path.name}:{i}", _command_of(line), f"{key}={value.rstrip('.,;')}"))
    for command, text in _help_texts():
        kind = command if command in ("train density", "data density", "train controller") else "run"
        for key, value in SET.findall(" ".join(text.split())):
            found.append((f"help of `{command}`", kind, f"{key}={value.rstrip('.,;')}"))
    return found


EXAMPLES = _examples()


def test_examples_were_found():
    where = {w.split(":")[0] for w, _, _ in EXAMPLES}
    assert {"README.md", "environments.md", "help of `plan`", "help of `env`"} <= where


@pytest.mark.parametrize(("where", "kind", "item"), EXAMPLES, ids=[f"{w}:{i}" for w, _, i in EXAMPLES])
def test_set_example_parses(where, kind, item):
    load_config(_config_classes()[kind], None, [item])


def test_data_density_help_states_the_dataclass_defaults():
    from density_planner.density.data import DensityDataConfig

    cfg = DensityDataConfig()
    text = " ".join(dict(_help_texts())["data density"].split())
    assert f"number of references (default {cfg.references})" in text
    assert f"initial errors per reference (default {cfg.samples})" in text
    assert f"(default {cfg.controller})" in text

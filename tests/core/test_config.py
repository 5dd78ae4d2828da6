"""Typed configuration: TOML loading, overrides, unknown keys, round trip."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from density_planner.config import apply_overrides, dumps_toml, from_dict, load_config, to_dict, update
from density_planner.errors import ConfigError


@dataclass(frozen=True)
class Inner:
    lr: float = 0.01
    steps: int = 10
    mode: Literal["a", "b"] = "a"

    def __post_init__(self):
        if self.lr <= 0:
            raise ValueError("lr must be > 0")


@dataclass(frozen=True)
class Outer:
    name: str = "x"
    box: tuple[float, float] = (0.0, 1.0)
    inner: Inner = field(default_factory=Inner)
    flag: bool = False


def test_from_dict_nested_and_coercion():
    cfg = from_dict(Outer, {"box": [1, 2], "inner": {"lr": 1, "mode": "b"}})
    assert cfg.box == (1.0, 2.0) and isinstance(cfg.box[0], float)
    assert cfg.inner == Inner(lr=1.0, steps=10, mode="b")


def test_unknown_key_lists_valid_keys():
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['lrr'\].*valid keys: \['lr', 'mode', 'steps'\]"):
        from_dict(Outer, {"inner": {"lrr": 1}})


@pytest.mark.parametrize(
    "data,match",
    [
        ({"inner": {"steps": 1.5}}, "integer"),
        ({"inner": {"mode": "c"}}, "not one of"),
        ({"flag": 1}, "true or false"),
        ({"box": [1.0]}, "expected 2 values"),
        ({"inner": {"lr": -1.0}}, "lr must be > 0"),
        ({"name": 3}, "string"),
    ],
)
def test_bad_values(data, match):
    with pytest.raises(ConfigError, match=match):
        from_dict(Outer, data)


def test_overrides_and_update():
    cfg = apply_overrides(Outer(), ["inner.lr=0.5", "inner.mode=b", "flag=true", "box=[3, 4]"])
    assert cfg.inner.lr == 0.5 and cfg.inner.mode == "b" and cfg.flag and cfg.box == (3.0, 4.0)
    assert update(cfg, {"inner": {"steps": 3}}).inner == Inner(0.5, 3, "b")
    with pytest.raises(ConfigError, match="key=value"):
        apply_overrides(Outer(), ["inner.lr"])


def test_toml_round_trip(tmp_path):
    cfg = Outer(name='q"uote', box=(0.5, -1.0), inner=Inner(0.2, 7, "b"), flag=True)
    path = tmp_path / "c.toml"
    path.write_text(dumps_toml(cfg))
    assert load_config(Outer, path) == cfg
    assert to_dict(cfg)["inner"] == {"lr": 0.2, "steps": 7, "mode": "b"}


def test_missing_and_invalid_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(Outer, tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("x = = 1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(Outer, bad)


def test_the_paper_preset_restores_the_papers_setting(tmp_path, monkeypatch):
    from density_planner.config import presets
    from density_planner.settings import RunConfig

    assert "paper" in presets()
    monkeypatch.chdir(tmp_path)  # a bare name, not a file here
    cfg = load_config(RunConfig, "paper", ["density_planner.seed=3"])
    assert (cfg.risk.estimator, cfg.risk.body) == ("paper", False)
    dp = cfg.density_planner
    assert (dp.weighting, dp.n_samples, dp.epochs_density, dp.seed) == ("density", 500, 100, 3)
    # everything else keeps its default
    assert dp.n_candidates == RunConfig().density_planner.n_candidates
    # a local file of that name wins over the preset; an unknown name lists the presets
    (tmp_path / "paper").write_text('[density_planner]\nn_samples = 7\n')
    assert load_config(RunConfig, "paper").density_planner.n_samples == 7
    with pytest.raises(ConfigError, match="shipped preset: .*paper"):
        load_config(RunConfig, "papr")

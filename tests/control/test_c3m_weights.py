"""Weights files: save/load round trip, clear errors for bad files, the shipped controller, the registry."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from density_planner.control.analytic import CarTrackingController
from density_planner.control.c3m import (
    C3MArchitecture,
    C3MController,
    C3MModel,
    load_c3m_controller,
    load_c3m_model,
    save_c3m_model,
    shipped_c3m_path,
)
from density_planner.control.c3m_training import contraction_diagnostics
from density_planner.control.registry import CONTROLLER_CHOICES, DEFAULT_CONTROLLER, load_controller
from density_planner.control.sampling import sample_tracking_states
from density_planner.errors import CheckpointError
from density_planner.io.checkpoint import load_weights, save_weights, weights_paths

SMALL = C3MArchitecture(hidden=16, metric_hidden=8, rank=3)


@pytest.fixture
def saved(tmp_path):
    torch.manual_seed(3)
    model = C3MModel(SMALL)
    pt, js = save_c3m_model(tmp_path / "ctrl", model, config={"seed": 3}, diagnostics={"x": 1.0}, command="cmd")
    return model, pt, js


def test_round_trip_gives_identical_outputs(saved):
    model, pt, js = saved
    assert pt.name == "ctrl.pt" and js.name == "ctrl.json"
    loaded, meta = load_c3m_model(pt)
    s = sample_tracking_states(200, torch.Generator().manual_seed(0))
    u_loaded = loaded.controller(s.x_hat, s.x_ref, s.u_ref)
    torch.testing.assert_close(u_loaded, model.controller(s.x_hat, s.x_ref, s.u_ref), rtol=0, atol=0)
    torch.testing.assert_close(loaded.metric(s.x), model.metric(s.x), rtol=0, atol=0)
    assert meta["kind"] == "c3m_car_controller" and meta["architecture"]["hidden"] == 16
    assert meta["training_config"] == {"seed": 3} and meta["command"] == "cmd" and meta["diagnostics"] == {"x": 1.0}
    for key in ("package_version", "torch_version", "schema_version"):
        assert key in meta
    # the same file through the registry, by path with or without suffix
    for spec in (pt, str(pt), str(pt.with_suffix(""))):
        assert isinstance(load_controller(spec), C3MController)


def test_weights_file_is_a_plain_state_dict(saved):
    _, pt, _ = saved
    state = torch.load(pt, weights_only=True)
    assert isinstance(state, dict) and all(isinstance(v, torch.Tensor) for v in state.values())
    assert "controller.w1.layers.0.weight" in state and "metric.l_pp" in state


def test_missing_files(tmp_path, saved):
    _, pt, js = saved
    with pytest.raises(CheckpointError, match="weights file not found: .*nothing.pt"):
        load_c3m_model(tmp_path / "nothing.pt")
    js.unlink()
    with pytest.raises(CheckpointError, match="metadata file not found: .*ctrl.json"):
        load_c3m_model(pt)


def test_corrupt_files(saved):
    _, pt, js = saved
    good = pt.read_bytes()
    pt.write_bytes(good[: len(good) // 2])
    with pytest.raises(CheckpointError, match="ctrl.pt is corrupt"):
        load_c3m_model(pt)
    pt.write_bytes(b"not a torch file at all")
    with pytest.raises(CheckpointError, match="corrupt"):
        load_c3m_model(pt)
    pt.write_bytes(good)
    js.write_text("{broken")
    with pytest.raises(CheckpointError, match="ctrl.json is not valid JSON"):
        load_c3m_model(pt)


def test_wrong_kind_and_schema(saved):
    _, pt, js = saved
    meta = json.loads(js.read_text())
    js.write_text(json.dumps({**meta, "kind": "density_mlp"}))
    with pytest.raises(CheckpointError, match="of kind 'density_mlp', expected 'c3m_car_controller'"):
        load_c3m_model(pt)
    js.write_text(json.dumps({**meta, "schema_version": 99}))
    with pytest.raises(CheckpointError, match="schema_version 99"):
        load_c3m_model(pt)


def test_architecture_mismatch_names_the_field(saved):
    _, pt, _ = saved
    expected = {**SMALL.to_dict(), "hidden": 32}
    with pytest.raises(CheckpointError, match="architecture mismatch: 'hidden': file has 16, expected 32"):
        load_weights(pt, kind="c3m_car_controller", expected_architecture=expected)


def test_state_dict_mismatch(saved, tmp_path):
    model, pt, js = saved
    # JSON says rank 3, tensors say rank 4: the shapes do not match what the JSON describes
    other = C3MModel(C3MArchitecture(hidden=16, metric_hidden=8, rank=4))
    torch.save(other.state_dict(), pt)
    with pytest.raises(CheckpointError, match="parameter 'controller.w1.layers.2.weight' has shape"):
        load_c3m_model(pt)
    state = model.state_dict()
    state.pop("metric.l_pp")
    torch.save(state, pt)
    with pytest.raises(CheckpointError, match=r"missing keys \['metric.l_pp'\]"):
        load_c3m_model(pt)
    torch.save([1, 2, 3], pt)
    with pytest.raises(CheckpointError, match="does not hold a state_dict"):
        load_c3m_model(pt)


def test_invalid_architecture_in_json(saved):
    _, pt, js = saved
    meta = json.loads(js.read_text())
    meta["architecture"]["rank"] = -1
    js.write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="invalid architecture"):
        load_c3m_model(pt)


def test_generic_save_weights_paths(tmp_path):
    pt, js = save_weights(tmp_path / "a" / "m.json", {"w": torch.ones(2)}, kind="k", architecture={"n": 2})
    assert (pt, js) == weights_paths(tmp_path / "a" / "m") and pt.is_file() and js.is_file()
    state, meta = load_weights(pt, kind="k", expected_architecture={"n": 2})
    assert torch.equal(state["w"], torch.ones(2)) and meta["n_parameters"] == 2
    with pytest.raises(ValueError, match="kind must be a non-empty string"):
        save_weights(tmp_path / "b", {}, kind="", architecture={})


# ------------------------------------------------------------------------------------------------ shipped weights
def test_shipped_weights_load_and_satisfy_the_condition():
    path = shipped_c3m_path()
    assert path.is_file() and path.with_suffix(".json").is_file()
    model, meta = load_c3m_model()
    assert meta["command"].startswith("density-planner train controller")
    reported = meta["diagnostics"]["contraction"]
    rate = meta["training_config"]["rate"]
    d = contraction_diagnostics(model, n=4000, rate=rate, seed=777, return_samples=True)
    # overall fraction (~0.94, limited by the infeasible low-speed band): binomial standard error with 4000
    # samples is 0.004, so 5 standard errors (0.02) around the fraction reported on 1e5 samples
    assert abs(d["frac_holds"] - reported["frac_holds"]) < 0.02
    # where the car moves (v >= 0.5 m/s, ~94 % of the samples) the condition holds on > 99 % of 1e5 samples;
    # standard error with ~3800 samples is 0.0014, so 0.98 is more than 5 standard errors below
    v = d["_samples"]["v"]
    holds = d["_samples"]["lambda_max"] < 0
    assert float(holds[v >= 0.5].float().mean()) >= 0.98
    assert reported["frac_holds_v_ge_0.5"] >= 0.99
    assert d["c2_max_frobenius"] < 1e-5  # zero by construction (float32 rounding)


def test_registry_defaults_to_shipped_c3m():
    assert DEFAULT_CONTROLLER == "c3m" and set(CONTROLLER_CHOICES) == {"c3m", "analytic"}
    assert isinstance(load_controller(), C3MController)
    assert isinstance(load_controller("c3m"), C3MController)
    assert isinstance(load_controller("analytic"), CarTrackingController)
    assert isinstance(load_c3m_controller(), C3MController)
    with pytest.raises(ValueError, match="unknown controller 'pid' for the system 'car'; valid choices: c3m, analytic"):
        load_controller("pid")
    with pytest.raises(CheckpointError, match="weights file not found"):
        load_controller("missing_controller.pt")


def test_copied_shipped_weights_load_from_anywhere(tmp_path):
    src = shipped_c3m_path()
    shutil.copy(src, tmp_path / "c.pt")
    shutil.copy(src.with_suffix(".json"), tmp_path / "c.json")
    assert isinstance(load_controller(tmp_path / "c.pt"), C3MController)

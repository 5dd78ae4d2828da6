"""Learned density predictors for any registered system: the state layout comes from the system (the car's features
and shipped networks unchanged, the kinematic single-track model's own), data / training / validation / the
shipped KS predictor end to end."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from density_planner.control.reference import make_reference
from density_planner.control.registry import load_controller, model_set
from density_planner.density.data import DensityDataConfig, _config_key, generate_density_data, load_density_data
from density_planner.density.liouville import ExactLiouville, LiouvilleConfig, propagate_density
from density_planner.density.network import (
    DensityLayout,
    DensityNetArchitecture,
    DensityNetwork,
    LearnedDensity,
    errors_to_outputs,
    load_density_model,
    outputs_to_errors,
    reference_features,
    sample_features,
    shipped_density_path,
    system_layout,
)
from density_planner.density.registry import load_learned_predictor, load_predictor
from density_planner.density.train import DensityTrainConfig, fit_normalisation, normalised_targets, train_density
from density_planner.density.validation import compare_with_exact, fresh_references
from density_planner.errors import CheckpointError
from density_planner.systems.car import KinematicCar, car_domain
from density_planner.systems.ks import DELTA, PSI, KinematicSingleTrack, V

SNAPSHOT = Path(__file__).parent / "data" / "shipped_car_predictions.pt"

#: a few KS references x samples, analytic controller (about a second)
KS_TINY = DensityDataConfig(references=8, samples=6, references_per_shard=2, validation_fraction=0.25, seed=3,
                            domain="ks")


# --------------------------------------------------------------------------------------------------- layouts
def test_layouts_come_from_the_systems():
    car, ks = system_layout("car"), system_layout("ks")
    assert car == DensityLayout.of(KinematicCar()) and ks == DensityLayout.of(KinematicSingleTrack())
    # the car: (px, py, theta, v, bias): heading 2, bias hidden; the paper's features and outputs
    assert (car.heading, car.hidden, car.speed) == (2, (4,), 3)
    assert car.learned == (2, 3) and car.reference_states == (3,) and car.n_out == 5 and car.n_reference_start == 3
    # KS: (px, py, delta, v, psi): heading 4, nothing hidden; steering angle and speed are reference features
    assert (ks.heading, ks.hidden, ks.speed) == (PSI, (), V)
    assert ks.learned == (DELTA, V, PSI) and ks.reference_states == (DELTA, V)
    assert ks.n_out == 6 and ks.n_reference_start == 4
    a = DensityNetArchitecture(system="ks")
    assert a.n_features == 5 + 4 + 2 * 10 and DensityNetwork(a).base_weight.shape == (101, 29, 6)
    assert DensityNetArchitecture().system == "car" and DensityNetArchitecture().n_features == 5 + 3 + 20
    with pytest.raises(ValueError, match="unknown system"):
        DensityNetArchitecture(system="boat")


def test_ks_features_rotate_with_the_yaw_angle_not_the_steering_angle():
    ks = system_layout("ks")
    start = torch.tensor([3.0, -2.0, 0.3, 7.0, math.pi / 2], dtype=torch.float64)
    xe0 = torch.tensor([0.4, -0.7, 0.02, 0.1, 0.05], dtype=torch.float64)
    s = sample_features(xe0, start, ks)
    # heading pi/2: longitudinal = world y, lateral = -world x; the other components in state order
    torch.testing.assert_close(s, torch.tensor([-0.7, -0.4, 0.02, 0.1, 0.05], dtype=torch.float64))
    params = torch.arange(20, dtype=torch.float64).reshape(2, 10)
    r = reference_features(start, params, ks)
    torch.testing.assert_close(r[:4], torch.tensor([0.0, 1.0, 0.3, 7.0], dtype=torch.float64), atol=1e-12,
                               rtol=0)
    torch.testing.assert_close(r[4:], params.flatten())
    # outputs: (e_long, e_lat, e_delta, e_v, e_psi, L), and back
    g = torch.Generator().manual_seed(0)
    xe = torch.randn(3, 101, 5, generator=g, dtype=torch.float64)
    lr = torch.randn(3, 101, generator=g, dtype=torch.float64)
    head = torch.randn(3, 101, generator=g, dtype=torch.float64)
    y = errors_to_outputs(xe, lr, head, ks)
    assert y.shape == (3, 101, 6)
    torch.testing.assert_close(y[..., 2:5], xe[..., 2:])
    back, lr2 = outputs_to_errors(y, xe[:, 0], head, ks)
    torch.testing.assert_close(back, xe)
    torch.testing.assert_close(lr2, lr)


def _ks_reference(batch=(2,), seed=0):
    g = torch.Generator().manual_seed(seed)
    system = KinematicSingleTrack()
    start = torch.tensor([5.0, -3.0, 0.05, 12.0, 2.5]).expand(*batch, 5)
    params = (torch.rand(*batch, 2, 10, generator=g) * 2 - 1) * torch.tensor([[0.1], [1.5]])
    ref = make_reference(system, start, params)
    x0 = ref.start.unsqueeze(-2) + (torch.rand(*batch, 7, 5, generator=g) - 0.5) * torch.tensor(
        [1.0, 1.0, 0.05, 0.5, 0.2])
    return system, ref, x0


@pytest.mark.parametrize("arch", ("trajectory", "pointwise"))
def test_ks_network_interface_exact_start_and_gradients(arch):
    torch.manual_seed(0)
    net = DensityNetwork(DensityNetArchitecture(arch=arch, hidden=16, layers=2, activation="tanh", system="ks"))
    with torch.no_grad():
        net.last.weight.normal_(0, 0.3)
        net.base_weight.normal_(0, 0.05)
    pred = LearnedDensity(net)
    system, ref, x0 = _ks_reference()
    lr0 = torch.randn(x0.shape[:-1])
    out = pred.predict(x0, lr0, ref)
    assert out.x.shape == (2, 7, 101, 5) and out.log_rho.shape == (2, 7, 101)
    torch.testing.assert_close(out.x[..., 0, :], x0)  # t = 0 is exact
    torch.testing.assert_close(out.log_rho[..., 0], lr0)
    assert bool(torch.isfinite(out.x).all()) and float(out.x[..., 1:, 2:].std()) > 0  # every state is learned
    # predict_at at the grid points equals the grid prediction
    t = torch.tensor([0.0, 2.0, 10.0])
    xa, la = net.predict_at(x0 - ref.start.unsqueeze(-2), ref.start, ref.params, t, ref.x_plan[..., [0, 20, 100], PSI])
    torch.testing.assert_close(xa, out.x[..., [0, 20, 100], :] - ref.x_plan[..., [0, 20, 100], :].unsqueeze(-3),
                               rtol=1e-4, atol=1e-4)
    # differentiable w.r.t. the reference parameters (the planner's second stage)
    params = ref.params.clone().requires_grad_(True)
    ref2 = make_reference(system, ref.start, params)
    pred.predict(x0, lr0, ref2).x[..., -1, :2].sum().backward()
    assert params.grad is not None and bool(torch.isfinite(params.grad).all()) and float(params.grad.abs().sum()) > 0


# ------------------------------------------------------------------------------------------ data / training
def test_ks_data_config_uses_the_systems_boxes():
    cfg = DensityDataConfig(domain="ks")
    ks = KinematicSingleTrack()
    assert cfg.controller == "analytic"
    assert cfg.start_low == tuple(ks.config.reference_start_min)
    assert cfg.start_high == tuple(ks.config.reference_start_max)
    assert cfg.param_scale == tuple(ks.config.reference_input_scale)
    # explicit values stay; a box of the wrong length is refused with the state names
    assert DensityDataConfig(domain="ks", param_scale=0.5).param_scale == 0.5
    with pytest.raises(ValueError, match="5 entries"):
        DensityDataConfig(domain="ks", start_low=(0.0, 0.0, 0.0, 1.0))
    # the car's sets are unchanged: their resume keys are those of the data written before other systems existed
    assert DensityDataConfig().start_low == (-12.0, -30.0, 0.0, 1.0, 0.0) and DensityDataConfig().param_scale == 2.0
    assert _config_key(DensityDataConfig()) == "03e6519196587f80"
    road = DensityDataConfig(domain="road", start_low=(-10, -10, -3.14159, 0.5, 0), start_high=(10, 10, 3.14159, 38, 0))
    # the road set is integrated with the error-controlled rk43 (its domain's scheme): other data, another key;
    # with RK4 named, the key of the fixed-step data written before (stop 55's coupled rule: 68cfce0803b3b2a0, stop
    # 56's saturation step of 1 tail width: 161842d135d777e6)
    assert _config_key(road) == "593e77e11ac2c50c"
    coupled = replace(road, liouville=LiouvilleConfig(log_density_rule="coupled"))
    assert _config_key(coupled) != _config_key(road)
    fixed = replace(road, liouville=LiouvilleConfig(integrator="rk4"))
    assert _config_key(fixed) == "b100456750eaab6a"


@pytest.fixture(scope="module")
def ks_tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("ks") / "data"
    generate_density_data(KS_TINY, out, workers=1)
    return out


def test_ks_data_are_exact_liouville_of_the_ks_closed_loop(ks_tiny):
    manifest = json.loads((ks_tiny / "manifest.json").read_text())
    assert manifest["complete"] and manifest["config"]["domain"] == "ks"
    train = load_density_data(ks_tiny, "train")
    assert train.system == "ks" and train.xe.shape == (6 * 6, 101, 5)
    # the stored heading is the yaw angle (state 4) of the reference, and the rows reproduce exact Liouville
    shard = torch.load(ks_tiny / "shard_00000.pt", weights_only=True)
    torch.testing.assert_close(train.x_ref_heading[0], shard["x_ref"][0, :, PSI])
    system = KinematicSingleTrack()
    ref = make_reference(system, shard["ref_start"], shard["params"])
    x0 = shard["ref_start"].unsqueeze(1) + shard["xe0"]
    traj = propagate_density(system, load_controller("analytic", models="ks"), x0, ref)
    torch.testing.assert_close(shard["xe"], traj.x - ref.x_plan.unsqueeze(-3), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(shard["log_ratio"], traj.log_rho - traj.log_rho0.unsqueeze(-1), rtol=1e-4, atol=1e-4)
    box = torch.tensor(system.initial_error_max) * KS_TINY.error_scale
    assert bool((shard["xe0"].abs() <= box).all())


def test_ks_training_smoke(ks_tiny, tmp_path):
    train, val = load_density_data(ks_tiny, "train"), load_density_data(ks_tiny, "val")
    net = DensityNetwork(DensityNetArchitecture(system="ks", hidden=16, layers=2))
    fit_normalisation(net, train)
    s, r, z = normalised_targets(net, train)
    assert s.shape == (36, 5) and r.shape == (36, 24) and z.shape == (36, 100, 6)
    y = net.baseline(s, r, net.base_weight[1:], net.base_bias[1:]) + net.out_scale[1:] * z
    torch.testing.assert_close(y, errors_to_outputs(train.xe, train.log_ratio, train.x_ref_heading,
                                                    net.layout)[:, 1:], rtol=1e-4, atol=1e-3)
    cfg = DensityTrainConfig(hidden=16, layers=2, epochs=3, batch_size=8, seed=0)
    result = train_density(cfg, train, val, tmp_path)
    a = result.model.architecture
    assert a.system == "ks" and result.epochs_run == 3
    assert all(math.isfinite(v) for v in result.history["val_loss"])
    assert result.history["train_loss"][-1] < result.history["train_loss"][0]
    # the trained network predicts KS states through LearnedDensity, close to exact Liouville at t = 0 ... 10 s
    system = KinematicSingleTrack()
    controller = load_controller("analytic", models="ks")
    ref, x0 = fresh_references(2, 4, seed=11, domain="ks")
    summary = compare_with_exact(LearnedDensity(result.model), ExactLiouville(system, controller), ref, x0).summary()
    assert summary["position_error_m"]["per_time"]["median"][0] == 0.0
    assert math.isfinite(summary["position_rmse_m"]) and summary["by_speed_band"]
    assert summary["error_state_mse_without_bias"] == pytest.approx(summary["error_state_mse"])  # nothing hidden


def test_training_refuses_mixed_systems(ks_tiny, tiny_data):
    with pytest.raises(ValueError, match="system"):
        train_density(DensityTrainConfig(hidden=8, layers=1, epochs=1), load_density_data(ks_tiny, "train"),
                      load_density_data(tiny_data, "val"))


# --------------------------------------------------------------------------------------- the car unchanged
@pytest.mark.parametrize("models", ("paper", "road"))
@pytest.mark.parametrize("arch", ("trajectory", "pointwise"))
def test_shipped_car_networks_predict_as_before(models, arch):
    """The car's shipped networks load (the paper files have no ``system`` entry in their JSON: the car) and
    predict what they predicted before the layout became the system's (outputs stored from that code; equal up to
    float32 rounding). The road entries were stored again whenever the road networks were re-trained (stops 36,
    49, 52, 60, 61, 62), with this test's own call: new weights need new outputs; the paper entries are still the
    pre-layout code's."""
    snap = torch.load(SNAPSHOT, weights_only=True)
    inputs, expected = snap[f"{models}/inputs"], snap[f"{models}/{arch}"]
    model, meta = load_density_model(shipped_density_path(arch, models))
    # the paper files predate the ``system`` entry (a file without one is the car's); the re-trained road files have it
    assert meta["architecture"].get("system", "car") == "car" and model.architecture.system == "car"
    if models == "paper":
        assert "system" not in meta["architecture"]
    ref = make_reference(KinematicCar(car_domain(models)), inputs["start"], inputs["params"])
    out = LearnedDensity(model, meta=meta).predict(inputs["x0"], torch.zeros(inputs["x0"].shape[:-1]), ref)
    torch.testing.assert_close(out.x, expected["x"], rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(out.log_rho, expected["log_rho"], rtol=1e-5, atol=1e-4)


# --------------------------------------------------------------------------------------- shipped KS predictor
def test_shipped_ks_predictor_is_the_default_and_close_to_exact():
    path = shipped_density_path("trajectory", "ks")
    if not path.is_file():
        pytest.fail(f"shipped weights missing: {path}")
    mset = model_set("ks")
    system = mset.make_system()
    controller = load_controller(None, models=mset)
    pred = load_predictor(None, system, controller, models="ks")
    assert isinstance(pred, LearnedDensity) and pred.name == "trajectory" and pred.layout == system_layout("ks")
    lo, hi = pred.speed_range
    assert lo <= 1.0 and hi >= 30.0
    meta = pred.meta
    assert meta["architecture"]["system"] == "ks" and meta["data"]["config"]["domain"] == "ks"
    assert meta["commands"]["data"].startswith("density-planner data density --system ks")
    assert path.stat().st_size < 4_000_000
    ref, x0 = fresh_references(4, 30, seed=424242, domain="ks")
    s = compare_with_exact(pred, ExactLiouville(system, controller), ref, x0).summary()
    pos, ld = s["position_error_m"]["overall"], s["log_density_abs_error"]["overall"]
    # a few times the errors of `validate density --models ks` (docs/systems.md): catches a broken file
    assert pos["median"] < 0.3 and pos["p95"] < 1.5, pos
    assert ld["median"] < 0.5 and ld["p95"] < 2.0, ld


def test_a_predictor_of_another_system_is_refused():
    ks = KinematicSingleTrack()
    ks_controller = load_controller(None, models="ks")
    with pytest.raises(CheckpointError, match="reads states of the system 'car'"):
        load_learned_predictor("trajectory", models="paper", system=ks)
    # with no name, a mismatching predictor falls back to exact Liouville
    assert isinstance(load_predictor(None, ks, ks_controller, models="paper"), ExactLiouville)


# ------------------------------------------------------------------------------------------------------- CLI
@pytest.mark.slow
def test_cli_data_train_validate_for_ks(tmp_path, capsys):
    from density_planner.cli import main

    data = tmp_path / "data"
    assert main(["data", "density", "--system", "ks", "--references", "8", "--samples", "3", "--set",
                 "references_per_shard=4", "--workers", "1", "--quiet", "--out", str(data)]) == 0
    manifest = json.loads((data / "manifest.json").read_text())
    assert manifest["config"]["domain"] == "ks" and manifest["config"]["controller"] == "analytic"
    assert manifest["command"].startswith("density-planner data density --system ks")
    out = tmp_path / "train"
    assert main(["train", "density", "--data", str(data), "--epochs", "1", "--set", "hidden=8", "--set", "layers=1",
                 "--threads", "1", "--quiet", "--out", str(out)]) == 0
    meta = json.loads((out / "density_trajectory.json").read_text())
    assert meta["architecture"]["system"] == "ks" and meta["controller"]["spec"] == "analytic"
    assert meta["commands"]["validate"].endswith("--models ks")
    val = tmp_path / "val"
    assert main(["validate", "density", "--system", "ks", "--density", str(out / "density_trajectory.pt"),
                 "--references", "2", "--samples", "3", "--figure-samples", "50", "--threads", "1",
                 "--out", str(val)]) == 0
    report = json.loads((val / "density_report.json").read_text())
    assert report["models"] == "ks" and report["controller"] == "analytic"
    # a KS predictor named for a car set is refused with one line naming the system
    capsys.readouterr()
    assert main(["validate", "density", "--models", "paper", "--density", str(out / "density_trajectory.pt"),
                 "--references", "1", "--samples", "2", "--out", str(tmp_path / "v2")]) == 2
    assert "reads states of the system 'ks'" in capsys.readouterr().err


def test_the_ks_set_is_found_from_the_system():
    ks = KinematicSingleTrack()
    pred = load_learned_predictor("trajectory", load_controller(None, models="ks"), system=ks)
    assert pred.layout == system_layout("ks")


@pytest.mark.parametrize(("models", "start", "acc"), [
    ("road", [0.0, 0.0, 0.3, 6.0, 0.0], [-2.0, -2.0, -2.0, -2.0, -1.0, -1.0, -1.0, 0.0, 0.0, 0.0]),
    ("ks", [0.0, 0.0, 0.0, 3.0, 0.3], [-3.0] * 10)])
def test_learned_predictor_follows_a_reference_that_stops(models, start, acc):
    """A reference that brakes to a stop stands still (the roll-out's hold); the shipped predictors read the inputs
    it applied (``Reference.segment_inputs``: no braking at rest) and stay close to exact Liouville. Fed the
    commanded braking instead, the KS predictor erred by 21 m (median) on the second case."""
    mset = model_set(models)
    system = mset.make_system()
    controller = load_controller(None, models=mset)
    pred = load_predictor(None, system, controller, models=models)
    start_t = torch.tensor(start)
    params = torch.zeros(1, 2, 10)
    params[0, 1] = torch.tensor(acc)
    ref = make_reference(system, start_t, params)
    assert float(ref.x[0, -1, 3]) == 0.0 and not torch.equal(ref.segment_inputs, ref.params)
    assert torch.equal(ref.segment_inputs[..., 1, 7:], torch.zeros(1, 3))
    g = torch.Generator().manual_seed(5)
    box = torch.tensor(system.initial_error_max)
    x0 = (start_t + 0.5 * box * (2 * torch.rand(1, 40, 5, generator=g) - 1)).clamp(
        min=torch.tensor(system.state_bounds[0]))
    s = compare_with_exact(pred, ExactLiouville(system, controller), ref, x0).summary()
    pos = s["position_error_m"]["overall"]
    assert pos["median"] < 0.3 and pos["p95"] < 1.0, pos

"""Learned density predictors: normalisation, frames, interface, exact parts, gradients, checkpoints, registry."""

from __future__ import annotations

import json
import math

import pytest
import torch

from density_planner.control.analytic import CarTrackingController
from density_planner.control.reference import make_reference
from density_planner.density.base import DensityPredictor
from density_planner.density.data import load_density_data
from density_planner.density.liouville import ExactLiouville, propagate_density
from density_planner.density.network import (
    DensityNetArchitecture,
    DensityNetwork,
    LearnedDensity,
    controller_fingerprint,
    errors_to_outputs,
    from_reference_frame,
    load_density_model,
    outputs_to_errors,
    save_density_model,
    system_layout,
    to_reference_frame,
)
from density_planner.density.registry import PREDICTOR_CHOICES, load_learned_predictor, load_predictor
from density_planner.density.train import fit_normalisation, normalised_targets
from density_planner.errors import CheckpointError
from density_planner.systems.car import KinematicCar

ARCHS = ("trajectory", "pointwise")
START = (1.0, -20.0, 1.2, 4.0, 0.0)


def tiny_net(arch: str, seed: int = 0, dtype=torch.float32) -> DensityNetwork:
    """A small untrained network with a random (non-zero) last layer and non-trivial normalisation buffers."""
    torch.manual_seed(seed)
    net = DensityNetwork(DensityNetArchitecture(arch=arch, hidden=16, layers=2, activation="tanh"))
    with torch.no_grad():
        net.last.weight.normal_(0, 0.3)
        net.last.bias.normal_(0, 0.1)
        net.in_mean.normal_(0, 0.1)
        net.in_std.uniform_(0.5, 2.0)
        net.base_weight.normal_(0, 0.05)
        net.base_bias.normal_(0, 0.05)
        net.out_scale.uniform_(0.1, 1.0)
    return net.to(dtype)


def sample_inputs(batch=(), n=7, dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    car = KinematicCar()
    params = (torch.rand(*batch, 2, 10, generator=g, dtype=torch.float64) * 2 - 1).to(dtype)
    start = torch.tensor(START, dtype=dtype).expand(*batch, 5)
    ref = make_reference(car, start, params)
    x0 = ref.start.unsqueeze(-2) + (torch.rand(*batch, n, 5, generator=g, dtype=torch.float64) - 0.5).to(dtype)
    x0[..., 4] = x0[..., 4] * 0.3
    lr0 = torch.randn(*batch, n, generator=g, dtype=torch.float64).to(dtype)
    return ref, x0, lr0


def test_frames_round_trip():
    g = torch.Generator().manual_seed(0)
    dx, dy, h = torch.randn(3, 50, generator=g, dtype=torch.float64)
    el, et = to_reference_frame(dx, dy, h)
    bx, by = from_reference_frame(el, et, h)
    torch.testing.assert_close(bx, dx)
    torch.testing.assert_close(by, dy)
    # heading 0: the reference frame is the world frame; heading pi/2: longitudinal = world y
    assert torch.allclose(torch.stack(to_reference_frame(dx, dy, torch.zeros(50, dtype=torch.float64))),
                          torch.stack([dx, dy]))
    el, et = to_reference_frame(dx, dy, torch.full((50,), math.pi / 2, dtype=torch.float64))
    torch.testing.assert_close(el, dy)
    torch.testing.assert_close(et, -dx)
    xe = torch.randn(4, 101, 5, generator=g, dtype=torch.float64)
    xe[..., 4] = xe[:, :1, 4]
    lr = torch.randn(4, 101, generator=g, dtype=torch.float64)
    heading = torch.randn(4, 101, generator=g, dtype=torch.float64)
    car = system_layout("car")
    y = errors_to_outputs(xe, lr, heading, car)
    xe2, lr2 = outputs_to_errors(y, xe[:, 0], heading, car)
    torch.testing.assert_close(xe2, xe)
    torch.testing.assert_close(lr2, lr)


def test_normalisation_round_trip(tiny_data):
    """Targets standardised with the fitted baseline and scale map back exactly, and are standardised."""
    train = load_density_data(tiny_data, "train")
    net = DensityNetwork(DensityNetArchitecture.default("trajectory"))
    fit_normalisation(net, train)
    s, r, z = normalised_targets(net, train)
    # standardised inputs: mean 0, std 1 (features with no spread, like the reference-start bias, stay finite)
    f = torch.cat([s, r], -1)
    assert torch.allclose(f.mean(0), torch.zeros(f.shape[1]), atol=1e-4)
    varying = f.std(0) > 1e-3
    assert torch.allclose(f.std(0)[varying], torch.ones(int(varying.sum())), atol=1e-3)
    # residual targets: per time step and channel mean ~0 (least-squares residual) and unit standard deviation
    assert float(z.mean(0).abs().max()) < 1e-3
    std = z.std(0)
    assert float((std - 1).abs().max()) < 0.05
    # round trip: baseline + scale * z reproduces the learned outputs in physical units
    y = net.baseline(s, r, net.base_weight[1:], net.base_bias[1:]) + net.out_scale[1:] * z
    truth = errors_to_outputs(train.xe, train.log_ratio, train.x_ref_heading, net.layout)[:, 1:]
    torch.testing.assert_close(y, truth, rtol=1e-4, atol=1e-3)
    # an untrained network (zero last layer) predicts the linear baseline: its training error is the
    # residual standard deviation stored as out_scale
    assert torch.all(net.out_scale > 0)


@pytest.mark.parametrize("arch", ARCHS)
@pytest.mark.parametrize("batch", [(), (3,)])
def test_interface_shapes_and_exact_parts(arch, batch):
    pred = LearnedDensity(tiny_net(arch))
    assert isinstance(pred, DensityPredictor) and pred.name == arch
    ref, x0, lr0 = sample_inputs(batch)
    out = pred.predict(x0, lr0, ref)
    assert out.x.shape == (*batch, 7, 101, 5) and out.log_rho.shape == (*batch, 7, 101)
    assert out.t.shape == (101,) and torch.allclose(out.t, torch.arange(101) * 0.1)
    # t = 0 is exact, the heading bias is constant
    torch.testing.assert_close(out.x[..., 0, :], x0)
    torch.testing.assert_close(out.log_rho[..., 0], lr0)
    torch.testing.assert_close(out.x[..., 4], x0[..., 4:5].expand_as(out.x[..., 4]))
    torch.testing.assert_close(out.log_rho0, lr0)
    # samples shared by a batch of references broadcast
    if batch:
        out2 = pred.predict(x0[0], lr0[0], ref)
        assert out2.x.shape == out.x.shape


@pytest.mark.parametrize("arch", ARCHS)
def test_predict_at_matches_grid(arch):
    net = tiny_net(arch)
    ref, x0, _ = sample_inputs((2,))
    start = ref.start
    xe0 = x0 - start.unsqueeze(-2)
    xe, lr = net(xe0, start, ref.params, ref.x_plan[..., 2])
    k = torch.tensor([0, 1, 37, 100])
    xe_k, lr_k = net.predict_at(xe0, start, ref.params, k.float() * 0.1, ref.x_plan[..., k, 2])
    torch.testing.assert_close(xe_k, xe[..., k, :], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(lr_k, lr[..., k], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("arch", ARCHS)
def test_translation_invariance(arch):
    """Shifting the reference (and the samples) in the plane shifts the prediction and keeps the density."""
    pred = LearnedDensity(tiny_net(arch))
    car = KinematicCar()
    ref, x0, lr0 = sample_inputs()
    shift = torch.tensor([5.0, -3.0, 0.0, 0.0, 0.0])
    ref2 = make_reference(car, ref.start + shift, ref.params)
    a, b = pred.predict(x0, lr0, ref), pred.predict(x0 + shift, lr0, ref2)
    torch.testing.assert_close(b.x, a.x + shift, rtol=0, atol=1e-4)
    torch.testing.assert_close(b.log_rho, a.log_rho)


def test_exact_liouville_is_translation_invariant():
    """The property the networks build in (no start position input) holds for the exact closed loop."""
    car, ctrl = KinematicCar(), CarTrackingController()
    ref, x0, _ = sample_inputs(dtype=torch.float64)
    shift = torch.tensor([7.0, 4.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    ref2 = make_reference(car, ref.start + shift, ref.params)
    a = propagate_density(car, ctrl, x0, ref)
    b = propagate_density(car, ctrl, x0 + shift, ref2)
    torch.testing.assert_close(b.x, a.x + shift, rtol=0, atol=1e-9)
    torch.testing.assert_close(b.log_rho, a.log_rho, rtol=0, atol=1e-9)


@pytest.mark.parametrize("arch", ARCHS)
def test_gradient_wrt_reference_parameters(arch):
    """Finite differences in float64 on a tiny untrained network: the prediction is differentiable w.r.t. the
    reference parameters and start (the planner's second stage backpropagates through it)."""
    pred = LearnedDensity(tiny_net(arch, dtype=torch.float64))
    car = KinematicCar()
    ref, x0, lr0 = sample_inputs(n=3, dtype=torch.float64)
    w_x = torch.randn(3, 101, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(1))

    def f(params, start):
        r = make_reference(car, start, params)
        out = pred.predict(x0, lr0, r)
        return (out.x * w_x).sum() + out.log_rho.sum()

    assert torch.autograd.gradcheck(f, (ref.params.clone().requires_grad_(True),
                                        ref.start.clone().requires_grad_(True)), eps=1e-6, atol=1e-5)


def test_checkpoint_round_trip_and_errors(tmp_path):
    net = tiny_net("trajectory")
    save_density_model(tmp_path / "w", net, extra={"controller": {"spec": "analytic", "fingerprint": "x"}})
    loaded, meta = load_density_model(tmp_path / "w.pt")
    for k, v in net.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v)
    assert meta["architecture"]["arch"] == "trajectory"
    with pytest.raises(CheckpointError, match="'trajectory' density predictor, expected 'pointwise'"):
        load_density_model(tmp_path / "w", arch="pointwise")
    with pytest.raises(CheckpointError, match="not found"):
        load_density_model(tmp_path / "missing.pt")
    # wrong kind (e.g. a controller file)
    meta_bad = dict(meta, kind="c3m_car_controller")
    (tmp_path / "k.json").write_text(json.dumps(meta_bad))
    (tmp_path / "k.pt").write_bytes((tmp_path / "w.pt").read_bytes())
    with pytest.raises(CheckpointError, match="kind"):
        load_density_model(tmp_path / "k.pt")
    # architecture in the JSON does not match the tensors
    meta_arch = dict(meta, architecture=dict(meta["architecture"], hidden=32))
    (tmp_path / "a.json").write_text(json.dumps(meta_arch))
    (tmp_path / "a.pt").write_bytes((tmp_path / "w.pt").read_bytes())
    with pytest.raises(CheckpointError, match="shape"):
        load_density_model(tmp_path / "a.pt")
    # invalid architecture entry
    (tmp_path / "i.json").write_text(json.dumps(dict(meta, architecture=dict(meta["architecture"], arch="rnn"))))
    (tmp_path / "i.pt").write_bytes((tmp_path / "w.pt").read_bytes())
    with pytest.raises(CheckpointError, match="invalid architecture"):
        load_density_model(tmp_path / "i.pt")
    # corrupt weights file
    (tmp_path / "c.json").write_text(json.dumps(meta))
    (tmp_path / "c.pt").write_bytes(b"\x00garbage")
    with pytest.raises(CheckpointError, match="corrupt"):
        load_density_model(tmp_path / "c.pt")
    # controller mismatch
    with pytest.raises(CheckpointError, match="was trained for the controller 'analytic'"):
        load_learned_predictor(tmp_path / "w.pt", CarTrackingController())


def test_registry(tmp_path):
    car, ctrl = KinematicCar(), CarTrackingController()
    assert {"exact", "learned", "trajectory", "pointwise"} <= set(PREDICTOR_CHOICES)
    assert isinstance(load_predictor("exact", car, ctrl), ExactLiouville)
    with pytest.raises(ValueError, match="unknown density predictor 'magic'"):
        load_predictor("magic", car, ctrl)
    # a weights file trained for this very controller loads by path
    net = tiny_net("pointwise")
    save_density_model(tmp_path / "mine", net,
                       extra={"controller": {"spec": "analytic", "fingerprint": controller_fingerprint(ctrl)}})
    pred = load_predictor(str(tmp_path / "mine.pt"), car, ctrl)
    assert isinstance(pred, LearnedDensity) and pred.name == "pointwise"
    # the default falls back to exact Liouville for a controller the shipped predictors were not trained for
    assert isinstance(load_predictor(None, car, ctrl), ExactLiouville)
    # naming a learned predictor for the wrong controller is an error with a hint
    with pytest.raises(CheckpointError, match="--density exact"):
        load_predictor("trajectory", car, ctrl)


def test_fingerprint_distinguishes_controllers():
    from density_planner.control.analytic import CarTrackingGains

    a, b = CarTrackingController(), CarTrackingController(CarTrackingGains(k_v=2.0))
    assert controller_fingerprint(a) == controller_fingerprint(CarTrackingController())
    assert controller_fingerprint(a) != controller_fingerprint(b)
    assert controller_fingerprint(a) == controller_fingerprint(CarTrackingController().double())


def test_reference_grid_mismatch_is_rejected():
    from density_planner.control.reference import PiecewiseConstantInputs

    pred = LearnedDensity(tiny_net("trajectory"))
    car = KinematicCar()
    for par in (PiecewiseConstantInputs(n_segments=20, segment_duration=0.5),
                PiecewiseConstantInputs(n_segments=12, plan_dt=0.2)):
        ref = make_reference(car, torch.tensor(START), torch.zeros(2, par.n_segments), par)
        with pytest.raises(ValueError, match="trained for a 10-s horizon.*--density exact"):
            pred.predict(ref.start + torch.zeros(4, 5), torch.zeros(4), ref)
    assert pred.mismatch(PiecewiseConstantInputs(n_segments=17)) is None  # whole 1-s segments: chained
    assert pred.mismatch(PiecewiseConstantInputs(n_segments=4)) is None  # fewer: one padded window


@pytest.mark.parametrize("n_segments", [1, 4, 9])
def test_shorter_reference_is_the_padded_window_cut_to_its_horizon(n_segments):
    """A horizon shorter than the trained one: the network's 10-s prediction along the reference's parameters
    followed by zero inputs, cut to the reference's own points (and differentiable w.r.t. its parameters)."""
    from density_planner.control.reference import PiecewiseConstantInputs

    pred = LearnedDensity(tiny_net("trajectory", dtype=torch.float64))
    car = KinematicCar()
    g = torch.Generator().manual_seed(5)
    params = torch.rand(2, 2, n_segments, generator=g, dtype=torch.float64) - 0.5
    start = torch.tensor(START, dtype=torch.float64).expand(2, 5)
    short = make_reference(car, start, params, PiecewiseConstantInputs(n_segments=n_segments))
    x0 = short.start.unsqueeze(-2) + 0.3 * (torch.rand(2, 6, 5, generator=g, dtype=torch.float64) - 0.5)
    log_rho0 = torch.randn(2, 6, generator=g, dtype=torch.float64)
    out = pred.predict(x0, log_rho0, short)
    n = 10 * n_segments + 1
    assert out.x.shape == (2, 6, n, 5) and out.log_rho.shape == (2, 6, n)
    assert torch.allclose(out.t, short.t_plan)
    padded = torch.cat([params, params.new_zeros(2, 2, 10 - n_segments)], dim=-1)
    full = pred.predict(x0, log_rho0, make_reference(car, start, padded))
    torch.testing.assert_close(out.x, full.x[..., :n, :])
    torch.testing.assert_close(out.log_rho, full.log_rho[..., :n])
    p = params.clone().requires_grad_(True)
    ref = make_reference(car, start, p, PiecewiseConstantInputs(n_segments=n_segments))
    pred.predict(x0, log_rho0, ref).x[..., -1, :2].sum().backward()
    assert torch.isfinite(p.grad).all() and p.grad[..., -1].abs().sum() > 0


def test_window_starts_cover_the_horizon_without_padding():
    pred = LearnedDensity(tiny_net("trajectory"))
    assert pred.windows(10) == [0]
    assert pred.windows(20) == [0, 10]
    assert pred.windows(17) == [0, 7]  # the last window ends with the reference (overlaps the first)
    assert pred.windows(25) == [0, 10, 15]


@pytest.mark.parametrize("n_segments", [17, 20])
def test_chained_windows_continue_from_the_predicted_state(n_segments):
    """A horizon longer than the trained one: the first 10 s are the network's own 10-s prediction (the reference's
    first 10 segments), and each later window is the network applied from the state and log-density predicted at
    its first segment, along the rest of the reference."""
    from density_planner.control.reference import PiecewiseConstantInputs

    pred = LearnedDensity(tiny_net("trajectory", dtype=torch.float64))
    car = KinematicCar()
    g = torch.Generator().manual_seed(3)
    long = PiecewiseConstantInputs(n_segments=n_segments)
    params = torch.rand(2, 2, n_segments, generator=g, dtype=torch.float64) - 0.5
    start = torch.tensor(START, dtype=torch.float64).expand(2, 5)
    ref = make_reference(car, start, params, long)
    x0 = ref.start.unsqueeze(-2) + 0.3 * (torch.rand(2, 6, 5, generator=g, dtype=torch.float64) - 0.5)
    log_rho0 = torch.randn(2, 6, generator=g, dtype=torch.float64)
    out = pred.predict(x0, log_rho0, ref)
    assert out.x.shape == (2, 6, 10 * n_segments + 1, 5) and out.log_rho.shape == (2, 6, 10 * n_segments + 1)
    assert torch.allclose(out.t, ref.t_plan)

    first = pred.predict(x0, log_rho0, make_reference(car, start, params[..., :10]))
    torch.testing.assert_close(out.x[..., :101, :], first.x)
    torch.testing.assert_close(out.log_rho[..., :101], first.log_rho)
    s = n_segments - 10  # the last window's first segment
    k = 10 * s
    tail_ref = make_reference(car, ref.x_plan[:, k], params[..., s:])
    tail = pred.predict(out.x[..., k, :], out.log_rho[..., k], tail_ref)
    # after 10 s the last window's prediction (an overlapping window adds only the points not yet predicted)
    torch.testing.assert_close(out.x[..., 101:, :], tail.x[..., 101 - k:, :], rtol=1e-6, atol=1e-5)
    torch.testing.assert_close(out.log_rho[..., 101:], tail.log_rho[..., 101 - k:], rtol=1e-6, atol=1e-5)
    # differentiable w.r.t. the reference parameters through every window
    p = params.clone().requires_grad_(True)
    pred.predict(x0, log_rho0, make_reference(car, start, p, long)).x[..., -1, :2].sum().backward()
    assert torch.isfinite(p.grad).all() and p.grad[..., -1].abs().sum() > 0


@pytest.mark.parametrize("n_segments", [4, 10, 17])
def test_trajectory_head_states_only_skips_the_log_density_with_the_same_states_and_gradient(n_segments):
    """``predict_states`` of the trajectory head (one window, a padded one, chained windows): the same states and
    the same gradient in the parameters as ``predict`` (float64 rounding); the log-densities after ``t = 0`` are NaN
    (left out, so that any use shows), ``log_rho0`` kept. The pointwise net predicts them anyway."""
    from density_planner.control.reference import PiecewiseConstantInputs

    car = KinematicCar()
    g = torch.Generator().manual_seed(9)
    par = PiecewiseConstantInputs(n_segments=n_segments)
    start = torch.tensor(START, dtype=torch.float64).expand(2, 5)
    params = torch.rand(2, 2, n_segments, generator=g, dtype=torch.float64) - 0.5
    x0 = start.unsqueeze(-2) + 0.3 * (torch.rand(2, 6, 5, generator=g, dtype=torch.float64) - 0.5)
    log_rho0 = torch.randn(2, 6, generator=g, dtype=torch.float64)
    for arch in ("trajectory", "pointwise"):
        pred = LearnedDensity(tiny_net(arch, dtype=torch.float64))
        outs, grads = [], []
        for method in (pred.predict, pred.predict_states):
            p = params.clone().requires_grad_(True)
            out = method(x0, log_rho0, make_reference(car, start, p, par))
            (grad,) = torch.autograd.grad(out.x.square().sum(), p)
            outs.append(out)
            grads.append(grad)
        full, states = outs
        # the same up to the rounding of a matrix product with fewer output rows
        torch.testing.assert_close(states.x, full.x, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(grads[1], grads[0], rtol=1e-10, atol=1e-10)
        assert float(grads[0].abs().max()) > 0
        assert torch.equal(states.log_rho[..., 0], full.log_rho[..., 0]) and torch.equal(states.log_rho0, log_rho0)
        if arch == "trajectory":
            assert bool(torch.isnan(states.log_rho[..., 1:]).all())
        else:
            assert torch.equal(states.log_rho, full.log_rho)

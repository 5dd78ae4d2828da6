"""Road domain (issue 14): car boxes, lateral-acceleration limit, smooth saturation, model sets, domain refusal."""

from __future__ import annotations

import logging
import math

import pytest
import torch

from density_planner.control.analytic import CarTrackingController
from density_planner.control.base import SmoothSaturation, soft_clip
from density_planner.control.registry import MODEL_SETS, load_controller, model_set, model_set_for_scene
from density_planner.control.sampling import sample_feasible_references, sample_tracking_states
from density_planner.errors import DomainError
from density_planner.systems.car import CarConfig, KinematicCar, car_domain, turn_rate_limit

F64 = torch.float64


# ------------------------------------------------------------------------------------------------- domain
def test_domains_speed_limits_and_names():
    assert CarConfig.paper().speed_max == 10.0
    road = CarConfig.road()
    assert road.speed_max == 40.0 and road.domain == "road"
    assert KinematicCar(road).speed_max == 40.0
    assert model_set("road").speed_max == 40.0 and model_set("paper").speed_max == 10.0
    assert car_domain("paper") == CarConfig()
    with pytest.raises(ValueError, match="unknown car domain 'x'.*paper, road"):
        car_domain("x")
    with pytest.raises(ValueError, match="unknown model set"):
        model_set("highway")
    assert model_set_for_scene("commonroad").name == "road"
    assert model_set_for_scene("random").name == "paper"
    assert model_set_for_scene("commonroad", override="paper").name == "paper"
    assert {n for n, m in MODEL_SETS.items() if m.system == "car"} == {"paper", "road"}


def test_road_config_rejects_inconsistent_actuator_box():
    with pytest.raises(ValueError, match="actuator box must strictly contain"):
        CarConfig(actuator_min=(-2.0, -2.0), actuator_max=(2.0, 2.0))  # inside the +-3 reference box
    with pytest.raises(ValueError, match="both be set"):
        CarConfig(actuator_min=(-4.0, -4.0))


def test_turn_rate_limit_is_below_the_hard_minimum_and_close_to_it():
    v = torch.linspace(0.0, 45.0, 901, dtype=F64)
    lim = turn_rate_limit(v, 1.0, 4.0)
    hard = torch.minimum(torch.ones_like(v), 4.0 / v.clamp_min(1e-12))
    assert bool((lim <= hard + 1e-12).all())
    assert bool((lim >= 2 ** -0.25 * hard - 1e-12).all())  # within 16 % (worst at the crossing speed)
    assert float((v * lim).max()) <= 4.0 + 1e-9  # lateral acceleration never above the limit
    assert bool((turn_rate_limit(v, 3.0, math.inf) == 3.0).all())  # the paper: no speed dependence


def test_road_references_respect_the_lateral_limit_and_span_the_speed_range(gen):
    car = KinematicCar(CarConfig.road())
    ref = sample_feasible_references(car, 300, gen, dtype=F64)
    v = ref.x[..., :-1, 3]
    assert bool((ref.u[..., 0].abs() <= car.turn_rate_limit(v) + 1e-9).all())
    assert float(ref.start[:, 3].max()) > 30.0 and float(ref.start[:, 3].min()) < 5.0
    assert float(ref.x[..., 3].max()) <= 40.0 + 0.4  # the state box (1 % of the steps may leave it)


def test_training_samples_skip_standstill_but_checks_do_not(gen):
    road = CarConfig.road()
    s = sample_tracking_states(4000, gen, road, min_speed=0.3)
    assert float(s.x[:, 3].min()) >= 0.3 - 1e-9
    assert float(s.x_ref[:, 3].min()) >= 0.0 and float(s.x_ref[:, 3].max()) <= 40.0
    full = sample_tracking_states(4000, gen, road)
    assert float(full.x[:, 3].min()) < 0.0  # the whole box (reversing included) for the checks
    lim = road.turn_rate_limit(s.x_ref[:, 3].double())
    assert bool((s.u_ref[:, 0].abs().double() <= lim + 1e-6).all())


# ------------------------------------------------------------------------------------------- saturation
def test_soft_clip_identity_inside_bounded_and_c1():
    z = torch.linspace(-12.0, 12.0, 4801, dtype=F64, requires_grad=True)
    k_lo, k_hi = torch.tensor(-6.0, dtype=F64), torch.tensor(3.0, dtype=F64)
    c_lo, c_hi = torch.tensor(-9.0, dtype=F64), torch.tensor(4.5, dtype=F64)
    s, ds, _, _ = soft_clip(z, k_lo, k_hi, c_lo, c_hi)
    inside = (z >= -6.0) & (z <= 3.0)
    assert torch.equal(s[inside], z[inside])
    assert bool((s > -9.0).all()) and bool((s < 4.5).all())
    (grad,) = torch.autograd.grad(s.sum(), z)
    assert torch.allclose(grad, ds, atol=1e-12)
    assert bool((ds > 0).all()) and bool((ds <= 1).all())
    # continuous derivative (and curvature) at the knees: finite differences across them
    h = 1e-4
    for knee in (3.0, -6.0):
        zz = torch.tensor([knee - h, knee, knee + h], dtype=F64)
        d = soft_clip(zz, k_lo, k_hi, c_lo, c_hi)[1]
        assert float((d - 1).abs().max()) < 1e-6


def test_soft_clip_bound_derivatives_match_autograd():
    z = torch.tensor([3.5, 5.0, -7.0, -8.5, 0.0], dtype=F64)
    k_hi = torch.tensor(3.0, dtype=F64, requires_grad=True)
    c_hi = torch.tensor(4.5, dtype=F64, requires_grad=True)
    k_lo = torch.tensor(-6.0, dtype=F64, requires_grad=True)
    c_lo = torch.tensor(-9.0, dtype=F64, requires_grad=True)
    s, _, dk, dc = soft_clip(z, k_lo, k_hi, c_lo, c_hi)
    dk, dc = dk.detach(), dc.detach()
    for i in range(len(z)):
        gk_hi, gc_hi, gk_lo, gc_lo = torch.autograd.grad(s[i], (k_hi, c_hi, k_lo, c_lo), retain_graph=True)
        above, below = float(z[i]) > 3.0, float(z[i]) < -6.0
        assert math.isclose(float(dk[i]), float(gk_hi if above else gk_lo if below else 0.0), abs_tol=1e-12)
        assert math.isclose(float(dc[i]), float(gc_hi if above else gc_lo if below else 0.0), abs_tol=1e-12)


def test_saturated_controller_tangents_match_forward_mode():
    car = CarConfig.road()
    ctrl = CarTrackingController(car=car).double()
    g = torch.Generator().manual_seed(3)
    x = torch.randn(64, 5, generator=g, dtype=F64) * torch.tensor([1, 1, 0.5, 3, 0.1], dtype=F64)
    x[:, 3] += torch.linspace(0.5, 39.0, 64, dtype=F64)
    x_ref = torch.zeros(64, 5, dtype=F64)
    x_ref[:, 3] = x[:, 3].detach().clone().clamp(0, 40)
    u_ref = torch.zeros(64, 2, dtype=F64)
    tangents = torch.eye(5, dtype=F64).reshape(5, 1, 5)
    u, du = ctrl.forward_with_tangents(x, x_ref, u_ref, tangents)
    jac = torch.func.jacfwd(lambda z: ctrl(z, x_ref, u_ref))(x)  # (64, 2, 64, 5)
    jac = torch.einsum("bibj->bij", jac)
    assert torch.allclose(du.permute(1, 2, 0), jac, atol=1e-10)
    assert torch.allclose(u, ctrl(x, x_ref, u_ref))
    # bounded by the speed-dependent actuator limits, and some samples do use the tail
    assert bool((u[:, 0].abs() <= car.turn_rate_limit(x[:, 3], actuator=True)).all())  # tanh rounds to 1 far out
    assert bool((u[:, 1] >= -9.0).all()) and bool((u[:, 1] <= 4.5).all())
    assert bool((u[:, 0].abs() > car.turn_rate_limit(x[:, 3])).any())


def test_saturation_passes_reference_inputs_unchanged():
    car = CarConfig.road()
    sat = SmoothSaturation.from_car(car)
    assert sat is not None and SmoothSaturation.from_car(CarConfig()) is None
    x_hat = torch.zeros(50, 5, dtype=F64)
    x_hat[:, 3] = torch.linspace(0.0, 40.0, 50, dtype=F64)
    u = torch.stack([car.turn_rate_limit(x_hat[:, 3]) * 0.999, torch.full((50,), -5.9, dtype=F64)], -1)
    assert torch.equal(sat(u, x_hat), u)


def test_saturation_skips_its_computation_exactly_when_nothing_is_beyond_the_knees(monkeypatch):
    """Inputs inside the reference box: ``__call__`` and ``with_tangents`` return their inputs, the values the
    whole computation gives (forced here); one input beyond a knee, in either channel and direction, is noticed."""
    car = CarConfig.road()
    sat = SmoothSaturation.from_car(car)
    assert sat is not None
    g = torch.Generator().manual_seed(5)
    x_hat = torch.zeros(40, 5, dtype=F64)
    x_hat[:, 3] = torch.linspace(0.0, 40.0, 40, dtype=F64)
    from density_planner.control.base import _turn_limit

    k = _turn_limit(x_hat[:, 3], sat.input_max[0], sat.lateral_accel_max)[0]  # the turn channel's knee
    hi, lo = sat.input_max[1], sat.input_min[1]
    u = torch.stack([k * (2 * torch.rand(40, generator=g, dtype=F64) - 1),
                     lo + (hi - lo) * torch.rand(40, generator=g, dtype=F64)], -1)
    u[0, 0], u[1, 0], u[2, 1], u[3, 1] = k[0], -k[1], hi, lo  # on the knees: not beyond
    du = torch.randn(5, 40, 2, generator=g, dtype=F64)
    dx = torch.randn(5, 40, 5, generator=g, dtype=F64)
    assert not sat.beyond_knees(u, x_hat)
    fast_u, (fast_s, fast_du) = sat(u, x_hat), sat.with_tangents(u, du, x_hat, dx)
    narrow = sat.with_tangents(u, du[:, :1], x_hat, dx)[1]  # tangents that broadcast over the batch
    monkeypatch.setattr(SmoothSaturation, "beyond_knees", lambda self, *args: True)
    assert torch.equal(fast_u, sat(u, x_hat))
    whole_s, whole_du = sat.with_tangents(u, du, x_hat, dx)
    assert torch.equal(fast_s, whole_s) and torch.equal(fast_du, whole_du)
    whole_narrow = sat.with_tangents(u, du[:, :1], x_hat, dx)[1]
    assert narrow.shape == whole_narrow.shape == (5, 40, 2) and torch.equal(narrow, whole_narrow)
    monkeypatch.undo()
    for channel, value in ((0, float(k[7]) * 1.0001), (0, -float(k[7]) * 1.0001), (1, hi + 1e-9), (1, lo - 1e-9)):
        v = u.clone()
        v[7, channel] = value
        assert sat.beyond_knees(v, x_hat), (channel, value)


def test_paper_controller_is_unchanged():
    """The paper set keeps its hard clip, and its fingerprint (the shipped density predictors check it)."""
    import json

    from density_planner.density.network import controller_fingerprint, shipped_density_path

    ctrl = load_controller("c3m")
    assert ctrl.saturation is None
    meta = json.loads(shipped_density_path("trajectory").with_suffix(".json").read_text())
    assert controller_fingerprint(ctrl) == meta["controller"]["fingerprint"]


# -------------------------------------------------------------------------------------------- refusal
def _tiny_predictor(fallback=None):
    from density_planner.density.network import DensityNetArchitecture, DensityNetwork, LearnedDensity

    net = DensityNetwork(DensityNetArchitecture(hidden=8, layers=1))
    meta = {"data": {"config": {"start_low": [-12.0, -30.0, 0.0, 1.0, 0.0],
                                "start_high": [12.0, 10.0, 6.28, 9.0, 0.0]}}}
    return LearnedDensity(net, meta=meta, fallback=fallback)


def _reference(v0: float):
    from density_planner.control.reference import make_reference

    car = KinematicCar()
    return make_reference(car, torch.tensor([0.0, 0.0, 0.0, v0, 0.0]), torch.zeros(2, 10))


def test_learned_predictor_refuses_starts_outside_its_training_speeds():
    pred = _tiny_predictor()
    assert pred.speed_range == (1.0, 9.0)
    x0 = torch.zeros(1, 3, 5)
    out = pred.predict(x0 + _reference(5.0).start, torch.zeros(1, 3), _reference(5.0))
    assert out.x.shape[-2] == 101
    with pytest.raises(DomainError, match=r"start speed 25.00 m/s lies outside the speed range \[1, 9\] m/s"):
        pred.predict(x0 + _reference(25.0).start, torch.zeros(1, 3), _reference(25.0))


def test_learned_predictor_trained_from_near_standstill_serves_standstill():
    """A predictor whose training speeds start at <= STANDSTILL_EXTENSION (0.5 m/s) serves starts down to v = 0 (the
    road car's measured accuracy there equals that at 0.5-1 m/s); one trained from 1 m/s does not."""
    from density_planner.density.network import STANDSTILL_EXTENSION

    pred = _tiny_predictor()
    assert pred.speed_range == (1.0, 9.0) and STANDSTILL_EXTENSION == 0.5
    assert "0.20 m/s lies outside" in (pred.domain_problem(_reference(0.2)) or "")
    pred.speed_range = (0.5, 9.0)
    assert pred.domain_problem(_reference(0.0)) is None and pred.domain_problem(_reference(0.3)) is None
    assert "-0.10 m/s lies outside" in (pred.domain_problem(_reference(-0.1)) or "")
    assert "9.50 m/s lies outside" in (pred.domain_problem(_reference(9.5)) or "")


def test_learned_predictor_falls_back_to_exact_with_a_warning(caplog):
    from density_planner.density.liouville import ExactLiouville

    car = KinematicCar()
    exact = ExactLiouville(car, CarTrackingController())
    pred = _tiny_predictor(fallback=exact)
    ref = _reference(25.0)
    x0 = ref.start + torch.zeros(1, 3, 5)
    with caplog.at_level(logging.WARNING):
        out = pred.predict(x0, torch.zeros(1, 3), ref)
    assert "using exact Liouville instead" in caplog.text
    expected = exact.predict(x0, torch.zeros(1, 3), ref)
    assert torch.equal(out.log_rho, expected.log_rho)


# ------------------------------------------------------------------------------------------ training smoke
def test_tiny_road_training_round_trip(tmp_path):
    """The existing training entry point on the road domain: seeded, resumable, domain recorded in the weights."""
    from density_planner.config import update
    from density_planner.control.c3m import C3MArchitecture, load_c3m_model
    from density_planner.control.c3m_training import C3MTrainConfig, train_c3m

    cfg = C3MTrainConfig(architecture=C3MArchitecture(hidden=16, metric_hidden=16, rank=4, v_range=(0.0, 40.0)),
                         epochs=1, steps_per_epoch=2, batch_size=64, eval_samples=200, domain="road",
                         min_speed=0.3)
    res = train_c3m(cfg, tmp_path, progress=False, diagnostics_samples=500)
    diag = res.diagnostics
    assert diag["domain"] == "road"
    assert "v_in_[30,41)" in diag["frac_holds_by_speed"] and "frac_saturation_slope_below_half" in diag
    model, meta = load_c3m_model(res.weights_path)
    assert model.car == CarConfig.road() and model.controller.saturation is not None
    assert meta["training_config"]["domain"] == "road"
    # resuming with more epochs continues from the checkpoint (same settings otherwise)
    res2 = train_c3m(update(cfg, {"epochs": 2}), tmp_path, progress=False, diagnostics_samples=200)
    assert res2.history.epoch == [1, 2]
    with pytest.raises(ValueError, match="domain must be one of"):
        C3MTrainConfig(domain="moon")


def test_tail_span_measures_a_sweep_through_the_bend_in_tail_widths():
    """``tail_span``: the span of the raw input in widths of the tail ``d = ceiling - knee`` where it meets the
    curved part ``[k, k + 3 d]`` (or its mirror), else 0; the largest over the channels; ``None`` without a smooth
    saturation (the paper's hard clip)."""
    car = CarConfig.road()
    sat = SmoothSaturation.from_car(car)
    assert sat is not None
    x_hat = torch.zeros(6, 5, dtype=F64)
    x_hat[:, 3] = 30.0
    knee, ceiling = (float(b[0, 0]) for b in sat._limits(torch.zeros(1, 2, dtype=F64), x_hat[:1])[1:4:2])
    k, d = knee, ceiling - knee  # the turn channel at 30 m/s: ~ a_lat / v, ~ twice that
    assert k == pytest.approx(car.lateral_accel_max / 30.0, rel=1e-3) and d == pytest.approx(k, rel=1e-3)
    a_knee, a_d = car.input_max[1], car.actuator_max[1] - car.input_max[1]
    z_lo = torch.tensor([[-0.5 * k, 0.0], [0.5 * k, 0.0], [k + 3.5 * d, 0.0], [-0.5 * k, 0.0], [0.0, a_knee - 0.1],
                         [0.0, -30.0]], dtype=F64)
    z_hi = torch.tensor([[0.5 * k, 0.0], [k + d, 0.0], [k + 5 * d, 0.0], [0.0, 0.0], [0.0, a_knee + 2 * a_d],
                         [0.0, 30.0]], dtype=F64)
    z_lo[3, 0] = -(k + 2 * d)  # the mirror: from inside the lower tail's bend up to 0
    span = sat.tail_span(z_lo, z_hi, x_hat)
    expected = [0.0,                          # inside the linear band
                (k + d - 0.5 * k) / d,        # into the upper bend
                0.0,                          # beyond the bend, where the tanh is flat
                (k + 2 * d) / d,              # out of the lower bend
                (2 * a_d + 0.1) / a_d,        # the acceleration channel's upper bend
                60.0 / a_d]                   # across both bends: the narrower tail's measure
    torch.testing.assert_close(span, torch.tensor(expected, dtype=F64), atol=1e-9, rtol=0)
    assert CarTrackingController().tail_span(z_lo, z_hi, x_hat) is None


def test_segment_turn_rate_limits_take_the_fastest_instant_of_each_segment(gen):
    car = KinematicCar(CarConfig.road())
    ref = sample_feasible_references(car, 50, gen, dtype=F64)
    m = ref.parameterization.steps_per_segment
    limits = car.segment_turn_rate_limits(ref.x, m)
    assert limits.shape == ref.params[:, 0].shape
    v = ref.x[..., 3].abs()
    for k in range(limits.shape[-1]):  # a loop over the 10 segments as the independent check
        fastest = v[:, k * m:(k + 1) * m + 1].amax(-1)
        torch.testing.assert_close(limits[:, k], car.turn_rate_limit(fastest))
    # the sampler's references respect the bound of every segment
    assert bool((ref.params[:, 0].abs() <= limits + 1e-9).all())
    with pytest.raises(ValueError, match="not whole segments"):
        car.segment_turn_rate_limits(ref.x[..., :-1, :], m)


def test_density_command_keeps_its_default_curve_within_the_lateral_limit(tmp_path, capsys):
    import numpy as np

    from density_planner.cli import main

    car = KinematicCar(CarConfig.road())
    rc = main(["density", "--models", "road", "--start", "0", "0", "0", "25", "--samples", "20", "--integrator",
               "rk4", "--out", str(tmp_path / "default")])
    assert rc == 0
    out = np.load(tmp_path / "default" / "density.npz")
    limits = car.segment_turn_rate_limits(torch.as_tensor(out["x_ref"]), 10)
    omega = torch.as_tensor(out["params"])[0]
    assert bool((omega.abs() <= limits + 1e-6).all()) and float(omega.abs().max()) > 0.05  # scaled, not dropped
    assert "warning" not in capsys.readouterr().err
    params = tmp_path / "p.json"  # the same curve given explicitly: planned as given, with one warning line
    params.write_text("[[0.3,0.3,0,-0.3,-0.3,0,0.2,0.2,0,0],[0.8,0.5,0.3,0,0,0,0,-0.3,-0.5,-0.5]]")
    rc = main(["density", "--models", "road", "--start", "0", "0", "0", "25", "--samples", "20", "--integrator",
               "rk4", "--params", str(params), "--out", str(tmp_path / "given")])
    assert rc == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "lateral-acceleration limit" in err[0] and "--params" in err[0]
    assert float(np.load(tmp_path / "given" / "density.npz")["params"][0].max()) == pytest.approx(0.3)

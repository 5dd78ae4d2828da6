"""The shipped learned predictors against exact Liouville on a handful of fresh references (shipped C3M
controller), and their metadata.

Tolerances: a few times the errors measured by ``density-planner validate density`` on 200 fresh references x
100 samples (docs/density.md) — the medians of 6 references x 40 samples scatter around those, and the test must
catch a broken or mismatched file (errors of metres and of tens in log-density), not re-validate the training.
"""

from __future__ import annotations

import pytest
import torch

from density_planner.control.registry import load_controller
from density_planner.density.liouville import ExactLiouville
from density_planner.density.network import LearnedDensity, controller_fingerprint, shipped_density_path
from density_planner.density.registry import DEFAULT_LEARNED, load_predictor
from density_planner.density.validation import compare_with_exact, fresh_references
from density_planner.systems.car import KinematicCar

ARCHS = ("trajectory", "pointwise")

#: (median, 95th percentile) of the position error [m] and of |log-density error| over all samples and times
TOLERANCES = {
    "trajectory": {"position": (0.15, 0.6), "log_density": (4.0, 16.0)},
    "pointwise": {"position": (0.2, 0.7), "log_density": (4.5, 20.0)},
}


def _shipped(arch: str) -> None:
    if not shipped_density_path(arch).is_file():
        pytest.fail(f"shipped weights missing: {shipped_density_path(arch)}")


@pytest.fixture(scope="module")
def controller():
    return load_controller("c3m")


@pytest.mark.parametrize("arch", ARCHS)
def test_shipped_predictor_close_to_exact_liouville(arch, controller):
    _shipped(arch)
    car = KinematicCar()
    pred = load_predictor(arch, car, controller)
    assert isinstance(pred, LearnedDensity) and pred.name == arch
    ref, x0 = fresh_references(6, 40, seed=424242)
    summary = compare_with_exact(pred, ExactLiouville(car, controller), ref, x0).summary()
    pos, ld = summary["position_error_m"]["overall"], summary["log_density_abs_error"]["overall"]
    tol = TOLERANCES[arch]
    assert pos["median"] < tol["position"][0] and pos["p95"] < tol["position"][1], pos
    assert ld["median"] < tol["log_density"][0] and ld["p95"] < tol["log_density"][1], ld


@pytest.mark.parametrize("arch", ARCHS)
def test_shipped_metadata(arch, controller):
    _shipped(arch)
    meta = load_predictor(arch, KinematicCar(), controller).meta
    assert meta["architecture"]["arch"] == arch
    assert meta["controller"]["fingerprint"] == controller_fingerprint(controller)
    for key in ("data", "training", "commands", "diagnostics"):
        assert meta[key], key
    assert meta["data"]["sizes"]["references_train"] > 1000
    assert meta["training"]["wall_time_s"] > 0
    assert meta["commands"]["train"].startswith("density-planner train density")
    assert shipped_density_path(arch).stat().st_size < 4_000_000  # a few MB at most


def test_default_learned_predictor_is_the_trajectory_head(controller):
    _shipped(DEFAULT_LEARNED)
    assert DEFAULT_LEARNED == "trajectory"
    pred = load_predictor(None, KinematicCar(), controller)
    assert isinstance(pred, LearnedDensity) and pred.name == "trajectory"
    pred2 = load_predictor("learned", KinematicCar(), controller)
    assert torch.equal(pred2.model.last.weight, pred.model.last.weight)


def test_shipped_road_predictor_chained_past_its_horizon_stays_close_to_exact():
    """A 20-s horizon from the road set's 10-s trajectory network (two chained windows) against exact Liouville.
    Measured by benchmarks/bench_chained_density.py (12 references x 40 samples): position error median 0.11-0.17 m
    after 10 s, as in the first window (docs/density.md); the tolerances catch a window that restarts from the wrong
    state or time."""
    from density_planner.control.reference import PiecewiseConstantInputs
    from density_planner.control.registry import model_set
    from density_planner.control.sampling import sample_feasible_references, sample_initial_errors

    system = model_set("road").make_system()
    ctrl = load_controller("c3m", models="road")
    par = PiecewiseConstantInputs(n_segments=20)
    gen = torch.Generator().manual_seed(11)
    ref = sample_feasible_references(system, 24, gen, parameterization=par)
    v = ref.x[:, ::par.steps_per_segment * 10, 3]  # reference speed at the window starts
    ref = ref.select(((v >= 0.5) & (v <= 38.0)).all(-1).nonzero()[:6, 0])
    xe0 = sample_initial_errors(ref.x.shape[0] * 30, gen, box=list(system.initial_error_max))
    x0 = ref.start.unsqueeze(-2) + xe0.reshape(ref.x.shape[0], 30, system.nx)
    pred = load_predictor("trajectory", system, ctrl, parameterization=par, models="road")
    lr0 = torch.zeros(x0.shape[:-1])
    a, b = pred.predict(x0, lr0, ref), ExactLiouville(system, ctrl).predict(x0, lr0, ref)
    err = (a.x[..., 101:, :2] - b.x[..., 101:, :2]).norm(dim=-1).flatten()
    assert err.median() < 0.35 and err.quantile(0.95) < 1.5, (err.median(), err.quantile(0.95))


def test_shipped_road_predictor_on_a_shorter_horizon_stays_close_to_exact():
    """A 4-s horizon from the road set's 10-s trajectory network (one window, inputs padded with zeros after 4 s)
    against exact Liouville over those 4 s: the closed loop is causal, and the network learned it (references
    with independent random inputs per segment); the same tolerances as the chained test."""
    from density_planner.control.reference import PiecewiseConstantInputs
    from density_planner.control.registry import model_set
    from density_planner.control.sampling import sample_feasible_references, sample_initial_errors

    system = model_set("road").make_system()
    ctrl = load_controller("c3m", models="road")
    par = PiecewiseConstantInputs(n_segments=4)
    gen = torch.Generator().manual_seed(12)
    ref = sample_feasible_references(system, 24, gen, parameterization=par)
    ref = ref.select(((ref.x[:, 0, 3] >= 0.5) & (ref.x[:, 0, 3] <= 38.0)).nonzero()[:6, 0])
    xe0 = sample_initial_errors(ref.x.shape[0] * 30, gen, box=list(system.initial_error_max))
    x0 = ref.start.unsqueeze(-2) + xe0.reshape(ref.x.shape[0], 30, system.nx)
    pred = load_predictor("trajectory", system, ctrl, parameterization=par, models="road")
    lr0 = torch.zeros(x0.shape[:-1])
    a, b = pred.predict(x0, lr0, ref), ExactLiouville(system, ctrl).predict(x0, lr0, ref)
    assert a.x.shape == b.x.shape
    err = (a.x[..., :2] - b.x[..., :2]).norm(dim=-1).flatten()
    assert err.median() < 0.35 and err.quantile(0.95) < 1.5, (err.median(), err.quantile(0.95))


def test_shipped_road_predictor_serves_stopped_starts_close_to_exact():
    """Starts below the road head's training range (0.5 m/s), which STANDSTILL_EXTENSION lets it serve: against exact
    Liouville its position error is of the size it has inside the range. Measured by
    benchmarks/bench_standstill_density.py (24 references x 50 samples, stop 62's head): median / p95 0.031 / 0.166 m
    below 0.5 m/s, 0.022 / 0.127 m at 1-2 m/s (docs/planner.md); the tolerances catch a head that extrapolates."""
    import math

    from density_planner.control.registry import model_set
    from density_planner.density.validation import compare_with_exact, fresh_references

    system = model_set("road").make_system()
    ctrl = load_controller("c3m", models="road")
    ref, x0 = fresh_references(6, 30, 13, domain="road", start_low=[-10.0, -10.0, -math.pi, 0.0, 0.0],
                               start_high=[10.0, 10.0, math.pi, 0.5, 0.0])
    assert float(ref.x[:, 0, 3].max()) < 0.5
    pred = load_predictor("trajectory", system, ctrl, models="road")
    assert isinstance(pred, LearnedDensity) and pred.domain_problem(ref) is None  # the network serves them
    err = compare_with_exact(pred, ExactLiouville(system, ctrl), ref, x0).position_error.flatten()
    assert err.median() < 0.1 and err.quantile(0.95) < 0.5, (err.median(), err.quantile(0.95))

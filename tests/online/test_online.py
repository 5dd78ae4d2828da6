"""The receding-horizon runner: warm start (shift of the previous plan), re-centred initial law, braking
manoeuvre, recorded fallbacks, and an end-to-end drive."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from density_planner.evaluation.online import (
    OnlineConfig,
    _replan_parameterization,
    _rescue,
    best_objective,
    braking_parameters,
    drive,
    recentred,
    refit_shift,
    shift_parameters,
    shifted_plan,
    warm_replan,
)
from density_planner.planners.density_planner import DensityPlanner, DensityPlannerConfig
from density_planner.planners.problem import PlanningProblem
from density_planner.systems.car import KinematicCar


# ------------------------------------------------------------------------------------------- pure functions
def test_shift_by_whole_segments_is_the_exact_shift():
    p = torch.arange(20, dtype=torch.float64).reshape(2, 10)
    tail = torch.tensor([-1.0, -2.0], dtype=torch.float64)
    out = shift_parameters(p, 2.0, 1.0, tail)
    torch.testing.assert_close(out[:, :8], p[:, 2:])
    torch.testing.assert_close(out[:, 8:], tail[:, None].expand(2, 2))
    torch.testing.assert_close(shift_parameters(p, 0.0, 1.0), p)


def test_shift_by_half_a_segment_averages_over_time():
    p = torch.tensor([[0.0, 2.0, 4.0]], dtype=torch.float64)
    out = shift_parameters(p, 0.5, 1.0, torch.tensor([10.0], dtype=torch.float64))
    # new segment j covers [0.5 + j, 1.5 + j]: half of old j and half of old j + 1 (the tail past 3 s)
    torch.testing.assert_close(out, torch.tensor([[1.0, 3.0, 7.0]], dtype=torch.float64))


def test_a_shifted_plan_goes_on_straight_and_brakes_or_holds_its_speed():
    """``shifted_plan`` (drive's warm start, bench_replan's too): the old inputs shifted; past the old horizon no
    turn and the braking that stops the reference's end speed within a segment, at most the hardest braking; with
    ``hold`` no acceleration either; cut to the replan's segments."""
    from density_planner.control.reference import PiecewiseConstantInputs, make_reference

    car = KinematicCar()
    par = PiecewiseConstantInputs(n_segments=6)
    params = torch.tensor([[0.1, -0.2, 0.0, 0.3, 0.1, -0.1], [1.0, 0.5, 0.0, -0.5, 0.2, 0.4]], dtype=torch.float64)
    a_min = float(car.input_bounds[0][1])
    for v0, clamped in ((0.0, False), (9.0, True)):  # the end speed stops within a segment, or at most a_min
        start = torch.tensor([0.0, 0.0, 0.0, v0, 0.0], dtype=torch.float64)
        ref = make_reference(car, start, params.unsqueeze(0), par).select(0)
        v_end = float(ref.x[-1, 3])
        assert (-v_end < a_min) == clamped
        warm = shifted_plan(car, params, ref, 2.0, 1.0, 5)
        assert warm.shape == (2, 5)
        torch.testing.assert_close(warm[:, :4], params[:, 2:])
        torch.testing.assert_close(warm[:, 4], torch.tensor([0.0, max(a_min, -v_end)], dtype=torch.float64))
        held = shifted_plan(car, params, ref, 2.0, 1.0, 6, hold=True)
        torch.testing.assert_close(held[:, 4:], torch.zeros(2, 2, dtype=torch.float64))


def test_refit_brings_a_half_segment_shift_back_onto_the_old_path():
    """Inputs shifted by half a segment (time-averaged) leave the old path; the Gauss-Newton refit follows it closer,
    stays within the input bounds, and leaves an exact (whole-segment) shift as it is."""
    from density_planner.control.reference import PiecewiseConstantInputs, plan_grid_reference

    car = KinematicCar()
    par = PiecewiseConstantInputs(n_segments=6)
    gen = torch.Generator().manual_seed(5)
    lo, hi = (torch.as_tensor(b, dtype=torch.float64)[:, None] for b in car.input_bounds)
    params = (lo + (hi - lo) * torch.rand(car.nu, 6, generator=gen, dtype=torch.float64)) * 0.6
    start = torch.tensor([0.0, 0.0, 0.3, 9.0, 0.0], dtype=torch.float64)
    x_old, _ = plan_grid_reference(car, start, params, par)

    def error(p: torch.Tensor, k: int) -> float:
        x_new, _ = plan_grid_reference(car, x_old[k], p, par)
        n = x_old.shape[0] - k
        return float((x_new[:n, :2] - x_old[k:, :2]).norm(dim=-1).max())

    half = shift_parameters(params, 0.5, 1.0)
    fit = refit_shift(car, par, x_old[5], half, x_old[5:], iterations=3)
    assert error(half, 5) > 0.2  # the averaged inputs drift (steering changes inside the new segments)
    assert error(fit, 5) < 0.5 * error(half, 5)
    assert bool(((fit >= lo - 1e-12) & (fit <= hi + 1e-12)).all())
    torch.testing.assert_close(refit_shift(car, par, x_old[5], half, x_old[5:], iterations=0), half)
    whole = shift_parameters(params, 1.0, 1.0)
    assert error(whole, 10) < 1e-9
    torch.testing.assert_close(refit_shift(car, par, x_old[10], whole, x_old[10:]), whole, atol=1e-9, rtol=0)


def test_replan_horizon_ends_with_the_goal():
    from density_planner.control.reference import PiecewiseConstantInputs

    par = PiecewiseConstantInputs(n_segments=8)
    assert _replan_parameterization(par, 8.0, 0.5, True) is par  # 7.5 s left: all 8 segments
    assert _replan_parameterization(par, 8.0, 1.0, True).n_segments == 7
    assert _replan_parameterization(par, 8.0, 3.5, True).n_segments == 5  # whole segments that reach the end
    assert _replan_parameterization(par, 8.0, 7.9, True).n_segments == 1
    assert _replan_parameterization(par, 8.0, 9.0, True).n_segments == 1  # one segment at least
    assert _replan_parameterization(par, 20.0, 1.0, True) is par  # the goal after the horizon
    assert _replan_parameterization(par, None, 1.0, True) is par  # no goal time given
    assert _replan_parameterization(par, 8.0, 3.5, False) is par
    short = _replan_parameterization(par, 8.0, 3.5, True)
    assert (short.segment_duration, short.dt, short.plan_dt) == (par.segment_duration, par.dt, par.plan_dt)


def test_reference_origin_overrides_the_law_mean(setup):
    car, _, scene, problem, _, plan = setup
    origin = plan.reference.x_plan[7].double()
    prob = dataclasses.replace(problem, reference_origin=origin)
    start = prob.reference_start(torch.float64)
    torch.testing.assert_close(start, car.nominal_state(origin.clone()))
    assert not torch.allclose(start, problem.reference_start(torch.float64))
    with pytest.raises(ValueError, match="reference_origin must be a finite state of shape"):
        dataclasses.replace(problem, reference_origin=torch.zeros(3))
    with pytest.raises(ValueError, match="reference_origin must be a finite state"):
        dataclasses.replace(problem, reference_origin=torch.full((car.nx,), math.nan))


def test_recentred_law_is_a_translation():
    from density_planner.density.distributions import paper_gaussian_mixture

    car = KinematicCar()
    law = paper_gaussian_mixture([0.0, 0.0, 1.0, 5.0, 0.0], car.config.initial_error_max,
                                 torch.Generator().manual_seed(3))
    target = torch.tensor([10.0, -4.0, 0.5, 7.0, float(law.mean[-1])], dtype=torch.float64)
    new = recentred(law, target)
    torch.testing.assert_close(new.mean, target, atol=1e-9, rtol=0)
    x = law.sample(64, torch.Generator().manual_seed(0), dtype=torch.float64)
    d = target - law.mean
    torch.testing.assert_close(new.log_prob(x + d), law.log_prob(x), atol=1e-9, rtol=0)


def test_braking_reaches_standstill_and_stays():
    car = KinematicCar()
    p = braking_parameters(car, 7.0, 1.0, 10, (-1.0, 0.0, 1.0))
    a = p[:, 1]
    v = 7.0 + torch.cumsum(a, dim=-1)  # 1-s segments
    assert torch.all(v >= -1e-9) and torch.allclose(v[:, -1], torch.zeros(3, dtype=torch.float64))
    lo, hi = car.input_bounds
    assert torch.all(a >= lo[1] - 1e-9)
    v_start = torch.cat([torch.full((3, 1), 7.0, dtype=torch.float64), v[:, :-1]], dim=-1)
    assert torch.all(p[:, 0][v_start <= 1e-9] == 0)  # no steering once stopped
    assert p[0, 0, 0] == lo[0] and p[2, 0, 0] == hi[0] and p[1, 0, 0] == 0


def test_config_validation():
    with pytest.raises(ValueError, match="period"):
        OnlineConfig(period=-0.5)
    assert OnlineConfig().period == 0.0  # one input segment
    assert OnlineConfig().replan_period(1.0) == 1.0 and OnlineConfig(period=0.5).replan_period(1.0) == 0.5
    with pytest.raises(ValueError, match="refit_iterations"):
        OnlineConfig(refit_iterations=-1)
    with pytest.raises(ValueError, match="replan_epochs"):
        OnlineConfig(replan_epochs=0)
    for bad in (-1, True, 1.5):
        with pytest.raises(ValueError, match="online.replan_patience must be an integer >= 0"):
            OnlineConfig(replan_patience=bad)
    with pytest.raises(ValueError, match="brake_steer"):
        OnlineConfig(brake_steer=(2.0,))
    for bad in (-0.1, 1.5, math.nan, True):
        with pytest.raises(ValueError, match="online.rescue_p_coll must be a probability"):
            OnlineConfig(rescue_p_coll=bad)


# ------------------------------------------------------------------------------------------ with a planner
@pytest.fixture(scope="module")
def setup():
    from density_planner.control.registry import load_controller, model_set_for_scene
    from density_planner.density.registry import load_predictor
    from density_planner.environment.random_scene import RandomSceneConfig, random_scene

    torch.set_num_threads(1)
    models = model_set_for_scene("random", None)
    car = KinematicCar(models.car)
    ctrl = load_controller("c3m", models=models)
    pred = load_predictor(None, car, ctrl)
    scene = random_scene(2, RandomSceneConfig(n_slices=141))
    problem = PlanningProblem.from_scene(scene, seed=0, system=car)
    planner = DensityPlanner(pred, DensityPlannerConfig(n_candidates=10, epochs_init=10, epochs_density=5,
                                                        n_samples=50, evaluation_samples=50))
    plan = planner.plan(problem)
    assert plan.ok
    return car, ctrl, scene, problem, planner, plan


def _replan_problem(problem, scene, state, t):
    from density_planner.environment.prediction import OraclePrediction

    mean = state.to(torch.float64).clone()
    mean[-1] = problem.initial_distribution.mean[-1]
    sc = OraclePrediction(scene).scene_at(t, problem.parameterization.horizon, start=problem.system.pose(state))
    return PlanningProblem(sc, recentred(problem.initial_distribution, mean), problem.system,
                           problem.parameterization, problem.risk)


def test_warm_start_from_the_planned_state_returns_the_shifted_plan(setup):
    car, _, scene, problem, planner, plan = setup
    t = 1.0  # one whole segment: the shifted plan continues the previous reference exactly
    state = plan.reference.x_plan[10]
    prob = _replan_problem(problem, scene, state, t)
    warm = shift_parameters(plan.params.double(), t, 1.0)
    res, used = warm_replan(planner, prob, warm, epochs=1, samples=50)  # one evaluation, no update
    assert used and res.ok
    torch.testing.assert_close(res.params.double(), warm, atol=1e-6, rtol=0)
    # the new reference is the previous one from t on (float32 Euler rollouts from the same state)
    torch.testing.assert_close(res.reference.x_plan[:91], plan.reference.x_plan[10:], atol=1e-4, rtol=0)
    # a few Adam steps move each parameter by at most update_clip per step and never raise the cost (keep_best)
    res3, _ = warm_replan(planner, prob, warm, epochs=4, samples=50)
    assert float((res3.params.double() - warm).abs().max()) <= 3 * planner.config.update_clip + 1e-6
    assert res3.cost_history["stage2"]["total"][0] == pytest.approx(res.cost_history["stage2"]["total"][0])


class _FailingPlanner(DensityPlanner):
    """Plans normally offline, but every replan's stage 2 raises."""

    def refine(self, *args, **kwargs):
        raise RuntimeError("injected failure")


def test_replan_patience_stops_a_replan_that_makes_no_progress(setup):
    """With ``patience`` a replan is the prefix of the full replan (the same samples and steps) that ends once its
    best objective has not fallen by the tolerance for ``patience`` iterations; without, all ``epochs`` run."""
    car, _, scene, problem, planner, plan = setup
    prob = _replan_problem(problem, scene, plan.reference.x_plan[10], 1.0)
    warm = shift_parameters(plan.params.double(), 1.0, 1.0)
    full, _ = warm_replan(planner, prob, warm, epochs=10, samples=50, seed=4)
    totals = full.cost_history["stage2"]["total"]
    assert full.iterations["stage2"] == len(totals) == 10
    cfg = planner.config
    for patience in (1, 2, 3):
        short, _ = warm_replan(planner, prob, warm, epochs=10, samples=50, seed=4, patience=patience)
        n = short.iterations["stage2"]
        assert n == len(short.cost_history["stage2"]["total"])
        assert short.cost_history["stage2"]["total"] == totals[:n]  # a prefix of the full replan
        # the rule (DensityPlannerConfig.patience): progress is a cost below the last progress's by the relative
        # tolerance plus the backtracking slack; the replan stops `patience` iterations after the last progress
        progress_at, progress_cost, stop = 0, totals[0], 10
        for k in range(1, 10):
            if totals[k] < progress_cost - cfg.patience_tolerance * abs(progress_cost) - cfg.backtrack_slack:
                progress_at, progress_cost = k, totals[k]
            if k - progress_at >= patience:
                stop = k + 1
                break
        assert n == stop
    # from the full replan's best iterate (nearly converged, the same scene) it stops early
    stalled, _ = warm_replan(planner, prob, full.params.double(), epochs=10, samples=50, seed=4, patience=2)
    assert stalled.iterations["stage2"] < 10


def test_failed_replans_fall_back_and_are_recorded(setup):
    car, ctrl, scene, problem, planner, plan = setup
    failing = _FailingPlanner(planner.predictor, planner.config)
    cfg = OnlineConfig(duration=2.0, period=0.5, replan_epochs=1, replan_samples=20, unsafe_p_coll=1.0)
    res = drive(scene, failing, ctrl, system=car, config=cfg, initial_plan=plan, distribution_seed=0)
    replans = [r for r in res.replans if r.status != "initial"]
    assert len(replans) == 3  # at 0.5, 1.0, 1.5 s
    for r in replans:
        assert r.status == "failed" and r.fallback == "previous"
        assert "injected failure" in r.reason
    # with the previous reference kept throughout, the executed run equals tracking the offline plan
    assert res.states.shape == (21, car.nx)
    # the figure data are copies: a view would keep each replan's whole window grid alive (a grid per replan)
    assert len(res.snapshots) == 4
    for snap in res.snapshots:
        for key in ("occupancy", "swept"):
            assert snap[key].flags["OWNDATA"], key
    # unsafe threshold 0: every kept reference is judged unsafe; braking replaces it only where it is safer
    cfg0 = dataclasses.replace(cfg, unsafe_p_coll=0.0)
    res0 = drive(scene, failing, ctrl, system=car, config=cfg0, initial_plan=plan, distribution_seed=0)
    for r in res0.replans[1:]:
        assert r.fallback in ("brake", "previous")
        if r.fallback == "brake":
            assert "least-risk braking" in r.reason
            b = float(r.reason.rsplit("P_coll ", 1)[1].rstrip(")"))
            assert b < r.previous_p_coll
        elif r.previous_p_coll > 0:
            assert "no safer" in r.reason
    # a reference that has ended is always replaced by braking: drive past the 10-s plan
    long = dataclasses.replace(cfg, duration=10.5, unsafe_p_coll=1.0)
    res_end = drive(scene, failing, ctrl, system=car, config=long, initial_plan=plan, keep_snapshots=False)
    last = res_end.replans[-1]
    assert last.t == pytest.approx(10.0) and last.fallback == "brake" and "ended" in last.reason
    assert res_end.states.shape[0] == 106 and res_end.states[-1, 3] < res_end.states[100, 3] - 0.5  # it brakes


def test_overrunning_replans_are_discarded_used_or_delayed(setup):
    car, ctrl, scene, problem, planner, plan = setup
    cfg = OnlineConfig(duration=1.0, period=0.5, replan_epochs=1, replan_samples=20, time_budget=1e-9,
                       unsafe_p_coll=1.0, overrun="discard")
    res = drive(scene, planner, ctrl, system=car, config=cfg, initial_plan=plan)
    r = res.replans[1]
    assert r.status == "overrun" and r.fallback == "previous" and "time_budget" in r.reason
    assert math.isnan(r.t_effective) and res.replans[0].t_effective == 0.0
    # "use": the overrun is recorded and the plan tracked from its measurement time
    res2 = drive(scene, planner, ctrl, system=car, config=dataclasses.replace(cfg, overrun="use"),
                 initial_plan=plan)
    assert res2.replans[1].status == "overrun" and res2.replans[1].fallback is None
    assert res2.replans[1].t_effective == pytest.approx(0.5)
    # "delay" (default): tracked from the first planning step after it finished, the previous reference meanwhile
    # (the discarded run's states up to then), and no replan starts while one runs
    long = dataclasses.replace(cfg, duration=4.0)
    discard = drive(scene, planner, ctrl, system=car, config=long, initial_plan=plan, keep_snapshots=False)
    delay = drive(scene, planner, ctrl, system=car, config=dataclasses.replace(long, overrun="delay"),
                  initial_plan=plan, keep_snapshots=False)
    assert OnlineConfig().overrun == "delay"
    ran = delay.replans[1:]
    assert ran and all(r.status == "overrun" and r.fallback is None and "online.overrun" in r.reason for r in ran)
    first = ran[0]
    assert first.t == pytest.approx(0.5)
    lag = max(1, math.ceil(first.wall_time / 0.1 - 1e-9))
    if 5 + lag < delay.states.shape[0]:
        assert first.t_effective == pytest.approx(0.5 + 0.1 * lag)
        k = 5 + lag
        np.testing.assert_array_equal(delay.states[: k + 1], discard.states[: k + 1])
    for prev, nxt in zip(ran, ran[1:]):
        assert nxt.t >= prev.t_effective - 1e-9 and math.isfinite(prev.t_effective)
    with pytest.raises(ValueError, match="online.overrun must be one of"):
        OnlineConfig(overrun="late")


def test_drive_end_to_end_on_a_random_scene(setup, tmp_path):
    car, ctrl, scene, problem, planner, plan = setup
    cfg = OnlineConfig(duration=3.0, period=0.5, replan_epochs=2, replan_samples=30, overrun="use")
    res = drive(scene, planner, ctrl, system=car, config=cfg, initial_plan=plan)
    assert res.states.shape == (31, car.nx) and res.inputs.shape == (30, car.nu)
    np.testing.assert_allclose(res.times, 0.1 * np.arange(31), atol=1e-9)
    assert [round(r.t, 6) for r in res.replans] == [0.0, 0.5, 1.0, 1.5, 2.0, 2.5]
    assert all(r.warm_start for r in res.replans[1:])
    # the best iterate is never worse than the warm start (stage 2 keeps the best; the warm start is iterate 0)
    assert all(0.0 <= r.cost_reduction <= 1.0 for r in res.replans[1:])
    summ = res.summary()
    assert summ["replans_improved"] == pytest.approx(np.mean([r.cost_reduction > 0 for r in res.replans[1:]]))
    # the warm replans' own times leave out those that ran a rescue (stage 1)
    warm = [r.wall_time for r in res.replans[1:] if r.warm_start and r.rescue is None]
    assert summ["n_warm_replans"] == len(warm) == summ["n_replans"] - sum(summ["rescues"].values())
    assert summ["warm_replan_wall_time_median"] == (pytest.approx(float(np.median(warm))) if warm else None)
    # the executed run's risk on the scene's own occupancy: the collision model on its states, max over time
    from density_planner.risk.collision import CollisionModel

    slices = scene.grid.slices_for(0.0, 0.1, res.states.shape[0])
    direct = CollisionModel(scene.grid, car, problem.risk).probability(
        torch.as_tensor(res.states, dtype=scene.grid.probs.dtype)[None], slices)
    assert summ["p_coll_executed"] == pytest.approx(float(direct.max), abs=1e-6)
    assert 0.0 <= summ["p_coll_executed"] <= 1.0
    assert res.verdict is not None and res.verdict.basis == "occupancy"
    assert np.isfinite(res.states).all()
    # the true initial state is a draw from the initial law, and deterministic given online.seed
    assert np.isfinite(float(problem.initial_distribution.log_prob(torch.as_tensor(res.true_initial_state)[None])))
    res_b = drive(scene, planner, ctrl, system=car, config=cfg, initial_plan=plan)
    np.testing.assert_array_equal(res.states, res_b.states)
    text = json.dumps(res.summary(), allow_nan=False)
    assert '"replans"' in text
    from density_planner.viz.online import animate_run, plot_run

    assert plot_run(scene, res, tmp_path / "run.png").stat().st_size > 10_000
    assert animate_run(scene, res, tmp_path / "run.gif").stat().st_size > 1_000
    assert math.isfinite(res.controller_step_time)


def test_replan_horizons_end_with_the_first_plan_on_random_scenes(setup):
    """A random scene's goal is to be reached at the end of the first plan (its goal cost is at its end); with
    ``shrink_horizon`` every replan plans to that time, however long the run (at least one segment), without it the
    full horizon from its own time."""
    car, ctrl, scene, problem, planner, plan = setup
    cfg = OnlineConfig(duration=3.0, period=1.0, replan_epochs=1, replan_samples=20, overrun="use")
    short = drive(scene, planner, ctrl, system=car, config=cfg, initial_plan=plan, keep_snapshots=True)
    full = drive(scene, planner, ctrl, system=car, config=dataclasses.replace(cfg, shrink_horizon=False),
                 initial_plan=plan, keep_snapshots=True)
    assert [round(r.t, 6) for r in short.replans] == [0.0, 1.0, 2.0]
    assert all(r.warm_start and r.status == "success" for r in short.replans[1:])
    # planning points: 10 per 1-s segment, plus the start; the first plan ends at 10 s
    assert [len(s["plan"]) for s in short.snapshots] == [101, 91, 81]
    assert [len(s["plan"]) for s in full.snapshots] == [101, 101, 101]
    # past the first plan's end: one segment
    from density_planner.evaluation.online import _replan_parameterization

    assert _replan_parameterization(problem.parameterization, 10.0, 11.5, True).n_segments == 1


def test_warm_replans_continue_the_previous_reference(setup):
    """A warm replan starts its reference at the previous reference's state at the replanning time (the controller
    goes on along the same path); with ``continue_reference = false`` at the measurement."""
    car, ctrl, scene, problem, planner, plan = setup
    true = plan.reference.x_plan[0].double().clone()
    true[1] += 0.4  # a true start 0.4 m beside the reference: the tracking error is still > 0.05 m at 0.5 s
    cfg = OnlineConfig(duration=1.0, period=0.5, replan_epochs=1, replan_samples=20, overrun="use")
    on = drive(scene, planner, ctrl, system=car, config=cfg, initial_plan=plan, true_state=true)
    off = drive(scene, planner, ctrl, system=car, config=dataclasses.replace(cfg, continue_reference=False),
                initial_plan=plan, true_state=true)
    assert on.replans[1].warm_start and off.replans[1].warm_start
    old = plan.reference.x_plan[5, :2].double().numpy()  # the previous reference at t = 0.5 s
    measured = on.states[5, :2]
    assert np.linalg.norm(measured - old) > 0.05
    np.testing.assert_allclose(on.snapshots[1]["plan"][0], old, atol=1e-4)
    np.testing.assert_allclose(off.snapshots[1]["plan"][0], measured, atol=1e-4)


def test_torch_free_controller_loop_matches_the_torch_loop(setup):
    car, ctrl, scene, problem, planner, plan = setup
    failing = _FailingPlanner(planner.predictor, planner.config)  # no replans: both track the offline plan
    cfg = OnlineConfig(duration=3.0, replan_epochs=1, replan_samples=20, unsafe_p_coll=1.0)
    fast = drive(scene, failing, ctrl, system=car, config=cfg, initial_plan=plan, keep_snapshots=False)
    slow = drive(scene, failing, ctrl, system=car, config=dataclasses.replace(cfg, fast_controller=False),
                 initial_plan=plan, keep_snapshots=False)
    # float64 numpy vs float32 torch Euler over 300 steps: round-off only
    np.testing.assert_allclose(fast.states, slow.states, atol=2e-3, rtol=0)
    np.testing.assert_allclose(fast.inputs, slow.inputs, atol=2e-3, rtol=0)


def test_online_planner_executes_in_receding_mode(setup):
    from density_planner.evaluation.simulate import ExecutionMode, execute, execution_mode
    from density_planner.planners.registry import PlannerContext, make_planner
    from density_planner.settings import RunConfig

    car, ctrl, scene, problem, planner, plan = setup
    cfg = RunConfig(density_planner=planner.config,
                    online=OnlineConfig(duration=1.0, period=0.5, replan_epochs=1, replan_samples=20,
                                                        overrun="use"))
    ctx = PlannerContext(system=car, controller=ctrl, config=cfg, predictor_factory=lambda: planner.predictor)
    online = make_planner("density_online", ctx)
    assert execution_mode(online) == ExecutionMode.RECEDING
    x0 = problem.initial_distribution.sample(1, torch.Generator().manual_seed(0))[0]
    run = execute(online, problem, x0)
    assert run.ok and run.states.shape == (11, car.nx) and run.applied_inputs.shape == (10, car.nu)
    assert run.step_times.shape == (10,) and float(run.step_times[5]) > float(run.step_times[4])  # replan at 0.5 s
    torch.testing.assert_close(run.states[0], x0.to(run.states.dtype))
    assert run.plan.extras["prediction"] == "oracle" and len(run.plan.extras["replans"]) == 2


def _full_cost(planner, problem, params):
    """Stage 1's selection objective (every term on) of parameters ``(K, nu, S)``."""
    from density_planner.control.reference import plan_grid_reference
    from density_planner.cost.composite import build_cost
    from density_planner.cost.terms import CostInputs

    objective = build_cost(problem.scene, planner.config.cost, optimisation=True, system=problem.system,
                           risk=problem.risk)
    start = problem.reference_start(planner.dtype, planner.device)
    x_plan, u_plan = plan_grid_reference(problem.system, start, params.to(planner.dtype), problem.parameterization)
    with torch.no_grad():
        return objective(CostInputs.single(x_plan, u_plan, planner._slices(problem))).total


def test_stage1_extra_seeds_compete_with_fresh_candidates(setup):
    """An extra seed is a stage-1 candidate: the chosen parameters never cost more than it (every term on)."""
    car, _, scene, problem, planner, plan = setup
    good = plan.params.detach()[None]
    chosen, history, _ = planner.initialise(problem, torch.Generator().manual_seed(5), extra_seeds=good)
    assert float(_full_cost(planner, problem, chosen[None])[0]) <= float(_full_cost(planner, problem, good)[0]) + 1e-6
    assert history["seed_candidates"] == [1.0]
    with pytest.raises(RuntimeError):  # a seed of the wrong shape is refused, not broadcast
        planner.initialise(problem, torch.Generator().manual_seed(5), extra_seeds=torch.zeros(1, 3))


def test_rescue_replaces_a_risky_warm_replan_by_a_better_one(setup):
    """A warm start that drives into an obstacle: ten small steps keep its risk; the rescue (stage 1 with the warm
    start among its candidates, then the same stage 2 on the same samples) finds a lower objective and is used."""
    car, _, scene, problem, planner, plan = setup
    t = 1.0
    state = plan.reference.x_plan[10]
    prob = _replan_problem(problem, scene, state, t)
    # the riskiest of a few constant-input warm starts (full steering to one side, accelerating)
    cands = [torch.stack([torch.full((10,), s), torch.full((10,), a)]).double()
             for s in (-1.0, 0.0, 1.0) for a in (0.0, 2.0)]
    tried = [(warm_replan(planner, prob, w, epochs=2, samples=50, seed=3)[0], w) for w in cands]
    res, warm = max(tried, key=lambda rw: float(rw[0].collision.max))
    assert float(res.collision.max) > 0.5  # the scene must offer a risky warm start for this test to mean anything
    cfg = OnlineConfig(replan_epochs=2, replan_samples=50, rescue_p_coll=0.5)
    from density_planner.evaluation.online import Replan

    rec = Replan(t, "success", 0.0)
    out = _rescue(planner, prob, warm, res, rec, cfg, seed=3)
    assert rec.rescue == "used" and out is not res
    assert best_objective(out) < best_objective(res)
    assert rec.rescue_p_coll == pytest.approx(float(out.collision.max))
    assert float(out.collision.max) < float(res.collision.max)
    # the same stage-2 samples: a rescue's stage 1 draws from a generator of its own
    again, _ = warm_replan(planner, prob, warm, epochs=2, samples=50, seed=3)
    assert again.cost_history["stage2"]["total"] == res.cost_history["stage2"]["total"]


def test_drive_records_rescues(setup, tmp_path):
    car, ctrl, scene, problem, planner, plan = setup
    cfg = OnlineConfig(duration=2.0, period=0.5, replan_epochs=2, replan_samples=30, overrun="use",
                       rescue_p_coll=0.0)  # every warm replan is rescued
    res = drive(scene, planner, ctrl, system=car, config=cfg, initial_plan=plan)
    warm = [r for r in res.replans[1:] if r.warm_start]
    assert warm and all(r.rescue in ("used", "kept") and math.isfinite(r.rescue_p_coll) for r in warm)
    for r in warm:
        if r.rescue == "used":
            assert r.p_coll == pytest.approx(r.rescue_p_coll)
    summ = res.summary()
    assert summ["rescues"]["used"] + summ["rescues"]["kept"] == len(warm)
    from density_planner.viz.online import plot_run

    assert plot_run(scene, res, tmp_path / "run.png", n_panels=2).stat().st_size > 10_000  # a rescue among panels
    never = drive(scene, planner, ctrl, system=car, config=dataclasses.replace(cfg, rescue_p_coll=1.0),
                  initial_plan=plan, keep_snapshots=False)
    assert all(r.rescue is None and math.isnan(r.rescue_p_coll) for r in never.replans)


def test_executed_p_coll_reads_the_scene_occupancy_along_the_path(setup):
    """Standing in a free cell: 0; standing on an occupied one (all of the vehicle's body inside a blob): ~1."""
    from density_planner.evaluation.online import executed_p_coll

    car, _, scene, problem, planner, plan = setup
    probs = scene.grid.probs[0]
    free = torch.nonzero(probs < 1e-6)
    occ = torch.nonzero(probs > 0.99)
    assert free.shape[0] and occ.shape[0]

    def standing(ij):
        xy = torch.tensor(scene.grid.origin, dtype=torch.float64) + (ij.double() + 0.5) * scene.grid.cell_size
        x = torch.zeros(11, car.nx, dtype=torch.float64)
        x[:, :2] = xy
        return x

    # a cell whose neighbourhood is free / occupied over the next second (the body covers a few cells)
    def pick(idx, value):
        for ij in idx[torch.randperm(idx.shape[0], generator=torch.Generator().manual_seed(0))[:200]]:
            i, j = int(ij[0]), int(ij[1])
            window = scene.grid.probs[:11, max(i - 40, 0):i + 41, max(j - 40, 0):j + 41]
            if (value == 0 and float(window.max()) < 1e-6) or (value == 1 and float(window.min()) > 0.99):
                return ij
        pytest.skip("no such neighbourhood on this scene")

    assert executed_p_coll(scene, car, problem.risk, standing(pick(free, 0)), 0.1) == pytest.approx(0.0, abs=1e-6)
    assert executed_p_coll(scene, car, problem.risk, standing(pick(occ, 1)), 0.1) > 0.95


def test_executed_p_coll_reads_the_road_edge_as_the_planners_do():
    """On a road scene the off-road cells are the road barrier's, not obstacles (``risk.road_edge = "barrier"``):
    the executed risk equals the planning problem's collision model on the same trajectory."""
    from pathlib import Path

    from density_planner.environment.commonroad import load_commonroad_scene
    from density_planner.evaluation.online import executed_p_coll
    from density_planner.risk.collision import RiskConfig

    data = Path(__file__).resolve().parents[2] / "src" / "density_planner" / "data" / "commonroad"
    scene = load_commonroad_scene(data / "USA_Lanker-1_1_T-1.xml")
    car = KinematicCar()
    problem = PlanningProblem.from_scene(scene, seed=0, system=car)
    x = torch.zeros(11, car.nx, dtype=torch.float64)
    x[:, :3] = torch.tensor(scene.start[:3], dtype=torch.float64)
    x[:, 0] += 6.0  # 6 m east of the start: off the road, clear of the road users
    slices = scene.grid.slices_for(float(scene.t_start), 0.1, 11)
    xs = x.to(scene.grid.probs.dtype)
    expected = float(problem.collision().probability(xs[None], slices).max)
    assert executed_p_coll(scene, car, problem.risk, x, 0.1) == pytest.approx(expected, abs=1e-6)
    occupied = float(problem.collision(road_edge="occupied").probability(xs[None], slices).max)
    edge_occupied = executed_p_coll(scene, car, RiskConfig(road_edge="occupied"), x, 0.1)
    assert edge_occupied == pytest.approx(occupied, abs=1e-6)
    assert expected < 0.05 and occupied > 0.99  # the road's edge is not an obstacle

"""MPC baselines M0 and M1-M3 (CasADi/IPOPT): built once, parameterised occupancy windows, closed-loop behaviour."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from baseline_scenes import GOAL, block_clearance, block_scene, small_empty, wall_scene

from density_planner.environment.grid import OccupancyGrid
from density_planner.environment.scene import Scene
from density_planner.planners.base import PlanStatus
from density_planner.planners.problem import PlanningProblem
from density_planner.risk import RiskConfig

pytest.importorskip("casadi", reason="the MPC baselines need the optional 'mpc' extra (casadi)")

from density_planner.planners.mpc import MPCConfig, MPCPlanner, tube_offsets  # noqa: E402


def _problem(scene: Scene, risk: RiskConfig | None = None) -> PlanningProblem:
    return PlanningProblem.from_scene(scene, seed=0, risk=risk)


def _cfg(**kwargs) -> MPCConfig:
    """MPC settings with a deterministic iteration limit only: IPOPT's CPU-time cap (0.1 s per step, the paper's
    setting) makes the iterates depend on the machine's load, so the tests never use it (conftest.py checks)."""
    return MPCConfig(**{"max_cpu_time": math.inf, **kwargs})


@pytest.fixture(scope="module")
def m0() -> MPCPlanner:
    return MPCPlanner(_cfg())


@pytest.fixture(scope="module")
def empty_run(m0):
    scene = small_empty()
    return scene, m0.plan(_problem(scene))


@pytest.fixture(scope="module")
def block_run(m0, empty_run):
    """M0's closed loop on the block scene by the module's planner, after its run on the empty scene (the NLP of
    that cell size serves both). ``reset`` forgets the warm start, so this is the plan of a fresh planner with the
    default settings (``max_iter = 300``, no tube); the run is shared by two tests (~25 s)."""
    return m0.plan(_problem(block_scene()))


def _occupancy_along(scene: Scene, states: torch.Tensor) -> torch.Tensor:
    k = scene.grid.slice_index(torch.arange(states.shape[0], dtype=torch.float64) * 0.1)
    return scene.grid.lookup(states[:, :2].double(), k)


def test_empty_scene_reaches_goal(empty_run):
    scene, res = empty_run
    assert res.status == PlanStatus.SUCCESS
    # the closed loop stops once within goal_stop_distance = 1 m of the goal (14 m away, ~4 s at <= 10 m/s)
    dist = float(torch.linalg.norm(res.states[-1, :2] - torch.tensor(GOAL)))
    assert dist < 1.0
    assert res.states.shape[0] < 101 and res.states.shape[1] == 5
    assert res.extras["n_failed_steps"] == 0
    assert res.collision is not None and float(res.collision.max) == 0.0
    assert set(res.cost) == {"goal", "input", "bounds", "collision", "total"}
    assert {"nlp_build", "tube_precompute", "online", "total"} <= set(res.timings)
    steps = len(res.extras["step_times"])
    assert steps == res.states.shape[0] - 1 == len(res.extras["step_status"])
    # every applied input respects the bounds
    assert np.abs(np.asarray(res.extras["applied_inputs"])).max() <= 3.0 + 1e-9


def test_tube_mpc_on_an_empty_scene_reaches_goal():
    scene = small_empty()
    res = MPCPlanner(_cfg(tube_radius=0.5, max_iter=10)).plan(_problem(scene))
    assert res.status == PlanStatus.SUCCESS
    assert float(torch.linalg.norm(res.states[-1, :2] - torch.tensor(GOAL))) < 1.0
    assert res.extras["tube_precomputed"] and res.extras["n_tube_offsets"] == 81


def test_wall_stops_short_without_entering():
    scene = wall_scene()  # P = 1 for y in [-2, 0], ramp to 0 at y = -3
    res = MPCPlanner(_cfg()).plan(_problem(scene))
    assert res.status == PlanStatus.SUCCESS
    occ = _occupancy_along(scene, res.states)
    # never inside the wall (P = 1 on the plateau): the whole run stays on the low part of the ramp
    assert float(occ.max()) < 0.5
    assert float(res.states[:, 1].max()) < -2.0
    # it does stop (the goal is unreachable): final speed close to zero
    assert float(res.states[-1, 3]) < 0.5


def test_goes_around_a_block_and_larger_tubes_keep_more_clearance(block_run):
    scene = block_scene()
    clear = {}
    for radius in (0.0, 0.3, 1.0):
        # M0 (no tube, max_iter 300): the shared run of the default planner
        res = block_run if radius == 0 else MPCPlanner(_cfg(tube_radius=radius, max_iter=10)).plan(_problem(scene))
        assert res.status == PlanStatus.SUCCESS, res.message
        clear[radius] = block_clearance(res.states)
        assert float(torch.linalg.norm(res.states[-1, :2] - torch.tensor(GOAL))) < 1.0
    # measured 1.02 / 1.29 / 2.00 m; the ordering is what the tube is for, margins of 0.1 m against noise
    assert clear[0.0] > 0.5
    assert clear[0.3] > clear[0.0] + 0.1
    assert clear[1.0] > clear[0.3] + 0.1


def test_nlp_is_built_once_and_steps_do_not_rebuild(m0, empty_run, block_run):
    builds = m0.n_builds
    assert builds == 1
    # a whole run on another scene with the same cell size: no new construction
    assert block_run.status == PlanStatus.SUCCESS
    assert block_run.extras["n_builds"] == builds and block_run.timings["nlp_build"] == 0.0
    # a different scene with the same cell size and a few manual steps: no new construction
    problem = _problem(block_scene())
    m0.reset(problem)
    state = problem.reference_start(torch.float64)[:4].numpy()
    for h in range(3):
        step = m0.solve(state, h)
        assert step.predicted.shape == (11, 4) and step.predicted_inputs.shape == (10, 2)
        assert step.step_time >= step.solve_time > 0
        # with the car's body (4 discs) IPOPT may also stop on its iteration limit in this scene's first steps
        assert step.status in ("Solve_Succeeded", "Solved_To_Acceptable_Level", "Maximum_Iterations_Exceeded")
        state = step.predicted[1]
    assert m0.n_builds == builds


def _field_scene() -> Scene:
    """Smooth time-varying occupancy everywhere (so that every window entry matters)."""
    scene = small_empty()
    g = scene.grid
    t = torch.arange(g.n_slices, dtype=torch.float32)[:, None, None] * 0.1
    x, y = g.xs.float()[None, :, None], g.ys.float()[None, None, :]
    probs = 0.5 + 0.4 * torch.sin(0.7 * x + 0.3 * t) * torch.cos(0.45 * y - 0.2 * t)
    return Scene(g.with_probs(probs), scene.start, scene.goal, scene.planning_box, name="field")


@pytest.mark.parametrize("radius,method", [(0.0, "auto"), (0.3, "precomputed"), (0.3, "offsets")])
def test_nlp_collision_term_matches_the_grid(radius, method):
    """The NLP's objective at its solution equals J_MPC recomputed with the grid's own bilinear lookup: the
    windows, their memory layout, the slice times and the tube sums are right."""
    scene = _field_scene()
    problem = _problem(scene)
    cfg = MPCConfig(tube_radius=radius, tube_method=method, max_iter=30, max_cpu_time=math.inf)
    mpc = MPCPlanner(cfg)
    mpc.reset(problem)
    state = np.array([0.3, -4.0, 1.2, 4.0])
    step_index = 7
    step = mpc.solve(state, step_index)
    xs = torch.as_tensor(step.predicted, dtype=torch.float64)
    us = torch.as_tensor(step.predicted_inputs, dtype=torch.float64)
    k = scene.grid.slice_index((step_index + torch.arange(1, 11, dtype=torch.float64)) * 0.1)
    d = torch.as_tensor(tube_offsets(radius, 0.1))
    model = problem.collision()  # the body: disc centres on the disc-dilated grid
    c = model.centres(xs[1:])  # (10, m, 2)
    s_k = model.body_grid.lookup(c[:, :, None, :] + d[None, None], k[:, None, None]).sum(dim=(-1, -2))
    w = mpc.weights
    growth = (step_index / 100) ** 2
    goal = w.goal * growth * float((xs[-1, :2] - torch.tensor(scene.goal, dtype=torch.float64)).pow(2).sum())
    expected = goal + w.input * float(us.pow(2).sum()) + w.collision * float(s_k.pow(2).sum())
    # float32 occupancy values: relative 1e-5
    assert step.objective == pytest.approx(expected, rel=1e-5, abs=1e-9)


def test_precomputed_and_offset_tubes_give_the_same_step():
    scene = _field_scene()
    # a point vehicle: this checks the tube mechanism (with the 4.5-m car in this dense field IPOPT needs more
    # than 300 iterations for either method)
    problem = _problem(scene, RiskConfig(body=False))
    out = {}
    for method in ("precomputed", "offsets"):
        mpc = MPCPlanner(MPCConfig(tube_radius=0.3, tube_method=method, max_iter=100, max_cpu_time=math.inf))
        mpc.reset(problem)
        out[method] = mpc.solve(np.array([0.3, -4.0, 1.2, 4.0]), 3)
    a, b = out["precomputed"], out["offsets"]
    assert a.success and b.success
    # the same NLP up to float rounding of the summed occupancy: same optimum
    assert a.objective == pytest.approx(b.objective, rel=1e-4)
    np.testing.assert_allclose(a.predicted, b.predicted, atol=1e-3)


def test_solver_limits_are_reported_not_raised():
    scene = block_scene()
    res = MPCPlanner(_cfg(max_iter=1, n_steps=5)).plan(_problem(scene))
    assert res.status == PlanStatus.SUCCESS  # the loop ran; every step applied its last iterate
    assert res.extras["n_failed_steps"] == 5
    assert res.extras["step_status_counts"] == {"Maximum_Iterations_Exceeded": 5}
    assert "did not converge" in res.message
    assert res.states.shape == (6, 5) and torch.isfinite(res.states).all()


def test_errors_become_status():
    from density_planner.density.distributions import UniformBox
    from density_planner.systems.base import System
    from density_planner.systems.linear import LinearSystem

    class NoSymbolic(LinearSystem):
        f_symbolic = System.f_symbolic

    scene = small_empty()
    system = NoSymbolic(torch.zeros(5, 5), torch.zeros(5, 2))
    problem = PlanningProblem(scene, UniformBox(torch.zeros(5) - 1, torch.zeros(5) + 1), system=system)
    res = MPCPlanner(_cfg()).plan(problem)
    assert res.status == PlanStatus.ERROR and "NoSymbolic has no symbolic dynamics" in res.message


def test_biased_measurement_changes_the_run():
    scene = block_scene()
    problem = _problem(scene)
    true_state = problem.reference_start(torch.float64).clone()
    true_state[4] = math.pi / 16  # heading bias of the measurement
    plain = MPCPlanner(_cfg(n_steps=6)).plan_from(problem, true_state)
    biased = MPCPlanner(_cfg(n_steps=6, biased_measurement=True)).plan_from(problem, true_state)
    assert plain.status == biased.status == PlanStatus.SUCCESS
    assert not torch.allclose(plain.states, biased.states)
    # the true state keeps its bias; the MPC only sees it in the heading
    assert float(biased.states[-1, 4]) == pytest.approx(math.pi / 16)


def test_large_maps_use_the_same_windows():
    """A 60 m x 50 m map at 0.2 m: same parameter count as a small map of that cell size, no rebuild."""
    big = OccupancyGrid(torch.zeros(101, 301, 251), origin=(-30.0, -20.0), cell_size=0.2)
    small = OccupancyGrid(torch.zeros(101, 61, 101), origin=(-6.0, -10.0), cell_size=0.2)
    start, goal = (0.0, -8.0, math.pi / 2, 3.0), (0.0, 6.0)
    mpc = MPCPlanner(_cfg(n_steps=3))
    for grid in (small, big):
        res = mpc.plan(_problem(Scene(grid, start, goal, (-5.0, 5.0, -9.0, 9.0))))
        assert res.status == PlanStatus.SUCCESS
    assert mpc.n_builds == 1


@pytest.mark.parametrize("kwargs", [{"horizon": 0}, {"stage_dt": 0.0}, {"tube_radius": -0.1}, {"max_iter": 0},
                                    {"max_cpu_time": 0.0}, {"max_cpu_time": None}, {"hessian": "bfgs"},
                                    {"tube_method": "fft"}])
def test_bad_config(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        MPCConfig(**kwargs)


def test_cpu_time_cap_defaults():
    """M0 keeps the paper's real-time budget (0.1 s per step); the tube MPCs stop on their 10 iterations only; an
    infinite cap is not passed to IPOPT, and ``inf`` is how TOML (``--set mpc.max_cpu_time=inf``) turns it off."""
    from density_planner.config import apply_overrides, dumps_toml
    from density_planner.planners._nlp import ipopt_options
    from density_planner.planners.mpc import TubeMPCConfig
    from density_planner.settings import RunConfig

    assert MPCConfig().max_cpu_time == 0.1 and MPCConfig().max_iter == 300
    assert TubeMPCConfig().max_cpu_time == math.inf and TubeMPCConfig().max_iter == 10
    assert "max_cpu_time" not in ipopt_options(max_iter=10, max_cpu_time=math.inf)["ipopt"]
    assert ipopt_options(max_iter=10, max_cpu_time=0.1)["ipopt"]["max_cpu_time"] == 0.1
    cfg = apply_overrides(RunConfig(), ["mpc.max_cpu_time=inf"])
    assert cfg.mpc.max_cpu_time == math.inf
    assert "max_cpu_time = inf" in dumps_toml(cfg)

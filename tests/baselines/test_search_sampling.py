"""Search- and sampling-based optimisers (ablation baselines): reach goals, respect the time limit, batch the
density predictions, deterministic per seed. No test reads the wall clock: the time limit is either infinite or
checked against a fake clock (speed is measured in benchmarks/)."""

from __future__ import annotations

import math

import pytest
import torch
from baseline_scenes import corridor_empty, wall_scene

from density_planner.control.analytic import CarTrackingController
from density_planner.density.base import DensityPredictor
from density_planner.density.liouville import ExactLiouville
from density_planner.planners.base import PlanStatus
from density_planner.planners.problem import PlanningProblem
from density_planner.planners.sampling import SamplingConfig, SamplingPlanner
from density_planner.planners.search import SearchConfig, SearchPlanner
from density_planner.systems.car import KinematicCar


class CountingPredictor(DensityPredictor):
    """Exact Liouville, recording the batch size and horizon of every call."""

    name = "counting"

    def __init__(self):
        self.inner = ExactLiouville(KinematicCar(), CarTrackingController())
        self.calls: list[tuple[int, int]] = []

    def predict(self, x0, log_rho0, reference):
        self.calls.append((int(reference.x.shape[0]), int(reference.params.shape[-1])))
        return self.inner.predict(x0, log_rho0, reference)


#: no time limit: a test's outcome cannot depend on the machine's speed or load
NO_LIMIT = math.inf


def _exact() -> ExactLiouville:
    return ExactLiouville(KinematicCar(), CarTrackingController())


@pytest.fixture(scope="module")
def problem() -> PlanningProblem:
    return PlanningProblem.from_scene(corridor_empty(), seed=0)


@pytest.mark.parametrize("planner_cls,config", [(SearchPlanner, SearchConfig(n_samples=20, time_limit=NO_LIMIT)),
                                                (SamplingPlanner, SamplingConfig(n_samples=20, time_limit=NO_LIMIT))])
def test_empty_scene_reaches_goal(problem, planner_cls, config):
    """No time limit (the result cannot depend on the machine's speed): the search ends by finding a plan."""
    res = planner_cls(_exact(), config).plan(problem)
    assert res.status == PlanStatus.SUCCESS, res.message
    # a solution's reference ends within goal_threshold = 3.8 m of the goal
    assert float(torch.linalg.norm(res.states[-1, :2] - torch.tensor(problem.goal))) < 3.8
    assert res.params.shape == (2, 10) and float(res.params.abs().max()) <= 3.0
    assert res.samples.x.shape == (20, 101, 5)
    assert res.cost["bounds"] == 0.0 and res.collision is not None
    assert res.timings["total"] >= res.timings["search"] > 0
    assert res.extras["depth"] == 10


def test_children_are_scored_in_one_batched_call(problem):
    pred = CountingPredictor()
    cfg = SearchConfig(n_samples=20, max_calls=4, horizon="node", time_limit=NO_LIMIT)
    res = SearchPlanner(pred, cfg).plan(problem)
    search_calls = pred.calls[:-1]  # the last call predicts the reported plan
    assert len(search_calls) == res.iterations["predictor_calls"] == res.extras["expansions"] == 4
    # 25 children per call; with the exact predictor only as long as the children (1, 2, ... segments)
    assert all(b == 25 for b, _ in search_calls)
    assert [n for _, n in search_calls] == sorted(n for _, n in search_calls)
    assert search_calls[0][1] == 1
    assert pred.calls[-1] == (1, 10)


def test_short_and_full_prediction_horizons_agree(problem):
    out = {}
    for horizon in ("node", "full"):
        cfg = SearchConfig(n_samples=20, max_calls=3, horizon=horizon, time_limit=NO_LIMIT)
        out[horizon] = SearchPlanner(_exact(), cfg).plan(problem)
    a, b = out["node"], out["full"]
    assert torch.equal(a.params, b.params)
    assert a.extras["path_cost"] == pytest.approx(b.extras["path_cost"], rel=1e-4)


@pytest.mark.parametrize("planner_cls,config_cls", [(SearchPlanner, SearchConfig),
                                                    (SamplingPlanner, SamplingConfig)])
def test_time_limit_is_respected(planner_cls, config_cls, monkeypatch):
    """A wall across the map: no acceptable full plan exists; the planners stop at the limit. The clock is a fake
    one that advances 0.5 s per predictor call (no wall time in tests): with a 2-s limit exactly 4 calls run."""
    import types

    import density_planner.planners._tree as tree

    clock = [0.0]
    monkeypatch.setattr(tree, "time", types.SimpleNamespace(perf_counter=lambda: clock[0]))
    exact = _exact()
    predict = exact.predict

    def ticking(*args, **kwargs):
        clock[0] += 0.5
        return predict(*args, **kwargs)

    monkeypatch.setattr(exact, "predict", ticking)
    problem = PlanningProblem.from_scene(wall_scene(), seed=0)
    res = planner_cls(exact, config_cls(n_samples=30, time_limit=2.0)).plan(problem)
    assert res.status == PlanStatus.TIMEOUT, res.message
    # the fourth call ends at 2.0 s on the fake clock; the reported plan's prediction is the fifth tick
    assert res.iterations["predictor_calls"] == 4
    assert res.timings["search"] == 2.0 and res.timings["total"] == 2.5
    assert "within the limit (2 s, 4 predictor calls)" in res.message
    assert "best partial plan" in res.message


@pytest.mark.parametrize("planner_cls,config",
                         [(SearchPlanner, SearchConfig(n_samples=20, max_calls=5, seed=3, time_limit=NO_LIMIT)),
                          (SamplingPlanner, SamplingConfig(n_samples=20, max_calls=5, seed=3, time_limit=NO_LIMIT))])
def test_deterministic_per_seed(problem, planner_cls, config):
    a = planner_cls(_exact(), config).plan(problem)
    b = planner_cls(_exact(), config).plan(problem)
    assert a.status == b.status
    assert a.params is not None and torch.equal(a.params, b.params)
    assert a.cost == b.cost


def test_nothing_acceptable_is_explained():
    """A car at rest: its samples have v < 0.1 m/s (outside the planning box), so J_B > 0 for every child."""
    from density_planner.environment.scene import Scene

    scene = corridor_empty()
    scene = Scene(scene.grid, (0.0, -28.0, math.pi / 2, 0.01), scene.goal, scene.planning_box)
    cfg = SearchConfig(n_samples=20, time_limit=NO_LIMIT)
    res = SearchPlanner(_exact(), cfg).plan(PlanningProblem.from_scene(scene, seed=0))
    assert res.status == PlanStatus.FAILED and res.states is None
    assert "'bounds' rule" in res.message
    assert res.extras["rejections"]["bounds"] == 25


def test_errors_become_status(problem):
    class Broken(DensityPredictor):
        def predict(self, x0, log_rho0, reference):
            raise RuntimeError("predictor exploded")

    res = SearchPlanner(Broken(), SearchConfig(n_samples=10)).plan(problem)
    assert res.status == PlanStatus.ERROR and "exploded" in res.message


@pytest.mark.parametrize("kwargs", [{"n_samples": 0}, {"time_limit": 0.0}, {"max_calls": 0}, {"choices": ()},
                                    {"horizon": "half"}, {"weighting": "none"}])
def test_bad_search_config(kwargs):
    with pytest.raises(ValueError):
        SearchConfig(**kwargs)


@pytest.mark.parametrize("kwargs", [{"batch_size": 0}, {"init_std": -1.0}, {"new_root_weight": -1.0}])
def test_bad_sampling_config(kwargs):
    with pytest.raises(ValueError):
        SamplingConfig(**kwargs)

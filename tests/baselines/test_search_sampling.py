"""Search- and sampling-based optimisers (ablation baselines): reach goals, respect the time limit, batch the
density predictions, deterministic per seed."""

from __future__ import annotations

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


def _exact() -> ExactLiouville:
    return ExactLiouville(KinematicCar(), CarTrackingController())


@pytest.fixture(scope="module")
def problem() -> PlanningProblem:
    return PlanningProblem.from_scene(corridor_empty(), seed=0)


@pytest.mark.parametrize("planner_cls,config", [(SearchPlanner, SearchConfig(n_samples=20, time_limit=120)),
                                                (SamplingPlanner, SamplingConfig(n_samples=20, time_limit=120))])
def test_empty_scene_reaches_goal(problem, planner_cls, config):
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
    res = SearchPlanner(pred, SearchConfig(n_samples=20, max_calls=4, horizon="node")).plan(problem)
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
        cfg = SearchConfig(n_samples=20, max_calls=3, horizon=horizon)
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
    assert res.status in (PlanStatus.TIMEOUT, PlanStatus.FAILED), res.message
    calls = res.iterations["predictor_calls"]
    assert calls <= 4
    if res.status == PlanStatus.TIMEOUT:
        assert calls == 4 and res.timings["search"] >= 2.0
        assert "within the limit (2 s, 4 predictor calls)" in res.message


@pytest.mark.parametrize("planner_cls,config", [(SearchPlanner, SearchConfig(n_samples=20, max_calls=5, seed=3)),
                                                (SamplingPlanner, SamplingConfig(n_samples=20, max_calls=5, seed=3))])
def test_deterministic_per_seed(problem, planner_cls, config):
    a = planner_cls(_exact(), config).plan(problem)
    b = planner_cls(_exact(), config).plan(problem)
    assert a.status == b.status
    assert a.params is not None and torch.equal(a.params, b.params)
    assert a.cost == b.cost


def test_nothing_acceptable_is_explained():
    """A car at rest: its samples have v < 0.1 m/s (outside the planning box), so J_B > 0 for every child."""
    import math

    from density_planner.environment.scene import Scene

    scene = corridor_empty()
    scene = Scene(scene.grid, (0.0, -28.0, math.pi / 2, 0.01), scene.goal, scene.planning_box)
    res = SearchPlanner(_exact(), SearchConfig(n_samples=20)).plan(PlanningProblem.from_scene(scene, seed=0))
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

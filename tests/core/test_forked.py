"""Work done in forked processes while this one goes on: ForkedCall, the road distance field computed beside the
planner, and the CommonRoad file read while the command line starts (density_planner.prefetch)."""

from __future__ import annotations

import multiprocessing as mp
import os
import sys
from pathlib import Path

import pytest

from density_planner.parallel import ForkedCall

needs_fork = pytest.mark.skipif("fork" not in mp.get_all_start_methods(), reason="needs fork")


def _fail(text: str) -> None:
    raise ValueError(text)


def _children() -> set[int]:
    return {p.pid for p in mp.active_children()}


@needs_fork
def test_forked_call_value_error_and_cancel():
    import numpy as np

    call = ForkedCall.start(np.arange, 5)
    assert call is not None
    assert call.result().tolist() == [0, 1, 2, 3, 4]
    with pytest.raises(RuntimeError, match="already taken"):
        call.result()
    failing = ForkedCall.start(_fail, "no road here")
    with pytest.raises(RuntimeError, match="ValueError: no road here"):
        failing.result()
    slow = ForkedCall.start(__import__("time").sleep, 30)
    pid = slow._proc.pid
    slow.cancel()
    slow.cancel()  # twice: nothing more
    assert pid not in _children() and not slow._proc.is_alive()


@needs_fork
def test_forked_call_runs_at_the_niceness_asked():
    """``nice``: the child runs that much nicer than this process (a call with time to spare yields its core)."""
    here = os.nice(0)
    for extra in (0, 5):
        call = ForkedCall.start(os.nice, 0, nice=extra)
        assert call is not None and call.result() == min(here + extra, 19)


def test_the_field_started_during_a_build_yields_its_core_only_where_its_lattice_is_small(monkeypatch):
    """map_ready starts the road's field at niceness 10 where its lattice holds no more points than a slice of the
    grid (it then ends within the build), at the build's own priority where it is larger (the planner would wait)."""
    import shapely

    from density_planner.environment import road_sdf

    asked = []
    monkeypatch.setattr(road_sdf._PENDING, "start", lambda *args, nice=0: asked.append(nice) or False)
    road = shapely.box(0.0, 0.0, 200.0, 100.0)
    with road_sdf.requesting_road_sdf(cell_size=0.2, margin=10.0):
        road_sdf.map_ready(road, (0.0, 0.0), 0.15, 1334, 667)  # 0.15-m grid cells: lattice (0.2 m) smaller
        road_sdf.map_ready(road, (0.0, 0.0), 0.5, 401, 201)  # 0.5-m grid cells: lattice larger than a slice
    assert asked == [road_sdf._BUILD_NICE, 0] and road_sdf._BUILD_NICE > 0


def test_forked_call_without_fork(monkeypatch):
    monkeypatch.setattr(mp, "get_all_start_methods", lambda: ["spawn"])
    assert ForkedCall.start(len, "abc") is None


@needs_fork
def test_pending_calls_are_filed_by_owner_and_key_and_end_with_their_owner():
    """One call per (owner, key); taken once; ended by ``cancel``, by the owner's end, and at a recycled id."""
    import gc
    import weakref

    from density_planner.parallel import PendingCalls

    class Owner:  # unhashable, like the planning problems
        __hash__ = None

    pending = PendingCalls()
    a, b = Owner(), Owner()
    before = _children()
    assert pending.start(a, "x", sum, [1, 2]) and not pending.start(a, "x", sum, [5])  # one per key
    assert pending.start(a, "y", sum, [3]) and pending.start(b, "x", sum, [4])
    assert sorted(pending.keys(a)) == ["x", "y"] and pending.keys(b) == ["x"] and pending.take(b, "y") is None
    assert pending.take(a, "x").result() == 3 and pending.keys(a) == ["y"]
    pending.cancel(a)
    assert pending.keys(a) == [] and pending.take(a, "y") is None
    call = pending._calls(b)["x"]
    del b
    gc.collect()  # the owner's end ends its call
    assert call._conn.closed and not pending._entries
    c, d = Owner(), Owner()
    assert pending.start(c, "x", sum, [1]) and pending.start(d, "x", sum, [2]) and len(pending) == 2
    calls = pending._entries[id(c)][1]
    stale = calls["x"]
    pending._entries[id(c)] = (weakref.ref(d), calls)  # as if the entry were another object's, now at c's id
    assert pending.keys(c) == [] and stale._conn.closed and len(pending) == 1
    pending.cancel(d)
    assert len(pending) == 0 and not [p for p in _children() if p not in before]


@needs_fork
def test_road_sdf_from_the_forked_process_equals_the_one_computed_here():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "planning"))
    import shapely
    from road_helpers import road_scene

    from density_planner.environment.road import GoalRegion
    from density_planner.environment.road_sdf import cancel_road_sdf, road_sdf_for_scene, start_road_sdf

    goal = GoalRegion(shapely.box(100.0, -1.0, 110.0, 4.0), (5.0, 6.0))
    before = _children()
    here = road_sdf_for_scene(road_scene(goal), cell_size=0.3)
    scene = road_scene(goal)
    assert start_road_sdf(scene, cell_size=0.3)
    assert not start_road_sdf(scene, cell_size=0.3)  # already being computed
    there = road_sdf_for_scene(scene, cell_size=0.3)
    assert there.values.dtype == here.values.dtype and bool((there.values == here.values).all())
    assert there.origin == here.origin and there.cell_size == here.cell_size
    assert not start_road_sdf(scene, cell_size=0.3)  # cached
    # a field nobody reads: cancel_road_sdf ends its process; a later read computes it here, the same
    other = road_scene(goal)
    assert start_road_sdf(other, cell_size=0.3)
    cancel_road_sdf(other)
    assert not [p for p in mp.active_children() if p.is_alive() and p.pid not in before]
    assert bool((road_sdf_for_scene(other, cell_size=0.3).values == here.values).all())


# ------------------------------------------------------------------------------------------------ prefetch
@pytest.fixture
def scenario_file(tmp_path: Path) -> Path:
    from density_planner.evaluation.environments import shipped_commonroad_dir

    src = sorted(shipped_commonroad_dir().glob("*.xml"))[0]
    dst = tmp_path / src.name
    dst.write_bytes(src.read_bytes())
    return dst


@needs_fork
def test_road_sdf_started_while_the_scene_is_built_is_the_one_read_later(scenario_file):
    """``requesting_road_sdf``: the importer starts the field once it knows the road and the grid (before the road
    users); the first read takes it over, equal to the field computed here; a build that fails ends its process."""
    from density_planner.api import build_scene, load_run_config
    from density_planner.environment import road_sdf
    from density_planner.environment.road_sdf import requesting_road_sdf, road_sdf_for_scene

    rc = load_run_config()
    before = _children()
    with requesting_road_sdf(cell_size=0.5):
        scene = build_scene("commonroad", rc, file=scenario_file)
        assert len(road_sdf._PENDING.keys(scene.road.drivable)) == 1  # started before the scene existed
    there = road_sdf_for_scene(scene, cell_size=0.5)
    assert road_sdf._PENDING.keys(scene.road.drivable) == []
    here = road_sdf_for_scene(build_scene("commonroad", rc, file=scenario_file), cell_size=0.5)
    assert bool((there.values == here.values).all()) and there.origin == here.origin
    assert there.cell_size == here.cell_size
    # another field read first (other cell size): computed here; the one started waits for its own read, and
    # cancel_road_sdf ends it
    with requesting_road_sdf(cell_size=0.5):
        other = build_scene("commonroad", rc, file=scenario_file)
    assert road_sdf_for_scene(other, cell_size=0.4).values.shape != here.values.shape
    assert [key for key, _ in road_sdf._PENDING.keys(other.road.drivable)] == [(0.5, 4_000_000, 10.0)]
    road_sdf.cancel_road_sdf(other)
    assert road_sdf._PENDING.keys(other.road.drivable) == []
    # an error inside the block: nothing is left running
    with pytest.raises(RuntimeError, match="stop"), requesting_road_sdf(cell_size=0.5):
        build_scene("commonroad", rc, file=scenario_file)
        raise RuntimeError("stop")
    assert road_sdf._STARTED == []
    assert not [p for p in _children() if p not in before]


@needs_fork
def test_prefetched_read_equals_a_direct_read_and_is_taken_once(scenario_file):
    from density_planner import prefetch
    from density_planner.environment.commonroad import read_commonroad

    direct_scenario, direct_problems = read_commonroad(scenario_file)
    assert prefetch.start_commonroad_read(scenario_file)
    assert not prefetch.start_commonroad_read(scenario_file)  # one at a time
    assert prefetch.take_commonroad_read(scenario_file.parent / "other.xml") is None  # another file: not this read
    scenario, problems = read_commonroad(scenario_file)  # takes it
    assert prefetch._PENDING is None
    assert str(scenario.scenario_id) == str(direct_scenario.scenario_id)
    assert sorted(o.obstacle_id for o in scenario.obstacles) == sorted(o.obstacle_id for o in direct_scenario.obstacles)
    assert sorted(la.lanelet_id for la in scenario.lanelet_network.lanelets) == sorted(
        la.lanelet_id for la in direct_scenario.lanelet_network.lanelets)
    assert list(problems.planning_problem_dict) == list(direct_problems.planning_problem_dict)


@needs_fork
def test_prefetch_of_a_changed_or_broken_file_is_not_used(scenario_file):
    from density_planner import prefetch
    from density_planner.environment.commonroad import read_commonroad
    from density_planner.errors import DataError

    assert prefetch.start_commonroad_read(scenario_file)
    st = scenario_file.stat()
    os.utime(scenario_file, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # changed since the read started
    assert prefetch.take_commonroad_read(scenario_file) is None
    prefetch.cancel_prefetch()
    assert prefetch._PENDING is None
    text = scenario_file.read_text()
    scenario_file.write_text(text[: len(text) // 2])  # truncated: the child fails, the caller reports it
    assert prefetch.start_commonroad_read(scenario_file)
    assert prefetch.take_commonroad_read(scenario_file) is None
    assert prefetch.start_commonroad_read(scenario_file)
    with pytest.raises(DataError, match="not a CommonRoad scenario|cannot read"):
        read_commonroad(scenario_file)
    prefetch.cancel_prefetch()


def test_command_line_prefetches_only_a_plan_or_drive_commonroad_file(monkeypatch):
    from density_planner import cli, prefetch

    started: list[str] = []
    monkeypatch.setattr(prefetch, "start_commonroad_read", lambda path: started.append(path) or True)
    cli._prefetch_scene(["plan", "--env", "commonroad", "--file", "a.xml", "--out", "o"])
    cli._prefetch_scene(["drive", "--env", "commonroad", "--file=b.XML"])
    cli._prefetch_scene(["plan", "--env", "random", "--out", "o"])
    cli._prefetch_scene(["plan", "--env", "commonroad", "--file", "a.xml", "--help"])
    cli._prefetch_scene(["bench", "commonroad", "--file", "a.xml"])
    cli._prefetch_scene(["plan", "--env", "commonroad", "--file", "a.json"])
    assert started == ["a.xml", "b.XML"]


def test_importing_the_package_and_its_command_line_does_not_import_torch():
    import subprocess

    code = ("import sys, density_planner, density_planner.cli, density_planner.prefetch; "
            "print('torch' in sys.modules, 'importlib.metadata' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    # nor the package's metadata (~0.05 s before the scene file's read could start): the version is read on use
    assert out.stdout.strip() == "False False"


def test_version_is_the_installed_distributions():
    import subprocess
    from importlib.metadata import version

    import density_planner

    assert density_planner.__version__ == version("density-planner")
    out = subprocess.run([sys.executable, "-m", "density_planner", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout == f"density-planner {density_planner.__version__}\n"


# ------------------------------------------------------------------------------------------------ route seeds
@needs_fork
def test_route_seeds_from_the_forked_process_equal_the_ones_computed_here():
    from dataclasses import replace

    import torch

    from density_planner.api import build_scene, load_run_config, set_up
    from density_planner.evaluation.environments import shipped_commonroad_dir
    from density_planner.planners import routes

    rc = load_run_config()
    scene = build_scene("commonroad", rc, file=shipped_commonroad_dir() / "USA_Lanker-1_1_T-1.xml", quiet=True)
    setup = set_up(scene, rc, kind="commonroad", planner="density", distribution_seed=0, progress=False)
    problem, cfg = setup.problem, setup.planner.config.routes
    here = routes.route_seed_parameters(problem, cfg)
    assert here is not None and len(here.routes) >= 3
    before = _children()
    assert routes.start_route_seeds(problem, cfg)
    assert not routes.start_route_seeds(problem, cfg)  # already being computed
    made_here = []
    real = routes._route_candidates
    routes._route_candidates = lambda plan, r: made_here.append(r) or real(plan, r)
    try:  # the routes split between the two processes: every second one made there, the seeds the same bits
        there = routes.route_seed_parameters(problem, cfg)
    finally:
        routes._route_candidates = real
    assert made_here == list(range(len(here.routes)))[::2]
    assert torch.equal(there.params, here.params) and torch.equal(there.targets, here.targets)
    assert there.labels == here.labels
    # asked for other seeds (another configuration or dtype): computed here, the process ended
    single = replace(cfg, max_routes=1)
    assert routes.start_route_seeds(problem, cfg)
    other = routes.route_seed_parameters(problem, single)
    assert torch.equal(other.params, routes.route_seed_parameters(problem, single).params)
    assert routes.start_route_seeds(problem, cfg, dtype=torch.float64)
    assert routes.route_seed_parameters(problem, cfg).params.dtype == torch.float32
    # seeds nobody takes: cancel_route_seeds ends the process
    assert routes.start_route_seeds(problem, cfg)
    routes.cancel_route_seeds(problem)
    routes.cancel_route_seeds(problem)  # twice: nothing more
    assert not routes._PENDING.keys(problem)
    assert not [p for p in mp.active_children() if p.is_alive() and p.pid not in before]
    # the planner's prepare() starts them (a road scene, the CPU) and its stage 1 takes them
    setup.planner.prepare(problem)
    assert routes._PENDING.keys(problem)
    assert torch.equal(setup.planner.seed_candidates(problem), here.params)
    assert not routes._PENDING.keys(problem)


def test_route_seeds_are_not_forked_where_they_cannot_be_used(monkeypatch):
    import torch

    from density_planner.planners import routes
    from density_planner.planners.routes import RouteSeedConfig

    class Problem:  # never read: each refusal comes first
        pass

    assert not routes.start_route_seeds(Problem(), RouteSeedConfig(enabled=False))
    assert not routes.start_route_seeds(Problem(), device=torch.device("meta"))
    monkeypatch.setattr(mp, "get_all_start_methods", lambda: ["spawn"])
    assert not routes.start_route_seeds(Problem())
    assert not routes._PENDING


def test_console_start_up_collects_no_garbage_and_then_freezes_what_it_imported():
    """The console script turns Python's cyclic collector off for its imports; once the command modules are
    imported the objects alive are frozen (never scanned again) and the collector is on again (a fresh process)."""
    import subprocess

    code = ("import gc, density_planner.cli as cli\n"
            "gc.disable(); cli._START_UP = True\n"
            "cli.build_parser(); cli._start_up_done()\n"
            "print(gc.isenabled(), gc.get_freeze_count() > 10000, cli._START_UP)\n"
            "cli._start_up_done(); print(gc.isenabled())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["True", "True", "False", "True"]

"""Random artificial scenes (docs/spec.md §8): determinism, parameter ranges, profile, motion, start/goal
rules."""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
import torch

from density_planner.config import from_dict
from density_planner.environment import (
    BoxObstacle,
    RandomSceneConfig,
    random_obstacles,
    random_scene,
    rasterise_boxes,
)
from density_planner.errors import ConfigError

SMALL = {"x_range": (0.0, 10.0), "y_range": (0.0, 10.0), "cell_size": 0.1}


def test_grid_layout():
    scene = random_scene(0)
    assert scene.grid.shape == (101, 241, 401)
    assert scene.grid.probs.dtype == torch.float32
    assert scene.grid.origin == (-12.0, -30.0) and scene.grid.cell_size == 0.1 and scene.grid.dt == 0.1
    assert scene.planning_box == (-9.9, 9.9, -29.9, 9.9)
    assert scene.name == "random-0"


def test_deterministic_per_seed():
    a, b, c = random_scene(5), random_scene(5), random_scene(6)
    assert torch.equal(a.grid.probs, b.grid.probs)
    assert a.start == b.start and a.goal == b.goal and a.meta == b.meta
    assert not torch.equal(a.grid.probs, c.grid.probs)


def test_same_scene_on_every_machine():
    # golden values: the stream is built from PCG64's raw output, which NumPy keeps identical everywhere
    boxes = random_obstacles(0)
    assert len(boxes) == 13
    assert boxes[0] == BoxObstacle(4.0, 2.0, 0.6, 0.5, 0.7, 22, 0, 0, "static")
    assert boxes[-1] == BoxObstacle(-6.0, -3.0, 2.9, 3.7, 0.9, 29, -2, 1, "dynamic")
    scene = random_scene(20)
    assert scene.start == pytest.approx(
        (-1.109936936697947, 8.984706621712782, -1.6695780751722937, 7.50507990155933), abs=1e-12
    )
    assert scene.goal == pytest.approx((-1.4232199776922192, -26.685868973097097), abs=1e-12)
    # float32 sums of the same numbers: identical up to summation order (1e-6 relative)
    assert float(random_scene(0).grid.probs.double().sum()) == pytest.approx(6178555.85, rel=1e-6)


def test_parameter_statistics_over_many_seeds():
    cfg = RandomSceneConfig()
    n_seeds = 400
    counts_static, counts_dynamic = [], []
    sizes, xs, ys, certs, spreads, vels = Counter(), Counter(), Counter(), Counter(), Counter(), Counter()
    for seed in range(n_seeds):
        boxes = random_obstacles(seed, cfg)
        static = [b for b in boxes if b.kind == "static"]
        dynamic = [b for b in boxes if b.kind == "dynamic"]
        counts_static.append(len(static))
        counts_dynamic.append(len(dynamic))
        for b in boxes:
            sizes.update([b.width, b.height])
            xs[b.x] += 1
            ys[b.y] += 1
            certs[b.certainty] += 1
            spreads[b.spread] += 1
        for b in static:
            assert b.vx == 0 and b.vy == 0
        for b in dynamic:
            vels.update([b.vx, b.vy])
    # every value of each range occurs, and nothing outside it
    assert set(counts_static) == {4, 5, 6, 7}
    assert set(counts_dynamic) == {6, 7, 8, 9}
    assert set(sizes) == {round(0.5 + 0.1 * i, 10) for i in range(35)}  # 0.5 ... 3.9 m
    assert set(xs) == set(map(float, range(-7, 7)))
    assert set(ys) == set(map(float, range(-23, 5)))
    assert set(certs) == {0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9}
    assert set(spreads) == set(range(1, 30))
    assert set(vels) == {-2, -1, 0, 1}
    # uniform counts: mean 5.5 / 7.5, standard error 1.12 / sqrt(400) = 0.056 -> 0.25 is > 4 standard errors
    assert np.mean(counts_static) == pytest.approx(5.5, abs=0.25)
    assert np.mean(counts_dynamic) == pytest.approx(7.5, abs=0.25)
    # velocity components uniform over 4 values: each about 25 % (about 6000 draws, +-4 % is > 6 standard
    # errors)
    total = sum(vels.values())
    assert all(abs(v / total - 0.25) < 0.04 for v in vels.values())


def test_walls_ramp_from_one_to_one_over_thirty():
    cfg = RandomSceneConfig(n_static=(0, 0), n_dynamic=(0, 0))
    probs = random_scene(1, cfg).grid.probs
    assert torch.all(probs[:, :51, :] == 1.0)  # x in [-12, -7]
    assert torch.all(probs[:, 190:, :] == 1.0)  # x in [7, 12]
    # ramp inward from x = -7 (index 50): (30 - d) / 30 at d cells, 0 from 30 cells (3 m) on
    d = torch.arange(1, 35)
    expected = torch.clamp(30 - d, min=0) / 30.0
    assert torch.allclose(probs[0, 50 + d, 200], expected.float(), atol=1e-6)
    assert torch.allclose(probs[0, 190 - d, 7], expected.float(), atol=1e-6)
    assert float(probs[:, 120, :].max()) == 0.0


def test_square_profile_of_one_box():
    box = BoxObstacle(x=4.0, y=4.0, width=1.0, height=0.5, certainty=0.8, spread=5)
    p = rasterise_boxes([box], n_slices=1, **SMALL)[0]
    # box cells: i 40..50, j 40..45
    assert np.allclose(p[40:51, 40:46], 0.8)
    assert p[39, 42] == pytest.approx(0.8 * 4 / 5) and p[36, 42] == pytest.approx(0.8 / 5)
    assert p[35, 42] == 0.0
    # Chebyshev distance: the diagonal neighbour at (2, 3) cells has d = 3
    assert p[52, 48] == pytest.approx(0.8 * 2 / 5)
    assert p.sum() > 0 and p.max() == pytest.approx(0.8)


def test_moving_box_centroid_moves_by_velocity_times_time():
    box = BoxObstacle(
        x=3.0, y=6.0, width=1.2, height=0.8, certainty=0.6, spread=4, vx=1, vy=-2, kind="dynamic"
    )
    p = rasterise_boxes([box], n_slices=12, **SMALL)
    ii, jj = np.meshgrid(np.arange(p.shape[1]), np.arange(p.shape[2]), indexing="ij")

    def centroid(k):
        w = p[k].astype(np.float64)
        return np.array([(w * ii).sum(), (w * jj).sum()]) / w.sum() * 0.1  # metres

    c0 = centroid(0)
    for k in (1, 5, 11):
        # 1 and -2 cells per 0.1-s slice = (1, -2) m/s; exact while the box stays on the map
        assert np.allclose(centroid(k) - c0, [0.1 * k, -0.2 * k], atol=1e-9)
        assert p[k].sum() == pytest.approx(p[0].sum(), rel=1e-6)


def test_zero_fill_when_shifting():
    # a box whose ramp is cut by the right border moves left: nothing enters from outside the map
    box = BoxObstacle(x=9.5, y=5.0, width=0.5, height=0.5, certainty=1.0, spread=10, vx=-1, kind="dynamic")
    p = rasterise_boxes([box], n_slices=6, **SMALL)
    for k in range(1, 6):
        assert np.all(p[k, 101 - k :, :] == 0.0)
        assert np.allclose(p[k, : 101 - k], p[0, k:])


def test_clamped_sum():
    a = BoxObstacle(4.0, 4.0, 1.0, 1.0, 0.9, 1)
    b = BoxObstacle(4.5, 4.5, 1.0, 1.0, 0.9, 1)
    p = rasterise_boxes([a, b], n_slices=1, **SMALL)[0]
    assert p.max() == 1.0 and p[42, 42] == pytest.approx(0.9) and p[47, 47] == 1.0


def test_fixed_start_and_goal_below_seed_20():
    for seed in (0, 7, 19):
        scene = random_scene(seed)
        assert scene.start == (0.0, -28.0, 1.5, 3.0) and scene.goal == (0.0, 8.0)


@pytest.mark.parametrize("seed", [20, 21, 33, 57])
def test_random_start_and_goal_pass_the_acceptance_tests(seed):
    cfg = RandomSceneConfig()
    scene = random_scene(seed)
    sx, sy, th, v = scene.start
    gx, gy = scene.goal
    assert -5 <= sx <= 5 and 5 <= sy <= 10 and -2.1 <= th <= -0.5 and 1 <= v <= 9
    assert -5 <= gx <= 5 and -30 <= gy <= -20
    assert 10 <= math.hypot(gx - sx, gy - sy) <= 70
    probs = scene.grid.probs.numpy()

    def window_max(k, x, y):
        i, j = round((x + 12) / 0.1), round((y + 30) / 0.1)
        return probs[k, max(i - 5, 0) : i + 6, max(j - 5, 0) : j + 6].max()

    assert window_max(0, sx, sy) <= cfg.start_max_occupancy
    assert window_max(10, sx + v * math.cos(th), sy + v * math.sin(th)) <= cfg.lookahead_max_occupancy
    assert window_max(100, gx, gy) <= cfg.goal_max_occupancy


def test_gives_up_after_max_attempts():
    cfg = RandomSceneConfig(distance_range=(100.0, 200.0), max_attempts=20)
    with pytest.raises(ValueError, match="20 attempts"):
        random_scene(25, cfg)


def test_config_validation():
    with pytest.raises(ValueError, match="n_static"):
        RandomSceneConfig(n_static=(7, 4))
    with pytest.raises(ValueError, match="whole number"):
        RandomSceneConfig(cell_size=0.7)
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(RandomSceneConfig, {"n_obstacles": 3})
    with pytest.raises(ValueError, match="seed"):
        random_scene(-1)

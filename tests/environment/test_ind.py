"""inD reader and scene builder on small synthetic recordings written in exactly the inD format."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from env_testdata import CAR_SPEED, CAR_Y, PED_X, PED_Y0, car_x, two_tracks

from density_planner.environment import (
    IndSceneConfig,
    OccupancyGrid,
    StartGoalConfig,
    load_ind_scene,
    read_recording_meta,
    read_tracks,
    read_tracks_meta,
    sample_start_goal,
)
from density_planner.environment.ind import tracks_in_window
from density_planner.errors import DataError
from ind_testdata import write_ind_recording


def test_readers_return_the_columns(ind_dir):
    tracks = read_tracks(ind_dir / "07_tracks.csv")
    assert tracks["frame"].size == 400 + 300
    assert tracks["xCenter"][:3] == pytest.approx([10.0, 10.2, 10.4])
    meta = read_tracks_meta(ind_dir / "07_tracksMeta.csv")
    assert list(meta["class"]) == ["car", "pedestrian"] and meta["initialFrame"].tolist() == [0, 100]
    rec = read_recording_meta(ind_dir / "07_recordingMeta.csv")
    assert rec["frameRate"] == 25.0 and rec["weekday"] == "Monday"


def test_resampling_is_exact_at_0_1_s(ind_dir):
    tracks = read_tracks(ind_dir / "07_tracks.csv")
    times = 2.0 + 0.1 * np.arange(101)
    win = tracks_in_window(tracks, 25.0, times)
    car = int(np.nonzero(win["ids"] == 1)[0][0])
    # 0.1 s = 2.5 frames: odd slices fall between two frames and are interpolated
    assert win["x"][car] == pytest.approx(car_x(times), abs=1e-9)
    assert win["vx"][car] == pytest.approx(np.full(101, CAR_SPEED))


def test_occupancy_peak_follows_the_track_at_the_right_slice(ind_dir):
    scene = load_ind_scene(ind_dir, 7, IndSceneConfig(start_time=2.0))
    grid = scene.grid
    assert grid.n_slices == 101 and grid.dt == 0.1 and grid.t0 == 2.0
    for k in (0, 7, 33, 100):
        t = 2.0 + 0.1 * k
        # restrict to the car's lane (the pedestrian walks at x = 30 m, far from y = -20 m)
        lane = grid.slice(k).clone()
        far = (grid.ys - CAR_Y).abs() > 3.0
        lane[:, far] = 0
        i, j = np.unravel_index(int(torch.argmax(lane)), lane.shape)
        # a 0.08-s stride (the paper's code) would be 0.02 * k * 5 m = 10 m off at k = 100
        assert float(grid.xs[i]) == pytest.approx(car_x(t), abs=0.11)  # one cell
        assert float(grid.ys[j]) == pytest.approx(CAR_Y, abs=0.11)
        # the peak is 1 up to the 0.4-m coarse-lattice interpolation (about 1 %)
        assert float(lane.max()) == pytest.approx(1.0, abs=0.02)
    # elongated along the heading (x): 1-sigma along (5.5 m behind) >> across (1.4 m)
    k, t = 50, 7.0
    p = lambda x, y: float(grid.lookup(torch.tensor([x, y], dtype=torch.float64), k))  # noqa: E731
    assert p(car_x(t) - 5.5, CAR_Y) == pytest.approx(math.exp(-0.5), abs=0.02)
    assert p(car_x(t), CAR_Y + 1.4) == pytest.approx(math.exp(-0.5), abs=0.02)
    assert p(car_x(t) + 5.5, CAR_Y) > p(car_x(t) - 5.5, CAR_Y)  # skewed forward (5 m/s)


def test_pedestrian_appears_at_its_first_frame(ind_dir):
    scene = load_ind_scene(ind_dir, 7, IndSceneConfig(start_time=2.0))
    grid = scene.grid
    at = lambda k: float(grid.lookup(torch.tensor([PED_X, PED_Y0], dtype=torch.float64), k))  # noqa: E731
    assert at(19) == 0.0  # t = 3.9 s
    assert at(20) == pytest.approx(
        1.0, abs=1e-5
    )  # t = 4.0 s = frame 100: a small pedestrian on the fine grid
    users = {u["track_id"]: u for u in scene.meta["road_users"]}
    assert (
        users[1]["class"] == "car" and users[2]["class"] == "pedestrian" and users[2]["slices_present"] == 81
    )
    json.dumps(scene.meta)  # JSON-serialisable


def test_heading_is_read_in_degrees(tmp_path):
    f = np.arange(100)
    t = f / 25.0
    d = 4.0 * t / math.sqrt(2)
    track = {
        "id": 5,
        "class": "truck_bus",
        "length": 8.0,
        "width": 2.5,
        "frames": f,
        "x": d,
        "y": d,
        "heading": np.full(f.size, 45.0),
        "vx": np.full(f.size, 4 / math.sqrt(2)),
        "vy": np.full(f.size, 4 / math.sqrt(2)),
    }
    write_ind_recording(tmp_path, 3, [track])
    scene = load_ind_scene(tmp_path, 3, IndSceneConfig(start_time=0.0, n_slices=11))
    grid = scene.grid
    c = 0.4 * 2.0 / math.sqrt(2)  # position at t = 1 s (slice 10)
    along = torch.tensor([c + 3.0, c + 3.0], dtype=torch.float64)  # 4.24 m along 45 deg
    across = torch.tensor([c + 3.0, c - 3.0], dtype=torch.float64)  # 4.24 m across
    assert float(grid.lookup(along, 10)) > 0.5 > float(grid.lookup(across, 10))


def test_start_and_goal_are_free_and_10_to_70_m_apart(ind_dir):
    scene = load_ind_scene(ind_dir, 7, IndSceneConfig(start_time=2.0, seed=4))
    sx, sy, th, v = scene.start
    gx, gy = scene.goal
    assert 10 <= math.hypot(gx - sx, gy - sy) <= 70 and 1 <= v <= 9
    grid = scene.grid

    def near(x, y):
        return torch.tensor(
            [[x + dx, y + dy] for dx in (-0.5, 0, 0.5) for dy in (-0.5, 0, 0.5)], dtype=torch.float64
        )

    assert float(grid.lookup(near(sx, sy), 0).max()) <= 0.1
    assert float(grid.lookup(near(gx, gy), 100).max()) <= 0.1
    b = scene.planning_box
    assert b == pytest.approx(
        (grid.bounds[0] + 0.1, grid.bounds[1] - 0.1, grid.bounds[2] + 0.1, grid.bounds[3] - 0.1)
    )
    again = load_ind_scene(ind_dir, 7, IndSceneConfig(start_time=2.0, seed=4))
    assert again.start == scene.start and again.goal == scene.goal


def test_sampler_gives_up_with_a_clear_error():
    probs = torch.zeros(11, 101, 101)
    grid = OccupancyGrid(probs, (0.0, 0.0), 0.1)  # a 10 m x 10 m map: no pair can be 10-70 m apart
    with pytest.raises(DataError, match="100 attempts.*apart"):
        sample_start_goal(grid, (0.1, 9.9, 0.1, 9.9), seed=0, config=StartGoalConfig(max_attempts=100))
    full = OccupancyGrid(torch.ones(11, 101, 101), (0.0, 0.0), 0.1)
    with pytest.raises(DataError, match="no free start cell"):
        sample_start_goal(full, (0.1, 9.9, 0.1, 9.9), seed=0)


def test_background_image_becomes_static_occupancy(tmp_path):
    from PIL import Image

    write_ind_recording(tmp_path, 1, two_tracks(), ortho_px_to_meter=0.1 / 12)  # 0.1 m per background pixel
    img = np.full((500, 800), 200, dtype=np.uint8)  # bright = free
    img[250:300, 100:200] = 20  # dark block: x in [10, 20) m, y in (-30, -25] m
    Image.fromarray(img).save(tmp_path / "01_background.png")
    scene = load_ind_scene(tmp_path, 1, IndSceneConfig(start_time=2.0, area=(0.0, 60.0, -45.0, -5.0)))
    grid = scene.grid
    block = torch.tensor(
        [[15.0, -27.5], [10.15, -25.15], [19.85, -29.85]], dtype=torch.float64
    )  # >= half a cell inside
    for k in (0, 50, 100):
        assert grid.lookup(block, k).tolist() == [1.0, 1.0, 1.0]
    assert float(grid.lookup(torch.tensor([45.0, -40.0], dtype=torch.float64), 0)) == 0.0
    assert scene.meta["background"] is True
    no_bg = load_ind_scene(
        tmp_path, 1, IndSceneConfig(start_time=2.0, area=(0.0, 60.0, -45.0, -5.0), use_background=False)
    )
    assert float(no_bg.grid.lookup(block[:1], 0)) < 1.0


def _rewrite(path, fn):
    lines = path.read_text().splitlines()
    path.write_text("\n".join(fn(lines)) + "\n")


def test_missing_files(tmp_path, ind_dir):
    with pytest.raises(DataError, match="07_recordingMeta.csv"):
        load_ind_scene(tmp_path / "nowhere", 7)
    (ind_dir / "07_tracks.csv").unlink()
    with pytest.raises(DataError, match="not found.*07_tracks.csv"):
        load_ind_scene(ind_dir, 7)


def test_missing_column(ind_dir):
    path = ind_dir / "07_tracks.csv"
    _rewrite(path, lambda ls: [ls[0].replace("heading", "yaw")] + ls[1:])
    with pytest.raises(DataError, match="missing column.*heading"):
        load_ind_scene(ind_dir, 7)


def test_non_numeric_value(ind_dir):
    path = ind_dir / "07_tracks.csv"

    def corrupt(ls):
        fields = ls[5].split(",")
        fields[4] = "abc"  # xCenter
        return ls[:5] + [",".join(fields)] + ls[6:]

    _rewrite(path, corrupt)
    with pytest.raises(DataError, match="line 6, column 'xCenter': 'abc' is not a number"):
        load_ind_scene(ind_dir, 7)


def test_nan_position(ind_dir):
    path = ind_dir / "07_tracks.csv"

    def corrupt(ls):
        fields = ls[9].split(",")
        fields[5] = "nan"  # yCenter
        return ls[:9] + [",".join(fields)] + ls[10:]

    _rewrite(path, corrupt)
    with pytest.raises(DataError, match="'yCenter' has 1 NaN.*line 10"):
        load_ind_scene(ind_dir, 7)


def test_empty_tracks(ind_dir):
    _rewrite(ind_dir / "07_tracks.csv", lambda ls: ls[:1])
    with pytest.raises(DataError, match="no track rows"):
        load_ind_scene(ind_dir, 7)


def test_track_without_meta_entry(ind_dir):
    _rewrite(ind_dir / "07_tracksMeta.csv", lambda ls: ls[:2])
    with pytest.raises(DataError, match=r"no entry for trackId\(s\) \[2\]"):
        load_ind_scene(ind_dir, 7, IndSceneConfig(start_time=5.0))


@pytest.mark.parametrize("start", [-1.0, 16.5, 100.0])
def test_window_outside_the_recording(ind_dir, start):
    if start < 0:
        with pytest.raises(ValueError, match="start_time"):
            IndSceneConfig(start_time=start)
        return
    with pytest.raises(DataError, match="outside recording 7"):
        load_ind_scene(ind_dir, 7, IndSceneConfig(start_time=start))  # the recording lasts 15.96 s


def test_window_past_the_recording_end_predicts_the_road_users(ind_dir):
    """Issue 13 item 2: a window running past the recording's end (15.96 s) is not refused; every road user
    continues at constant velocity and heading, with a footprint that widens and flattens with time."""
    from density_planner.environment.footprints import FootprintConfig

    cfg = IndSceneConfig(start_time=10.0, cell_size=0.2, area=(40.0, 160.0, -30.0, -10.0))
    scene = load_ind_scene(ind_dir, 7, cfg)
    assert scene.meta["recording_end_s"] == pytest.approx(15.96, abs=0.05)
    assert scene.meta["road_users_predicted"] >= 1
    g = scene.grid
    # the car drives along +x at 5 m/s on y = 0 (env_testdata.two_tracks): its peak keeps moving at 5 m/s
    probs = g.probs[:, :, round((-20.0 - g.origin[1]) / g.cell_size)]  # the row y = -20
    xs = g.origin[0] + g.cell_size * np.arange(g.probs.shape[1])
    k1, k2 = 70, 100  # t = 17 s and 20 s: both predicted
    x1, x2 = xs[int(probs[k1].argmax())], xs[int(probs[k2].argmax())]
    assert x2 - x1 == pytest.approx(5.0 * 3.0, abs=2 * cfg.cell_size + 0.5)
    # the uncertainty grows: the peak drops below the recorded one, the footprint widens
    assert float(probs[k2].max()) < float(probs[50].max())
    assert int((probs[k2] > 0.05).sum()) > int((probs[50] > 0.05).sum())
    assert FootprintConfig().prediction_std_rate_along > 0


def test_grid_size_guard(ind_dir):
    with pytest.raises(ValueError, match="max_cells"):
        load_ind_scene(ind_dir, 7, IndSceneConfig(start_time=2.0, max_cells=1_000_000))

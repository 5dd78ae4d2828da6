"""Scene container: save/load round trip and validation."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from density_planner.environment import (
    OccupancyGrid,
    Scene,
    load_scene,
    random_scene,
    save_scene,
    validate_scene,
)
from density_planner.errors import DataError


def small_scene(**kw) -> Scene:
    probs = torch.zeros(3, 21, 31)
    probs[:, :3, :] = 1.0  # a wall at x <= 0.2 m
    args = {
        "grid": OccupancyGrid(probs, (0.0, 0.0), 0.1),
        "start": (1.0, 1.0, 0.0, 2.0),
        "goal": (1.5, 2.5),
        "planning_box": (0.1, 1.9, 0.1, 2.9),
        "name": "small",
        "meta": {"k": [1, 2]},
    }
    args.update(kw)
    return Scene(**args)


def test_round_trip(tmp_path):
    scene = random_scene(21)
    path = save_scene(scene, tmp_path / "scene.npz")
    back = load_scene(path)
    assert torch.equal(back.grid.probs, scene.grid.probs)
    assert back.start == scene.start and back.goal == scene.goal and back.planning_box == scene.planning_box
    assert back.name == scene.name and back.meta == json.loads(json.dumps(scene.meta))
    # the grid part is also readable as a plain grid file
    assert torch.equal(OccupancyGrid.load(path).probs, scene.grid.probs)


def test_version_1_files_with_a_car_state_are_read(tmp_path):
    """Scene files of format 1 stored the car's 5-entry start state (bias 0): read as the pose and speed."""
    from density_planner.io.atomic import atomic_save_npz

    scene = small_scene()
    header = {"scene_format_version": 1, "name": "old", "start": [1.0, 1.0, 0.0, 2.0, 0.0], "goal": [1.5, 2.5],
              "planning_box": [0.1, 1.9, 0.1, 2.9], "t_start": 0.0, "meta": {}}
    path = atomic_save_npz(tmp_path / "v1.npz", **scene.grid.to_arrays(), scene_json=np.asarray(json.dumps(header)))
    assert load_scene(path).start == (1.0, 1.0, 0.0, 2.0)
    header["start"][4] = 0.1  # a biased start is no pose
    path = atomic_save_npz(tmp_path / "v1b.npz", **scene.grid.to_arrays(), scene_json=np.asarray(json.dumps(header)))
    with pytest.raises(DataError, match="zero heading bias"):
        load_scene(path)


def test_load_errors(tmp_path):
    with pytest.raises(DataError, match="not found"):
        load_scene(tmp_path / "none.npz")
    OccupancyGrid(torch.zeros(1, 2, 2), (0, 0), 1.0).save(tmp_path / "grid.npz")
    with pytest.raises(DataError, match="not a scene file"):
        load_scene(tmp_path / "grid.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(DataError, match="not a readable .npz file"):
        load_scene(tmp_path / "junk.npz")


def test_validate_scene_accepts_a_good_scene():
    assert validate_scene(small_scene()).name == "small"
    assert validate_scene(random_scene(3)).name == "random-3"


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"goal": (5.0, 1.0)}, "goal .* outside the map"),
        ({"start": (1.0, 9.0, 0.0, 2.0)}, "start position .* outside the map"),
        ({"start": (0.1, 1.0, 0.0, 2.0)}, "occupied cell at t=0"),
        ({"start": (1.0, 1.0, 0.0, -1.0)}, "speed"),
        ({"planning_box": (5.0, 6.0, 0.0, 1.0)}, "does not overlap"),
    ],
)
def test_validate_scene_rejects(changes, match):
    with pytest.raises(ValueError, match=match):
        validate_scene(small_scene(**changes))


def test_validate_scene_rejects_nan_after_in_place_edit():
    scene = small_scene()
    scene.grid.probs[1, 5, 5] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        validate_scene(scene)


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), 1.5, -0.2])
def test_validate_scene_rejects_out_of_range_after_in_place_edit(value):
    scene = small_scene()
    scene.grid.probs[2, 3, 4] = value
    with pytest.raises(ValueError, match=r"outside \[0, 1\]"):
        validate_scene(scene)


def test_scene_construction_errors():
    with pytest.raises(ValueError, match="start must have 4"):
        small_scene(start=(1.0, 2.0))
    with pytest.raises(ValueError, match="start must have 4"):  # a car state is not a pose
        small_scene(start=(1.0, 1.0, 0.0, 2.0, 0.0))
    with pytest.raises(ValueError, match="finite"):
        small_scene(goal=(np.nan, 1.0))
    with pytest.raises(ValueError, match="planning_box"):
        small_scene(planning_box=(2.0, 1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="JSON"):
        save_scene(small_scene(meta={"x": object()}), "/tmp/never-written.npz")

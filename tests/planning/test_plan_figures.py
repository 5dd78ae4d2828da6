"""The plan's animation: frames, timing and what each frame shows."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import block_scene
from PIL import Image

from density_planner.viz.plan import animate_plan


def _straight(T: int) -> np.ndarray:
    t = 0.1 * np.arange(T)
    return np.stack([np.zeros(T), -20.0 + 3.0 * t, np.full(T, np.pi / 2), np.full(T, 3.0), np.zeros(T)], axis=1)


def _frames(path) -> list[np.ndarray]:
    im = Image.open(path)
    out = []
    for i in range(im.n_frames):
        im.seek(i)
        out.append(np.asarray(im.convert("RGB")).copy())
    return out


@pytest.mark.parametrize("T, every, n_frames, duration", [(101, 2, 51, 100), (171, 4, 43, 200)])
def test_animation_frames_and_playback(tmp_path, T, every, n_frames, duration):
    """At most max_frames + 1 frames (every = 2, more on long horizons), played at twice real time; the same
    file twice (deterministic), and the occupancy block visible in the first frame."""
    scene = block_scene()
    states = _straight(min(T, scene.grid.n_slices))
    if T > states.shape[0]:  # a longer plan than the grid: the last slice is held
        states = _straight(T)
    path = animate_plan(scene, states, tmp_path / "a.gif")
    im = Image.open(path)
    assert im.n_frames == n_frames and im.info["duration"] == duration
    again = animate_plan(scene, states, tmp_path / "b.gif")
    assert all(np.array_equal(a, b) for a, b in zip(_frames(path), _frames(again)))
    first = _frames(path)[0]
    assert (first.max(-1) < 60).any()  # the block (p = 0.9) is dark grey on the white road
    with pytest.raises(ValueError, match="every must be an integer"):
        animate_plan(scene, states, tmp_path / "c.gif", every=0)

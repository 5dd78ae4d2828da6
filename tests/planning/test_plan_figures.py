"""The plan's animation (frames, timing, what each frame shows) and which process draws which figure."""

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


class _Laps:
    def __init__(self) -> None:
        self.names: list[str] = []

    def lap(self, name: str) -> None:
        self.names.append(name)


@pytest.mark.skipif("fork" not in __import__("multiprocessing").get_all_start_methods(), reason="needs fork")
def test_gif_and_costs_figure_are_drawn_beside_plan_png_once_each(tmp_path, monkeypatch):
    """plan.gif and costs.png are drawn by two forked children while plan.png is drawn here: at the same time
    (each waits until the other two have started), each once, all written; a child that fails is named."""
    import time

    import torch
    from helpers import empty_scene

    import density_planner.viz.plan as viz_plan
    from density_planner.api import write_plan_figures
    from density_planner.planners.base import PlanResult, PlanStatus

    scene = empty_scene()
    result = PlanResult("density", PlanStatus.SUCCESS, states=torch.tensor(_straight(101), dtype=torch.float32),
                        cost_history={"stage1": {"total": [3.0, 2.0, 1.0]}})
    draw_costs, draw_plan = viz_plan.plot_costs, viz_plan.plot_plan
    marks = tmp_path / "marks"  # one line per figure started, from any process

    def mark(name):
        with open(marks, "a") as fh:
            fh.write(f"{name}\n")

    def wait_for_all(n=3):  # 60 s at most
        for _ in range(600):
            if marks.exists() and len(marks.read_text().splitlines()) >= n:
                return
            time.sleep(0.1)
        raise AssertionError("the figures were not drawn at the same time")

    def costs(history, path, **kwargs):
        mark(f"costs {path.parent.name}")
        wait_for_all()
        return draw_costs(history, path, **kwargs)

    def gif(scene, states, path, **kwargs):
        mark(f"gif {path.parent.name}")
        wait_for_all()
        path.write_bytes(b"GIF89a")

    def plan(*args, **kwargs):
        mark("plan")
        wait_for_all()
        return draw_plan(*args, **kwargs)

    monkeypatch.setattr(viz_plan, "plot_costs", costs)
    monkeypatch.setattr(viz_plan, "animate_plan", gif)
    monkeypatch.setattr(viz_plan, "plot_plan", plan)
    (tmp_path / "both").mkdir()
    laps = _Laps()
    written = write_plan_figures(tmp_path / "both", scene, result, None, clock=laps)
    assert sorted(written) == ["costs.png", "plan.gif", "plan.png"] and laps.names == ["plan_png", "child_wait"]
    assert all((tmp_path / "both" / name).stat().st_size > 0 for name in written)
    assert sorted(marks.read_text().splitlines()) == ["costs both", "gif both", "plan"]

    def broken_costs(history, path, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(viz_plan, "plot_costs", broken_costs)
    monkeypatch.setattr(viz_plan, "plot_plan", draw_plan)
    (tmp_path / "broken").mkdir()
    with pytest.raises(RuntimeError, match=r"drawing .*costs.png \(exit code 1\) failed; rerun with --no-gif"):
        write_plan_figures(tmp_path / "broken", scene, result, None, clock=_Laps())
    # without fork: in turn, here
    monkeypatch.setattr(viz_plan, "plot_costs", draw_costs)
    monkeypatch.setattr("multiprocessing.get_all_start_methods", lambda: ["spawn"])
    (tmp_path / "turn").mkdir()
    laps = _Laps()
    written = write_plan_figures(tmp_path / "turn", scene, result, None, clock=laps)
    assert laps.names == ["plan_png", "gif", "costs_png"] and sorted(written) == ["costs.png", "plan.gif", "plan.png"]


@pytest.mark.parametrize("aspect", [0.34, 0.7, 1.0, 1.8, 2.5, 3.0])
@pytest.mark.parametrize("n_snap, lines, colorbar", [(6, 1, True), (4, 3, True), (1, 2, False), (7, 1, True)])
def test_plan_layout_keeps_panels_and_their_labels_apart_inside_the_figure(aspect, n_snap, lines, colorbar):
    """plot_plan's fixed layout: every panel with the margins its tick labels, axis labels and title need lies
    inside the figure below the header, no two of them overlap, the overview's box has the region's aspect (equal
    axes fill it) and the snapshots are square."""
    from density_planner.viz.plan import _PlanLayout as L

    lay = L.of(aspect, n_snap, header_lines=lines, colorbar=colorbar)
    w, h = lay.size

    def inches(r, left=0.0, bottom=0.0, right=0.0, top=0.0):
        return (r[0] * w - left, r[1] * h - bottom, r[0] * w + r[2] * w + right, r[1] * h + r[3] * h + top)

    over = inches(lay.overview, L.OVER_LEFT - 0.05, L.OVER_BOTTOM - 0.05)
    boxes = [over] + [inches(r, L.SNAP_LEFT - 0.05, L.SNAP_BOTTOM - 0.05, 0.0, L.SNAP_TOP - 0.05)
                      for r in lay.snapshots]
    assert (lay.colorbar is not None) == colorbar and len(lay.snapshots) == n_snap
    if colorbar:
        boxes.append(inches(lay.colorbar, 0.0, 0.0, L.BAR_LABELS - 0.05))
    assert lay.header >= L.VERDICT_TOP + L.LINE * lines  # below the verdict's last line
    for x0, y0, x1, y1 in boxes:
        assert 0.0 <= x0 < x1 <= w + 1e-9 and 0.0 <= y0 < y1 <= h - lay.header + 1e-9
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            assert a[2] <= b[0] or b[2] <= a[0] or a[3] <= b[1] or b[3] <= a[1], (a, b)
    assert lay.overview[2] * w / (lay.overview[3] * h) == pytest.approx(aspect)
    assert max(lay.overview[2] * w, lay.overview[3] * h) >= 3.5  # the main panel stays large
    for r in lay.snapshots:
        assert r[2] * w == pytest.approx(r[3] * h) and r[2] * w >= 1.5


def test_animation_cell_map_draws_what_imshow_draws():
    """The GIF's pixel -> cell map (occupancy copied into the frame's pixels) shows what imshow's nearest-cell
    display shows: over an image that covers part of the axes (the rest left alone), every pixel whose centre is at
    least a pixel away from a cell edge has imshow's colour."""
    import matplotlib.pyplot as plt
    from matplotlib import colormaps

    from density_planner.viz.plan import _cell_map
    from density_planner.viz.style import agg_canvas

    rng = np.random.default_rng(0)
    h, w = 7, 11
    cells = colormaps["viridis"](rng.random((h, w)), bytes=True)  # (h, w, 4) opaque, rows from the bottom
    extent = (-3.3, 8.1, -1.7, 5.2)
    fig = plt.figure(figsize=(4.0, 3.0), dpi=80)
    ax = fig.add_axes((0.15, 0.12, 0.8, 0.8))
    ax.set_xlim(-5.0, 7.0)  # the image leaves the axes on the right and top, and does not reach the left and bottom
    ax.set_ylim(-3.0, 4.0)
    ax.set_facecolor("red")
    img = ax.imshow(cells, origin="lower", extent=extent, interpolation="nearest")
    canvas = agg_canvas(fig)
    canvas.draw()
    drawn = np.asarray(canvas.buffer_rgba()).copy()
    img.remove()
    canvas.draw()
    mine = np.asarray(canvas.buffer_rgba()).copy()
    rows, cols, at = _cell_map(ax, extent, (h, w), mine.shape[0])
    assert at is not None
    mine.view(np.uint32)[..., 0][at] = np.ascontiguousarray(cells).view(np.uint32)[..., 0].take(rows, 0).take(cols, 1)
    plt.close(fig)
    # pixels away from every cell edge (in x and y) and from the axes' box edge: equal
    inv = ax.transData.inverted()
    H = mine.shape[0]
    yy, xx = np.mgrid[0:H, 0:mine.shape[1]]
    data = inv.transform(np.column_stack([xx.ravel() + 0.5, H - yy.ravel() - 0.5]))
    fx = (data[:, 0] - extent[0]) / (extent[1] - extent[0]) * w
    fy = (data[:, 1] - extent[2]) / (extent[3] - extent[2]) * h
    px_per_cell = min(ax.bbox.width / 12.0 * (extent[1] - extent[0]) / w,  # axes 12 m wide, 7 m high
                      ax.bbox.height / 7.0 * (extent[3] - extent[2]) / h)
    margin = 1.0 / px_per_cell  # one pixel, in cells
    away = (np.abs(fx - np.round(fx)) > margin) & (np.abs(fy - np.round(fy)) > margin)
    x0, y0, x1, y1 = ax.bbox.extents
    inside_box = (xx.ravel() + 0.5 > x0 + 1) & (xx.ravel() + 0.5 < x1 - 1) & (H - yy.ravel() - 0.5 > y0 + 1) & (
        H - yy.ravel() - 0.5 < y1 - 1)
    check = (away & inside_box).reshape(H, -1)
    assert check.sum() > 1000
    assert np.array_equal(mine[check], drawn[check])
    # the image is there (not the red face) where it covers the axes, and the face where it does not
    on_image = check & ((fx >= 0) & (fx < w) & (fy >= 0) & (fy < h)).reshape(H, -1)
    assert on_image.sum() > 500 and (check & ~on_image).sum() > 100
    assert not (mine[on_image][:, :3] == [255, 0, 0]).all(-1).any()
    assert (mine[check & ~on_image][:, :3] == [255, 0, 0]).all()


def test_overview_shows_the_goal_region_only_near_the_plan():
    """A goal lanelet that runs on far past a short plan: the overview (and the GIF's window) holds the plan and the
    goal region within GOAL_REGION_REACH of it, not the whole lanelet; a goal region far from the plan adds
    nothing beyond the goal point."""
    from dataclasses import replace

    import shapely
    from road_helpers import road_scene

    from density_planner.environment.road import GoalRegion
    from density_planner.viz.plan import GOAL_REGION_REACH, _region_of_interest

    states = np.stack([np.linspace(10.0, 30.0, 21), np.full(21, 1.75), np.zeros(21), np.full(21, 5.0),
                       np.zeros(21)], axis=1)
    near = road_scene(GoalRegion(shapely.box(25.0, 0.0, 155.0, 3.5), (0.0, 10.0)))
    near = replace(near, goal=(30.0, 1.75))
    x0, x1, _, _ = _region_of_interest(near, states, None)
    assert x0 == pytest.approx(10.0 - 12.0) and x1 == pytest.approx(30.0 + GOAL_REGION_REACH + 12.0)
    whole = road_scene(GoalRegion(shapely.box(25.0, 0.0, 45.0, 3.5), (0.0, 10.0)))
    whole = replace(whole, goal=(30.0, 1.75))
    assert _region_of_interest(whole, states, None)[1] == pytest.approx(45.0 + 12.0)  # all of a small region
    far = road_scene(GoalRegion(shapely.box(120.0, 0.0, 155.0, 3.5), (0.0, 10.0)))
    far = replace(far, goal=(30.0, 1.75))
    assert _region_of_interest(far, states, None)[1] == pytest.approx(30.0 + 12.0)

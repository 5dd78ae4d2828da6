"""OccupancyGrid: transforms, bilinear lookup (values and gradients), central-difference gradient, files."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from density_planner.environment import OccupancyGrid
from density_planner.errors import DataError


def make_grid(dtype=torch.float32, seed=0) -> OccupancyGrid:
    g = torch.Generator().manual_seed(seed)
    probs = torch.rand((3, 5, 4), generator=g, dtype=torch.float64).to(dtype)
    return OccupancyGrid(probs, origin=(-1.0, 2.0), cell_size=0.5, dt=0.1)


def test_geometry():
    grid = make_grid()
    assert grid.shape == (3, 5, 4) and grid.n_slices == 3
    assert grid.bounds == (-1.0, 1.0, 2.0, 3.5)
    assert torch.allclose(grid.xs, torch.tensor([-1.0, -0.5, 0.0, 0.5, 1.0], dtype=torch.float64))
    assert torch.allclose(grid.times, torch.tensor([0.0, 0.1, 0.2], dtype=torch.float64))


def test_artificial_map_is_241_by_401():
    grid = OccupancyGrid(torch.zeros(101, 241, 401), origin=(-12.0, -30.0), cell_size=0.1)
    assert grid.bounds == pytest.approx((-12.0, 12.0, -30.0, 10.0))


def test_transforms_round_trip():
    grid = make_grid()
    xy = torch.randn(10, 7, 2, dtype=torch.float64) * 3
    # float64 round-off only
    assert torch.allclose(grid.cell_to_world(grid.world_to_cell(xy)), xy, atol=1e-12)
    c = torch.randn(6, 2, dtype=torch.float64) * 4
    assert torch.allclose(grid.world_to_cell(grid.cell_to_world(c)), c, atol=1e-12)
    # cell centres have integer coordinates
    centre = torch.tensor([grid.xs[3], grid.ys[2]], dtype=torch.float64)
    assert torch.allclose(grid.world_to_cell(centre), torch.tensor([3.0, 2.0], dtype=torch.float64))


def test_cell_index_rounds_and_clamps():
    grid = make_grid()
    xy = torch.tensor([[-1.0, 2.0], [0.24, 2.76], [1.2, 3.0], [-1.3, 1.0]], dtype=torch.float64)
    idx, inside = grid.cell_index(xy)
    assert idx.tolist() == [[0, 0], [2, 2], [4, 2], [0, 0]]
    assert inside.tolist() == [True, True, True, False]


def test_lookup_matches_hand_computed_bilinear_value():
    probs = torch.zeros(2, 3, 3)
    # corners of the cell (1, 1)-(2, 2) in slice 1
    probs[1, 1, 1], probs[1, 2, 1], probs[1, 1, 2], probs[1, 2, 2] = 0.1, 0.5, 0.3, 0.9
    grid = OccupancyGrid(probs, origin=(0.0, 0.0), cell_size=2.0)
    # x = 2.5 m -> 1.25 cells (fx = 0.25), y = 3.0 m -> 1.5 cells (fy = 0.5)
    value = grid.lookup(torch.tensor([2.5, 3.0]), 1)
    expected = 0.75 * (0.5 * 0.1 + 0.5 * 0.3) + 0.25 * (0.5 * 0.5 + 0.5 * 0.9)  # = 0.325
    assert float(value) == pytest.approx(expected, abs=1e-6)  # float32 round-off
    # slice 0 is empty there
    assert float(grid.lookup(torch.tensor([2.5, 3.0]), 0)) == 0.0


def test_lookup_at_cell_centres_returns_cell_values():
    grid = make_grid()
    ii, jj = torch.meshgrid(torch.arange(5), torch.arange(4), indexing="ij")
    xy = grid.cell_to_world(torch.stack([ii, jj], -1).double())
    for k in range(3):
        assert torch.allclose(grid.lookup(xy, k), grid.probs[k].double(), atol=1e-7)


def test_lookup_outside_gets_fill_and_broadcasts():
    grid = make_grid()
    out = torch.tensor([[5.0, 2.5], [-1.01, 2.5], [0.0, 3.6]])
    assert grid.lookup(out, 0).tolist() == [1.0, 1.0, 1.0]
    assert grid.lookup(out, 0, fill=0.0).tolist() == [0.0, 0.0, 0.0]
    xy = torch.zeros(4, 7, 2) + torch.tensor([0.1, 2.6])
    k = torch.tensor([0, 1, 2, 1])[:, None]
    val = grid.lookup(xy, k)
    assert val.shape == (4, 7)
    assert torch.allclose(val[1], val[3])
    assert val.dtype == torch.float32
    assert grid.lookup(xy.double(), k).dtype == torch.float64


def test_lookup_rejects_bad_slices():
    grid = make_grid()
    with pytest.raises(ValueError, match="slice index"):
        grid.lookup(torch.zeros(2), 3)
    with pytest.raises(ValueError, match="integer"):
        grid.lookup(torch.zeros(2), torch.tensor(1.0))
    with pytest.raises(ValueError, match="trailing dimension 2"):
        grid.lookup(torch.zeros(3), 0)


def test_lookup_gradcheck_float64():
    grid = make_grid(torch.float64, seed=3)
    g = torch.Generator().manual_seed(1)
    # interior points away from cell centres (the bilinear interpolant has kinks on the lattice lines)
    c = (
        torch.rand(8, 2, generator=g, dtype=torch.float64) * 0.6
        + 0.2
        + torch.tensor([1.0, 1.0], dtype=torch.float64)
    )
    xy = grid.cell_to_world(c).requires_grad_(True)
    k = torch.tensor([0, 1, 2, 0, 1, 2, 0, 1])
    assert torch.autograd.gradcheck(lambda p: grid.lookup(p, k), (xy,), eps=1e-6, atol=1e-8)


def test_gradient_of_linear_ramp_is_its_slope():
    a, b = 0.02, -0.01  # probability per cell along x and y
    i = torch.arange(20, dtype=torch.float64)[:, None]
    j = torch.arange(15, dtype=torch.float64)[None, :]
    probs = (0.4 + a * i + b * j).expand(2, 20, 15)
    grid = OccupancyGrid(probs, origin=(0.0, 0.0), cell_size=0.1)
    grad = grid.gradient()
    assert grad.shape == (2, 20, 15, 2)
    # exact for a linear function, also with the one-sided differences at the borders (float64)
    assert torch.allclose(grad[..., 0], torch.full_like(grad[..., 0], a), atol=1e-12)
    assert torch.allclose(grad[..., 1], torch.full_like(grad[..., 1], b), atol=1e-12)
    # per metre: divide by the cell size
    assert float(grad[0, 5, 5, 0] / grid.cell_size) == pytest.approx(0.2)
    assert grid.gradient() is grad  # cached


def test_gradient_central_and_one_sided_differences():
    i = torch.arange(6, dtype=torch.float64)
    probs = (i**2 / 100)[None, :, None].expand(1, 6, 3)
    grad = OccupancyGrid(probs, origin=(0.0, 0.0), cell_size=1.0).gradient()[0, :, 0, 0]
    expected = torch.tensor([0.01, 0.02, 0.04, 0.06, 0.08, 0.09], dtype=torch.float64)
    assert torch.allclose(grad, expected, atol=1e-12)


def test_views():
    grid = make_grid()
    assert torch.equal(grid.max_over_time(), grid.probs.amax(0))
    assert torch.equal(grid.slice(-1), grid.probs[2])
    with pytest.raises(ValueError, match="slice index"):
        grid.slice(3)
    assert grid.to(dtype=torch.float64).probs.dtype == torch.float64
    assert grid.to("cpu") is grid
    assert int(grid.slice_index(0.14)) == 1 and int(grid.slice_index(5.0, clamp=True)) == 2
    with pytest.raises(ValueError, match="outside the occupancy grid's time span"):
        grid.slice_index(5.0)


def test_save_load_round_trip(tmp_path):
    grid = OccupancyGrid(make_grid().probs, origin=(-1.0, 2.0), cell_size=0.5, dt=0.2, t0=3.0)
    path = grid.save(tmp_path / "grid.npz")
    back = OccupancyGrid.load(path)
    assert torch.equal(back.probs, grid.probs)
    assert (back.origin, back.cell_size, back.dt, back.t0) == (grid.origin, 0.5, 0.2, 3.0)
    with pytest.raises(DataError, match="not found"):
        OccupancyGrid.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(DataError, match="missing array"):
        OccupancyGrid.load(tmp_path / "other.npz")


@pytest.mark.parametrize(
    ("probs", "kwargs", "match"),
    [
        (torch.zeros(5, 4), {}, "shape"),
        (torch.zeros(1, 1, 4), {}, "cells per axis"),
        (torch.full((2, 3, 3), float("nan")), {}, "NaN"),
        (torch.full((2, 3, 3), 1.5), {}, r"\[0, 1\]"),
        (torch.full((2, 3, 3), -0.2), {}, r"\[0, 1\]"),
        (torch.zeros(2, 3, 3), {"cell_size": 0.0}, "cell_size"),
        (torch.zeros(2, 3, 3), {"dt": -1.0}, "dt"),
        (torch.zeros(2, 3, 3), {"origin": (0.0,)}, "origin"),
        ("abc", {}, "tensor or numpy"),
    ],
)
def test_validation(probs, kwargs, match):
    args = {"origin": (0.0, 0.0), "cell_size": 0.1, **kwargs}
    with pytest.raises(ValueError, match=match):
        OccupancyGrid(probs, **args)


def test_numpy_and_integer_input_become_float32():
    grid = OccupancyGrid(np.ones((2, 3, 3), dtype=np.int64), origin=(0, 0), cell_size=1)
    assert grid.probs.dtype == torch.float32 and grid.cell_size == 1.0


def test_drop_caches_forgets_derived_grids_and_recomputes_them_equal():
    g = torch.Generator().manual_seed(0)
    grid = OccupancyGrid(torch.rand(3, 6, 5, generator=g), origin=(0.0, 0.0), cell_size=0.5)
    first = grid.gradient()
    assert grid.gradient() is first  # cached
    grid.drop_caches()
    again = grid.gradient()
    assert again is not first
    torch.testing.assert_close(again, first)


def test_value_range_is_remembered_until_an_in_place_edit(monkeypatch):
    """The constructor's range check is remembered: validating the scene again reads no cell; a torch edit of the
    grid in place (its version counter) is seen and checked again."""
    from density_planner.environment.scene import Scene, validate_scene

    probs = torch.zeros(3, 20, 30)
    probs[1, 4:8, 5:9] = 0.7
    grid = OccupancyGrid(probs, origin=(0.0, 0.0), cell_size=0.5)
    scene = Scene(grid, (1.0, 1.0, 0.0, 1.0), (8.0, 12.0), (0.0, 9.5, 0.0, 14.5), name="ranged")
    passes = []
    real = torch.aminmax
    monkeypatch.setattr(torch, "aminmax", lambda t: passes.append(1) or real(t))
    assert grid.value_range() == (0.0, pytest.approx(0.7))
    validate_scene(scene)
    validate_scene(scene)
    assert passes == []
    grid.probs[2, 10, 10] = 0.9  # in place: seen
    assert grid.value_range() == (0.0, pytest.approx(0.9)) and passes == [1]
    grid.probs[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        validate_scene(scene)
    assert len(passes) == 2
    grid.drop_caches()  # forgotten with the other derived values: computed again
    assert np.isnan(grid.value_range()[0]) and len(passes) == 3


def test_a_range_vouched_for_skips_the_pass_over_the_cells(monkeypatch):
    """``in_range=True`` (the importers' rasteriser, windows and copies of a checked grid): no pass over the cells at
    construction or validation, ``value_range`` gives the bounds [0, 1]; an in-place edit is checked again exactly."""
    from density_planner.environment.scene import Scene, validate_scene

    probs = torch.zeros(3, 20, 30)
    probs[1, 4:8, 5:9] = 0.7
    passes = []
    real = torch.aminmax
    monkeypatch.setattr(torch, "aminmax", lambda t: passes.append(1) or real(t))
    grid = OccupancyGrid(probs, origin=(0.0, 0.0), cell_size=0.5, in_range=True)
    scene = Scene(grid, (1.0, 1.0, 0.0, 1.0), (8.0, 12.0), (0.0, 9.5, 0.0, 14.5), name="vouched")
    validate_scene(scene)
    assert grid.value_range() == (0.0, 1.0) and passes == []
    window = OccupancyGrid(probs, origin=(0.0, 0.0), cell_size=0.5).window(1, 2)  # the parent's check only
    assert passes == [1] and window.value_range() == (0.0, 1.0) and len(passes) == 1
    grid.probs[0, 0, 0] = 2.0  # in place: checked exactly again
    with pytest.raises(ValueError, match=r"outside \[0, 1\] \(found 0 to 2;"):
        validate_scene(scene)

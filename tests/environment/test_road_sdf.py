"""Signed distance field of the drivable area: sign, exact values near the edge, gradient direction, extrapolation."""

from __future__ import annotations

import numpy as np
import pytest
import shapely
import torch

from density_planner.environment.road_sdf import RoadSDF

# an L-shaped road: a horizontal strip and a vertical one (non-convex corner)
L_ROAD = shapely.union(shapely.box(0, 0, 40, 4), shapely.box(36, 0, 40, 30))


@pytest.fixture(scope="module")
def sdf() -> RoadSDF:
    return RoadSDF.from_geometry(L_ROAD, (-10, 50, -10, 40), cell_size=0.2, dtype=torch.float64)


def test_sign_and_values_match_the_exact_distance(sdf):
    gen = np.random.default_rng(0)
    pts = gen.uniform([-9, -9], [49, 39], size=(400, 2))
    exact = shapely.distance(L_ROAD.boundary, shapely.points(pts))
    inside = shapely.contains_xy(L_ROAD, pts[:, 0], pts[:, 1])
    exact = np.where(inside, -exact, exact)
    got = sdf(torch.as_tensor(pts)).numpy()
    assert np.all(np.sign(got[np.abs(exact) > 0.2]) == np.sign(exact[np.abs(exact) > 0.2]))
    # bilinear interpolation of exact values near the edge, of the EDT (within one cell) elsewhere
    near = np.abs(exact) < 0.5
    assert np.abs(got - exact)[near].max() < 0.05
    assert np.abs(got - exact).max() < 0.2 + 1e-9


def test_gradient_points_away_from_the_road(sdf):
    pts = torch.tensor([[20.0, 8.0], [20.0, -5.0], [45.0, 15.0], [30.0, 20.0], [20.0, 1.3]], dtype=torch.float64,
                       requires_grad=True)
    (g,) = torch.autograd.grad(sdf(pts).sum(), pts)
    expected = torch.tensor([[0, 1], [0, -1], [1, 0], [-1, 0], [0, -1]], dtype=torch.float64)
    # off the road the gradient has unit length and points away from it (no plateau); on the road it points to
    # the nearest edge (1.3 m below, 2.7 m above)
    assert torch.allclose(g, expected, atol=0.05)


def test_outside_the_lattice_it_keeps_growing(sdf):
    pts = torch.tensor([[20.0, 100.0], [20.0, 200.0], [-100.0, 2.0]], dtype=torch.float64, requires_grad=True)
    v = sdf(pts)
    vals = v.detach()
    assert float(vals[1]) == pytest.approx(float(vals[0]) + 100.0)
    assert float(vals[2]) == pytest.approx(100.0, abs=0.3)
    (g,) = torch.autograd.grad(v.sum(), pts)
    # the distance to the lattice adds a unit slope outwards on top of the field's own gradient at its edge
    assert g[:2, 1].tolist() == pytest.approx([1.0, 1.0], abs=1e-3) and float(g[0, 0]) < 0  # away from (38, 30)
    assert g[2].tolist() == pytest.approx([-1.0, 0.0], abs=1e-3)


def test_gradcheck_inside_cells(sdf):
    pts = torch.tensor([[20.03, 5.07], [37.11, 12.29], [5.5, -3.3]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(sdf, (pts,), eps=1e-6, atol=1e-5)


def test_cell_size_grows_to_the_budget_and_bad_input_is_refused():
    coarse = RoadSDF.from_geometry(L_ROAD, (-10, 50, -10, 40), cell_size=0.01, max_cells=10_000)
    assert coarse.values.numel() <= 10_500 and coarse.cell_size > 0.01
    with pytest.raises(ValueError, match="bounds"):
        RoadSDF.from_geometry(L_ROAD, (5, 0, 0, 5))
    with pytest.raises(ValueError, match="drivable"):
        RoadSDF.from_geometry(shapely.Polygon(), (0, 5, 0, 5))


def _bilinear_reference(sdf: RoadSDF, xy: torch.Tensor) -> torch.Tensor:
    """Bilinear interpolation written out with index gathers, continued outside by the distance to the lattice."""
    nx, ny = sdf.shape
    x0, x1, y0, y1 = sdf.extent
    lo, hi = xy.new_tensor([x0, y0]), xy.new_tensor([x1, y1])
    c = torch.minimum(torch.maximum(xy, lo), hi)
    outside = (xy - c).norm(dim=-1)
    g = (c - lo) / sdf.cell_size
    i0 = torch.floor(g[..., 0]).clamp(0, nx - 2).long()
    j0 = torch.floor(g[..., 1]).clamp(0, ny - 2).long()
    fx, fy = g[..., 0] - i0, g[..., 1] - j0
    v = sdf.values.to(xy)
    inner = ((v[i0, j0] * (1 - fx) + v[i0 + 1, j0] * fx) * (1 - fy)
             + (v[i0, j0 + 1] * (1 - fx) + v[i0 + 1, j0 + 1] * fx) * fy)
    return inner + outside


def test_lookup_is_the_bilinear_interpolation_with_offset_and_gradient(sdf):
    gen = torch.Generator().manual_seed(1)
    pts = torch.rand(5000, 2, generator=gen, dtype=torch.float64) * torch.tensor([90.0, 80.0]) - torch.tensor(
        [20.0, 20.0], dtype=torch.float64)  # a fifth of them off the lattice
    pts.requires_grad_(True)
    ref = _bilinear_reference(sdf, pts)
    got = sdf(pts, offset=0.15)
    assert torch.allclose(got, ref + 0.15, atol=1e-10)
    (g_ref,) = torch.autograd.grad(ref.sum(), pts)
    (g_got,) = torch.autograd.grad(sdf(pts).sum(), pts)
    assert torch.allclose(g_got, g_ref, atol=1e-9)
    # batch shape kept, float32 agrees to its precision
    p32 = pts.detach().float().reshape(50, 100, 2)
    assert sdf(p32).shape == (50, 100)
    assert torch.allclose(sdf(p32).double().reshape(-1), ref.detach(), atol=1e-3)

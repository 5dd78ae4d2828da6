"""The collision cost's compiled CPU path (numba kernels, closed-form gradients) gives the tensor path's value and
autograd gradients, in the states and in the weights."""

from __future__ import annotations

import pytest
import torch

from density_planner.cost.composite import CostConfig
from density_planner.cost.terms import CollisionCost, CostInputs, _FusedCollision
from density_planner.environment import random_scene
from density_planner.risk import CollisionModel
from density_planner.systems.car import KinematicCar

pytest.importorskip("numba")


def _cloud(dtype: torch.dtype, batch: int, n: int, t: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample clouds around a path through random scene 0's obstacles (inside its map), and weights (1, N, T)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.zeros(batch, n, t, 5, dtype=torch.float64)
    x[..., 0] = torch.linspace(-9.0, 9.0, t, dtype=torch.float64)
    x[..., 1] = -8.0 + 6.0 * torch.linspace(0.0, 1.0, t, dtype=torch.float64).sin()
    x[..., :2] += (0.8 * torch.randn(batch, n, t, 2, generator=g, dtype=torch.float64)).clamp(-2.5, 2.5)
    x[..., 2] = 3.2 * torch.rand(batch, n, t, generator=g, dtype=torch.float64) - 1.6
    w = torch.rand(1, n, t, generator=g, dtype=torch.float64)
    return x.to(dtype), (w / w.sum(-2, keepdim=True)).to(dtype)


def _value_and_grads(term: CollisionCost, x: torch.Tensor, w: torch.Tensor, slices: torch.Tensor, scale: torch.Tensor,
                     *, kernels: bool = False):
    """The term's value and its gradients in ``x`` and ``w``; ``kernels``: through the compiled kernels directly
    (whatever path ``term`` would choose)."""
    xr, wr = x.clone().requires_grad_(True), w.clone().requires_grad_(True)
    if kernels:
        out = term.kernels(xr, wr, slices)
        assert out is not None  # the compiled path serves these clouds
        j = _FusedCollision.apply(xr, wr, *out)
    else:
        j = term(CostInputs(x=xr, weights=wr, u_ref=torch.zeros(x.shape[-2] - 1, 2, dtype=x.dtype), slices=slices))
    gx, gw = torch.autograd.grad((j * scale).sum(), (xr, wr))
    return j.detach(), gx, gw


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("body", [True, False])
def test_compiled_collision_kernels_match_the_tensor_path(dtype, body):
    """Value (per candidate) and gradients in the states (positions and heading) and in the broadcast weights, on a
    fresh memo (cells filled between the kernels' passes) and on a filled one, for the car's body (four discs,
    clamped to the map) and a point vehicle, on the scene's grid and on a replan window of it (slices offset)."""
    scene = random_scene(0)
    cfg = CostConfig()
    tol = {"rtol": 1e-4, "atol": 1e-3} if dtype == torch.float32 else {"rtol": 1e-10, "atol": 1e-9}
    for grid, slices in ((scene.grid, torch.arange(101)), (scene.grid.window(20, 61), torch.arange(61))):
        model = CollisionModel(grid, KinematicCar() if body else None)
        fused = CollisionCost(model, beta=cfg.beta, plateau_scales=cfg.plateau_scales)
        tensor = CollisionCost(model, beta=cfg.beta, plateau_scales=cfg.plateau_scales, fused=False)
        scale = torch.tensor([1.0, -2.0, 0.5], dtype=dtype)
        for seed in (0, 1):
            x, w = _cloud(dtype, 3, 40, len(slices), seed)
            a = _value_and_grads(fused, x, w, slices, scale, kernels=True)
            b = _value_and_grads(tensor, x, w, slices, scale)
            assert float(b[0].min()) > 0 and float(b[1][..., 2].abs().max()) > (0 if body else -1)
            for u, v in zip(a, b):
                assert u.shape == v.shape and u.dtype == v.dtype
                torch.testing.assert_close(u, v, **tol)
            if body:  # the term itself takes the compiled path for a body (the point's tensor path is as fast)
                for u, v in zip(_value_and_grads(fused, x, w, slices, scale), a):
                    torch.testing.assert_close(u, v, rtol=0, atol=0)
            else:
                assert float(a[1][..., 2:].abs().max()) == 0.0


def test_compiled_kernels_decline_a_point_off_the_map():
    """A point vehicle's states beyond the map are read by the tensor path (desired positions off the grid): the
    kernels decline."""
    scene = random_scene(0)
    cfg = CostConfig()
    term = CollisionCost(scene.grid, beta=cfg.beta, plateau_scales=cfg.plateau_scales)
    x, w = _cloud(torch.float64, 2, 10, 101, 3)
    assert term.kernels(x, w, torch.arange(101)) is not None
    x[0, 0, 50, 0] = 1e4  # far off the map
    assert term.kernels(x, w, torch.arange(101)) is None

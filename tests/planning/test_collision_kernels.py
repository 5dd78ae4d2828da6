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


def test_kernels_compiled_ahead_of_time_equal_the_just_in_time_ones(tmp_path, monkeypatch):
    """The extension module of :mod:`density_planner.cost._aot` (the installed one, else one built here) returns what
    numba's just-in-time kernels return, bit for bit, for float32 and float64 states; a module is only loaded for
    the exact kernel source it was compiled from."""
    import importlib

    import numpy as np

    from density_planner.cost import _aot, _jit

    compiled = _aot.load()
    if compiled is None:
        try:
            _aot.build(tmp_path)
        except Exception as exc:  # noqa: BLE001 - no C compiler or no numba.pycc here
            pytest.skip(f"cannot compile ahead of time here: {exc}")
        monkeypatch.syspath_prepend(str(tmp_path))
        compiled = _aot.CompiledKernels(importlib.import_module(_aot.module_name()))
    rng = np.random.default_rng(0)
    for dtype in (np.float32, np.float64):
        b, t, n, m, nx, ny, slices = 3, 7, 11, 4, 40, 30, 5
        x = np.ascontiguousarray(rng.uniform(-1.0, 5.0, (b, t, n, 5)).astype(dtype))
        w = rng.uniform(0.0, 1.0, (b, t, n)).astype(dtype)
        off = np.array([-1.5, -0.5, 0.5, 1.5], dtype=dtype)
        unit = np.array([1.0, 0.0], dtype=dtype)
        origin = np.array([-0.2, -0.3], dtype=dtype)
        k = rng.integers(0, slices, t).astype(np.int64)
        bounds = np.array([0.0, 3.8, 0.0, 2.8], dtype=dtype)
        known = rng.uniform(size=slices * nx * ny) < 0.5
        table = rng.uniform(-1.0, 4.0, (slices * nx * ny, 3)).astype(dtype)
        outs = []
        for kernels in (compiled, _jit):
            lin = np.empty((b, t, n, m), dtype=np.int64)
            flags = kernels.cells(x, 0, 1, 2, off, unit, origin, dtype(0.1), nx, ny, k, bounds, True, known, lin)
            value, gx, gw = np.empty(b), np.zeros_like(x), np.empty_like(w)
            kernels.accumulate(x, w, lin, table, 0, 1, 2, off, unit, value, gx, gw)
            outs.append((flags, lin, value, gx, gw))
        assert outs[0][0] == outs[1][0] and outs[0][0][0] > 0
        for u, v in zip(outs[0][1:], outs[1][1:]):
            np.testing.assert_array_equal(u, v)
    # another kernel source: another module name, and nothing compiled for it
    source = tmp_path / "_jit.py"
    source.write_text(_aot._SOURCE.read_text() + "\n# changed\n")
    name = _aot.module_name()
    monkeypatch.setattr(_aot, "_SOURCE", source)
    assert _aot.module_name() != name and _aot.load() is None

"""The torch-free one-state C3M evaluation equals the torch controller (both shipped model sets)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from density_planner.control.fast import NumpyC3M
from density_planner.control.registry import load_controller, model_set_for_scene


@pytest.mark.parametrize("kind", ["random", "commonroad"])
def test_numpy_controller_matches_torch(kind):
    models = model_set_for_scene(kind, None)
    ctrl = load_controller("c3m", models=models).double()
    fast = NumpyC3M(ctrl)
    g = torch.Generator().manual_seed(0)
    n = 200
    vmax = 10.0 if kind == "random" else 30.0
    x_ref = torch.stack([torch.rand(n, generator=g, dtype=torch.float64) * 40 - 20,
                         torch.rand(n, generator=g, dtype=torch.float64) * 40 - 20,
                         torch.rand(n, generator=g, dtype=torch.float64) * 6 - 3,
                         torch.rand(n, generator=g, dtype=torch.float64) * vmax,
                         torch.zeros(n, dtype=torch.float64)], dim=-1)
    # errors large enough to reach the saturation in some channels
    x_hat = x_ref + torch.randn(n, 5, generator=g, dtype=torch.float64) * torch.tensor([2.0, 2.0, 0.5, 2.0, 0.0],
                                                                                        dtype=torch.float64)
    x_hat[:, 3] = x_hat[:, 3].clamp_min(0.0)
    u_ref = torch.randn(n, 2, generator=g, dtype=torch.float64)
    with torch.no_grad():
        u_torch = ctrl(x_hat, x_ref, u_ref).numpy()
    u_np = np.stack([fast(a, b, c) for a, b, c in zip(x_hat.numpy(), x_ref.numpy(), u_ref.numpy())])
    np.testing.assert_allclose(u_np, u_torch, atol=1e-6, rtol=0)
    # some samples saturate, some do not (the test covers both branches)
    raw = ctrl.raw(x_hat, x_ref, u_ref).detach().numpy()
    assert (np.abs(raw - u_torch) > 1e-3).any() and (np.abs(raw - u_torch) < 1e-12).any()


def test_rejects_other_controllers():
    with pytest.raises(ValueError, match="C3MController"):
        NumpyC3M(object())

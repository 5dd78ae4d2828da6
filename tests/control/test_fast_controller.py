"""The torch-free one-state C3M evaluation (numpy, and compiled with numba where installed) equals the torch
controller (both shipped model sets), and the compiled closed loop equals the numpy one."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from density_planner.control.fast import NumpyC3M
from density_planner.control.registry import load_controller, model_set_for_scene


def _needs(compiled: bool) -> None:
    if compiled:
        pytest.importorskip("numba")


@pytest.mark.parametrize("compiled", [False, True], ids=["numpy", "numba"])
@pytest.mark.parametrize("kind", ["random", "commonroad"])
def test_numpy_controller_matches_torch(kind, compiled):
    _needs(compiled)
    models = model_set_for_scene(kind, None)
    ctrl = load_controller("c3m", models=models).double()
    fast = NumpyC3M(ctrl, compiled=compiled)
    assert fast.compiled == compiled
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


@pytest.mark.parametrize("kind", ["random", "commonroad"])
def test_compiled_closed_loop_matches_numpy(kind):
    """50 Euler steps of the heading-biased closed loop from states that saturate an input and from ones that do
    not, with and without the standstill clamp: the compiled loop's final state and first input equal numpy's."""
    _needs(True)
    ctrl = load_controller("c3m", models=model_set_for_scene(kind, None))
    jit, ref = NumpyC3M(ctrl, compiled=True), NumpyC3M(ctrl, compiled=False)
    rng = np.random.default_rng(1)
    k = 50
    t = np.arange(k) * 0.01
    v_ref = 6.0 if kind == "random" else 20.0
    x_refs = np.stack([v_ref * t, 0.2 * t, np.full(k, 0.01), np.full(k, v_ref), np.zeros(k)], axis=-1)
    u_refs = np.tile([0.0, 0.0], (k, 1))
    saturated = 0
    for scale in (0.05, 0.3, 3.0):
        for standstill in (False, True):
            x0 = x_refs[0] + rng.normal(size=5) * np.array([scale, scale, scale / 4, scale, 0.0])
            x0[4] = rng.uniform(-0.2, 0.2)  # heading bias
            xa, ua = jit.track(x0, x_refs, u_refs, 0.01, standstill=standstill)
            xb, ub = ref.track(x0, x_refs, u_refs, 0.01, standstill=standstill)
            np.testing.assert_allclose(xa, xb, atol=1e-9, rtol=0)
            np.testing.assert_allclose(ua, ub, atol=1e-9, rtol=0)
            assert np.abs(xa - x0).max() > 1e-3  # the loop moved the state
            raw = ref.raw(np.array([x0[0], x0[1], x0[2] + x0[4], x0[3], 0.0]), x_refs[0], u_refs[0])
            saturated += int(np.abs(raw - ua).max() > 1e-6)
    assert 0 < saturated < 6  # both branches of the saturation were driven


def test_compiled_track_refuses_an_empty_reference():
    _needs(True)
    fast = NumpyC3M(load_controller("c3m", models=model_set_for_scene("random", None)), compiled=True)
    with pytest.raises(ValueError, match="at least one step"):
        fast.track(np.zeros(5), np.zeros((0, 5)), np.zeros((0, 2)), 0.01)


@pytest.mark.parametrize("compiled", [False, True], ids=["numpy", "numba"])
def test_evaluate_each_equals_one_call_per_state(compiled):
    _needs(compiled)
    fast = NumpyC3M(load_controller("c3m", models=model_set_for_scene("commonroad", None)), compiled=compiled)
    rng = np.random.default_rng(2)
    x_refs = np.column_stack([rng.uniform(-5, 5, (7, 2)), rng.uniform(-3, 3, 7), rng.uniform(0, 30, 7), np.zeros(7)])
    x_hats = x_refs + rng.normal(size=(7, 5)) * np.array([1.0, 1.0, 0.3, 1.0, 0.0])
    u_refs = rng.normal(size=(7, 2))
    each = fast.evaluate_each(x_hats, x_refs, u_refs)
    one = np.stack([fast(a, b, c) for a, b, c in zip(x_hats, x_refs, u_refs)])
    np.testing.assert_allclose(each, one, atol=1e-12, rtol=0)
    assert fast.evaluate_each(x_hats[:0], x_refs[:0], u_refs[:0]).shape == (0, 2)
    with pytest.raises(ValueError, match="same number of rows"):
        fast.evaluate_each(x_hats, x_refs[:3], u_refs)


def test_warm_up_compiles_every_kernel_for_the_types_used():
    """``make install``'s warm-up leaves each kernel with the signature the controller then calls it with (no
    compilation at the first ``drive``)."""
    _needs(True)
    from density_planner.control import _jit
    from density_planner.control.fast import warm_up

    assert warm_up()
    fast = NumpyC3M(load_controller("c3m", models=model_set_for_scene("commonroad", None)), compiled=True)
    before = {k: len(getattr(_jit, k).signatures) for k in ("control", "control_many", "track")}
    fast(np.zeros(5), np.zeros(5), np.zeros(2))
    fast.evaluate_each(np.zeros((2, 5)), np.zeros((2, 5)), np.zeros((2, 2)))
    fast.track(np.zeros(5), np.zeros((3, 5)), np.zeros((3, 2)), 0.01, standstill=True)
    after = {k: len(getattr(_jit, k).signatures) for k in ("control", "control_many", "track")}
    assert after == before and min(before.values()) >= 1

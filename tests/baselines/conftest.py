"""Baseline tests run torch single-threaded: their predictor calls are many small batches, for which extra
OpenMP threads on a shared machine cost more than they give.

No baseline test may solve with IPOPT's CPU-time cap: how many iterations fit in a CPU-time budget depends on the
machine and its load, so a capped run is not reproducible. The guard below fails any test that builds an NLP with
a finite ``max_cpu_time`` (tests set ``max_cpu_time = math.inf`` and rely on the deterministic ``max_iter``)."""

from __future__ import annotations

import math

import pytest


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    """Every test here on one torch thread (tests/conftest.py)."""


@pytest.fixture(autouse=True)
def _no_cpu_time_cap(monkeypatch):
    try:
        from density_planner.planners import _nlp, mpc, oracle
    except ImportError:  # pragma: no cover - the modules import without casadi
        yield
        return
    original = _nlp.ipopt_options
    capped: list[float] = []

    def recording(*, max_iter, max_cpu_time=math.inf, **kwargs):
        if max_cpu_time != math.inf:
            capped.append(max_cpu_time)  # recorded, not raised: the planners turn exceptions into a status
        return original(max_iter=max_iter, max_cpu_time=max_cpu_time, **kwargs)

    for module in (mpc, oracle):
        monkeypatch.setattr(module, "ipopt_options", recording)
    yield
    assert not capped, (f"a test solved with IPOPT's CPU-time cap ({capped[0]} s): results would depend on the "
                        "machine's load; set max_cpu_time=math.inf and limit max_iter")

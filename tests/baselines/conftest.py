"""Baseline tests run torch single-threaded: their predictor calls are many small batches, for which extra
OpenMP threads on a shared machine cost more than they give."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)

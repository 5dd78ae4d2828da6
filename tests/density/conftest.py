"""Shared fixtures of the density tests: session-wide tiny data sets (generated once, read-only)."""

from __future__ import annotations

import pytest
from density_testdata import SMALL, TINY, make_data


@pytest.fixture(scope="session")
def tiny_data(tmp_path_factory):
    return make_data(tmp_path_factory.mktemp("tiny"), TINY)


@pytest.fixture(scope="session")
def small_data(tmp_path_factory):
    return make_data(tmp_path_factory.mktemp("small"), SMALL)


@pytest.fixture(autouse=True)
def _one_thread(one_torch_thread):
    """Every test here on one torch thread (tests/conftest.py)."""

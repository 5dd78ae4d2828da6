"""Fixtures of the environment tests: small synthetic inD recordings and the CommonRoad scenarios shipped with
the package."""

from __future__ import annotations

from pathlib import Path

import pytest
from env_testdata import two_tracks


@pytest.fixture
def ind_dir(tmp_path: Path) -> Path:
    """A folder with recording 7: a car driving along +x at 5 m/s and a pedestrian appearing at t = 4 s."""
    from ind_testdata import write_ind_recording

    write_ind_recording(tmp_path, 7, two_tracks())
    return tmp_path


@pytest.fixture
def commonroad_dir() -> Path:
    """The BSD-licensed CommonRoad scenarios in the package (density_planner/data/commonroad): never skipped."""
    from density_planner.evaluation.environments import shipped_commonroad_dir

    return shipped_commonroad_dir()

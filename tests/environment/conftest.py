"""Fixtures of the environment tests: small synthetic inD recordings and the shared CommonRoad scenarios."""

from __future__ import annotations

from pathlib import Path

import pytest
from env_testdata import two_tracks

SHARED = (Path(__file__).resolve().parents[2] / ".." / "shared").resolve()
COMMONROAD_DIR = SHARED / "data" / "commonroad"


@pytest.fixture
def ind_dir(tmp_path: Path) -> Path:
    """A folder with recording 7: a car driving along +x at 5 m/s and a pedestrian appearing at t = 4 s."""
    from density_planner.environment import write_ind_recording

    write_ind_recording(tmp_path, 7, two_tracks())
    return tmp_path


@pytest.fixture
def commonroad_dir() -> Path:
    if not COMMONROAD_DIR.is_dir():
        pytest.skip(f"shared CommonRoad scenarios not found ({COMMONROAD_DIR})")
    return COMMONROAD_DIR

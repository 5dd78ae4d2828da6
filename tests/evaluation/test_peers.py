"""The reactive-planner peer adapter: result parsing, missing environment, and (where the peer's environment
exists) one real run."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from density_planner.errors import DataError
from density_planner.evaluation.peers import (
    REACTIVE_SCRIPT,
    default_reactive_python,
    parse_peer_result,
    run_reactive_peer,
)

SHIPPED = Path(__file__).resolve().parents[2] / "src" / "density_planner" / "data" / "commonroad"


def test_parse_converts_steps_to_absolute_times():
    raw = {"status": "ok", "reason": "", "dt": 0.1, "states": [[3, 1.0, 2.0, 0.5, 4.0], [4, 1.4, 2.0, 0.5, 4.0]],
           "planning_time_s": 0.2, "n_replans": 1, "vehicle": {"length": 4.5, "width": 1.6}}
    run = parse_peer_result(raw)
    np.testing.assert_allclose(run.times, [0.3, 0.4])
    assert run.states.shape == (2, 4)
    assert run.status == "ok" and run.n_replans == 1


@pytest.mark.parametrize("states", [[[0, 1.0, float("nan"), 0.0, 1.0]], [[0, 1.0]], "x"])
def test_parse_rejects_malformed_results(states):
    with pytest.raises(DataError, match="malformed peer result"):
        parse_peer_result({"states": states, "dt": 0.1})


def test_missing_environment_names_the_script(tmp_path):
    xml = next(SHIPPED.glob("*.xml"))
    with pytest.raises(DataError, match="make_reactive_venv.sh"):
        run_reactive_peer(xml, python=tmp_path / "nope" / "python")


def test_missing_scenario(tmp_path):
    with pytest.raises(DataError, match="scenario file not found"):
        run_reactive_peer(tmp_path / "missing.xml")


def test_driver_ships_with_the_repository():
    assert REACTIVE_SCRIPT.is_file()


@pytest.mark.slow
@pytest.mark.skipif(not default_reactive_python().exists(), reason="peer environment not created "
                    "(bash benchmarks/peers/make_reactive_venv.sh)")
def test_real_peer_run_starts_at_the_planning_problem():
    xml = SHIPPED / "ZAM_Tutorial-1_2_T-1.xml"
    if not xml.is_file():
        xml = next(SHIPPED.glob("*.xml"))
    run = run_reactive_peer(xml, timeout=300)
    assert run.states.shape[0] >= 1
    # times start at the planning problem's initial time and advance by the scenario's step
    if run.states.shape[0] > 1:
        assert np.all(np.diff(run.times) > 0)

"""Peer planners that run in their own virtual environments, judged by this package's verdict.

The only peer today is CommonRoad's sampling-based Frenet planner, ``commonroad-reactive-planner`` 2025.1 (what
CommonRoad users run). It pins ``commonroad-io < 2025`` and Python < 3.12, so it never shares this package's
environment: ``bash benchmarks/peers/make_reactive_venv.sh`` creates ``.peers/reactive-venv`` and
``benchmarks/peers/run_reactive.py`` drives the planner there with its default settings (its docstring lists
the few execution settings and version mismatches handled). This module starts that script in a subprocess and
returns its executed trajectory as arrays on the scenario's absolute time axis, ready for the verdict.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DataError

__all__ = ["PeerRun", "REACTIVE_SCRIPT", "default_reactive_python", "run_reactive_peer"]

#: the driver script, run with the peer's own Python
REACTIVE_SCRIPT = Path(__file__).resolve().parents[3] / "benchmarks" / "peers" / "run_reactive.py"

#: environment variable naming the peer's Python interpreter (default: ``.peers/reactive-venv/bin/python`` in the
#: repository)
REACTIVE_PYTHON_ENV = "DENSITY_PLANNER_REACTIVE_PYTHON"


@dataclass
class PeerRun:
    """What a peer planner executed on one scenario.

    Attributes:
        status: ``"ok"`` when the peer reports success by its own goal test, else ``"failed"``.
        reason: the peer's failure reason ("" on success).
        times: ``(K,)`` absolute scenario times [s] of the executed states (``time_step * dt``).
        states: ``(K, 4)`` executed states of the vehicle's centre ``(x [m], y [m], heading [rad], v [m/s])``.
        planning_time: summed wall time of the peer's replans [s] (its own measurement).
        wall_time: wall time of the whole subprocess [s] (start-up and scenario loading included).
        n_replans: number of replans.
        vehicle: ``{"length": m, "width": m}`` of the peer's vehicle.
        raw: the driver's JSON output.
    """

    status: str
    reason: str
    times: np.ndarray
    states: np.ndarray
    planning_time: float
    wall_time: float
    n_replans: int
    vehicle: dict[str, float]
    raw: dict[str, Any] = field(repr=False, default_factory=dict)


def default_reactive_python() -> Path:
    """The peer's interpreter: ``$DENSITY_PLANNER_REACTIVE_PYTHON`` or ``.peers/reactive-venv/bin/python``."""
    env = os.environ.get(REACTIVE_PYTHON_ENV)
    if env:
        return Path(env)
    return REACTIVE_SCRIPT.parents[2] / ".peers" / "reactive-venv" / "bin" / "python"


def run_reactive_peer(
    scenario: str | Path, *, python: str | Path | None = None, timeout: float = 600.0
) -> PeerRun:
    """Run the reactive planner on ``scenario`` in its own environment.

    Args:
        scenario: CommonRoad XML file.
        python: the peer's interpreter (default :func:`default_reactive_python`).
        timeout: wall-clock limit [s] of the subprocess; a run past it is a failed run with that reason.

    Raises:
        DataError: the peer's environment or driver is missing (names the script that creates it), or the scenario
            file does not exist.
    """
    import time

    scenario = Path(scenario)
    if not scenario.is_file():
        raise DataError(f"scenario file not found: {scenario}")
    python = Path(python) if python is not None else default_reactive_python()
    if not python.exists():
        raise DataError(
            f"the reactive planner's environment is missing ({python}); create it with "
            f"`bash benchmarks/peers/make_reactive_venv.sh` or set {REACTIVE_PYTHON_ENV}"
        )
    if not REACTIVE_SCRIPT.is_file():
        raise DataError(f"peer driver not found: {REACTIVE_SCRIPT} (it ships with the repository, not the wheel)")
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            [str(python), str(REACTIVE_SCRIPT), str(scenario)],
            capture_output=True,
            text=True,
            timeout=timeout,
            check=False,
            env={**os.environ, "PYTHONWARNINGS": "ignore"},
        )
    except subprocess.TimeoutExpired:
        return _failed(f"peer exceeded its {timeout:g}-s limit", time.perf_counter() - t0)
    wall = time.perf_counter() - t0
    line = next((ln for ln in proc.stdout.splitlines()[::-1] if ln.startswith("{")), None)
    if line is None:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1][:200]
        return _failed(f"peer exited with code {proc.returncode} and no result ({tail})", wall)
    return parse_peer_result(json.loads(line), wall_time=wall)


def parse_peer_result(raw: dict[str, Any], *, wall_time: float = float("nan")) -> PeerRun:
    """A :class:`PeerRun` from the driver's JSON (validated: a malformed result raises :class:`DataError`)."""
    try:
        rows = np.asarray(raw.get("states", []), dtype=np.float64).reshape(-1, 5)
        dt = float(raw.get("dt", 0.1))
    except (TypeError, ValueError) as exc:
        raise DataError(f"malformed peer result ({exc})") from exc
    if not np.isfinite(rows).all():
        raise DataError("malformed peer result: non-finite states")
    return PeerRun(
        status=str(raw.get("status", "failed")),
        reason=str(raw.get("reason", "")),
        times=rows[:, 0] * dt,
        states=rows[:, 1:5].copy(),
        planning_time=float(raw.get("planning_time_s", float("nan"))),
        wall_time=wall_time,
        n_replans=int(raw.get("n_replans", 0)),
        vehicle=dict(raw.get("vehicle", {})),
        raw=raw,
    )


def _failed(reason: str, wall: float) -> PeerRun:
    return PeerRun("failed", reason, np.zeros(0), np.zeros((0, 4)), float("nan"), wall, 0, {}, {"reason": reason})


if __name__ == "__main__":  # pragma: no cover - manual use: python -m density_planner.evaluation.peers FILE.xml
    run = run_reactive_peer(sys.argv[1])
    print(run.status, run.reason, len(run.times), f"{run.planning_time:.2f} s")

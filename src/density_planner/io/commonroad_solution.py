"""CommonRoad solution files (``solution.xml``) of planned trajectories.

:func:`write_solution` turns a car trajectory ``(T, nx)`` on the planning grid into a CommonRoad
``PlanningProblemSolution`` and writes it with commonroad-io's ``CommonRoadSolutionWriter``, so the plan can be
handed to the CommonRoad tools (feasibility checker, goal check, cost evaluation, benchmark upload). The vehicle
model, vehicle type and cost function come from :class:`SolutionConfig` (``[solution]`` in the run
configuration):

* ``KS`` (kinematic single-track, default): position, orientation and velocity from the state (the system's
  ``position_indices``, ``heading_index``, ``speed_index``); the steering angle from the state where the system has
  one (a state named ``delta``: the KS system, :mod:`density_planner.systems.ks`, whose states are CommonRoad's KS
  states), else from the yaw rate ``omega`` of the car model, ``delta = atan(l_wb omega / v)`` (wheelbase
  ``l_wb = a + b`` of the vehicle type), clipped to the vehicle's steering limits, held at its previous value while
  ``v`` is ~0;
* ``ST`` (single-track): as ``KS`` plus ``yaw_rate = omega`` (for a steering-angle state ``v tan(delta) / l_wb``) and
  ``slip_angle = 0`` (the kinematic models have no slip);
* ``PM`` (point mass): position and the velocity vector ``v (cos theta, sin theta)``.

The trajectory is resampled (linearly) to the scenario's time step, starting at the planning problem's initial
time step; the heading is shifted by a multiple of 2 pi so that the first orientation lies in ``[-pi, pi)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["SolutionConfig", "write_solution", "solution_states", "read_solution"]

_MODELS = ("KS", "ST", "PM")
_TYPES = ("FORD_ESCORT", "BMW_320i", "VW_VANAGON")


@dataclass(frozen=True)
class SolutionConfig:
    """What ``solution.xml`` names (TOML section ``[solution]``)."""

    #: CommonRoad vehicle model of the written states: KS (kinematic single-track), ST (single-track), PM (point
    #: mass)
    vehicle_model: str = "KS"
    #: CommonRoad vehicle type (its wheelbase and steering limits derive the steering angle): FORD_ESCORT,
    #: BMW_320i, VW_VANAGON
    vehicle_type: str = "BMW_320i"
    #: CommonRoad cost function id (e.g. SM1, JB1, WX1, SA1, SM2, SM3, MW1, TR1)
    cost_function: str = "SM1"

    def __post_init__(self) -> None:
        from ..errors import ConfigError

        if self.vehicle_model not in _MODELS:
            raise ConfigError(f"solution.vehicle_model must be one of {', '.join(_MODELS)}, got "
                              f"{self.vehicle_model!r}")
        if self.vehicle_type not in _TYPES:
            raise ConfigError(f"solution.vehicle_type must be one of {', '.join(_TYPES)}, got {self.vehicle_type!r}")
        if (self.vehicle_model, self.cost_function) == (SolutionConfig.vehicle_model, SolutionConfig.cost_function):
            return  # the defaults (a valid pair, tests/io): no import of commonroad's solution module (~0.1 s)
        try:
            from commonroad.common.solution import SupportedCostFunctions
        except ImportError:  # checked again when writing
            return
        supported = [c.name for c in SupportedCostFunctions[self.vehicle_model].value]
        if self.cost_function not in supported:
            raise ConfigError(f"solution.cost_function must be one of {', '.join(supported)} for vehicle model "
                              f"{self.vehicle_model}, got {self.cost_function!r}")


def _vehicle_parameters(vehicle_type: str) -> tuple[float, float, float]:
    """``(wheelbase, steering_min, steering_max)`` of a CommonRoad vehicle type."""
    from commonroad.common.solution import VehicleType

    number = VehicleType[vehicle_type].value
    module = __import__(f"vehiclemodels.parameters_vehicle{number}", fromlist=["x"])
    p = getattr(module, f"parameters_vehicle{number}")()
    return float(p.a + p.b), float(p.steering.min), float(p.steering.max)


def solution_states(
    states: np.ndarray,
    inputs: np.ndarray | None,
    dt: float,
    *,
    scenario_dt: float,
    initial_time_step: int,
    config: SolutionConfig,
    state_index: dict[str, int],
) -> list[Any]:
    """CommonRoad states of ``config.vehicle_model`` from the states ``(T, nx)`` (``k dt`` after the initial time
    step; ``state_index`` maps ``px, py, theta, v`` and, for a steering-angle state, ``delta`` to their columns) and
    their yaw-rate inputs ``(T - 1, nu)`` (``None``: finite differences of the heading; unused with ``delta``)."""
    from commonroad.scenario.state import KSState, PMState, STState

    x = np.asarray(states, dtype=np.float64)
    px, py, th, v = (x[:, state_index[n]] for n in ("px", "py", "theta", "v"))
    th = th - 2 * math.pi * math.floor((th[0] + math.pi) / (2 * math.pi))
    delta = x[:, state_index["delta"]] if "delta" in state_index else None
    if delta is not None:
        wheelbase = _vehicle_parameters(config.vehicle_type)[0]
        omega = v * np.tan(delta) / wheelbase
    elif inputs is not None and len(inputs):
        omega = np.asarray(inputs, dtype=np.float64)[:, 0]
        omega = np.concatenate([omega, omega[-1:]])[: len(x)]
    else:
        omega = np.gradient(th, dt) if len(x) > 1 else np.zeros(len(x))
    t = dt * np.arange(len(x))
    n_out = int(math.floor(t[-1] / scenario_dt + 1e-9)) + 1
    ts = scenario_dt * np.arange(n_out)

    def at(a: np.ndarray) -> np.ndarray:
        return np.interp(ts, t, a)

    px, py, th, v = at(px), at(py), at(th), at(v)
    if delta is not None:
        omega = at(np.asarray(omega))
    else:
        omega = np.asarray(omega)[np.minimum(np.searchsorted(t, ts + 1e-9, side="right") - 1, len(x) - 1)]
    out = []
    if config.vehicle_model == "PM":
        for k in range(n_out):
            out.append(PMState(time_step=initial_time_step + k, position=np.array([px[k], py[k]]),
                               velocity=float(v[k] * math.cos(th[k])), velocity_y=float(v[k] * math.sin(th[k]))))
        return out
    wheelbase, smin, smax = _vehicle_parameters(config.vehicle_type)
    steer = np.zeros(n_out)
    if delta is not None:
        steer = at(delta)
    else:
        prev = 0.0
        for k in range(n_out):
            if abs(v[k]) > 1e-3:
                prev = float(np.clip(math.atan(wheelbase * omega[k] / v[k]), smin, smax))
            steer[k] = prev
    for k in range(n_out):
        common = dict(time_step=initial_time_step + k, position=np.array([px[k], py[k]]),
                      steering_angle=float(steer[k]), velocity=float(v[k]), orientation=float(th[k]))
        if config.vehicle_model == "KS":
            out.append(KSState(**common))
        else:
            out.append(STState(**common, yaw_rate=float(omega[k]), slip_angle=0.0))
    return out


def preload(config: SolutionConfig | None = None) -> None:
    """Import what :func:`write_solution` needs (~0.2 s), e.g. in a process that waits for a plan to write."""
    try:
        from commonroad.common import common_scenario, solution  # noqa: F401
        from commonroad.scenario import trajectory  # noqa: F401

        _vehicle_parameters((config or SolutionConfig()).vehicle_type)
    except ImportError:  # write_solution says what is missing
        pass


def write_solution(
    path: str | Path,
    states: Any,
    inputs: Any | None,
    dt: float,
    *,
    scenario_id: str,
    planning_problem_id: int,
    scenario_dt: float,
    initial_time_step: int,
    config: SolutionConfig | None = None,
    state_names: tuple[str, ...] = ("px", "py", "theta", "v", "theta_bias"),
    computation_time: float | None = None,
    frame_offset: tuple[float, float] = (0.0, 0.0),
    system: Any = None,
) -> Path:
    """Write ``states (T, nx)`` (``k dt`` after the initial time step, inputs ``(T - 1, nu)`` or ``None``) as the
    solution of planning problem ``planning_problem_id`` of scenario ``scenario_id`` to ``path`` (atomically).

    ``frame_offset``: the scene's local frame relative to the file's (the importer moves far UTM coordinates to a
    local frame, ``scene.meta["frame_offset"]``); positions are written in the FILE's coordinates.

    ``system`` (a :class:`~density_planner.systems.base.System`, optional) locates position, heading and speed by
    its facts instead of the names ``px, py, theta, v``; a system with a steering-angle state (``delta``) writes it
    as the steering angle, and a system built for a CommonRoad vehicle (``system.vehicle.name``) must be written with
    that ``vehicle_type``."""
    try:
        from commonroad.common.common_scenario import ScenarioID
        from commonroad.common.solution import (
            CommonRoadSolutionWriter,
            CostFunction,
            PlanningProblemSolution,
            Solution,
            VehicleModel,
            VehicleType,
        )
        from commonroad.scenario.trajectory import Trajectory
    except ImportError:
        from ..errors import OptionalDependencyError

        raise OptionalDependencyError("commonroad-io", "commonroad", "writing solution.xml") from None
    config = config or SolutionConfig()
    if hasattr(states, "detach"):
        states = states.detach().cpu().numpy()
    if inputs is not None and hasattr(inputs, "detach"):
        inputs = inputs.detach().cpu().numpy()
    index = _state_index(state_names, system)
    vehicle = getattr(getattr(system, "vehicle", None), "name", None)
    if vehicle is not None and vehicle != config.vehicle_type:
        from ..errors import ConfigError

        raise ConfigError(f"solution.vehicle_type is {config.vehicle_type} but the {type(system).__name__} system "
                          f"models the {vehicle}; set solution.vehicle_type = \"{vehicle}\"")
    if any(frame_offset):
        import numpy as np

        states = np.array(states, dtype=np.float64, copy=True)
        states[:, index["px"]] += float(frame_offset[0])
        states[:, index["py"]] += float(frame_offset[1])
    cr_states = solution_states(states, inputs, dt, scenario_dt=scenario_dt, initial_time_step=initial_time_step,
                                config=config, state_index=index)
    trajectory = Trajectory(initial_time_step, cr_states)
    pps = PlanningProblemSolution(
        planning_problem_id=int(planning_problem_id),
        vehicle_model=VehicleModel[config.vehicle_model],
        vehicle_type=VehicleType[config.vehicle_type],
        cost_function=CostFunction[config.cost_function],
        trajectory=trajectory,
    )
    sid = ScenarioID.from_benchmark_id(scenario_id, "2020a")
    solution = Solution(sid, [pps], computation_time=computation_time)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    CommonRoadSolutionWriter(solution).write_to_file(output_path=str(tmp.parent), filename=tmp.name, overwrite=True)
    tmp.replace(path)
    return path


def _state_index(state_names: tuple[str, ...], system: Any) -> dict[str, int]:
    """Columns of ``px, py, theta, v`` (and ``delta`` where the state has a steering angle)."""
    if system is None:
        index = {n: state_names.index(n) for n in ("px", "py", "theta", "v")}
    else:
        if system.heading_index is None or system.speed_index is None:
            raise ValueError(f"solution.xml needs a system with heading and speed; {type(system).__name__} has none")
        ix, iy = system.position_indices
        index = {"px": ix, "py": iy, "theta": system.heading_index, "v": system.speed_index}
        state_names = tuple(system.state_names)
    if "delta" in state_names:
        index["delta"] = state_names.index("delta")
    return index


def read_solution(path: str | Path) -> Any:
    """The ``Solution`` of a CommonRoad solution file (commonroad-io's reader)."""
    from commonroad.common.solution import CommonRoadSolutionReader

    return CommonRoadSolutionReader.open(str(path))

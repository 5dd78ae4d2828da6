"""The system owns its facts: registry, pose <-> state, hidden states, planning bounds, the [system] section."""

from __future__ import annotations

import math

import pytest
import torch

from density_planner.config import dumps_toml, from_dict, load_config, to_dict
from density_planner.control.registry import load_controller, model_set, model_set_for_scene
from density_planner.settings import RunConfig
from density_planner.systems import KinematicCar, LinearSystem, SystemConfig, make_system, system_names
from density_planner.systems.car import car_domain
from density_planner.systems.registry import register_system


def test_registry_builds_the_car_in_each_domain_and_names_the_valid_choices():
    assert "car" in system_names()
    for domain, v_max in (("paper", 10.0), ("road", 40.0)):
        car = make_system("car", domain)
        assert isinstance(car, KinematicCar) and car.speed_max == v_max
    with pytest.raises(ValueError, match="unknown system 'boat'; valid choices: .*car"):
        make_system("boat")
    with pytest.raises(ValueError, match="no domain 'moon'; valid choices: paper, road"):
        make_system("car", "moon")


def test_registering_a_name_twice_is_refused(monkeypatch):
    from density_planner.systems import registry

    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))

    def build(domain):
        return LinearSystem([[0.0]], [[1.0]])

    register_system("test-linear-1d", domains=("only",), description="test")(build)
    register_system("test-linear-1d", domains=("only",), description="test")(build)  # same builder: fine
    with pytest.raises(ValueError, match="registered twice"):
        register_system("test-linear-1d", domains=("only",), description="test")(lambda d: build(d))


@pytest.mark.parametrize("heading", [-3.0, 0.5, 3.1, 7.0, -10.0])
def test_car_pose_round_trip_wraps_the_heading_into_its_box(heading):
    car = KinematicCar(car_domain("paper"))
    x = car.state_from_pose(1.0, -2.0, heading, 4.0)
    assert len(x) == car.nx and x[4] == 0.0
    lo, hi = car.state_bounds
    assert lo[2] <= x[2] <= hi[2] and math.cos(x[2]) == pytest.approx(math.cos(heading))
    assert math.sin(x[2]) == pytest.approx(math.sin(heading))
    pose = car.pose(torch.tensor(x))
    assert pose == pytest.approx((1.0, -2.0, x[2], 4.0))


def test_nominal_state_zeroes_the_hidden_bias_only():
    car = KinematicCar()
    x = torch.tensor([[1.0, 2.0, 0.3, 4.0, 0.2]])
    assert car.hidden_states == (4,)
    torch.testing.assert_close(car.nominal_state(x), torch.tensor([[1.0, 2.0, 0.3, 4.0, 0.0]]))
    lin = LinearSystem([[0.0, 0.0], [0.0, 0.0]], [[1.0, 0.0], [0.0, 1.0]])
    assert lin.nominal_state(x[:, :2]) is not None and torch.equal(lin.nominal_state(x[:, :2]), x[:, :2])


def test_car_planning_bounds_are_the_papers_box_and_scale_with_the_domain():
    paper = KinematicCar(car_domain("paper")).planning_bounds()
    assert paper[0][2:4] == pytest.approx((-math.pi + 0.2, 0.1)) and paper[1][2:4] == pytest.approx(
        (3 * math.pi - 0.2, 9.9))
    assert math.isinf(paper[0][0]) and math.isinf(paper[1][4])  # position from the scene, bias free
    road = KinematicCar(car_domain("road")).planning_bounds()
    assert road[1][3] == pytest.approx(39.9)


def test_a_system_without_heading_refuses_a_heading_and_has_no_error_box():
    lin = LinearSystem([[0.0, 0.0], [0.0, 0.0]], [[1.0, 0.0], [0.0, 1.0]])
    assert lin.state_from_pose(1.0, 2.0, 0.0, 0.0) == (1.0, 2.0)
    with pytest.raises(ValueError, match="no heading state"):
        lin.state_from_pose(1.0, 2.0, 0.5, 0.0)
    with pytest.raises(NotImplementedError, match="initial_error_max"):
        _ = lin.initial_error_max
    assert lin.speed_max == math.inf and lin.pose(torch.tensor([1.0, 2.0])) == (1.0, 2.0, 0.0, 0.0)


def test_model_sets_follow_the_scene_kind_within_the_system():
    assert model_set_for_scene("random").name == "paper"
    assert model_set_for_scene("commonroad").name == "road"
    assert model_set_for_scene("commonroad", "paper").name == "paper"
    assert model_set_for_scene("random", "auto", "car").name == "paper"
    with pytest.raises(ValueError, match="unknown model set"):
        model_set("nope")
    with pytest.raises(ValueError, match="unknown system 'boat'"):
        model_set_for_scene("random", None, "boat")
    assert load_controller("analytic", models="road").car.domain == "road"


def test_system_section_round_trips_through_toml(tmp_path):
    cfg = from_dict(RunConfig, {"system": {"name": "car", "models": "road", "controller": "analytic",
                                           "density": "exact"}})
    path = tmp_path / "config.toml"
    path.write_text(dumps_toml(cfg))
    again = load_config(RunConfig, path)
    assert again.system == SystemConfig("car", "road", "analytic", "exact")
    assert to_dict(again) == to_dict(cfg)
    with pytest.raises(ValueError, match="non-empty string"):
        SystemConfig(name="")

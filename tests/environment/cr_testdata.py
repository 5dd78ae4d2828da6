"""Hand-made CommonRoad 2020a scenarios for the importer tests (a uniquely named module: safe to import).

The road: two parallel straight lanelets along +x from x = 0 to 200 m, lanelet 1 on y in [0, 3.5] and lanelet 2
on y in [3.5 + gap, 7 + gap], and a sidewalk lanelet 3 on y in [-2, 0]. The ego starts at (10, 1.75) heading
+x at 5 m/s at time step ``start_step``; its recording is dynamic obstacle 10 (commonroad-crime convention).
Obstacle 11 drives in lanelet 2 at 5 m/s and its recording stops after ``n_recorded`` steps; obstacle 12 has a
set-based prediction (a box moving 1 m per step for 5 steps); static obstacle 20 stands at (150, 5.25).
"""

from __future__ import annotations

from pathlib import Path


def _pt(x: float, y: float) -> str:
    return f"<point><x>{x}</x><y>{y}</y></point>"


def _lanelet(lid: int, y0: float, y1: float, ltype: str, extra: str = "", x0: float = 0.0, x1: float = 200.0,
             xs: tuple[float, ...] = ()) -> str:
    xs = xs or (x0, x1)
    left = "".join(_pt(x, y1) for x in xs)
    right = "".join(_pt(x, y0) for x in xs)
    return (f'<lanelet id="{lid}"><leftBound>{left}<lineMarking>solid</lineMarking></leftBound>'
            f"<rightBound>{right}<lineMarking>solid</lineMarking></rightBound>{extra}"
            f"<laneletType>{ltype}</laneletType></lanelet>")


def _state(tag: str, x: float, y: float, theta: float, v: float, step: int) -> str:
    return (f"<{tag}><position>{_pt(x, y)}</position><orientation><exact>{theta}</exact></orientation>"
            f"<time><exact>{step}</exact></time><velocity><exact>{v}</exact></velocity>"
            f"<acceleration><exact>0.0</exact></acceleration></{tag}>")


def _rect(length: float, width: float, cx: float | None = None, cy: float | None = None, o: float = 0.0) -> str:
    centre = "" if cx is None else f"<orientation>{o}</orientation><center><x>{cx}</x><y>{cy}</y></center>"
    return f"<rectangle><length>{length}</length><width>{width}</width>{centre}</rectangle>"


def scenario_xml(
    *,
    gap: float = 0.0,
    start_step: int = 0,
    start_speed: float = 5.0,
    start_x: str = "10.0",
    ego_recorded: bool = True,
    n_recorded: int = 20,
    goal: str | None = None,
    planning_problem: bool = True,
    traffic_light: bool = False,
    lanelet_x: str | None = None,
    dt: float = 0.1,
) -> str:
    """The scenario described in the module docstring as XML text (options change one part each)."""
    light_ref = '<stopLine>' + _pt(100.0, 0.0) + _pt(100.0, 3.5) + '<lineMarking>solid</lineMarking></stopLine>' \
        '<trafficLightRef ref="300"/>' if traffic_light else ""
    lanelets = [
        _lanelet(1, 0.0, 3.5, "urban", light_ref),
        _lanelet(2, 3.5 + gap, 7.0 + gap, "urban"),
        _lanelet(3, -2.0, 0.0, "sidewalk"),
    ]
    if lanelet_x is not None:  # a vertex with a bad coordinate
        lanelets.append(f'<lanelet id="4"><leftBound><point><x>{lanelet_x}</x><y>12</y></point>{_pt(200, 12)}'
                        f"<lineMarking>solid</lineMarking></leftBound><rightBound>{_pt(0, 9)}{_pt(200, 9)}"
                        "<lineMarking>solid</lineMarking></rightBound><laneletType>urban</laneletType></lanelet>")
    light = ""
    if traffic_light:  # 2 s green, 3 s red, from time step 0
        light = ('<trafficLight id="300"><cycle><cycleElement><duration>20</duration><color>green</color>'
                 '</cycleElement><cycleElement><duration>30</duration><color>red</color></cycleElement>'
                 f'<timeOffset>0</timeOffset></cycle><position>{_pt(100.0, -0.5)}</position>'
                 "<active>true</active></trafficLight>")
    obstacles = []
    n_steps = 100
    if ego_recorded:
        states = "".join(_state("state", 10.0 + 0.5 * k, 1.75, 0.0, 5.0, k) for k in range(1, n_steps + 1))
        obstacles.append('<dynamicObstacle id="10"><type>car</type><shape>' + _rect(4.5, 1.8) + "</shape>"
                         + _state("initialState", 10.0 + 0.5 * 0, 1.75, 0.0, 5.0, 0)
                         + f"<trajectory>{states}</trajectory></dynamicObstacle>")
    states = "".join(_state("state", 30.0 + 0.5 * k, 5.25 + gap, 0.0, 5.0, k) for k in range(1, n_recorded + 1))
    obstacles.append('<dynamicObstacle id="11"><type>car</type><shape>' + _rect(4.0, 2.0) + "</shape>"
                     + _state("initialState", 30.0, 5.25 + gap, 0.0, 5.0, 0)
                     + f"<trajectory>{states}</trajectory></dynamicObstacle>")
    occ = "".join(f"<occupancy><shape>{_rect(4.0, 2.0, 60.0 + k, 1.75)}</shape><time><exact>{k}</exact></time>"
                  "</occupancy>" for k in range(1, 6))
    obstacles.append('<dynamicObstacle id="12"><type>car</type><shape>' + _rect(4.0, 2.0) + "</shape>"
                     + _state("initialState", 60.0, 1.75, 0.0, 10.0, 0)
                     + f"<occupancySet>{occ}</occupancySet></dynamicObstacle>")
    obstacles.append('<staticObstacle id="20"><type>parkedVehicle</type><shape>' + _rect(4.0, 2.0) + "</shape>"
                     + _state("initialState", 150.0, 5.25 + gap, 0.0, 0.0, 0) + "</staticObstacle>")
    if goal is None:
        goal = f"<position>{_rect(10.0, 3.5, 80.0, 1.75)}</position><time><intervalStart>80</intervalStart>" \
               "<intervalEnd>100</intervalEnd></time>"
    problem = ""
    if planning_problem:
        problem = (f'<planningProblem id="100"><initialState><position>{_pt(start_x, 1.75)}</position>'
                   f"<velocity><exact>{start_speed}</exact></velocity><orientation><exact>0.0</exact></orientation>"
                   "<yawRate><exact>0.0</exact></yawRate><slipAngle><exact>0.0</exact></slipAngle>"
                   f"<time><exact>{start_step}</exact></time></initialState><goalState>{goal}</goalState>"
                   "</planningProblem>")
    return ("<?xml version='1.0' encoding='UTF-8'?>\n"
            f'<commonRoad timeStepSize="{dt}" commonRoadVersion="2020a" author="tests" affiliation="tests" '
            'source="hand-made" benchmarkID="ZAM_Handmade-1_1_T-1" date="2024-01-01">'
            "<location><geoNameId>-999</geoNameId><gpsLatitude>999</gpsLatitude><gpsLongitude>999</gpsLongitude>"
            "</location><scenarioTags><Urban/></scenarioTags>"
            + "".join(lanelets) + light + "".join(obstacles) + problem + "</commonRoad>")


def write_scenario(path: Path, **options) -> Path:
    path.write_text(scenario_xml(**options))
    return path

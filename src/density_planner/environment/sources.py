"""Scene sources: one registration per kind of scene (``random``, ``ind``, ``commonroad``, ``file``), and the one
function that builds a scene from a :class:`SceneRequest`, used by the command line (``--env KIND``) and the
benchmarks alike.

A source is registered with :func:`register_scene_source`: its builder ``builder(request, run_config, system) ->
Scene``, a description and the request fields it reads (``seed``, ``file``, ``data_dir``, ``recording``,
``start_time``; the others are refused with a one-line error) and requires. Which model set (system domain,
controller and density weights) a kind of scene needs is registered with the model set
(:attr:`density_planner.control.registry.ModelSet.scene_kinds`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from .scene import Scene

__all__ = ["SceneRequest", "SceneSource", "register_scene_source", "scene_source", "scene_kinds", "build_scene"]


@dataclass(frozen=True)
class SceneRequest:
    """Which scene to build: its source ``kind`` and the options that source reads (``None``: not given)."""

    kind: str
    #: random: scene number (default 0); ind: seed of the start/goal sampler; commonroad: seed of the start/goal
    #: sampler (with ``sample_start_goal``)
    seed: int | None = None
    #: commonroad: scenario ``.xml``; file: scene ``.npz`` written by ``density-planner env``
    file: str | Path | None = None
    #: ind: folder with the ``NN_*.csv`` files
    data_dir: str | Path | None = None
    #: ind: recording number
    recording: int | None = None
    #: ind: start of the window [s] (default 0)
    start_time: float | None = None
    #: commonroad: sample a start and goal on the road instead of the planning problem (``None``: the
    #: configuration's ``commonroad.sample_start_goal``)
    sample_start_goal: bool | None = None

    def given(self) -> tuple[str, ...]:
        """Names of the options that are set."""
        return tuple(f.name for f in fields(self) if f.name != "kind" and getattr(self, f.name) is not None)


@dataclass(frozen=True)
class SceneSource:
    """A registered scene source (see the module docstring)."""

    kind: str
    builder: Callable[[SceneRequest, Any, Any], Scene]
    description: str
    #: request options it reads
    uses: tuple[str, ...] = ()
    #: request options it needs, and how the error names them (e.g. ``"--data-dir D and --recording N"``)
    requires: tuple[str, ...] = ()
    requires_text: str = ""


_SOURCES: dict[str, SceneSource] = {}


def register_scene_source(kind: str, description: str, *, uses: tuple[str, ...] = (), requires: tuple[str, ...] = (),
                          requires_text: str = "") -> Callable:
    """Decorator registering ``builder(request, run_config, system) -> Scene`` as the source ``kind``."""

    def deco(builder: Callable[[SceneRequest, Any, Any], Scene]) -> Callable[[SceneRequest, Any, Any], Scene]:
        if kind in _SOURCES and _SOURCES[kind].builder is not builder:
            raise ValueError(f"scene source {kind!r} registered twice")
        _SOURCES[kind] = SceneSource(kind, builder, description, tuple(uses), tuple(requires),
                                     requires_text or " and ".join("--" + r.replace("_", "-") for r in requires))
        return builder

    return deco


def scene_kinds() -> tuple[str, ...]:
    """Registered scene source kinds."""
    return tuple(_SOURCES)


def scene_source(kind: str) -> SceneSource:
    """The registration of the scene source ``kind``."""
    if kind not in _SOURCES:
        raise ValueError(f"unknown scene kind {kind!r}; valid choices: {', '.join(_SOURCES)}")
    return _SOURCES[kind]


def build_scene(request: SceneRequest, run_config: Any, *, system: Any = None, where: str | None = None,
                quiet: bool = True) -> Scene:
    """The scene ``request`` asks for, built with the matching section of ``run_config``
    (:class:`~density_planner.settings.RunConfig`).

    Args:
        system: supplies the speed and acceleration bounds of the sources that check the start's domain
            (CommonRoad); ``None``: the source's default.
        where: how error messages name the source (default ``--env KIND``).
        quiet: silence the warnings commonroad-io logs about every legacy element it converts.

    Raises:
        ValueError: an unknown kind, a missing option or an option the source does not read (one line naming the
            command-line flag).
    """
    source = scene_source(request.kind)
    where = where or f"--env {request.kind}"
    missing = [name for name in source.requires if getattr(request, name) is None]
    if missing:
        raise ValueError(f"{where} needs {source.requires_text}")
    for name in request.given():
        if name not in source.uses:
            raise ValueError(f"--{name.replace('_', '-')} is not used with {where}")
    if quiet:
        logging.getLogger("commonroad").setLevel(logging.ERROR)
    return source.builder(request, run_config, system)


# ------------------------------------------------------------------------------------------------ the sources
@register_scene_source("random", "random artificial scene (the paper's generator; [random_scene])",
                       uses=("seed",))
def _random(request: SceneRequest, run_config: Any, system: Any) -> Scene:
    from .random_scene import random_scene

    return random_scene(request.seed or 0, run_config.random_scene)


@register_scene_source("ind", "inD recording: a window of recorded traffic ([ind])",
                       uses=("seed", "data_dir", "recording", "start_time"), requires=("data_dir", "recording"),
                       requires_text="--data-dir D and --recording N")
def _ind(request: SceneRequest, run_config: Any, system: Any) -> Scene:
    from ..config import update
    from .ind import load_ind_scene

    changes: dict[str, Any] = {} if request.seed is None else {"seed": request.seed}
    if request.start_time is not None:
        changes["start_time"] = request.start_time
    assert request.data_dir is not None and request.recording is not None  # required by the registration
    return load_ind_scene(request.data_dir, request.recording, update(run_config.ind, changes))


@register_scene_source("commonroad", "CommonRoad XML scenario ([commonroad]; extra 'commonroad')",
                       uses=("seed", "file", "sample_start_goal"), requires=("file",), requires_text="--file F.xml")
def _commonroad(request: SceneRequest, run_config: Any, system: Any) -> Scene:
    from ..config import update
    from .commonroad import load_commonroad_scene

    changes: dict[str, Any] = {} if request.seed is None else {"seed": request.seed}
    if request.sample_start_goal is not None:
        changes["sample_start_goal"] = request.sample_start_goal
    assert request.file is not None  # required by the registration
    return load_commonroad_scene(request.file, update(run_config.commonroad, changes), system=system)


@register_scene_source("file", "a saved scene (.npz written by `density-planner env`)",
                       uses=("file",), requires=("file",), requires_text="--file SCENE.npz")
def _file(request: SceneRequest, run_config: Any, system: Any) -> Scene:
    from .scene import load_scene

    assert request.file is not None  # required by the registration
    return load_scene(request.file)

"""The environments of a benchmark sweep: :class:`EnvSpec` (how to build one, JSON-serialisable and cheap to ship
to workers), the sweeps' lists of environments (:func:`artificial_envs`, :func:`real_envs`) and
:func:`build_scene`, which turns a spec into a scene through the scene sources of
:mod:`density_planner.environment.sources` (the same builders as the command line's ``--env``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

__all__ = ["stable_seed", "EnvSpec", "artificial_envs", "real_envs", "shipped_commonroad_dir",
           "SHIPPED_REAL_SCENARIOS", "build_scene"]


def stable_seed(*parts: Any) -> int:
    """A seed in ``[0, 2^31)`` from ``parts`` (SHA-256 of their text; independent of the Python process)."""
    text = "/".join(str(p) for p in parts)
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "little") % (2**31)


@dataclass(frozen=True)
class EnvSpec:
    """How to build one benchmark environment (JSON-serialisable, cheap to ship to workers).

    Attributes:
        kind: ``"random"`` (artificial scene number ``seed``), ``"commonroad"`` (``file``; ``seed`` 0 = the
            scenario's planning problem, else a sampled start/goal pair) or ``"ind"`` (``data_dir``,
            ``recording``, window starting at ``start_time`` [s], start/goal sampler seed ``seed``).
        index: the environment's number in the sweep (seed of the initial distribution unless
            ``distribution_seed`` is given).
        name: unique name (file names of the records).
        distribution_seed: seed of the initial distribution (:attr:`law_seed`); ``bench commonroad`` derives it
            from the scenario's name, so that a scenario's initial law does not depend on the other files of its
            folder (its sorted position, the index, does).
    """

    kind: Literal["random", "commonroad", "ind"]
    index: int
    seed: int
    name: str
    file: str | None = None
    data_dir: str | None = None
    recording: int | None = None
    start_time: float | None = None
    distribution_seed: int | None = None

    @property
    def law_seed(self) -> int:
        """Seed of the environment's initial distribution: ``distribution_seed``, else the index."""
        return self.index if self.distribution_seed is None else self.distribution_seed

    def as_dict(self) -> dict[str, Any]:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}

    def request(self):
        """The :class:`~density_planner.environment.sources.SceneRequest` of this environment."""
        from ..environment.sources import SceneRequest

        if self.kind == "random":
            return SceneRequest("random", seed=self.seed)
        if self.kind == "ind":
            return SceneRequest("ind", seed=self.seed, data_dir=self.data_dir, recording=self.recording,
                                start_time=self.start_time or 0.0)
        if self.kind == "commonroad":
            file = str(self.file)
            if file.startswith(_SHIPPED + "/"):
                file = str(shipped_commonroad_dir() / file[len(_SHIPPED) + 1 :])
            # seed > 0: a start and goal sampled on the road instead of the scenario's planning problem
            sampled = self.seed > 0
            return SceneRequest("commonroad", file=file, seed=self.seed if sampled else None,
                                sample_start_goal=True if sampled else None)
        raise ValueError(f"unknown environment kind {self.kind!r}; valid choices: random, commonroad, ind")


def artificial_envs(indices: Sequence[int]) -> tuple[EnvSpec, ...]:
    """Random artificial scenes with the given numbers (``random_scene(i)``)."""
    return tuple(EnvSpec("random", int(i), int(i), f"random-{int(i)}") for i in indices)


#: prefix of the shipped CommonRoad scenarios in :attr:`EnvSpec.file` (resolved on the worker)
_SHIPPED = "<shipped>"


#: the shipped CommonRoad scenarios `bench real` uses without --data-dir
SHIPPED_REAL_SCENARIOS = ("USA_Peach-4_8_T-1.xml", "USA_US101-4_1_T-1.xml")


def shipped_commonroad_dir() -> Path:
    """Folder of the CommonRoad scenarios shipped with the package (NGSIM, BSD-3 licence file beside them)."""
    from importlib.resources import files

    return Path(str(files("density_planner") / "data" / "commonroad"))


def _ind_recordings(data_dir: Path) -> list[int]:
    recs = []
    for p in sorted(data_dir.glob("*_tracks.csv")):
        stem = p.name[: -len("_tracks.csv")]
        if stem.isdigit():
            recs.append(int(stem))
    return recs


def _ind_duration(data_dir: Path, recording: int) -> float | None:
    from ..environment.ind import ind_paths, read_recording_meta

    try:
        meta = read_recording_meta(ind_paths(data_dir, recording)["recording_meta"])
    except ValueError:
        return None
    d = meta.get("duration")
    return float(d) if isinstance(d, float) and math.isfinite(d) else None


def real_envs(
    indices: Sequence[int], data_dir: str | Path | None = None, *, window: float = 10.0
) -> tuple[EnvSpec, ...]:
    """Recorded-traffic environments.

    With ``data_dir``: inD recordings there (``NN_tracks.csv`` ...) or CommonRoad scenarios (``*.xml``). inD: the
    environment ``i`` uses recording ``i mod R``, a seeded random ``window``-second period of it and start/goal
    seed ``i``. CommonRoad: scenario ``i mod F`` with start/goal seed ``i div F`` (0: its planning problem).
    Without ``data_dir`` the shipped CommonRoad scenarios are used.
    """
    folder = Path(data_dir) if data_dir is not None else shipped_commonroad_dir()
    if not folder.is_dir():
        raise ValueError(f"--data-dir {folder} is not a directory")
    recordings = _ind_recordings(folder)
    if recordings:
        out = []
        for i in indices:
            rec = recordings[int(i) % len(recordings)]
            duration = _ind_duration(folder, rec)
            rng = np.random.default_rng(stable_seed("ind-window", rec, i))
            start = float(np.round(rng.uniform(0.0, duration - window), 1)) if duration and duration > window else (
                (int(i) // len(recordings)) * window)
            out.append(EnvSpec("ind", int(i), int(i), f"ind-rec{rec:02d}-t{start:g}-s{int(i)}", data_dir=str(folder),
                               recording=rec, start_time=start))
        return tuple(out)
    files = sorted(folder.glob("*.xml"))
    if data_dir is None:  # the package ships more scenarios (tests, examples); `bench real` uses the two NGSIM ones
        files = [f for f in files if f.name in SHIPPED_REAL_SCENARIOS]
    if not files:
        raise ValueError(f"--data-dir {folder} holds neither inD recordings (NN_tracks.csv) nor CommonRoad "
                         "scenarios (*.xml)")
    out = []
    for i in indices:
        f = files[int(i) % len(files)]
        k = int(i) // len(files)
        name = f"{_SHIPPED}/{f.name}" if data_dir is None else str(f)
        out.append(EnvSpec("commonroad", int(i), k, f"cr-{f.stem}-s{k}", file=name))
    return tuple(out)


def build_scene(env: EnvSpec, run_config: Any, system: Any = None):
    """The :class:`~density_planner.environment.scene.Scene` of ``env`` built with ``run_config``'s sections
    (``system``: the domain checks of CommonRoad scenes; default the run's system for the scene kind, see
    :func:`~density_planner.planners.context.run_system`)."""
    from ..environment.sources import build_scene as build_source_scene
    from ..planners.context import run_system

    scene = build_source_scene(env.request(), run_config, system=system or run_system(run_config, env.kind),
                               where=f"environment {env.name}")
    if scene.name != env.name:
        scene = dataclasses.replace(scene, name=env.name)
    return scene

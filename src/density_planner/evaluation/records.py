"""Benchmark records on disk: one JSON file per run under ``DIR/records/<setting>/`` and one map per environment
(``maps/<env>.npz``); reading them back (:func:`scan_records`, :func:`load_records`), checking them
(:func:`record_problem`) and the part of a record that must not depend on where it ran (:func:`identity_view`).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .benchmark_settings import SETTINGS

__all__ = ["RECORD_SCHEMA", "record_path", "map_path", "scene_map_arrays", "record_problem", "read_record",
           "BadRecord", "scan_records", "load_records", "load_scene_map", "identity_view"]

log = logging.getLogger(__name__)

#: version of the record layout
RECORD_SCHEMA = 1


def record_path(out: str | Path, setting: str, env: str, planner: str, variant: str) -> Path:
    """``DIR/records/<setting>/<env>__<planner>__<variant>.json``."""
    return Path(out) / "records" / setting / f"{env}__{planner}__{variant}.json"


def map_path(out: str | Path, setting: str, env: str) -> Path:
    """``DIR/records/<setting>/maps/<env>.npz``."""
    return Path(out) / "records" / setting / "maps" / f"{env}.npz"


def scene_map_arrays(scene) -> dict[str, Any]:
    """Compact picture of a scene for the figures: time-max occupancy as uint8 (0-255), geometry, start, goal."""
    occ = scene.grid.max_over_time().detach().cpu().float().numpy()
    return {
        "occupancy_u8": np.round(np.clip(occ, 0, 1) * 255).astype(np.uint8),
        "origin": np.asarray(scene.grid.origin, dtype=np.float64),
        "cell_size": np.float64(scene.grid.cell_size),
        "start": np.asarray(scene.start, dtype=np.float64),
        "goal": np.asarray(scene.goal, dtype=np.float64),
        "planning_box": np.asarray(scene.planning_box, dtype=np.float64),
        "name": np.asarray(scene.name),
    }


#: record keys that must be strings, and the number-or-null metrics the summary reads
_RECORD_KEYS = ("setting", "env", "planner", "variant", "status")
_SUMMARY_METRICS = ("final_distance", "goal_cost", "collision_cost", "input_cost", "bounds_cost",
                    "collision_probability_max", "mc_collision_mean", "mc_collision_frequency")


def record_problem(record: Any) -> str | None:
    """Why ``record`` (parsed JSON) is not a benchmark record, or ``None`` when it is one."""
    if not isinstance(record, dict):
        return f"a JSON object expected, got {type(record).__name__}"
    missing = [k for k in _RECORD_KEYS if k not in record]
    if missing:
        return f"missing key(s) {missing}"
    bad = [k for k in _RECORD_KEYS if not isinstance(record[k], str) or not record[k]]
    if bad:
        return f"key(s) {bad} must be non-empty strings"
    for key in ("metrics", "timings", "env_spec"):
        if record.get(key) is not None and not isinstance(record[key], dict):
            return f"{key!r} must be an object or null, got {type(record[key]).__name__}"
    for key in _SUMMARY_METRICS:
        v = (record.get("metrics") or {}).get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            return f"metrics.{key} must be a number or null, got {v!r}"
    for key in ("offline", "online_per_step"):
        v = (record.get("timings") or {}).get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
            return f"timings.{key} must be a number or null, got {v!r}"
    if not isinstance(record.get("failed", False), bool):
        return f"'failed' must be true or false, got {record['failed']!r}"
    if not isinstance(record.get("failure_reason") or "", str):
        return f"'failure_reason' must be a string, got {record['failure_reason']!r}"
    return None


def read_record(path: Path) -> dict[str, Any] | None:
    """The record at ``path``, or ``None`` (with a warning) when it is unreadable or not a record."""
    r, problem = _read_record(path)
    if problem:
        log.warning("ignoring %s: %s", path, problem)
    return r


def _read_record(path: Path) -> tuple[dict[str, Any] | None, str | None]:
    try:
        r = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        return None, f"unreadable JSON ({exc})"
    problem = record_problem(r)
    return (None, f"not a benchmark record ({problem})") if problem else (r, None)


@dataclass(frozen=True)
class BadRecord:
    """A record file that could not be used: its path, why, and the run it stands for (from its name)."""

    path: Path
    reason: str
    setting: str
    env: str | None
    planner: str | None
    variant: str | None


def scan_records(out: str | Path, setting: str | None = None) -> tuple[list[dict[str, Any]], list[BadRecord]]:
    """``(records, bad)``: the valid records under ``DIR/records`` (as :func:`load_records`) and the files that are
    unreadable or not records (truncated, ``42``, missing keys, wrong types)."""
    root = Path(out) / "records"
    if not root.is_dir():
        return [], []
    dirs = [root / setting] if setting else sorted(p for p in root.iterdir() if p.is_dir())
    records, bad = [], []
    for d in dirs:
        for p in sorted(d.glob("*.json")):
            r, problem = _read_record(p)
            if problem:
                parts = p.stem.split("__")
                env, planner, variant = parts if len(parts) == 3 else (None, None, None)
                bad.append(BadRecord(p, problem, d.name, env, planner, variant))
                log.warning("ignoring %s: %s", p, problem)
                continue
            assert r is not None  # no problem: the record was read
            records.append(r)
    return _sorted_records(records), bad


def load_records(out: str | Path, setting: str | None = None) -> list[dict[str, Any]]:
    """All valid records under ``DIR/records`` (one setting, or all), sorted by setting, environment index,
    planner, variant; files that are not records are skipped with a warning (:func:`scan_records` lists them)."""
    return scan_records(out, setting)[0]


def _sorted_records(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    order = {name: i for i, name in enumerate(SETTINGS)}

    def key(r: dict[str, Any]) -> tuple:
        index = (r.get("env_spec") or {}).get("index", 0)
        return (order.get(r["setting"], 99), r["setting"], index if isinstance(index, int) else 0, r["env"],
                r["planner"], r["variant"])

    return sorted(records, key=key)


def load_scene_map(out: str | Path, setting: str, env: str) -> dict[str, Any] | None:
    """The map stored for ``env`` (see :func:`scene_map_arrays`), or ``None``."""
    path = map_path(out, setting, env)
    if not path.is_file():
        return None
    from ..io.npz import read_npz

    return read_npz(path, what="benchmark map")


def identity_view(record: dict[str, Any]) -> dict[str, Any]:
    """The part of a record that must not depend on how or where it ran (no wall times, no provenance)."""
    return {k: v for k, v in record.items() if k not in ("timings", "run_info")}


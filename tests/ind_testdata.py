"""Small inD recordings for the tests and benchmarks (the real data set is licensed and cannot be shipped):
:func:`write_ind_recording` writes road-user tracks as the three inD CSV files the reader
(:mod:`density_planner.environment.ind`) expects. Importable from every test folder (``tests/`` is on the path)
and from ``benchmarks/bench_env.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from density_planner.environment.ind import ind_paths
from density_planner.io.atomic import atomic_write_text

__all__ = ["write_ind_recording"]

_TRACKS_HEADER = (
    "recordingId",
    "trackId",
    "frame",
    "trackLifetime",
    "xCenter",
    "yCenter",
    "heading",
    "width",
    "length",
    "xVelocity",
    "yVelocity",
    "xAcceleration",
    "yAcceleration",
    "lonVelocity",
    "latVelocity",
    "lonAcceleration",
    "latAcceleration",
)
_TRACKS_META_HEADER = (
    "recordingId",
    "trackId",
    "initialFrame",
    "finalFrame",
    "numFrames",
    "width",
    "length",
    "class",
)
_RECORDING_META_HEADER = (
    "recordingId",
    "locationId",
    "frameRate",
    "speedLimit",
    "weekday",
    "startTime",
    "duration",
    "numTracks",
    "numVehicles",
    "numVRUs",
    "latLocation",
    "lonLocation",
    "xUtmOrigin",
    "yUtmOrigin",
    "orthoPxToMeter",
)


def write_ind_recording(
    data_dir: str | Path,
    recording: int,
    tracks: list[dict],
    *,
    frame_rate: float = 25.0,
    duration: float | None = None,
    ortho_px_to_meter: float = 0.0126,
) -> dict[str, Path]:
    """Write road-user tracks as the three inD CSV files of ``recording`` (atomically); returns their paths.

    Each entry of ``tracks`` is a dict with ``id`` (int), ``class`` (inD class name), ``length``, ``width``
    [m] and equally long arrays ``frames`` (consecutive ints), ``x``, ``y`` [m], ``heading`` [deg], ``vx``,
    ``vy`` [m/s]. All columns of the inD format are written (accelerations 0, lon/lat velocities from the
    heading). Used by the tests and benchmarks, since the real data set cannot be shipped.
    """
    paths = ind_paths(data_dir, recording)
    rec = int(recording)
    lines = [",".join(_TRACKS_HEADER)]
    meta_lines = [",".join(_TRACKS_META_HEADER)]
    last = 0
    n_vru = 0
    for tr in tracks:
        frames = np.asarray(tr["frames"], dtype=np.int64)
        x, y = np.asarray(tr["x"], float), np.asarray(tr["y"], float)
        hd = np.asarray(tr["heading"], float)
        vx, vy = np.asarray(tr["vx"], float), np.asarray(tr["vy"], float)
        c, s = np.cos(np.radians(hd)), np.sin(np.radians(hd))
        lon, lat = (vx * c + vy * s).tolist(), (-vx * s + vy * c).tolist()
        x, y, hd, vx, vy = x.tolist(), y.tolist(), hd.tolist(), vx.tolist(), vy.tolist()
        width, length = float(tr["width"]), float(tr["length"])
        for i, f in enumerate(frames.tolist()):
            lines.append(
                f"{rec},{tr['id']},{f},{i},{x[i]!r},{y[i]!r},{hd[i]!r},{width!r},{length!r},{vx[i]!r},"
                f"{vy[i]!r},0.0,0.0,{lon[i]!r},{lat[i]!r},0.0,0.0"
            )
        if frames.size:
            meta_lines.append(
                f"{rec},{tr['id']},{frames[0]},{frames[-1]},{frames.size},{width!r},{length!r},{tr['class']}"
            )
            last = max(last, int(frames[-1]))
        n_vru += tr["class"] in ("pedestrian", "bicycle")
    dur = duration if duration is not None else last / frame_rate
    rec_line = (
        f"{rec},1,{frame_rate!r},13.89,Monday,08:00,{dur!r},{len(tracks)},{len(tracks) - n_vru},{n_vru},"
        f"50.78,6.07,0.0,0.0,{ortho_px_to_meter!r}"
    )
    atomic_write_text(paths["tracks"], "\n".join(lines) + "\n")
    atomic_write_text(paths["tracks_meta"], "\n".join(meta_lines) + "\n")
    atomic_write_text(paths["recording_meta"], ",".join(_RECORDING_META_HEADER) + "\n" + rec_line + "\n")
    return paths

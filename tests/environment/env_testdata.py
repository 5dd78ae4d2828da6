"""Synthetic inD data shared by the environment tests (a uniquely named module: safe to import from tests)."""

from __future__ import annotations

import numpy as np

#: the two-track recording written by :func:`two_track_recording`
CAR_X0, CAR_Y, CAR_SPEED = 10.0, -20.0, 5.0  # m, m, m/s (moves along +x from frame 0)
PED_X, PED_Y0, PED_SPEED, PED_FIRST = 30.0, -40.0, 1.2, 100  # appears at frame 100 (t = 4 s), walks along +y
N_FRAMES = 400  # 16 s at 25 Hz


def car_x(t: float) -> float:
    return CAR_X0 + CAR_SPEED * t


def two_tracks() -> list[dict]:
    f = np.arange(N_FRAMES)
    t = f / 25.0
    fp = f[PED_FIRST:]
    tp = fp / 25.0
    return [
        {
            "id": 1,
            "class": "car",
            "length": 4.5,
            "width": 1.8,
            "frames": f,
            "x": car_x(t),
            "y": np.full(f.size, CAR_Y),
            "heading": np.zeros(f.size),
            "vx": np.full(f.size, CAR_SPEED),
            "vy": np.zeros(f.size),
        },
        {
            "id": 2,
            "class": "pedestrian",
            "length": 0.0,
            "width": 0.0,
            "frames": fp,
            "x": np.full(fp.size, PED_X),
            "y": PED_Y0 + PED_SPEED * (tp - tp[0]),
            "heading": np.full(fp.size, 90.0),
            "vx": np.zeros(fp.size),
            "vy": np.full(fp.size, PED_SPEED),
        },
    ]

"""Benchmark: time to build environments (issue 4 target: <= 1 s each on the development machine).

Metrics (median wall time over repetitions, after one warm-up):

* ``random``: :func:`random_scene` for 5 seeds >= 20 (241 x 401 cells x 101 slices, with the start/goal
  search);
* ``ind``: :func:`load_ind_scene` on a synthetic inD recording written beforehand (not timed): 60 road users
  (36 cars, 4 trucks/buses, 8 bicycles, 12 pedestrians) moving through a 100 m x 80 m map during the 10-s
  window, 0.1-m cells (1001 x 801 x 101 = 81 M cells), CSV reading, resampling, footprints, start/goal
  sampling included;
* ``ind footprints only``: :func:`rasterise_road_users` on the same resampled users.

Run: ``.venv/bin/python benchmarks/bench_env.py [--repeat N]``.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from density_planner.environment import IndSceneConfig, load_ind_scene, random_scene
from density_planner.environment.footprints import RoadUserTracks, rasterise_road_users
from density_planner.environment.ind import class_id, read_tracks, read_tracks_meta, tracks_in_window

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the inD writer of the tests
from ind_testdata import write_ind_recording  # noqa: E402

AREA = (0.0, 100.0, -80.0, 0.0)


def synthetic_tracks(seed: int = 0, duration: float = 20.0) -> list[dict]:
    """60 road users on straight lines with constant speed crossing the map (recorded at 25 Hz)."""
    rng = np.random.default_rng(seed)
    classes = ["car"] * 36 + ["truck_bus"] * 4 + ["bicycle"] * 8 + ["pedestrian"] * 12
    frames = np.arange(int(duration * 25) + 1)
    t = frames / 25.0
    tracks = []
    for i, cls in enumerate(classes):
        speed = {"car": 8.0, "truck_bus": 6.0, "bicycle": 4.0, "pedestrian": 1.3}[cls] * rng.uniform(0.2, 1.5)
        heading = rng.uniform(-math.pi, math.pi)
        x0, y0 = rng.uniform(AREA[0], AREA[1]), rng.uniform(AREA[2], AREA[3])
        x = x0 + speed * math.cos(heading) * (t - duration / 2)
        y = y0 + speed * math.sin(heading) * (t - duration / 2)
        length, width = {
            "car": (4.6, 1.9),
            "truck_bus": (11.0, 2.6),
            "bicycle": (1.8, 0.6),
            "pedestrian": (0.5, 0.5),
        }[cls]
        tracks.append(
            {
                "id": i,
                "class": cls,
                "length": length,
                "width": width,
                "frames": frames,
                "x": x,
                "y": y,
                "heading": np.full(frames.size, math.degrees(heading)),
                "vx": np.full(frames.size, speed * math.cos(heading)),
                "vy": np.full(frames.size, speed * math.sin(heading)),
            }
        )
    return tracks


def timed(fn, repeat: int) -> list[float]:
    fn()  # warm-up
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")

    seeds = iter(range(20, 10_000))
    t_random = timed(lambda: random_scene(next(seeds)), max(args.repeat, 5))
    scene = random_scene(20)
    print(
        f"random scene {tuple(scene.grid.shape)}: median {statistics.median(t_random):.3f} s "
        f"(min {min(t_random):.3f}, max {max(t_random):.3f}, {len(t_random)} seeds)"
    )

    with tempfile.TemporaryDirectory() as tmp:
        write_ind_recording(tmp, 1, synthetic_tracks())
        cfg = IndSceneConfig(start_time=5.0, area=AREA)
        t_ind = timed(lambda: load_ind_scene(tmp, 1, cfg), args.repeat)
        scene = load_ind_scene(tmp, 1, cfg)
        print(
            f"inD scene {tuple(scene.grid.shape)} from 60 road users: median "
            f"{statistics.median(t_ind):.3f} s "
            f"(min {min(t_ind):.3f}, max {max(t_ind):.3f}, {len(t_ind)} runs)"
        )

        tracks = read_tracks(Path(tmp) / "01_tracks.csv")
        meta = read_tracks_meta(Path(tmp) / "01_tracksMeta.csv")
        times = 5.0 + 0.1 * np.arange(101)
        win = tracks_in_window(tracks, 25.0, times)
        rows = np.searchsorted(meta["trackId"], win["ids"])
        users = RoadUserTracks(
            win["x"],
            win["y"],
            win["heading"],
            win["vx"] * np.cos(win["heading"]) + win["vy"] * np.sin(win["heading"]),
            meta["length"][rows],
            meta["width"][rows],
            np.array([class_id(c) for c in meta["class"][rows]]),
            win["ids"],
        )
        shape = scene.grid.shape
        t_fp = timed(
            lambda: rasterise_road_users(users, origin=scene.grid.origin, cell_size=0.1, shape=shape),
            args.repeat,
        )
        print(
            f"  of which footprints: median {statistics.median(t_fp):.3f} s "
            f"({int(users.present.sum())} user-slices)"
        )


if __name__ == "__main__":
    main()

"""How wrong is the observed-only prediction on recorded traffic? For every car, truck, bus and motorcycle seen at
``t_start``, ``t_start + 2 s`` and ``t_start + 4 s`` of each CommonRoad file, its prediction (``--motion-model``
cv, ctrv or lane, the lane model at constant speed or with ``--lane-speed idm``, from its last observed state)
against its recorded position ``tau`` later, in the frame of its
observed heading: RMS, median and 95th percentile of the along- and across-heading errors per ``tau`` (for the lane
model's mixture of branches, a vehicle's error on each axis is the root of the weighted mean of its branches' squared
errors; and the position error of the mixture, of its most likely branch and of its best branch) (docs/environments.md,
"How wrong is constant velocity on recorded traffic?"). ``--half 0|1`` takes every second file (0, 2, 4, ... or
1, 3, 5, ...) to fit on one half and check on the other.

    python benchmarks/bench_prediction_error.py --scenarios ../shared/data/commonroad-suite [--half 0]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

VEHICLES = ("car", "truck", "bus", "motorcycle")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenarios", type=Path, required=True)
    p.add_argument("--half", type=int, choices=(0, 1), default=None)
    p.add_argument("--motion-model", choices=("cv", "ctrv", "lane"), default="cv")
    p.add_argument("--lane-speed", choices=("constant", "idm"), default="constant",
                   help="the lane model's speed: constant, or the car-following model (IDM)")
    p.add_argument("--accel-hold", type=float, default=None,
                   help="with --lane-speed idm: the observed acceleration is kept this long [s] (default: the "
                        "config's online.prediction.accel_hold)")
    p.add_argument("--accel-window", type=float, default=None,
                   help="the observed acceleration's window [s] (default: online.prediction.accel_window)")
    args = p.parse_args()

    from density_planner.api import load_run_config
    from density_planner.environment.commonroad import load_commonroad_scene
    from density_planner.environment.prediction import ObservedPrediction, PredictionConfig
    from density_planner.planners.context import run_system

    cfg = load_run_config()
    system = run_system(cfg, "commonroad")
    taus = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    errors: dict[float, list[tuple[float, float]]] = {float(t): [] for t in taus}
    files = sorted(args.scenarios.glob("*.xml"))
    if args.half is not None:
        files = files[args.half::2]
    for f in files:
        try:
            scene = load_commonroad_scene(f, cfg.commonroad, system=system)
        except (ValueError, OSError) as exc:  # refused files have no prediction to check
            print(f"{f.name}: skipped ({str(exc).splitlines()[0]})")
            continue
        users = {u.obstacle_id: u for u in scene.road.obstacles}
        extra = {} if args.accel_hold is None else {"accel_hold": args.accel_hold}
        if args.accel_window is not None:
            extra["accel_window"] = args.accel_window
        pred = ObservedPrediction(scene, PredictionConfig(motion_model=args.motion_model, lane_speed=args.lane_speed,
                                                          **extra))
        for t0 in scene.t_start + np.array([0.0, 2.0, 4.0]):
            obs = pred.observe(t0)
            if obs.ids.size == 0:
                continue
            tracks = pred.tracks(t0, t0 + taus)
            weight = np.ones(tracks.n_users) if tracks.weight is None else tracks.weight
            for i, oid in enumerate(obs.ids):
                u = users.get(int(oid))
                if u is None or u.static or u.kind not in VEHICLES:
                    continue
                recorded = ~u.predicted if u.predicted is not None else np.ones(len(u.times), bool)
                times, poses = u.times[recorded], u.poses[recorded]
                if len(times) < 2:
                    continue
                c, s = np.cos(obs.heading[i]), np.sin(obs.heading[i])
                for j, tau in enumerate(taus):
                    t = t0 + tau
                    if t < times[0] or t > times[-1] + 1e-6:
                        continue
                    rows = tracks.ids == oid  # one row per branch of the lane model
                    dx = np.interp(t, times, poses[:, 0]) - tracks.x[rows, j]
                    dy = np.interp(t, times, poses[:, 1]) - tracks.y[rows, j]
                    w = weight[rows] / weight[rows].sum()
                    dist = np.hypot(dx, dy)
                    errors[float(tau)].append((np.sqrt(np.sum(w * (dx * c + dy * s) ** 2)),
                                               np.sqrt(np.sum(w * (-dx * s + dy * c) ** 2)),
                                               np.sqrt(np.sum(w * dist**2)), dist[np.argmax(w)], dist.min()))
    lane = f", lane speed {args.lane_speed}" if args.motion_model == "lane" else ""
    if args.motion_model == "lane" and args.lane_speed == "idm":
        chosen = PredictionConfig(**extra)
        lane += f", acceleration held {chosen.accel_hold:g} s (window {chosen.accel_window:g} s)"
    print(f"{len(files)} files, motion model {args.motion_model}{lane}")
    head = ("tau s", "n", "along RMS", "median", "p95", "across RMS", "median", "p95")
    print(" ".join(f"{h:>{w}}" for h, w in zip(head, (6, 6, 10, 7, 6, 11, 7, 6))))
    for tau, rows in errors.items():
        if not rows:
            continue
        a = np.abs(np.asarray(rows))
        print(f"{tau:6.1f} {len(a):6d} {np.sqrt(np.mean(a[:, 0] ** 2)):10.2f} {np.median(a[:, 0]):7.2f} "
              f"{np.percentile(a[:, 0], 95):6.1f} {np.sqrt(np.mean(a[:, 1] ** 2)):11.2f} {np.median(a[:, 1]):7.2f} "
              f"{np.percentile(a[:, 1], 95):6.1f}")
    print("\nposition error [m], median / RMS: of the mixture (root of the weighted mean square), of its most likely "
          "branch, of its best branch (one branch: all three the same)")
    for tau, rows in errors.items():
        if rows:
            a = np.asarray(rows)[:, 2:]
            print(f"{tau:6.1f} " + "  ".join(f"{np.median(a[:, m]):5.2f} / {np.sqrt(np.mean(a[:, m] ** 2)):5.2f}"
                                             for m in range(3)))


if __name__ == "__main__":
    main()

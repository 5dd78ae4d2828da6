"""Figure: the observed-only prediction along the lanes at constant speed against car following (IDM), with the
recorded future, for the vehicles of one CommonRoad file at its start (docs/environments.md, "Car following").

    python benchmarks/plot_car_following.py [--file src/density_planner/data/commonroad/USA_Peach-4_8_T-1.xml]
        [--out docs/images/prediction-car-following.png] [--horizon 5]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--file", type=Path, default=REPO / "src/density_planner/data/commonroad/USA_Peach-4_8_T-1.xml")
    p.add_argument("--out", type=Path, default=REPO / "docs/images/prediction-car-following.png")
    p.add_argument("--horizon", type=float, default=5.0, help="prediction time [s]")
    args = p.parse_args()

    import matplotlib.pyplot as plt

    from density_planner.api import load_run_config
    from density_planner.environment.commonroad import load_commonroad_scene
    from density_planner.environment.prediction import ObservedPrediction, PredictionConfig
    from density_planner.planners.context import run_system
    from density_planner.viz.plan import _geometry_patches

    cfg = load_run_config()
    scene = load_commonroad_scene(args.file, cfg.commonroad, system=run_system(cfg, "commonroad"))
    t0 = scene.t_start
    times = t0 + np.arange(0.0, args.horizon + 1e-9, 0.5)
    const = ObservedPrediction(scene, PredictionConfig(lane_speed="constant")).tracks(t0, times)
    idm = ObservedPrediction(scene, PredictionConfig(lane_speed="idm")).tracks(t0, times)
    users = {u.obstacle_id: u for u in scene.road.obstacles}
    moved = np.hypot(const.x - idm.x, const.y - idm.y)[:, -1] > 1.0
    shown = sorted(set(idm.ids[moved].tolist())) or sorted(set(idm.ids.tolist()))
    xy = np.concatenate([np.column_stack([const.x[const.ids == i].ravel(), const.y[const.ids == i].ravel()])
                         for i in shown])
    lo, hi = xy.min(axis=0) - 15.0, xy.max(axis=0) + 15.0

    fig, ax = plt.subplots(figsize=(9.0, 9.0 * (hi[1] - lo[1]) / max(hi[0] - lo[0], 1e-9) * 0.9 + 1.0),
                           layout="constrained")
    for ring in _geometry_patches(scene.road.drivable):
        ax.fill(ring[:, 0], ring[:, 1], color="0.93", lw=0)
    for oid in sorted(set(idm.ids.tolist())):
        u = users[int(oid)]
        rec = (u.times >= t0 - 1e-9) & (u.times <= times[-1] + 1e-9) & ~np.asarray(u.predicted, dtype=bool)
        ax.plot(u.poses[rec, 0], u.poses[rec, 1], "-", color="tab:blue", lw=1.2, alpha=0.7,
                label="recorded" if oid == shown[0] else None)
        r = np.nonzero(idm.ids == oid)[0][0]
        ax.plot(idm.x[r, 0], idm.y[r, 0], "s", color="black", ms=5)
    for name, tr, style in (("constant speed", const, dict(mfc="none", mec="tab:red")),
                            ("car following (IDM)", idm, dict(mfc="tab:green", mec="tab:green"))):
        rows = np.isin(tr.ids, shown)
        ax.plot(tr.x[rows, 1:].ravel(), tr.y[rows, 1:].ravel(), "o", ms=4, ls="none", label=name, **style)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"{scene.name}: vehicles observed at t = {t0:.1f} s (squares), predicted every 0.5 s for "
                 f"{args.horizon:.0f} s along their lanes", fontsize=9)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out} ({len(shown)} vehicles whose predictions differ by > 1 m at the end)")


if __name__ == "__main__":
    main()

"""``density-planner env``: build a scene (random, inD recording or CommonRoad file) and write it with
pictures."""

from __future__ import annotations

import argparse
import time

from ._common import add_config, add_out, add_system, apply_system_args, check_out, out_dir
from ._scenes import add_scene_args, scene_from_args

KINDS = ("random", "ind", "commonroad")


def register(sub: argparse._SubParsersAction, groups: dict) -> None:
    p = sub.add_parser(
        "env",
        help="build an environment (occupancy grid + start/goal) and draw it",
        description="Build a scene from one of three sources and write DIR/occupancy.npz (grid, start, goal, "
        "planning box, metadata; reload with density_planner.environment.load_scene), DIR/scene.json, "
        "DIR/occupancy.png (t=0 and time-max occupancy with start and goal) and DIR/occupancy.gif (the "
        "slices). "
        "--config/--set change the run configuration; the sections [random_scene], [ind] and [commonroad] "
        "configure the sources, e.g. --set ind.cell_size=0.2.",
    )
    add_scene_args(p, flag="--kind", kinds=KINDS)
    p.add_argument("--no-gif", action="store_true", help="skip occupancy.gif")
    add_system(p, density=False)
    add_config(p)
    add_out(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from density_planner.environment.scene import save_scene, scene_summary
    from density_planner.io.atomic import atomic_write_json

    from ..config import load_config
    from ..settings import RunConfig

    check_out(args.out)
    run_config = apply_system_args(args, load_config(RunConfig, args.config, args.overrides))
    t0 = time.perf_counter()
    scene = scene_from_args(args, run_config, kind_flag="--kind")
    elapsed = time.perf_counter() - t0
    out = out_dir(args.out)
    save_scene(scene, out / "occupancy.npz")
    atomic_write_json(out / "scene.json", {**scene.to_json_dict(), "build_time_s": elapsed})
    from density_planner.viz.occupancy import animate_occupancy, plot_occupancy

    plot_occupancy(scene, out / "occupancy.png")
    written = ["occupancy.npz", "scene.json", "occupancy.png"]
    if not args.no_gif:
        animate_occupancy(scene, out / "occupancy.gif")
        written.append("occupancy.gif")
    p_start = float(scene.grid.lookup(torch.tensor(scene.start[:2], dtype=torch.float64),
                                      scene.grid.slice_index(scene.t_start)))
    print(
        f"{scene_summary(scene)}; P_occ at start {p_start:.2f}; built in {elapsed:.2f} s; "
        f"wrote {', '.join(str(out / w) for w in written)}"
    )
    return 0

"""``density-planner env``: build a scene (random, inD recording or CommonRoad file) and write it with
pictures."""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from ._common import add_config, add_out, out_dir

KINDS = ("random", "ind", "commonroad")


def register(sub: argparse._SubParsersAction, groups: dict) -> None:
    p = sub.add_parser(
        "env",
        help="build an environment (occupancy grid + start/goal) and draw it",
        description="Build a scene from one of three sources and write DIR/occupancy.npz (grid, start, goal, "
        "planning box, metadata; reload with density_planner.environment.load_scene), DIR/scene.json, "
        "DIR/occupancy.png (t=0 and time-max occupancy with start and goal) and DIR/occupancy.gif (the "
        "slices). "
        "--config/--set change the configuration of the chosen source (RandomSceneConfig, IndSceneConfig or "
        "CommonRoadSceneConfig), e.g. --set cell_size=0.2.",
    )
    p.add_argument("--kind", required=True, choices=KINDS, help="source of the scene")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="random: scene number (default 0); ind/commonroad: seed of the start/goal sampler "
        "(default: the configuration's seed, 0)",
    )
    p.add_argument(
        "--data-dir", type=Path, default=None, metavar="D", help="ind: folder with the NN_*.csv files"
    )
    p.add_argument("--recording", type=int, default=None, metavar="N", help="ind: recording number")
    p.add_argument(
        "--start-time",
        type=float,
        default=None,
        metavar="S",
        help="ind: start of the 10-s window in seconds (default 0)",
    )
    p.add_argument("--file", type=Path, default=None, metavar="F.xml", help="commonroad: scenario file")
    p.add_argument("--no-gif", action="store_true", help="skip occupancy.gif")
    add_config(p)
    add_out(p)
    p.set_defaults(func=run)


def _build(args: argparse.Namespace):
    from density_planner.config import load_config, update

    if args.seed is not None and args.seed < 0:
        raise ValueError(f"--seed must be >= 0, got {args.seed}")
    seed = {} if args.seed is None else {"seed": args.seed}
    if args.kind == "random":
        from density_planner.environment.random_scene import RandomSceneConfig, random_scene

        for flag, value in (
            ("--data-dir", args.data_dir),
            ("--recording", args.recording),
            ("--file", args.file),
            ("--start-time", args.start_time),
        ):
            if value is not None:
                raise ValueError(f"{flag} is not used with --kind random")
        cfg = load_config(RandomSceneConfig, args.config, args.overrides)
        return random_scene(args.seed or 0, cfg)
    if args.kind == "ind":
        from density_planner.environment.ind import IndSceneConfig, load_ind_scene

        if args.data_dir is None or args.recording is None:
            raise ValueError("--kind ind needs --data-dir D and --recording N")
        if args.file is not None:
            raise ValueError("--file is not used with --kind ind (use --data-dir and --recording)")
        cfg = load_config(IndSceneConfig, args.config, args.overrides)
        cfg = update(cfg, seed)
        if args.start_time is not None:
            cfg = update(cfg, {"start_time": args.start_time})
        return load_ind_scene(args.data_dir, args.recording, cfg)
    from density_planner.environment.commonroad import CommonRoadSceneConfig, load_commonroad_scene

    if args.file is None:
        raise ValueError("--kind commonroad needs --file F.xml")
    for flag, value in (
        ("--data-dir", args.data_dir),
        ("--recording", args.recording),
        ("--start-time", args.start_time),
    ):
        if value is not None:
            raise ValueError(f"{flag} is not used with --kind commonroad")
    cfg = load_config(CommonRoadSceneConfig, args.config, args.overrides)
    cfg = update(cfg, seed)
    if not args.verbose:  # commonroad-io warns about every legacy (2020a) intersection element it converts
        logging.getLogger("commonroad").setLevel(logging.ERROR)
    return load_commonroad_scene(args.file, cfg)


def run(args: argparse.Namespace) -> int:
    import torch

    from density_planner.environment.scene import save_scene, scene_summary
    from density_planner.io.atomic import atomic_write_json

    out = out_dir(args.out)
    t0 = time.perf_counter()
    scene = _build(args)
    elapsed = time.perf_counter() - t0
    save_scene(scene, out / "occupancy.npz")
    atomic_write_json(out / "scene.json", {**scene.to_json_dict(), "build_time_s": elapsed})
    from density_planner.viz.occupancy import animate_occupancy, plot_occupancy

    plot_occupancy(scene, out / "occupancy.png")
    written = ["occupancy.npz", "scene.json", "occupancy.png"]
    if not args.no_gif:
        animate_occupancy(scene, out / "occupancy.gif")
        written.append("occupancy.gif")
    p_start = float(scene.grid.lookup(torch.tensor(scene.start[:2], dtype=torch.float64), 0))
    print(
        f"{scene_summary(scene)}; P_occ at start {p_start:.2f}; built in {elapsed:.2f} s; "
        f"wrote {', '.join(str(out / w) for w in written)}"
    )
    return 0

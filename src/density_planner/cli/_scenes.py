"""Scene selection shared by the ``env``, ``plan`` and ``bench`` commands."""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from ..config import update

__all__ = ["SCENE_KINDS", "add_scene_args", "scene_from_args"]

SCENE_KINDS = ("random", "ind", "commonroad", "file")


def add_scene_args(p: argparse.ArgumentParser, *, flag: str = "--env", required: bool = True,
                   kinds: tuple[str, ...] = SCENE_KINDS) -> None:
    p.add_argument(flag, dest="kind", required=required, choices=kinds,
                   help="scene source: random artificial scene, inD recording, CommonRoad XML"
                   + (", or a saved scene (.npz from `density-planner env`)" if "file" in kinds else ""))
    p.add_argument("--seed", type=int, default=None,
                   help="random: scene number (default 0); ind: seed of the start/goal sampler; commonroad: "
                   "its seed with --set commonroad.sample_start_goal=true")
    p.add_argument("--data-dir", type=Path, default=None, metavar="D", help="ind: folder with the NN_*.csv files")
    p.add_argument("--recording", type=int, default=None, metavar="N", help="ind: recording number")
    p.add_argument("--start-time", type=float, default=None, metavar="S",
                   help="ind: start of the 10-s window in seconds (default 0)")
    p.add_argument("--file", type=Path, default=None, metavar="FILE",
                   help="commonroad: scenario .xml; file: scene .npz written by `density-planner env`")


def _reject(args: argparse.Namespace, kind: str, names: tuple[str, ...]) -> None:
    for name in names:
        if getattr(args, name.lstrip("-").replace("-", "_")) is not None:
            raise ValueError(f"{name} is not used with {kind}")


def scene_from_args(args: argparse.Namespace, run_config, *, kind_flag: str = "--env"):
    """Build the scene selected by the scene arguments with the matching section of ``run_config``."""
    if args.seed is not None:
        from ..checks import check_seed

        check_seed("--seed", args.seed)
    kind = args.kind
    where = f"{kind_flag} {kind}"
    seed = {} if args.seed is None else {"seed": args.seed}
    if kind == "random":
        from ..environment.random_scene import random_scene

        _reject(args, where, ("--data-dir", "--recording", "--file", "--start-time"))
        return random_scene(args.seed or 0, run_config.random_scene)
    if kind == "ind":
        from ..environment.ind import load_ind_scene

        if args.data_dir is None or args.recording is None:
            raise ValueError(f"{where} needs --data-dir D and --recording N")
        _reject(args, where, ("--file",))
        cfg = update(run_config.ind, seed)
        if args.start_time is not None:
            cfg = update(cfg, {"start_time": args.start_time})
        return load_ind_scene(args.data_dir, args.recording, cfg)
    if kind == "commonroad":
        from ..environment.commonroad import load_commonroad_scene

        if args.file is None:
            raise ValueError(f"{where} needs --file F.xml")
        _reject(args, where, ("--data-dir", "--recording", "--start-time"))
        if not getattr(args, "verbose", 0):  # commonroad-io warns about every legacy element it converts
            logging.getLogger("commonroad").setLevel(logging.ERROR)
        from ._common import run_system

        # the domain checks (start speed, reachable region) use the run's system in the domain of the scene's model
        # set (the car on recorded traffic: road, 0-40 m/s)
        system = run_system(run_config, kind)
        return load_commonroad_scene(args.file, update(run_config.commonroad, seed), system=system)
    if kind == "file":
        from ..environment.scene import load_scene

        if args.file is None:
            raise ValueError(f"{where} needs --file SCENE.npz")
        _reject(args, where, ("--data-dir", "--recording", "--start-time", "--seed"))
        return load_scene(args.file)
    raise ValueError(f"unknown scene kind {kind!r}; valid choices: {', '.join(SCENE_KINDS)}")

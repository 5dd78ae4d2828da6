"""Scene selection shared by the ``env``, ``plan``, ``drive``, ``validate risk`` commands: the command-line face of
:mod:`density_planner.environment.sources`."""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["add_scene_args", "scene_request", "scene_from_args"]


def add_scene_args(p: argparse.ArgumentParser, *, flag: str = "--env", required: bool = True,
                   kinds: tuple[str, ...] | None = None) -> None:
    """The scene flags; ``kinds`` limits the sources (default: every registered one)."""
    from ..environment.sources import scene_kinds, scene_source

    kinds = kinds or scene_kinds()
    p.add_argument(flag, dest="kind", required=required, choices=kinds,
                   help="scene source: " + "; ".join(f"{k}: {scene_source(k).description}" for k in kinds))
    p.add_argument("--seed", type=int, default=None,
                   help="random: scene number (default 0); ind: seed of the start/goal sampler; commonroad: "
                   "its seed with --set commonroad.sample_start_goal=true")
    p.add_argument("--data-dir", type=Path, default=None, metavar="D", help="ind: folder with the NN_*.csv files")
    p.add_argument("--recording", type=int, default=None, metavar="N", help="ind: recording number")
    p.add_argument("--start-time", type=float, default=None, metavar="S",
                   help="ind: start of the 10-s window in seconds (default 0)")
    p.add_argument("--file", type=Path, default=None, metavar="FILE",
                   help="commonroad: scenario .xml; file: scene .npz written by `density-planner env`")


def scene_request(args: argparse.Namespace):
    """The :class:`~density_planner.environment.sources.SceneRequest` of the scene arguments."""
    from ..environment.sources import SceneRequest

    if args.seed is not None:
        from ..checks import check_seed

        check_seed("--seed", args.seed)
    return SceneRequest(args.kind, seed=args.seed, file=args.file, data_dir=args.data_dir,
                        recording=args.recording, start_time=args.start_time)


def scene_from_args(args: argparse.Namespace, run_config, *, kind_flag: str = "--env", both_cores: bool = False):
    """Build the scene selected by the scene arguments with the matching section of ``run_config`` (its
    ``[system]`` section already holds ``--system`` / ``--models``; :func:`density_planner.api.build_scene`).
    ``both_cores`` (commands that build one scene and nothing else meanwhile: ``plan``, ``drive``): the grid's
    upsampling uses two threads on a CPU with two or more cores
    (:func:`~density_planner.environment.footprints.set_raster_threads`; the same grid to the bit)."""
    from ..api import build_scene
    from ..parallel import default_workers

    request = scene_request(args)  # checks --seed
    threads = min(2, default_workers()) if both_cores and getattr(args, "device", "cpu") == "cpu" else None
    return build_scene(request.kind, run_config, seed=request.seed, file=request.file, data_dir=request.data_dir,
                       recording=request.recording, start_time=request.start_time, raster_threads=threads,
                       where=f"{kind_flag} {args.kind}", quiet=not getattr(args, "verbose", 0))

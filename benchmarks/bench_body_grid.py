"""Wall time of the body's disc-dilated grid (``risk.body_grid``) on recorded road scenes: the dense dilation of the
whole grid against the tiled one that :func:`~density_planner.risk.body.body_grid` uses (``dilate_sparse``: only the
tiles within the disc's reach of an occupied cell), both quantised to bytes as ``body_grid`` does; checks that the
two are equal cell for cell.

For each scenario: the road-users grid the collision model reads (``risk.collision_grid``), its shape, the share of
occupied cells and of active tiles, and the median of ``--repeat`` timings of each dilation.

Usage::

    PYTHONPATH=src python benchmarks/bench_body_grid.py --scenarios ../shared/data/commonroad-suite --limit 5
    PYTHONPATH=src python benchmarks/bench_body_grid.py            # the shipped scenarios
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch


def _timed(fn, repeat: int) -> tuple[float, torch.Tensor]:
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    assert out is not None
    return statistics.median(times), out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", type=Path, default=None, help="folder of CommonRoad *.xml (default: the shipped)")
    p.add_argument("--limit", type=int, default=5, help="first N scenarios of the folder (sorted by name)")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)

    from density_planner.environment.commonroad import load_commonroad_scene
    from density_planner.evaluation.environments import shipped_commonroad_dir
    from density_planner.risk.body import (
        _LEVELS,
        DiscCover,
        _active_tiles,
        _reach_and_tile,
        dequantise,
        dilate,
        dilate_sparse,
        quantise_up,
    )
    from density_planner.risk.collision import collision_grid
    from density_planner.systems.registry import make_system

    folder = args.scenarios or shipped_commonroad_dir()
    files = sorted(Path(folder).glob("*.xml"))[: args.limit]
    if not files:
        print(f"bench_body_grid: no *.xml in {folder}", file=sys.stderr)
        return 2
    car = make_system("car", "road")
    radius = DiscCover.of(car.footprint, has_heading=True).radius
    print(f"disc radius {radius:.3f} m; median of {args.repeat} runs, {args.threads} thread(s)")
    print("scenario | grid (T x NX x NY) | cell [m] | occupied | active tiles | dense [s] | tiled [s] | speed-up")
    for f in files:
        scene = load_commonroad_scene(str(f), system=car)
        grid = collision_grid(scene)
        probs = grid.probs
        rho = radius / grid.cell_size
        h, tile = _reach_and_tile(rho, 32)  # as dilate_sparse with its default tile
        n_tiles = probs.shape[0] * -(-probs.shape[1] // tile) * -(-probs.shape[2] // tile)

        def dense(probs: torch.Tensor = probs, rho: float = rho) -> torch.Tensor:
            return dequantise(dilate(quantise_up(probs, _LEVELS), rho), _LEVELS, probs.dtype)

        def tiled(probs: torch.Tensor = probs, rho: float = rho) -> torch.Tensor:
            return dilate_sparse(probs, rho, levels=_LEVELS)

        t_dense, a = _timed(dense, args.repeat)
        t_tiled, b = _timed(tiled, args.repeat)
        if not torch.equal(a, b):
            print(f"bench_body_grid: {f.name}: the tiled dilation differs from the dense one", file=sys.stderr)
            return 1
        active = _active_tiles(probs, tile, h).shape[0] / n_tiles
        print(f"{f.stem} | {' x '.join(map(str, probs.shape))} | {grid.cell_size:g} | "
              f"{float((probs > 0).float().mean()):.1%} | {active:.1%} | {t_dense:.2f} | {t_tiled:.2f} | "
              f"{t_dense / t_tiled:.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())

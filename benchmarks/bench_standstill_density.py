"""Benchmark: accuracy of the road set's learned trajectory head at low start speeds, against exact Liouville.

The road head is trained on reference start speeds from 0.5 m/s up; ``density.network.STANDSTILL_EXTENSION`` lets it
serve starts down to standstill. For each band of start speed (``[0, 0.5)`` is the extension, the others are inside
the training range), ``--references`` random feasible references of the road model set starting in the band
(position and heading anywhere, ``--samples`` initial states each from the system's XE0 box) are predicted by the
shipped head (and by each ``--density FILE``) and by exact Liouville (the road set's default scheme). Prints the
position error median / p95 [m] over all points, at 10 s, and the median / p95 absolute log-density error
(1 torch thread). The docstring of ``STANDSTILL_EXTENSION`` and docs/planner.md ("Stopped starts") quote it.

    python benchmarks/bench_standstill_density.py [--references 24] [--samples 50] [--density FILE ...]
"""

from __future__ import annotations

import argparse
import math

import torch

from density_planner.control.registry import load_controller, model_set
from density_planner.density.registry import load_predictor
from density_planner.density.validation import compare_with_exact, fresh_references

#: bands of reference start speed [m/s]
BANDS = ((0.0, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, 5.0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--references", type=int, default=24, help="references per band (default 24)")
    ap.add_argument("--samples", type=int, default=50, help="initial states per reference (default 50)")
    ap.add_argument("--seed", type=int, default=7000, help="seed of the first band's references (default 7000)")
    ap.add_argument("--density", nargs="*", default=[], metavar="FILE", help="other trajectory heads to compare")
    args = ap.parse_args()
    torch.set_num_threads(1)
    system, ctrl = model_set("road").make_system(), load_controller("c3m", models="road")
    exact = load_predictor("exact", system, ctrl, models="road")
    heads = {"shipped": load_predictor("trajectory", system, ctrl, models="road")}
    heads.update({f: load_predictor(f, system, ctrl, models="road") for f in args.density})
    print(f"{args.references} references x {args.samples} samples per band (road set, exact Liouville as truth)")
    print("| start speed [m/s] | head | position error median / p95 [m] | at 10 s | |log-density error| median / p95 |")
    print("| --- | --- | --- | --- | --- |")
    for i, (lo, hi) in enumerate(BANDS):
        ref, x0 = fresh_references(args.references, args.samples, args.seed + i, domain="road",
                                   start_low=[-10.0, -10.0, -math.pi, lo, 0.0],
                                   start_high=[10.0, 10.0, math.pi, hi, 0.0])
        for name, head in heads.items():
            c = compare_with_exact(head, exact, ref, x0)
            pe, le = c.position_error.double(), c.log_density_error.abs().double()
            print(f"| [{lo:g}, {hi:g}) | {name} | {_mp(pe)} | {_mp(pe[..., -1])} | {_mp(le, 2)} |", flush=True)


def _mp(x: torch.Tensor, digits: int = 3) -> str:
    flat = x.reshape(-1)
    return f"{float(flat.median()):.{digits}f} / {float(torch.quantile(flat, 0.95)):.{digits}f}"


if __name__ == "__main__":
    main()

"""Probe: why a heading bias leaves a steady lateral offset under a static tracking law (docs/controller.md).

Linearised about a straight reference at speed v, a law ``omega = -k_lat e_lat - k_head e_head`` on the *measured*
errors settles at the lateral offset ``y* = -(k_head / k_lat) b`` for a heading bias ``b``, whatever else it does.
This script measures, for a model set's controller:

1. the gains at zero error on straight references (central differences of the unsaturated law ``raw``, float64):
   ``k_lat = -d omega / d e_lat``, ``k_head = -d omega / d e_head``, and the predicted offset for ``b = pi/16``;
2. the closed loop's own offset: the true car (Euler 0.01 s, 30 s) driving a straight reference from zero error
   with the bias ``b = pi/16`` (the applied, saturated law), its lateral error at the end.

    python benchmarks/probe_bias_offset.py [--models road] [--controller c3m|analytic|FILE.pt]
"""

from __future__ import annotations

import argparse
import math

import torch

from density_planner.control.reference import PiecewiseConstantInputs, make_reference
from density_planner.control.registry import load_controller, model_set
from density_planner.density.liouville import LiouvilleConfig, simulate_closed_loop

SPEEDS = (2.0, 5.0, 10.0, 20.0, 30.0, 38.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default="road")
    ap.add_argument("--controller", default="c3m")
    ap.add_argument("--bias", type=float, default=math.pi / 16)
    args = ap.parse_args()
    torch.set_num_threads(1)
    mset = model_set(args.models)
    system = mset.make_system()
    ctrl = load_controller(args.controller, models=mset).to(torch.float64)
    dt64 = torch.float64
    v = torch.tensor(SPEEDS, dtype=dt64)
    n = len(SPEEDS)
    x_ref = torch.zeros(n, system.nx, dtype=dt64)
    x_ref[:, 3] = v
    u_ref = torch.zeros(n, 2, dtype=dt64)
    h = 1e-4

    def omega(dy: float, dth: float) -> torch.Tensor:
        x_hat = x_ref.clone()
        x_hat[:, 1] += dy
        x_hat[:, 2] += dth
        return ctrl.raw(x_hat[:, :4], x_ref[:, :4], u_ref)[:, 0]

    with torch.no_grad():
        k_lat = -(omega(h, 0.0) - omega(-h, 0.0)) / (2 * h)
        k_head = -(omega(0.0, h) - omega(0.0, -h)) / (2 * h)
        y_pred = (k_head / k_lat * args.bias).abs()
        # closed loop, 30 s of Euler 0.01 s along the straight reference (zero inputs), true state with the bias
        reference = make_reference(system, x_ref, torch.zeros(n, 2, 30, dtype=dt64),
                                   PiecewiseConstantInputs(n_segments=30))
        x0 = x_ref.clone()
        x0[:, 4] = args.bias
        _, x = simulate_closed_loop(system, ctrl, x0.unsqueeze(-2), reference, config=LiouvilleConfig("euler", 0.01))
        y_sim = (x[:, 0, -1, 1] - reference.x[:, -1, 1]).abs()
    print(f"{mset.name} set, controller {args.controller}, bias {args.bias:.4f} rad")
    print("| v [m/s] | " + " | ".join(f"{s:g}" for s in SPEEDS) + " |")
    print("| --- |" + " --- |" * n)
    rows = (("k_lat [1/(m s)]", k_lat), ("k_head [1/s]", k_head), ("y* = k_head/k_lat b [m]", y_pred),
            ("closed loop at 30 s [m]", y_sim))
    for name, vals in rows:
        print(f"| {name} | " + " | ".join(f"{float(t):.2f}" for t in vals) + " |")


if __name__ == "__main__":
    main()

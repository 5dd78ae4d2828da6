"""Exact Liouville on the road domain: stop 53's speed-step schedule (RK4 at the step of each band of the references'
top speed) against the error-controlled dopri5, per band, on 100 random road references x 20 samples of a seed,
against float64 RK4 at 0.005 s; largest log-density error and wall time (float32, one thread, inference mode; the
table in docs/core.md, "An error-controlled integrator").

    python benchmarks/compare_liouville_schemes.py [--seed 0] [--tolerance 5e-5]
"""

from __future__ import annotations

import argparse
import copy
import time

import torch

from density_planner.control.registry import load_controller, model_set
from density_planner.control.sampling import sample_feasible_references, sample_initial_errors
from density_planner.density.liouville import LiouvilleConfig, propagate_density

#: bands of the references' top speed [m/s] and stop 53's RK4 step for each
BANDS = ((0.0, 15.0, 0.1), (15.0, 20.0, 0.05), (20.0, 25.0, 0.025), (25.0, 45.0, 0.02))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, default=0, help="seed of the references and initial errors (default 0)")
    p.add_argument("--tolerance", type=float, default=5e-5, help="dopri5's tolerance (default 5e-5)")
    args = p.parse_args()
    torch.set_num_threads(1)
    system = model_set("road").make_system()
    controller = load_controller(None, models="road")
    gen = torch.Generator().manual_seed(args.seed)
    ref64 = sample_feasible_references(system, 100, gen, dtype=torch.float64)
    xe0 = sample_initial_errors(2000, gen, box=system.config.initial_error_max, dtype=torch.float64)
    x0 = ref64.start.unsqueeze(-2) + xe0.reshape(100, 20, system.nx)
    top = ref64.x[..., 3].abs().amax(-1)
    truth = propagate_density(system, copy.deepcopy(controller).double(), x0, ref64,
                              config=LiouvilleConfig("rk4", 0.005)).log_rho
    r32 = type(ref64)(ref64.params.float(), ref64.x.float(), ref64.u.float(), ref64.parameterization)
    c32 = copy.deepcopy(controller).float()

    def run(sel, config):
        t0 = time.perf_counter()
        with torch.inference_mode():
            out = propagate_density(system, c32, x0.float()[sel], r32.select(sel), config=config)
        return time.perf_counter() - t0, float((out.log_rho.double() - truth[sel]).abs().max())

    for lo, hi, step in BANDS:
        sel = torch.nonzero((top >= lo) & (top < hi)).squeeze(-1)
        if not len(sel):
            continue
        ws, es = run(sel, LiouvilleConfig("rk4", step))
        wd, ed = run(sel, LiouvilleConfig("dopri5", tolerance=args.tolerance))
        print(f"seed {args.seed} [{lo:g},{hi:g}) m/s, {len(sel)} refs: schedule (rk4 {step} s) {es:.3f} nats "
              f"{ws:.2f} s | dopri5 {args.tolerance:g}: {ed:.3f} nats {wd:.2f} s", flush=True)


if __name__ == "__main__":
    main()

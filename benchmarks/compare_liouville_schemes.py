"""Exact Liouville on the road domain: the fixed RK4 step against the error-controlled schemes, per band of the
references' top speed, on 100 random road references x 20 samples of a seed, against float64 RK4 at 0.005 s;
largest log-density error [nats] and wall time [s] (float32, one thread, inference mode, each band integrated as
one batch; the table in docs/core.md, "Error control").

    python benchmarks/compare_liouville_schemes.py [--seed 0] [--schemes rk4,rk43,dopri5] [--saturation-step 2]
                                                   [--tolerance TOL] [--rules quadrature,coupled]

A scheme ``NAME:RULE`` (e.g. ``rk43:coupled``) names the error-controlled scheme's log-density rule
(``LiouvilleConfig.log_density_rule``; default the configuration's, "quadrature"); ``--rules`` runs every
error-controlled scheme with each rule.
"""

from __future__ import annotations

import argparse
import copy
import time

import torch

from density_planner.control.registry import load_controller, model_set
from density_planner.control.sampling import sample_feasible_references, sample_initial_errors
from density_planner.density.integrators import PAIRS
from density_planner.density.liouville import LiouvilleConfig, propagate_density

#: bands of the references' top speed [m/s]
BANDS = ((0.0, 15.0), (15.0, 20.0), (20.0, 25.0), (25.0, 45.0))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seed", type=int, default=0, help="seed of the references and initial errors (default 0)")
    p.add_argument("--schemes", default="rk4,rk43,dopri5",
                   help="comma-separated schemes, each at dt = 0.1 s (default rk4,rk43,dopri5)")
    p.add_argument("--tolerance", type=float, default=None,
                   help="tolerance of the error-controlled schemes (default: each scheme's own)")
    p.add_argument("--saturation-step", type=float, default=None,
                   help="LiouvilleConfig.saturation_step (default: the configuration's, 2; 0 turns it off)")
    p.add_argument("--rules", default=None,
                   help="comma-separated log-density rules run for every error-controlled scheme (default: the "
                   "configuration's, quadrature)")
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
    extra = {} if args.saturation_step is None else {"saturation_step": args.saturation_step}
    configs = {}
    for spec in args.schemes.split(","):
        name, _, rule = spec.partition(":")
        rules = [rule] if rule else (args.rules.split(",") if args.rules and name in PAIRS else [None])
        for r in rules:
            kw = dict(extra, **({} if r is None else {"log_density_rule": r}))
            configs[name if r is None else f"{name}:{r}"] = LiouvilleConfig(name, tolerance=args.tolerance, **kw)

    def run(sel, config):
        t0 = time.perf_counter()
        with torch.inference_mode():
            out = propagate_density(system, c32, x0.float()[sel], r32.select(sel), config=config)
        return time.perf_counter() - t0, float((out.log_rho.double() - truth[sel]).abs().max())

    run(torch.arange(4), next(iter(configs.values())))  # warm-up: the first call pays one-time costs
    totals = dict.fromkeys(configs, 0.0)
    worst = dict.fromkeys(configs, 0.0)
    for lo, hi in BANDS:
        sel = torch.nonzero((top >= lo) & (top < hi)).squeeze(-1)
        if not len(sel):
            continue
        line = f"seed {args.seed} [{lo:g},{hi:g}) m/s, {len(sel)} refs:"
        for name, config in configs.items():
            w, e = run(sel, config)
            totals[name] += w
            worst[name] = max(worst[name], e)
            line += f" | {name} {e:.3f} nats {w:.2f} s"
        print(line, flush=True)
    print(f"seed {args.seed} all: " + " | ".join(f"{n} {worst[n]:.3f} nats {totals[n]:.2f} s" for n in configs))


if __name__ == "__main__":
    main()

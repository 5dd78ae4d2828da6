"""``density-planner density``: propagate the initial density along a reference with exact Liouville."""

from __future__ import annotations

import argparse
import sys
import time
from typing import get_args

import numpy as np
import torch

from ..systems.base import LiouvilleScheme
from ._common import (
    add_device,
    add_out,
    add_seed,
    add_system,
    check_out,
    load_params_file,
    out_dir,
    resolve_device,
    resolve_dtype,
)

#: default start pose [x, y, heading, speed] (the fixed start of the artificial scenes)
DEFAULT_START = (0.0, -28.0, 1.5, 3.0)
#: default reference parameters (2, 10) of a two-input system: for the car a gentle S-curve while speeding up, then
#: braking (other input counts: zeros)
DEFAULT_PARAMS = (
    (0.3, 0.3, 0.0, -0.3, -0.3, 0.0, 0.2, 0.2, 0.0, 0.0),
    (0.8, 0.5, 0.3, 0.0, 0.0, 0.0, 0.0, -0.3, -0.5, -0.5),
)


def register(sub: argparse._SubParsersAction, groups: dict) -> None:
    p = sub.add_parser(
        "density",
        help="propagate the initial density along a reference (exact Liouville)",
        description="Sample the default initial distribution (the paper's 5-component Gaussian mixture on the "
        "XE0 box around the start), track a reference with the controller, integrate the Liouville equation "
        "along every trajectory and write DIR/density.npz and DIR/density.png.",
    )
    p.add_argument("--samples", type=int, default=500, help="number of initial samples (default 500)")
    p.add_argument("--params", type=str, default=None, metavar="FILE",
                   help="reference parameters (nu x 10) as .json/.npy/.npz (default: a built-in S-curve)")
    p.add_argument("--start", type=float, nargs=4, default=DEFAULT_START, metavar="X",
                   help="start pose x y heading speed, mapped to the system's state (default: %(default)s)")
    p.add_argument("--integrator", default=None, choices=get_args(LiouvilleScheme),
                   help="integration scheme (default: the system's, rk4 or for the road domain the error-controlled "
                   "rk43)")
    p.add_argument("--dt", type=float, default=None,
                   help="integration step [s] (default 0.1 for rk4 and the error-controlled rk43 and dopri5, whose "
                   "steps it bounds; 0.01 euler)")
    p.add_argument("--tolerance", type=float, default=None,
                   help="rk43 / dopri5: largest local error per step of every state component and of the "
                   "log-density (default: the scheme's own, 3e-3 / 5e-5)")
    add_system(p, density=False)
    add_seed(p)
    add_device(p)
    add_out(p)
    p.set_defaults(func=run)


def _within_lateral_limit(car, reference, *, start_speed: float, default: bool):
    """A car with a lateral-acceleration limit (the road domain) bounds its references' turn rate by the speed
    (:meth:`~density_planner.systems.car.KinematicCar.segment_turn_rate_limits`). The built-in S-curve's turn rates
    are scaled into that bound (the speed profile, hence the bound, is unchanged); a reference from ``--params``
    beyond it is planned as given with a one-line warning on stderr (the controller's saturation then bends it)."""
    limits_of = getattr(car, "segment_turn_rate_limits", None)
    i = car.turn_rate_input
    if limits_of is None or i is None:
        return reference
    from ..control.reference import make_reference

    limit = limits_of(reference.x, reference.parameterization.steps_per_segment)  # (S,)
    omega = reference.params[i]
    excess = omega.abs() - limit
    if not bool((excess > 1e-6 * (1.0 + limit)).any()):
        return reference
    if default:
        params = reference.params.clone()
        params[i] = torch.clamp(omega, -limit, limit)
        return make_reference(car, reference.x[0], params, reference.parameterization)
    k = int(excess.argmax())
    print(f"density-planner: warning: --params turns at {float(omega[k].abs()):.3g} rad/s on segment {k} where the "
          f"car's lateral-acceleration limit allows {float(limit[k]):.3g} rad/s at the reference's speed (start "
          f"{start_speed:g} m/s); the controller saturates there: lower the turn rates or the speed", file=sys.stderr)
    return reference


def run(args: argparse.Namespace) -> int:
    from ..config import update
    from ..control.reference import make_reference
    from ..control.registry import load_controller, model_set_for_scene
    from ..density.distributions import paper_gaussian_mixture
    from ..density.liouville import IntegratorName, LiouvilleConfig, propagate_density
    from ..io.atomic import atomic_save_npz
    from ..memory import check_memory
    from ..systems.registry import SystemConfig

    if args.samples < 1:
        raise ValueError(f"--samples must be >= 1, got {args.samples}")
    check_out(args.out)
    device, dtype = resolve_device(args.device), resolve_dtype(args.dtype)
    # per sample: the saved trajectory (101 x (nx + 1)), the integrator's working set of one step and the arrays
    # written to the .npz (measured: 14 KB per sample at float32, 20000 samples)
    itemsize = 8 if dtype == torch.float64 else 4
    check_memory(args.samples * (101 * 6 * (itemsize + 8) + 8192), f"--samples {args.samples}",
                 "lower --samples")
    sys_cfg = update(SystemConfig(), {k: v for k, v in (("name", args.system), ("models", args.models)) if v})
    models = model_set_for_scene("random", sys_cfg.models, sys_cfg.name)
    car = models.make_system()
    controller = load_controller(args.controller, models=models).to(device=device, dtype=dtype)

    where = "reference parameters" if args.params is None else f"--params {args.params}"
    default = np.asarray(DEFAULT_PARAMS) if car.nu == 2 else np.zeros((car.nu, 10))
    params = default if args.params is None else load_params_file(args.params)
    if params.shape != (car.nu, 10):
        raise ValueError(f"{where}: reference parameters must have shape ({car.nu}, 10), got {params.shape}")
    if not np.isfinite(params).all():
        raise ValueError(f"{where}: reference parameters contain NaN or infinite values")
    lo, hi = car.input_bounds
    if (params < np.asarray(lo)[:, None]).any() or (params > np.asarray(hi)[:, None]).any():
        raise ValueError(f"{where}: reference parameters must lie within the input bounds [{lo}, {hi}]")
    if not all(np.isfinite(args.start)):
        raise ValueError("--start contains NaN or infinite values")
    start = torch.tensor(car.state_from_pose(*args.start), dtype=dtype, device=device)

    integrator: IntegratorName = args.integrator or LiouvilleConfig().scheme(car)
    dt = args.dt if args.dt is not None else (0.01 if integrator == "euler" else 0.1)
    config = LiouvilleConfig(integrator=integrator, dt=dt, tolerance=args.tolerance)

    out = out_dir(args.out)  # every input is valid: create the output directory
    gen = torch.Generator().manual_seed(args.seed)
    dist = paper_gaussian_mixture(start.cpu().double(), car.initial_error_max, gen)
    x0 = dist.sample(args.samples, gen, dtype=dtype, device=device)
    log_rho0 = dist.log_prob(x0)
    ref_start = car.nominal_state(start.clone())  # the reference is the nominal (unbiased) trajectory
    reference = make_reference(car, ref_start, torch.as_tensor(params, dtype=dtype, device=device))
    reference = _within_lateral_limit(car, reference, start_speed=args.start[3], default=args.params is None)

    t0 = time.perf_counter()
    with torch.no_grad():
        traj = propagate_density(car, controller, x0, reference, log_rho0=log_rho0, config=config)
    elapsed = time.perf_counter() - t0

    arrays = {
        "t": traj.t.cpu().numpy(),
        "x": traj.x.cpu().numpy(),
        "log_rho": traj.log_rho.cpu().numpy(),
        "log_rho0": traj.log_rho0.cpu().numpy(),
        "x_ref": reference.x_plan.cpu().numpy(),
        "params": reference.params.cpu().numpy(),  # as integrated (the built-in curve within the lateral limit)
    }
    atomic_save_npz(out / "density.npz", **arrays)
    from ..viz.density import plot_density_snapshots

    plot_density_snapshots(arrays["t"], arrays["x"], arrays["log_rho"], arrays["x_ref"], out / "density.png",
                           title=f"{args.samples} samples, {config.describe(car)}, {elapsed:.2f}s")
    print(f"propagated {args.samples} samples over {float(traj.t[-1]):.1f} s in {elapsed:.2f} s "
          f"({config.describe(car)}); wrote {out / 'density.npz'} and {out / 'density.png'}")
    return 0

"""Wall time of the controller's online step for one state: the torch C3M controller vs the torch-free
:class:`~density_planner.control.fast.NumpyC3M`, numpy and compiled (numba) (issue 17 target: <= 0.1 ms).

Usage::

    PYTHONPATH=src python benchmarks/bench_controller_step.py [--models road] [--n 2000]

Prints the median time of one controller evaluation and of one 0.1-s step of the online loop: 10 evaluations at
the 0.01-s Euler step of the closed loop, timed as ``NumpyC3M.track`` runs it in ``drive`` (the torch controller:
10 evaluations; for ``NumpyC3M`` also ``evaluate_each`` on 10 given states, as the benchmarks' executions time it),
on one thread.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np
import torch


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--models", default="road", choices=("paper", "road"))
    p.add_argument("--n", type=int, default=2000)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    from density_planner.control.fast import NumpyC3M
    from density_planner.control.registry import load_controller, model_set

    models = model_set(args.models)
    ctrl = load_controller("c3m", models=models)
    x_ref = torch.tensor([[1.0, 2.0, 0.3, 8.0, 0.0]])
    x_hat = x_ref + torch.tensor([[0.3, -0.2, 0.05, 0.4, 0.0]])
    u_ref = torch.tensor([[0.1, 0.5]])
    xr, xh, ur = x_ref[0].double().numpy(), x_hat[0].double().numpy(), u_ref[0].double().numpy()
    x_refs, u_refs = np.tile(xr, (10, 1)), np.tile(ur, (10, 1))

    def timeit(fn) -> float:
        for _ in range(50):
            fn()
        ts = []
        for _ in range(args.n):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        return float(np.median(ts))

    with torch.no_grad():
        t_torch = timeit(lambda: ctrl(x_hat, x_ref, u_ref))
    rows = [("torch C3MController", t_torch, 10 * t_torch)]
    paths = [("NumpyC3M (numpy)", NumpyC3M(ctrl, compiled=False))]
    fast = NumpyC3M(ctrl)
    if fast.compiled:
        paths.append(("NumpyC3M (numba)", fast))
    else:
        print("numba is not installed: the compiled path is not timed (pip install 'density-planner[fast]')")
    x_hats = np.tile(xh, (10, 1))
    for name, f in paths:
        rows.append((name, timeit(lambda f=f: f(xh, xr, ur)), timeit(lambda f=f: f.track(xh, x_refs, u_refs, 0.01)),
                     timeit(lambda f=f: f.evaluate_each(x_hats, x_refs, u_refs))))
    for name, t_eval, t_step, *each in rows:
        extra = f" ({1e3 * each[0]:.3f} ms as 10 given states, evaluate_each)" if each else ""
        print(f"{name:20s}: {1e6 * t_eval:7.1f} us per evaluation, {1e3 * t_step:6.3f} ms per 0.1-s step{extra}")
    print("target: <= 0.1 ms per online step (one state)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""A fixed workload that measures how fast this machine is right now, for reading timings across days.

Wall times of the ``plan`` command on the project's virtual 2-core machine drift by 5-15 % between days (stop 47's
code: 4.89 s median over the suite one day, 5.69 s another), and a pure-Python loop does not show it: the command
spends much of its time on memory (fresh pages of a 0.5-GiB grid, tensor passes over it) and in torch's small
operations. This script times one of each, as the command does them, on one thread, in a fresh process:

- ``faults``: a 256-MiB float32 tensor written for the first time, then clamped in place (first touch of fresh
  memory, then a pass over it);
- ``ops``: 20 000 small torch operations on (250, 128) tensors (the per-operation cost that bounds the exact
  re-check and the planner's iterations);
- ``python``: a pure-Python loop of 3 million additions.

Prints the best of 3 repetitions of each and their sum (``reference``), e.g. before and after a benchmark
(``bench_plan_command.py`` does). A guide to the machine's state, not a correction factor: within one hour it moved
0.66 -> 0.71 s while the plan command's exact re-check went 0.49 -> 0.65 s with the same code.

    python benchmarks/machine_reference.py [--json]
"""

from __future__ import annotations

import argparse
import json
import time


def _faults() -> float:
    import torch

    t = time.perf_counter()
    a = torch.empty(64 * 2**20, dtype=torch.float32)
    a.fill_(0.5)
    a.clamp_(0.0, 1.0)
    dt = time.perf_counter() - t
    del a
    return dt


def _ops() -> float:
    import torch

    x = torch.rand(250, 128)
    w = torch.rand(128, 128) * 0.01
    t = time.perf_counter()
    for _ in range(2000):  # 10 operations each
        y = torch.tanh(x @ w)
        z = (1.0 - y * y) * x
        x = torch.where(z > 0.5, y, z).clamp(0.0, 1.0).sum(-1, keepdim=True) * 0.001 + x * 0.999
        x = x.contiguous()
    return time.perf_counter() - t


def _python() -> float:
    t = time.perf_counter()
    s = 0
    for i in range(3_000_000):
        s += i
    return time.perf_counter() - t


def measure(repeats: int = 3) -> dict[str, float]:
    """Best of ``repeats`` seconds of each part, and their sum ``reference``."""
    import torch

    torch.set_num_threads(1)
    out = {name: min(fn() for _ in range(repeats)) for name, fn in (("faults", _faults), ("ops", _ops),
                                                                    ("python", _python))}
    out["reference"] = sum(out.values())
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--json", action="store_true", help="print one JSON object")
    args = p.parse_args()
    res = measure()
    if args.json:
        print(json.dumps({k: round(v, 4) for k, v in res.items()}))
    else:
        print(" ".join(f"{k} {v:.3f} s" for k, v in res.items()))


if __name__ == "__main__":
    main()

"""glibc malloc thresholds set on import (``density_planner.memory.tune_allocator``), checked in fresh processes
with ``mallinfo2``: where a 20 MiB tensor comes from (the heap or its own mapping) and whether freeing it keeps it."""

from __future__ import annotations

import ctypes
import json
import os
import subprocess
import sys
import textwrap

import pytest

glibc = pytest.mark.skipif(
    not sys.platform.startswith("linux") or not hasattr(ctypes.CDLL(None), "mallinfo2"),
    reason="glibc >= 2.33 (mallinfo2) only",
)

PROBE = textwrap.dedent("""
    import ctypes, json
    import density_planner  # noqa: F401 - the import applies the thresholds
    import density_planner.memory as memory
    import torch

    class MallInfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                     "fsmblks", "uordblks", "fordblks", "keepcost")]

    libc = ctypes.CDLL(None)
    libc.mallinfo2.restype = MallInfo2
    before = libc.mallinfo2()
    x = torch.ones(5 * 2**20)  # 20 MiB
    held = libc.mallinfo2()
    del x
    after = libc.mallinfo2()
    mib = 2**20
    print(json.dumps({"tuned": memory._tuned, "again": memory.tune_allocator(),
                      "heap": (held.arena - before.arena) / mib, "mapped": (held.hblkhd - before.hblkhd) / mib,
                      "kept": (after.arena - before.arena) / mib}))
""")


def probe(**env: str) -> dict:
    environ = {k: v for k, v in os.environ.items()
               if not k.startswith("MALLOC_") and k != "DENSITY_PLANNER_TUNE_MALLOC"}
    out = subprocess.run([sys.executable, "-c", PROBE], env={**environ, **env}, capture_output=True, text=True,
                         check=True, timeout=120)
    return json.loads(out.stdout.strip().splitlines()[-1])


@glibc
def test_import_serves_mid_sized_tensors_from_the_heap_and_keeps_them():
    r = probe()
    assert r["tuned"] is True and r["again"] is True  # idempotent
    assert r["heap"] > 15 and r["mapped"] == 0  # below the 32 MiB threshold: the heap, not a mapping
    assert r["kept"] > 15  # freed, but below the 128 MiB trim threshold: kept for the next iteration


@glibc
@pytest.mark.parametrize("env", [{"DENSITY_PLANNER_TUNE_MALLOC": "0"}, {"MALLOC_TRIM_THRESHOLD_": "131072"}])
def test_opt_out_leaves_glibc_defaults(env):
    r = probe(**env)
    assert r["tuned"] is False and r["again"] is False
    assert r["mapped"] >= 19.9 and r["heap"] < 1  # glibc's initial 128 KiB threshold: its own mapping
    assert r["kept"] < 1

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
def test_opt_out_leaves_the_allocator_alone():
    r = probe(DENSITY_PLANNER_TUNE_MALLOC="0")
    assert r["tuned"] is False and r["again"] is False  # glibc's adaptive thresholds: where 20 MiB go depends on
    # what the imports freed, so only the flag is checked here


@glibc
def test_glibc_settings_of_the_user_win():
    """A glibc threshold variable set by the user disables the tuning; glibc then keeps its 128 KiB mmap threshold
    (setting any threshold turns its adaptation off): 20 MiB get their own mapping, returned on ``del``."""
    r = probe(MALLOC_TRIM_THRESHOLD_="131072")
    assert r["tuned"] is False and r["again"] is False
    assert r["mapped"] >= 19.9 and r["heap"] < 1
    assert r["kept"] < 1

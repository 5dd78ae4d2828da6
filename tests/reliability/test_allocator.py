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


def _rss_bytes() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(not os.path.exists("/proc/self/statm"), reason="Linux /proc only")
def test_lazy_zeros_touch_only_the_pages_written():
    """``lazy_zeros``: zeros of the asked shape and dtype, writable, shared with numpy; a 256 MiB block costs
    resident memory only for the pages written (a few cells far apart), not for the whole block as ``torch.zeros``
    does; small blocks and other devices are plain ``torch.zeros``."""
    import torch

    from density_planner.memory import lazy_zeros

    for dtype in (torch.bool, torch.uint8, torch.float32):
        z = lazy_zeros((4, 512, 1024), dtype)
        assert z.shape == (4, 512, 1024) and z.dtype == dtype and z.is_contiguous()
        assert not bool(z.any())
        z[1, 2, 3] = 1
        assert int(z.to(torch.int64).sum()) == 1 and z.numpy()[1, 2, 3] == 1
    small = lazy_zeros((10,), torch.float64)
    assert small.dtype == torch.float64 and float(small.abs().sum()) == 0.0
    before = _rss_bytes()
    big = lazy_zeros((256 * 2**20,), torch.uint8)
    big[:: 2**24] = 1  # 16 cells, 16 MiB apart
    grown = _rss_bytes() - before
    assert grown < 8 * 2**20, grown
    assert int(big.count_nonzero()) == 16
    reference = torch.zeros(64 * 2**20, dtype=torch.uint8)
    assert _rss_bytes() - before - grown >= 32 * 2**20  # the measurement sees a torch.zeros block
    del big, reference

"""Memory estimates checked before large allocations: a request that cannot fit is refused up front with one line
naming the setting that sizes it, instead of a ``MemoryError`` (or the OOM killer) minutes later.

``check_memory(nbytes, what, fix)`` compares an estimate with the memory available now (``MemAvailable`` of
``/proc/meminfo``, or psutil where installed). The environment variable ``DENSITY_PLANNER_MEMORY_LIMIT`` (bytes,
or a number with a suffix ``K``, ``M``, ``G``) sets the budget explicitly, e.g. to keep a job under a cluster's
memory limit.

``tune_allocator()`` (run once when the package is imported) fixes glibc's ``malloc`` thresholds so that the
tensors a planning iteration frees are reused by the next one instead of being handed back to the kernel and
faulted in again (see its docstring; ``DENSITY_PLANNER_TUNE_MALLOC=0`` leaves the allocator alone).
"""

from __future__ import annotations

import ctypes
import math
import os
import sys
from typing import TYPE_CHECKING, Any

from .errors import ResourceError

if TYPE_CHECKING:
    import torch

__all__ = ["available_memory", "memory_budget", "check_memory", "format_bytes", "tune_allocator", "lazy_zeros",
           "MEMORY_LIMIT_ENV", "TUNE_MALLOC_ENV"]

#: environment variable overriding the memory budget [bytes; suffixes K, M, G, T accepted]
MEMORY_LIMIT_ENV = "DENSITY_PLANNER_MEMORY_LIMIT"

#: environment variable: ``0`` leaves the C allocator's thresholds as they are (:func:`tune_allocator`)
TUNE_MALLOC_ENV = "DENSITY_PLANNER_TUNE_MALLOC"
#: glibc's own environment settings of the thresholds; any of them set means the user chose, and is respected
_GLIBC_MALLOC_ENV = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")
#: requests from this size on get their own mapping [bytes]: glibc's largest dynamic threshold (32 MiB on 64 bits)
MMAP_THRESHOLD = 32 * 2**20
#: free memory at the top of the heap kept for reuse up to this size [bytes]
TRIM_THRESHOLD = 128 * 2**20
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameters (glibc's malloc.h)
_tuned: bool | None = None

_SUFFIX = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def format_bytes(n: float) -> str:
    """``3.6 GiB``, ``412 MiB``, ``12 KiB``."""
    n = float(n)
    for unit, scale in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if abs(n) >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n:.0f} B"


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation now (``None`` when it cannot be determined)."""
    try:
        import psutil

        return int(psutil.virtual_memory().available)
    except Exception:  # noqa: BLE001 - psutil is optional
        pass
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - non-POSIX
        return None


def memory_budget() -> int | None:
    """The budget large requests are checked against: ``DENSITY_PLANNER_MEMORY_LIMIT`` if set, else the memory
    available now."""
    text = os.environ.get(MEMORY_LIMIT_ENV, "").strip()
    if text:
        unit = text[-1].upper() if text[-1].isalpha() else ""
        number = text[:-1] if unit else text
        try:
            value = float(number) * _SUFFIX[unit]
        except (ValueError, KeyError):
            raise ResourceError(f"{MEMORY_LIMIT_ENV}={text!r} is not a size (e.g. 4G, 512M or a number of bytes)"
                                ) from None
        if not value > 0:
            raise ResourceError(f"{MEMORY_LIMIT_ENV} must be > 0, got {text!r}")
        return int(value)
    return available_memory()


def check_memory(nbytes: float, what: str, fix: str) -> None:
    """Raise :class:`~density_planner.errors.ResourceError` (a ``ValueError``: exit code 2) when ``what`` needs an
    estimated ``nbytes`` of memory, more than :func:`memory_budget`; ``fix`` names the setting to change (e.g.
    ``"raise random_scene.cell_size"``)."""
    budget = memory_budget()
    if budget is None or nbytes <= budget:
        return
    source = MEMORY_LIMIT_ENV if os.environ.get(MEMORY_LIMIT_ENV, "").strip() else "available on this machine"
    raise ResourceError(
        f"{what} needs about {format_bytes(nbytes)} of memory, more than the {format_bytes(budget)} {source}; "
        f"{fix}"
    )


def tune_allocator() -> bool:
    """Fix glibc ``malloc``'s mmap threshold at 32 MiB and its trim threshold at 128 MiB; ``True`` when applied.

    A planner iteration allocates and frees tens of tensors of 0.1-10 MiB (sample clouds, their gradients). glibc
    adapts its thresholds to the sizes it has seen freed, and with the default adaptation the top of the heap was
    returned to the kernel (``brk``) and faulted in again on every iteration of the density planner's second stage:
    72 000 page faults and 0.12-0.16 s of system time per plan at the paper's settings (``benchmarks/bench_plan.py
    --paper``), against ~40 with the fixed thresholds. Blocks below 32 MiB then come from the heap, and up to
    128 MiB of freed memory stays with the process for reuse. Applied once per process (a forked worker inherits
    it); a no-op off glibc, with ``DENSITY_PLANNER_TUNE_MALLOC=0``, or when glibc's own ``MALLOC_*_`` threshold
    variables are set (the user chose).
    """
    global _tuned
    if _tuned is not None:
        return _tuned
    _tuned = False
    if os.environ.get(TUNE_MALLOC_ENV, "").strip() == "0" or any(k in os.environ for k in _GLIBC_MALLOC_ENV):
        return False
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)  # the C library the interpreter runs on
        if not hasattr(libc, "gnu_get_libc_version"):  # musl and others: their mallopt is a stub or absent
            return False
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # pragma: no cover - no dynamic C library
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _tuned = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    return _tuned


def lazy_zeros(shape: tuple[int, ...], dtype: torch.dtype, device: Any = "cpu") -> torch.Tensor:
    """A tensor of zeros whose memory is touched only where it is used: on the CPU a block of 1 MiB or more is an
    anonymous memory mapping (the kernel's zero page until a page is written, in 4-KiB pages: numpy's own large
    arrays ask for 2-MiB pages, each zeroed whole on its first touch), smaller ones ``torch.zeros``, as on other
    devices. For the per-cell masks and tables over a whole space-time grid of which a plan reads a small part:
    ``torch.zeros`` writes every byte (a replan on recorded traffic spent ~0.1 s of its ~0.3 s zero-filling the masks
    of its fresh occupancy window, 100-500 MB, of which it reads a few thousand cells)."""
    import mmap

    import numpy as np
    import torch

    device = torch.device(device)
    proto = torch.empty(0, dtype=dtype)
    nbytes = math.prod(int(d) for d in shape) * proto.element_size()
    if device.type != "cpu" or nbytes < _LAZY_ZEROS_MIN:
        return torch.zeros(shape, dtype=dtype, device=device)
    block = mmap.mmap(-1, nbytes)  # private, anonymous: zero-filled by the kernel page by page
    return torch.from_numpy(np.frombuffer(block, dtype=proto.numpy().dtype).reshape(shape))  # keeps the mapping


#: blocks from this size on are mapped by :func:`lazy_zeros` [bytes]
_LAZY_ZEROS_MIN = 1 << 20

"""Memory estimates checked before large allocations: a request that cannot fit is refused up front with one line
naming the setting that sizes it, instead of a ``MemoryError`` (or the OOM killer) minutes later.

``check_memory(nbytes, what, fix)`` compares an estimate with the memory available now (``MemAvailable`` of
``/proc/meminfo``, or psutil where installed). The environment variable ``DENSITY_PLANNER_MEMORY_LIMIT`` (bytes,
or a number with a suffix ``K``, ``M``, ``G``) sets the budget explicitly, e.g. to keep a job under a cluster's
memory limit.
"""

from __future__ import annotations

import os

from .errors import ResourceError

__all__ = ["available_memory", "memory_budget", "check_memory", "format_bytes", "MEMORY_LIMIT_ENV"]

#: environment variable overriding the memory budget [bytes; suffixes K, M, G, T accepted]
MEMORY_LIMIT_ENV = "DENSITY_PLANNER_MEMORY_LIMIT"

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

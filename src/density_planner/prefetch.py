"""Reading a CommonRoad file in a second process while this one starts up.

A ``plan --env commonroad`` command spends its first second importing torch, on one core; commonroad-io's reader
(its own imports and the XML: 0.3-1.6 s on suite scenarios) needs none of it. :func:`start_commonroad_read`, called
by the command line before it imports anything heavy, forks a process that reads the file with commonroad-io and
sends back the pickled ``(scenario, planning_problem_set)`` (plain Python objects, 0.1-1 MB); the command's
:func:`~density_planner.environment.commonroad.read_commonroad` takes it with :func:`take_commonroad_read` after its
own checks of the file. Anything unexpected (the file changed since, the reader failed, no ``fork``) leaves the
reading to the caller, who then reads the file as without a prefetch (and reports its errors).

This module imports neither torch nor commonroad-io.
"""

from __future__ import annotations

import os
import pickle
import sys
import warnings
from pathlib import Path
from typing import Any

__all__ = ["start_commonroad_read", "take_commonroad_read", "cancel_prefetch"]

#: the read in flight: (resolved path, (size, mtime_ns), pid, read end of the pipe)
_PENDING: tuple[str, tuple[int, int], int, int] | None = None


def _identity(path: str | Path) -> tuple[str, tuple[int, int]] | None:
    try:
        p = Path(path).resolve()
        st = p.stat()
    except OSError:
        return None
    return str(p), (st.st_size, st.st_mtime_ns)


def start_commonroad_read(path: str | Path) -> bool:
    """Fork a process that reads the CommonRoad file ``path``; returns whether one was started (not without
    ``fork``, for a missing file, or while another read is in flight)."""
    global _PENDING
    if _PENDING is not None or not hasattr(os, "fork"):
        return False
    ident = _identity(path)
    if ident is None:
        return False
    for stream in (sys.stdout, sys.stderr):  # the child would print what is still buffered here once more
        stream.flush()
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: read, send, end without running the parent's exit handlers
        code = 0
        try:
            os.close(read_end)
            payload = _read(ident[0])
            with os.fdopen(write_end, "wb") as fh:
                fh.write(payload)
        except BaseException:  # noqa: BLE001 - the parent reads the file itself
            code = 1
        finally:
            os._exit(code)
    os.close(write_end)
    _PENDING = (ident[0], ident[1], pid, read_end)
    return True


def _read(path: str) -> bytes:
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's
    from commonroad.common.file_reader import CommonRoadFileReader

    with warnings.catch_warnings():  # as read_commonroad does: NaN coordinates are checked by the caller
        warnings.simplefilter("ignore", RuntimeWarning)
        value = CommonRoadFileReader(path).open()
    return pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)


def take_commonroad_read(path: str | Path) -> tuple[Any, Any] | None:
    """The ``(scenario, planning_problem_set)`` read by :func:`start_commonroad_read` for this same file (same
    resolved path, size and modification time), waiting for it if needed; ``None`` where there is none or the read
    failed (the caller then reads the file)."""
    global _PENDING
    if _PENDING is None:
        return None
    ident = _identity(path)
    if ident is None or ident != (_PENDING[0], _PENDING[1]):
        return None
    _, _, pid, fd = _PENDING
    _PENDING = None
    with os.fdopen(fd, "rb") as fh:
        payload = fh.read()
    _, status = os.waitpid(pid, 0)
    if status != 0 or not payload:
        return None
    try:
        value = pickle.loads(payload)
    except Exception:  # noqa: BLE001 - e.g. a commonroad-io that cannot be imported here: read it there
        return None
    return value if isinstance(value, tuple) and len(value) == 2 else None


def cancel_prefetch() -> None:
    """End a read in flight (its result unused)."""
    global _PENDING
    if _PENDING is None:
        return
    _, _, pid, fd = _PENDING
    _PENDING = None
    os.close(fd)
    try:
        os.kill(pid, 9)
        os.waitpid(pid, 0)
    except (ProcessLookupError, ChildProcessError):  # pragma: no cover - already gone
        pass

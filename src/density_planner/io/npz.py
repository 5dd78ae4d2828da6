"""Guarded reading of ``.npz`` / ``.npy`` files given by users (scenes, grids, reference parameters).

Before any array is loaded, the header of every member is read and its declared size (shape x item size) is
checked against a limit, so a small compressed file that inflates to gigabytes (a "zip bomb") is refused in
milliseconds instead of filling the memory. Truncated or corrupt archives, object arrays (pickles) and unreadable
headers all become one :class:`~density_planner.errors.DataError` naming the file.

The limit is :data:`DEFAULT_MAX_BYTES` (2 GiB: a scene of 300 M float32 cells, the scene builders' ``max_cells``,
takes 1.1 GiB) or the environment variable ``DENSITY_PLANNER_MAX_FILE_BYTES``, and never more than the memory
available (:func:`density_planner.memory.check_memory`).
"""

from __future__ import annotations

import math
import os
import zipfile
import zlib
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..memory import check_memory, format_bytes

__all__ = ["read_npz", "read_npy", "npz_members", "DEFAULT_MAX_BYTES", "MAX_FILE_BYTES_ENV"]

#: default limit on the total declared size of the arrays of one file [bytes]
DEFAULT_MAX_BYTES = 2 * 2**30
#: environment variable overriding :data:`DEFAULT_MAX_BYTES` [bytes]
MAX_FILE_BYTES_ENV = "DENSITY_PLANNER_MAX_FILE_BYTES"

#: what reading a corrupt archive can raise
_READ_ERRORS = (OSError, EOFError, ValueError, zipfile.BadZipFile, zlib.error, KeyError, RuntimeError)


def _limit(max_bytes: int | None) -> int:
    if max_bytes is not None:
        return int(max_bytes)
    text = os.environ.get(MAX_FILE_BYTES_ENV, "").strip()
    if text:
        try:
            return int(float(text))
        except ValueError:
            raise DataError(f"{MAX_FILE_BYTES_ENV}={text!r} is not a number of bytes") from None
    return DEFAULT_MAX_BYTES


def _header(fh, source: str) -> tuple[tuple[int, ...], np.dtype]:
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
    elif version == (2, 0):
        shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
    else:
        # 3.0 (utf-8 header): numpy's reader of it is private, hence not in its type stubs
        shape, _, dtype = getattr(np.lib.format, "_read_array_header")(fh, version)  # noqa: B009 - not in the stubs
    if dtype.hasobject:
        raise DataError(f"{source}: holds an object array (a pickle); only numeric arrays are read")
    return tuple(int(d) for d in shape), dtype


def npz_members(path: str | Path) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Declared ``(shape, dtype)`` of every array of the ``.npz`` at ``path`` (reads headers only)."""
    path = Path(path)
    out = {}
    try:
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                name = info.filename
                if not name.endswith(".npy"):
                    continue
                with zf.open(info) as fh:
                    out[name[:-4]] = _header(fh, f"{path} ({name})")
    except DataError:
        raise
    except _READ_ERRORS as exc:
        raise DataError(f"{path}: not a readable .npz file (truncated or corrupt: {exc})") from exc
    return out


def _declared(members: dict[str, tuple[tuple[int, ...], np.dtype]]) -> tuple[int, str]:
    total, biggest, text = 0, -1, ""
    for name, (shape, dtype) in members.items():
        n = math.prod(shape) * dtype.itemsize
        total += n
        if n > biggest:
            biggest, text = n, f"{name} {' x '.join(map(str, shape)) or 'scalar'} {dtype}"
    return total, text


def _check_size(path: Path, total: int, biggest: str, max_bytes: int | None, what: str) -> None:
    limit = _limit(max_bytes)
    if total > limit:
        raise DataError(
            f"{path}: declares {format_bytes(total)} of arrays (largest: {biggest}), more than the "
            f"{format_bytes(limit)} allowed for {what} files (set {MAX_FILE_BYTES_ENV} to raise the limit)"
        )
    check_memory(total, f"reading {path}", f"use a smaller {what} file")


def read_npz(path: str | Path, *, what: str = "input", max_bytes: int | None = None) -> dict[str, np.ndarray]:
    """All arrays of the ``.npz`` at ``path`` after checking their declared sizes (see the module docstring).

    Raises :class:`DataError` for a missing, truncated or corrupt file, object arrays, or arrays larger than the
    limit; :class:`~density_planner.errors.ResourceError` when they would not fit into memory.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{what} file not found: {path}")
    members = npz_members(path)
    total, biggest = _declared(members)
    _check_size(path, total, biggest, max_bytes, what)
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: np.asarray(z[k]) for k in z.files}
    except _READ_ERRORS as exc:
        raise DataError(f"{path}: not a readable .npz file (truncated or corrupt: {exc})") from exc


def read_npy(path: str | Path, *, what: str = "input", max_bytes: int | None = None) -> np.ndarray:
    """The array of the ``.npy`` at ``path`` after checking its declared size."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{what} file not found: {path}")
    try:
        with path.open("rb") as fh:
            shape, dtype = _header(fh, str(path))
    except DataError:
        raise
    except _READ_ERRORS as exc:
        raise DataError(f"{path}: not a readable .npy file ({exc})") from exc
    total, biggest = _declared({"array": (shape, dtype)})
    _check_size(path, total, biggest, max_bytes, what)
    try:
        return np.load(path, allow_pickle=False)
    except _READ_ERRORS as exc:
        raise DataError(f"{path}: not a readable .npy file (truncated or corrupt: {exc})") from exc

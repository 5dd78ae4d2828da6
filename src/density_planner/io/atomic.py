"""Atomic file writes: write to a temporary file in the target directory, then rename over the target.

An interrupted run therefore never leaves a half-written result: a file either has its old content, its new
content, or does not exist.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

__all__ = ["atomic_write_bytes", "atomic_write_text", "atomic_write_json", "atomic_save_torch", "atomic_save_npz"]


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


#: permissions of written files: as ``open(path, "w")`` would create them (0666 minus the umask)
_FILE_MODE = 0o666 & ~_current_umask()


def _atomic(path: str | Path, writer: Callable[[IO[bytes]], object]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            writer(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    return _atomic(path, lambda fh: fh.write(data))


def atomic_write_text(path: str | Path, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def _json_default(obj: Any) -> Any:
    try:
        import numpy as np

        if isinstance(obj, np.generic):
            return obj.item()
        if isinstance(obj, np.ndarray):
            return obj.tolist()
    except ImportError:  # pragma: no cover
        pass
    try:
        import torch

        if isinstance(obj, torch.Tensor):
            return obj.detach().cpu().tolist()
    except ImportError:  # pragma: no cover
        pass
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable")


def atomic_write_json(path: str | Path, data: Any, *, indent: int = 2) -> Path:
    """Write ``data`` as JSON (numpy/torch values converted to lists; NaN/inf written as null)."""
    text = json.dumps(_sanitize(data), indent=indent, default=_json_default, allow_nan=False)
    return atomic_write_text(path, text + "\n")


def _sanitize(obj: Any) -> Any:
    if isinstance(obj, float) and (obj != obj or obj in (float("inf"), float("-inf"))):
        return None
    if isinstance(obj, dict):
        return {str(k): _sanitize(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_sanitize(v) for v in obj]
    try:
        import numpy as np

        if isinstance(obj, np.ndarray):
            return _sanitize(obj.tolist())
        if isinstance(obj, np.floating):
            return _sanitize(float(obj))
    except ImportError:  # pragma: no cover
        pass
    return obj


def atomic_save_torch(path: str | Path, obj: Any) -> Path:
    import torch

    return _atomic(path, lambda fh: torch.save(obj, fh))


def atomic_save_npz(path: str | Path, **arrays: Any) -> Path:
    """Save arrays to a compressed ``.npz`` atomically (the file name is kept exactly as given)."""
    import numpy as np

    return _atomic(path, lambda fh: np.savez_compressed(fh, **arrays))

"""The collision cost's kernels (:mod:`._jit`) compiled ahead of time into an extension module: a command then
loads them in ~1 ms instead of importing numba and loading its cache (~0.4-0.5 s in a fresh process: numba's
typing registries, then the cached machine code; ~0.2 s more of a ``plan`` command's wall time while the route
seeds and the road's distance field are computed beside it).

:func:`build` compiles the functions of :mod:`._jit` with numba's ahead-of-time compiler (``numba.pycc``, which
needs a C compiler) for float32 and float64 states, into ``_collision_aot_<hash>`` beside this file; ``<hash>`` is
that of :mod:`._jit`'s source, so a module compiled from another version of the kernels is never loaded (stale
ones are removed by the next build). ``make install`` builds it (``python -m density_planner.cost._aot``); where it
cannot (no numba, no C compiler, a numba without ``pycc``) it says so and :func:`load` returns ``None``: the
collision cost then runs the same kernels through numba's just-in-time compiler (:mod:`._jit`), or its tensor path
without numba. The compiled module needs neither numba nor a compiler at run time. Its results are those of the
just-in-time kernels (``tests/planning/test_collision_kernels.py``).

This module imports neither numba nor torch.
"""

from __future__ import annotations

import hashlib
import importlib
import sys
from pathlib import Path

import numpy as np

__all__ = ["build", "load", "module_name"]

_HERE = Path(__file__).resolve().parent
_SOURCE = _HERE / "_jit.py"
_PREFIX = "_collision_aot_"


def module_name() -> str | None:
    """Name of the compiled module for this exact :mod:`._jit` source (``None`` where the source cannot be read)."""
    try:
        return _PREFIX + hashlib.sha256(_SOURCE.read_bytes()).hexdigest()[:16]
    except OSError:
        return None


def _signatures(f: str) -> dict[str, str]:
    """numba signatures of the two kernels for states of numba type ``f`` (``float32`` / ``float64``): the arrays
    the collision cost makes contiguous are declared so (``::1``), the small ones of any layout."""
    x = f"{f}[:,:,:,::1]"
    cells = (f"Tuple((int64, boolean))({x}, int64, int64, int64, {f}[:], {f}[:], {f}[:], {f}, int64, int64, "
             f"int64[:], {f}[:], boolean, boolean[:], int64[:,:,:,::1])")
    accumulate = (f"void({x}, {f}[:,:,::1], int64[:,:,:,::1], {f}[:,:], int64, int64, int64, {f}[:], {f}[:], "
                  f"float64[::1], {x}, {f}[:,:,::1])")
    return {"cells": cells, "accumulate": accumulate}


_SUFFIX = {"float32": "f4", "float64": "f8"}


class CompiledKernels:
    """:mod:`._jit`'s ``cells`` and ``accumulate`` (same arguments) from the compiled module, chosen by the states'
    dtype; ``warm_up`` does nothing (nothing to compile or load)."""

    def __init__(self, module) -> None:
        self.module = module
        self._cells = {np.dtype(f): getattr(module, f"cells_{s}") for f, s in _SUFFIX.items()}
        self._accumulate = {np.dtype(f): getattr(module, f"accumulate_{s}") for f, s in _SUFFIX.items()}

    def cells(self, x: np.ndarray, *args):
        return self._cells[x.dtype](x, *args)

    def accumulate(self, x: np.ndarray, *args) -> None:
        self._accumulate[x.dtype](x, *args)

    def warm_up(self, dtypes: tuple = ()) -> None:
        pass


def load() -> CompiledKernels | None:
    """The compiled kernels of this source of :mod:`._jit`, or ``None`` where :func:`build` has not made them."""
    name = module_name()
    if name is None:
        return None
    try:
        return CompiledKernels(importlib.import_module(f"{__package__}.{name}"))
    except (ImportError, AttributeError):  # a broken or foreign file: the just-in-time kernels serve
        return None


def build(output_dir: str | Path | None = None) -> Path:
    """Compile the kernels into ``output_dir`` (default: beside this file) and remove the modules of other sources
    there; returns the module's path.

    Raises:
        ImportError: numba (the ``fast`` extra) or its ``pycc`` is not installed.
        Exception: whatever the C compiler step raised (e.g. no compiler).
    """
    import warnings

    out = Path(output_dir) if output_dir is not None else _HERE
    name = module_name()
    if name is None:
        raise OSError(f"cannot read {_SOURCE}")
    with warnings.catch_warnings():  # numba marks pycc as pending deprecation; it is what compiles ahead of time
        warnings.simplefilter("ignore")
        from numba.pycc import CC

        from . import _jit

        cc = CC(name)
        cc.output_dir = str(out)
        cc.verbose = False
        for f, s in _SUFFIX.items():
            for kernel, sig in _signatures(f).items():
                cc.export(f"{kernel}_{s}", sig)(getattr(_jit, kernel).py_func)
        cc.compile()
    built = next(p for p in out.glob(name + ".*") if p.suffix in (".so", ".pyd"))
    for old in out.glob(_PREFIX + "*"):
        if not old.name.startswith(name):
            old.unlink(missing_ok=True)
    return built


def main() -> int:
    """``python -m density_planner.cost._aot``: build, or say why not (exit code 0 either way: the just-in-time
    kernels serve)."""
    try:
        path = build()
    except Exception as exc:  # noqa: BLE001 - optional: reported in one line
        print(f"density-planner: the collision kernels were not compiled ahead of time ({type(exc).__name__}: {exc});"
              " numba's just-in-time kernels serve where numba is installed", file=sys.stderr)
        return 0
    print(f"density-planner: compiled the collision kernels into {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Seeded random numbers that are identical on every machine and NumPy version.

NumPy guarantees the raw 64-bit output of ``PCG64(seed)`` (seeded through ``SeedSequence``) to be stable, but
not the algorithms of ``Generator.uniform`` / ``Generator.integers``. This stream derives its numbers from the
raw output directly: ``u = (raw >> 11) * 2**-53`` (53-bit uniform in [0, 1)) and integers as ``lo + floor(u *
n)``.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["Stream"]


class Stream:
    """Uniform floats and integers from one ``PCG64(seed)`` stream (scalar or vector draws)."""

    def __init__(self, seed: int):
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self._bits = np.random.PCG64(int(seed))

    def _unit(self, size: int | None) -> float | np.ndarray:
        if size is None:
            return (int(self._bits.random_raw()) >> 11) * 2.0**-53
        raw = np.asarray(self._bits.random_raw(size), dtype=np.uint64)
        return (raw >> np.uint64(11)).astype(np.float64) * 2.0**-53

    def uniform(self, lo: float = 0.0, hi: float = 1.0, size: int | None = None):
        """Uniform in ``[lo, hi)`` (a float, or an array of ``size``)."""
        return lo + (hi - lo) * self._unit(size)

    def integer(self, lo: int, hi: int) -> int:
        """Uniform integer in ``[lo, hi]`` inclusive."""
        n = hi - lo + 1
        return lo + min(int(self._unit(None) * n), n - 1)

    def integers(self, lo: int, hi: int, size: int) -> np.ndarray:
        """``size`` uniform integers in ``[lo, hi]`` inclusive."""
        n = hi - lo + 1
        return lo + np.minimum((np.asarray(self._unit(size)) * n).astype(np.int64), n - 1)

    def on_grid(self, lo: float, hi: float, step: float) -> float:
        """Uniform value of ``lo + i * step`` within ``[lo, hi]``, rounded to 10 decimals."""
        n = int(math.floor((hi - lo) / step + 1e-9))
        return round(lo + step * self.integer(0, n), 10)

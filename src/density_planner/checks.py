"""Input validation helpers shared by all modules.

Each check raises a :class:`ValueError` whose message names the argument, so bad input never turns into
silent garbage further down the pipeline.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch

__all__ = [
    "check_tensor",
    "check_positive",
    "check_choice",
    "check_finite_number",
    "check_seed",
    "MAX_SEED",
    "default_dtype_device",
    "broadcast_shape",
]


def check_tensor(
    name: str,
    value: Any,
    *,
    last_dims: Sequence[int | None] | None = None,
    min_ndim: int | None = None,
    ndim: int | None = None,
    finite: bool = True,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
    floating: bool = True,
) -> torch.Tensor:
    """Validate (and convert) ``value`` to a tensor.

    Args:
        name: argument name used in error messages.
        last_dims: required sizes of the trailing dimensions (``None`` entries are free).
        min_ndim / ndim: required number of dimensions.
        finite: reject NaN and infinite entries.
        dtype / device: convert to these (default: keep, or torch's default dtype for non-tensors).
        floating: require a floating point dtype.
    """
    if not isinstance(value, torch.Tensor):
        try:
            value = torch.as_tensor(value, dtype=dtype or torch.get_default_dtype(), device=device)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ValueError(f"{name} must be a tensor or array of numbers ({exc})") from exc
    elif dtype is not None or device is not None:
        value = value.to(dtype=dtype or value.dtype, device=device or value.device)
    if floating and not value.is_floating_point():
        value = value.to(torch.get_default_dtype())
    if ndim is not None and value.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {tuple(value.shape)}")
    if last_dims is not None:
        need = len(last_dims)
        if value.ndim < need or any(
            d is not None and value.shape[value.ndim - need + i] != d for i, d in enumerate(last_dims)
        ):
            want = ", ".join("*" if d is None else str(d) for d in last_dims)
            raise ValueError(f"{name} must have trailing shape ({want}), got shape {tuple(value.shape)}")
    if min_ndim is not None and value.ndim < min_ndim:
        raise ValueError(f"{name} must have at least {min_ndim} dimensions, got shape {tuple(value.shape)}")
    if finite and value.is_floating_point() and not bool(torch.isfinite(value).all()):
        bad = int((~torch.isfinite(value)).sum())
        raise ValueError(f"{name} contains {bad} NaN or infinite value(s)")
    return value


def check_positive(name: str, value: float, *, allow_zero: bool = False) -> float:
    """Require a finite positive (or non-negative) number."""
    check_finite_number(name, value)
    if value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {value}")
    return value


def check_finite_number(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return value


#: the largest seed accepted anywhere (one rule for every seed: an integer in [0, 2^63 - 1], the non-negative
#: int64 range that torch, NumPy and JSON all hold exactly)
MAX_SEED = 2**63 - 1


def check_seed(name: str, value: Any) -> int:
    """Require a seed: an integer in ``[0, MAX_SEED]`` (the rule for every seed option and config key)."""
    import numpy as np

    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer in [0, 2^63 - 1], got {value!r}")
    if not 0 <= int(value) <= MAX_SEED:
        raise ValueError(f"{name} must be an integer in [0, 2^63 - 1], got {value}")
    return int(value)


def check_choice(name: str, value: str, choices: Sequence[str]) -> str:
    """Require ``value`` to be one of ``choices`` (error lists the valid ones)."""
    if value not in choices:
        raise ValueError(f"unknown {name} {value!r}; valid choices: {', '.join(map(str, choices))}")
    return value


def default_dtype_device(*tensors: Any) -> tuple[torch.dtype, torch.device]:
    """dtype and device of the first tensor among ``tensors`` (torch defaults when there is none)."""
    for t in tensors:
        if isinstance(t, torch.Tensor):
            return (t.dtype if t.is_floating_point() else torch.get_default_dtype()), t.device
    return torch.get_default_dtype(), torch.device("cpu")


def broadcast_shape(*shapes: Sequence[int]) -> tuple[int, ...]:
    """Broadcast shape of ``shapes`` (numpy rules); ``ValueError`` if they do not broadcast.

    Pure Python: ``torch.broadcast_shapes`` imports sympy on first use (half a second).
    """
    ndim = max((len(s) for s in shapes), default=0)
    out = [1] * ndim
    for s in shapes:
        for i, d in enumerate(s, start=ndim - len(s)):
            if d == 1 or d == out[i]:
                continue
            if out[i] != 1:
                raise ValueError(f"shapes {[tuple(x) for x in shapes]} do not broadcast")
            out[i] = d
    return tuple(out)

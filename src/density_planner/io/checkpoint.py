"""Weights files (``state_dict`` + JSON metadata) and resumable training checkpoints.

A trained model is stored as two files side by side::

    NAME.pt     the ``state_dict`` only (``torch.save``; loaded with ``weights_only=True``, never a pickled class)
    NAME.json   kind, schema version, architecture, training configuration, package and torch versions,
                diagnostics and the command that reproduces the file

Loading checks the kind, the architecture and the ``state_dict`` keys and shapes, and raises a
:class:`~density_planner.errors.CheckpointError` naming the file and the offending field for every problem
(missing file, missing JSON, corrupt file, wrong kind, architecture mismatch, key/shape mismatch).

Training checkpoints (:func:`save_training_state` / :func:`load_training_state`) are single ``.pt`` files with
plain containers of tensors and numbers (model and optimiser state, RNG state, epoch, history), also loaded
with ``weights_only=True``. All writes are atomic.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ..errors import CheckpointError
from .atomic import atomic_save_torch, atomic_write_json

__all__ = [
    "SCHEMA_VERSION",
    "weights_paths",
    "save_weights",
    "load_weights",
    "check_state_dict",
    "hash_state",
    "save_training_state",
    "load_training_state",
]

logger = logging.getLogger(__name__)

#: version of the JSON metadata layout written by :func:`save_weights`
SCHEMA_VERSION = 1


def _package_version() -> str:
    from .. import __version__

    return __version__


def weights_paths(path: str | Path) -> tuple[Path, Path]:
    """``(NAME.pt, NAME.json)`` for ``path`` given as ``NAME``, ``NAME.pt`` or ``NAME.json``."""
    path = Path(path)
    base = path.with_suffix("") if path.suffix in (".pt", ".json") else path
    return base.with_name(base.name + ".pt"), base.with_name(base.name + ".json")


def save_weights(
    path: str | Path,
    state_dict: Mapping[str, torch.Tensor],
    *,
    kind: str,
    architecture: Mapping[str, Any],
    config: Mapping[str, Any] | None = None,
    diagnostics: Mapping[str, Any] | None = None,
    command: str | None = None,
    extra: Mapping[str, Any] | None = None,
) -> tuple[Path, Path]:
    """Write ``NAME.pt`` (the ``state_dict``, tensors moved to the CPU) and ``NAME.json`` (metadata), atomically.

    Args:
        path: ``NAME``, ``NAME.pt`` or ``NAME.json``.
        state_dict: the model's parameters and buffers.
        kind: what the weights are (e.g. ``"c3m_controller"``); checked on loading.
        architecture: the constructor arguments that determine the ``state_dict`` layout; checked on loading.
        config: the training configuration.
        diagnostics: final validation numbers.
        command: the command line that reproduces the file.
        extra: further JSON-serialisable entries.

    Returns:
        The two paths written.
    """
    if not kind:
        raise ValueError("save_weights: kind must be a non-empty string")
    pt_path, json_path = weights_paths(path)
    cpu_state = {str(k): v.detach().cpu().clone() for k, v in state_dict.items()}
    meta: dict[str, Any] = {
        "kind": kind,
        "schema_version": SCHEMA_VERSION,
        "weights_file": pt_path.name,
        "architecture": dict(architecture),
        "training_config": dict(config or {}),
        "package_version": _package_version(),
        "torch_version": torch.__version__,
        "command": command,
        "diagnostics": dict(diagnostics or {}),
        "n_parameters": int(sum(v.numel() for v in cpu_state.values() if v.is_floating_point())),
    }
    if extra:
        meta.update(dict(extra))
    atomic_save_torch(pt_path, cpu_state)
    atomic_write_json(json_path, meta)
    logger.info("wrote %s and %s", pt_path, json_path)
    return pt_path, json_path


def _normalise(value: Any) -> Any:
    """JSON round-trip form of ``value`` (tuples become lists) for comparisons."""
    return json.loads(json.dumps(value, default=str))


def _architecture_diff(expected: Mapping[str, Any], found: Mapping[str, Any]) -> list[str]:
    exp, got = _normalise(dict(expected)), _normalise(dict(found))
    diffs = []
    for key in sorted(set(exp) | set(got)):
        if key not in got:
            diffs.append(f"{key!r} missing in file (expected {exp[key]!r})")
        elif key not in exp:
            diffs.append(f"unexpected field {key!r} = {got[key]!r}")
        elif exp[key] != got[key]:
            diffs.append(f"{key!r}: file has {got[key]!r}, expected {exp[key]!r}")
    return diffs


def load_weights(
    path: str | Path,
    *,
    kind: str,
    expected_architecture: Mapping[str, Any] | None = None,
    module: nn.Module | None = None,
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read a weights file written by :func:`save_weights`.

    Args:
        path: ``NAME``, ``NAME.pt`` or ``NAME.json``.
        kind: required ``kind`` entry of the metadata.
        expected_architecture: if given, must equal the stored architecture field by field.
        module: if given, the ``state_dict`` keys and shapes are checked against it and loaded into it.

    Returns:
        ``(state_dict, meta)``.

    Raises:
        CheckpointError: missing ``.pt`` or ``.json`` file, corrupt file, wrong kind, architecture mismatch,
            ``state_dict`` key or shape mismatch.
    """
    pt_path, json_path = weights_paths(path)
    if not pt_path.is_file():
        raise CheckpointError(f"weights file not found: {pt_path}")
    if not json_path.is_file():
        raise CheckpointError(f"metadata file not found: {json_path} (it must lie next to {pt_path.name})")
    try:
        meta = json.loads(json_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CheckpointError(f"metadata file {json_path} is not valid JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise CheckpointError(f"metadata file {json_path} must hold a JSON object")
    for key in ("kind", "schema_version", "architecture"):
        if key not in meta:
            raise CheckpointError(f"metadata file {json_path} has no {key!r} entry")
    if meta["kind"] != kind:
        raise CheckpointError(f"{json_path}: weights are of kind {meta['kind']!r}, expected {kind!r}")
    if not isinstance(meta["schema_version"], int) or meta["schema_version"] > SCHEMA_VERSION:
        raise CheckpointError(
            f"{json_path}: schema_version {meta['schema_version']!r} is not supported (this package reads "
            f"versions <= {SCHEMA_VERSION}; update density-planner)"
        )
    if expected_architecture is not None:
        diffs = _architecture_diff(expected_architecture, meta["architecture"])
        if diffs:
            raise CheckpointError(f"{json_path}: architecture mismatch: " + "; ".join(diffs))
    try:
        state = torch.load(pt_path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for corrupt files (RuntimeError, EOFError, pickle...)
        raise CheckpointError(f"weights file {pt_path} is corrupt or not a torch state_dict ({exc})") from exc
    if not isinstance(state, Mapping) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()
    ):
        raise CheckpointError(f"weights file {pt_path} does not hold a state_dict (a mapping name -> tensor)")
    state = dict(state)
    for key, value in state.items():  # NaN weights would only show later as a plan without a finite cost
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            bad = int((~torch.isfinite(value)).sum())
            raise CheckpointError(
                f"weights file {pt_path}: parameter {key!r} holds {bad} NaN or infinite value(s); the weights are "
                "corrupt (restore or retrain them)"
            )
    if module is not None:
        check_state_dict(module, state, pt_path)
        module.load_state_dict(state)
    return state, meta


def check_state_dict(module: nn.Module, state: Mapping[str, torch.Tensor], source: str | Path = "state_dict") -> None:
    """Raise :class:`CheckpointError` if ``state`` does not match ``module.state_dict()`` in keys and shapes."""
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing keys {missing[:5]}{' ...' if len(missing) > 5 else ''}")
        if unexpected:
            parts.append(f"unexpected keys {unexpected[:5]}{' ...' if len(unexpected) > 5 else ''}")
        raise CheckpointError(f"{source}: state_dict does not match the model: " + "; ".join(parts))
    for key, value in own.items():
        if tuple(state[key].shape) != tuple(value.shape):
            raise CheckpointError(
                f"{source}: parameter {key!r} has shape {tuple(state[key].shape)}, the model expects "
                f"{tuple(value.shape)}"
            )


def save_training_state(path: str | Path, state: Mapping[str, Any]) -> Path:
    """Write a resumable training checkpoint (plain containers of tensors and numbers) atomically."""
    return atomic_save_torch(path, dict(state))


def load_training_state(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_training_state` (``weights_only=True``)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"training checkpoint not found: {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # see load_weights
        raise CheckpointError(f"training checkpoint {path} is corrupt ({exc})") from exc
    if not isinstance(state, dict):
        raise CheckpointError(f"training checkpoint {path} does not hold a dictionary")
    return state


def hash_state(h: Any, module: nn.Module, *, dtype: torch.dtype | None = None) -> None:
    """Feed the state of ``module`` (its ``state_dict``: parameters and buffers, by sorted name) to the hashlib
    object ``h``; tensors are hashed as their raw bytes, converted to ``dtype`` first when given. The one digest of
    weights: controller fingerprints (:func:`density_planner.density.network.controller_fingerprint`) and the
    benchmarks' component digests use it."""
    for name, value in sorted(module.state_dict().items()):
        h.update(name.encode())
        v = value.detach() if dtype is None else value.detach().to(dtype)
        h.update(v.cpu().contiguous().numpy().tobytes())

"""File input/output helpers: atomic writes and checkpoints (state_dict + JSON config)."""

from .atomic import atomic_save_npz, atomic_save_torch, atomic_write_bytes, atomic_write_json, atomic_write_text
from .checkpoint import (
    SCHEMA_VERSION,
    check_state_dict,
    load_training_state,
    load_weights,
    save_training_state,
    save_weights,
    weights_paths,
)

__all__ = [
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_write_json",
    "atomic_save_torch",
    "atomic_save_npz",
    "SCHEMA_VERSION",
    "weights_paths",
    "save_weights",
    "load_weights",
    "check_state_dict",
    "save_training_state",
    "load_training_state",
]

"""File input/output helpers: atomic writes and checkpoints (state_dict + JSON config)."""

from .atomic import atomic_save_npz, atomic_save_torch, atomic_write_bytes, atomic_write_json, atomic_write_text

__all__ = ["atomic_write_bytes", "atomic_write_text", "atomic_write_json", "atomic_save_torch", "atomic_save_npz"]

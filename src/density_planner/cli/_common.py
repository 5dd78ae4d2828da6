"""Options and helpers shared by the CLI commands (parsing happens only here, never in the library)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

__all__ = [
    "add_out",
    "add_seed",
    "add_device",
    "add_controller",
    "add_system",
    "apply_system_args",
    "add_threads",
    "apply_threads",
    "add_config",
    "resolve_device",
    "resolve_dtype",
    "load_params_file",
    "out_dir",
    "add_progress",
    "show_progress",
    "check_out",
]


def add_out(p: argparse.ArgumentParser, required: bool = True) -> None:
    p.add_argument("--out", type=Path, required=required, metavar="DIR", help="output directory (created)")


def add_seed(p: argparse.ArgumentParser, default: int = 0) -> None:
    p.add_argument("--seed", type=int, default=default, help=f"random seed (default {default}; 0 <= S < 2^63)")


def add_progress(p: argparse.ArgumentParser) -> None:
    """``--progress/--no-progress`` (default: on when stderr is a terminal) and ``-q/--quiet`` (= --no-progress).
    Progress bars written to a file or pipe would fill logs with carriage-return frames."""
    p.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="show progress bars (default: only when stderr is a terminal)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars (same as --no-progress)")


def show_progress(args: argparse.Namespace) -> bool:
    """Whether to draw progress bars: ``--progress``/``--no-progress`` if given, else stderr is a terminal."""
    import sys

    if getattr(args, "quiet", False):
        return False
    choice = getattr(args, "progress", None)
    if choice is not None:
        return bool(choice)
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


def add_device(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cpu", help="torch device: cpu (default), cuda, cuda:N or auto")
    p.add_argument("--dtype", default="float32", choices=("float32", "float64"), help="floating point precision")
    add_threads(p)


def add_threads(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="torch CPU threads (default 1: the work is many small tensor operations, for which more "
                   "OpenMP threads cost more than they gain and oversubscribe shared machines; 0 = torch's default)")


def apply_threads(threads: int | None) -> None:
    """Set torch's intra-op threads from ``--threads`` (None -> 1, 0 -> leave torch's default)."""
    if threads is None:
        threads = 1
    if threads < 0:
        raise ValueError(f"--threads must be >= 0, got {threads}")
    if threads:
        torch.set_num_threads(threads)


def add_controller(p: argparse.ArgumentParser) -> None:
    from ..control.registry import CONTROLLER_CHOICES

    p.add_argument(
        "--controller",
        default=None,
        metavar="NAME|FILE",
        help=f"tracking controller ([system] controller): the car's {', '.join(CONTROLLER_CHOICES)}, another "
        "system's registered name, or a C3M weights file (default: the model set's default, c3m for the car)",
    )


def add_system(p: argparse.ArgumentParser, *, density: bool = True) -> None:
    """``--system``, ``--models``, ``--controller`` (and ``--density``): shorthands for the keys of the ``[system]``
    section (:class:`~density_planner.systems.registry.SystemConfig`), so the written ``config.toml`` holds them."""
    from ..systems.registry import system_names

    p.add_argument("--system", default=None, metavar="NAME",
                   help=f"dynamics ([system] name): {', '.join(system_names())} (default car)")
    p.add_argument("--models", default=None, metavar="SET",
                   help="model set ([system] models: the system's domain with its controller and density weights), "
                        "e.g. paper or road for the car (default: by scene kind, road for recorded road scenes, "
                        "paper for the paper's random scenes)")
    add_controller(p)
    if density:
        p.add_argument("--density", default=None, metavar="NAME",
                       help="density predictor ([system] density): exact (Liouville), learned, trajectory, "
                            "pointwise or a weights file (default: the learned one trained for the controller, else "
                            "exact)")


def apply_system_args(args: argparse.Namespace, run_config):
    """``run_config`` with the ``[system]`` keys given on the command line (``--system`` etc.) replaced
    (:func:`density_planner.api.with_system`)."""
    from ..api import with_system

    return with_system(run_config, system=getattr(args, "system", None), models=getattr(args, "models", None),
                       controller=getattr(args, "controller", None), density=getattr(args, "density", None))


def add_config(p: argparse.ArgumentParser, example: str = "density_planner.n_candidates=50") -> None:
    """``--config FILE.toml`` and ``--set KEY=VALUE``; ``example`` is a valid key of the command's configuration
    (tests/test_set_examples.py parses every example)."""
    p.add_argument("--config", type=Path, default=None, metavar="FILE.toml",
                   help="configuration file (TOML), or the name of a shipped preset: 'paper' (the paper's setting: "
                        "point vehicle, binned risk estimator, density weights, 500 samples, 100 stage-2 iterations)")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=f"override one configuration value, e.g. --set {example} (repeatable)",
    )


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise ValueError(f"invalid --device {name!r}; use cpu, cuda, cuda:N or auto") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda requested but no CUDA device is available (use --device cpu)")
    return device


def resolve_dtype(name: str) -> torch.dtype:
    return {"float32": torch.float32, "float64": torch.float64}[name]


def context_from_args(args: argparse.Namespace, run_config, *, progress: bool = False, parameterization=None,
                      system=None):
    """:func:`~density_planner.planners.context.build_context` for the scene kind, ``--device`` and ``--dtype`` of
    the command line (``--system``, ``--models``, ``--controller`` and ``--density`` are in ``run_config``'s
    ``[system]`` section: :func:`apply_system_args`)."""
    from ..planners.context import build_context

    return build_context(run_config, kind=getattr(args, "kind", None), parameterization=parameterization,
                         system=system, device=resolve_device(args.device), dtype=resolve_dtype(args.dtype),
                         progress=progress)


def check_out(path: Path) -> Path:
    """Validate ``--out`` without creating it (commands create it only once every input is valid)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ValueError(f"--out {path} exists and is not a directory")
    parent = next((p for p in path.absolute().parents if p.exists()), None)
    if parent is not None and not parent.is_dir():
        raise ValueError(f"--out {path}: {parent} is not a directory")
    return path


def out_dir(path: Path) -> Path:
    path = check_out(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"--out {path}: cannot create the directory ({exc.strerror or exc})") from exc
    return path


def load_params_file(path: Path, option: str = "--params") -> np.ndarray:
    """Reference parameters from ``.json`` (a list, or an object with ``"params"``), ``.npy`` or ``.npz``; errors
    name ``option`` and the file."""
    from ..io.npz import read_npy, read_npz

    path = Path(path)
    where = f"{option} {path}"
    if not path.is_file():
        raise FileNotFoundError(f"{where}: parameter file not found")
    try:
        if path.suffix == ".json":
            data = json.loads(path.read_text())
            if isinstance(data, dict):
                if "params" not in data:
                    raise ValueError("the JSON object has no 'params' entry")
                data = data["params"]
            arr = np.asarray(data, dtype=np.float64)
        elif path.suffix == ".npy":
            arr = read_npy(path, what="parameter", max_bytes=2**20)
        elif path.suffix == ".npz":
            z = read_npz(path, what="parameter", max_bytes=2**20)
            if "params" not in z:
                raise ValueError("no 'params' array")
            arr = z["params"]
        else:
            raise ValueError("unsupported parameter file type (use .json, .npy or .npz)")
        arr = np.asarray(arr, dtype=np.float64)
    except (ValueError, TypeError, UnicodeDecodeError) as exc:  # incl. JSONDecodeError, ragged lists, DataError
        text = str(exc).split("\n")[0]
        if "inhomogeneous" in text or "sequence" in text:
            text = "the rows have different lengths (a 2 x 10 table of numbers is expected)"
        text = text.replace(f"{path}: ", "")
        raise ValueError(f"{where}: cannot read reference parameters ({text})") from None
    if arr.ndim == 3 and arr.shape[0] == 1:
        arr = arr[0]
    return arr

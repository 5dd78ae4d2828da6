"""Training data for the learned density predictors: exact Liouville propagation along random references.

The data belong to one *model set* (``DensityDataConfig.domain``: a registered system in one of its domains with
its tracking controllers, :mod:`density_planner.control.registry`): the car's ``paper`` and ``road`` sets, the
kinematic single-track model's ``ks``. Everything system-specific comes from the set's
:class:`~density_planner.systems.base.System`: the state dimension ``nx``, the reference-start box, the XE0 box
(``initial_error_max``), the heading.

Every *shard* holds ``B`` random feasible references (parameters ``clamp(param_scale N(0, 1))`` to the input box,
starts uniform in the reference-start box, references leaving the state box rejected;
:func:`~density_planner.control.sampling.sample_feasible_references`) and ``N`` initial errors per reference,
uniform in the XE0 box including hidden states such as the car's heading bias
(:func:`~density_planner.control.sampling.sample_initial_errors`). All ``B x N`` closed loops of a shard are
propagated together by :func:`~density_planner.density.liouville.propagate_density` (``x0`` of shape
``(B, N, nx)``), so a shard costs one batched integration, not ``B`` separate ones.

A shard file ``shard_NNNNN.pt`` (``torch.save`` of plain tensors, read with ``weights_only=True``) stores, in
float32::

    xe0        (B, N, nx)      initial error x0 - x_ref(0) (the car: m, m, rad, m/s, rad; last entry heading bias)
    ref_start  (B, nx)         reference start x_ref(0)
    params     (B, nu, S)      reference parameters (piecewise-constant inputs)
    t          (T,)            output times [s] (the 0.1-s planning grid, T = 101)
    xe         (B, N, T, nx)   error trajectory x(t) - x_ref(t)
    log_ratio  (B, N, T)       log rho(x(t), t) - log rho0(x0) = -int_0^t div f_cl   (paper Eq. (2))
    x_ref      (B, T, nx)      reference on the planning grid (for figures and checks)

Shards are written atomically, one task per shard, through :func:`~density_planner.parallel.run_tasks` (joblib
processes locally, a Dask scheduler for a cluster). Shard ``i`` draws from a generator seeded by ``(seed, i)``,
so the data set does not depend on the number of workers or on the order in which shards finish, and a run that
was interrupted resumes by skipping the shards that are already complete. The last shards (by
``validation_fraction``) hold the validation references: the split is by reference.

``manifest.json`` records the configuration, the split, the sizes and the timing.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from ..checks import check_seed
from ..errors import DataError
from ..io.atomic import atomic_save_torch, atomic_write_json
from .liouville import LiouvilleConfig

__all__ = [
    "DensityDataConfig",
    "DensityData",
    "shard_seed",
    "generate_shard",
    "generate_density_data",
    "load_density_data",
    "read_manifest",
    "SHARD_KEYS",
]

logger = logging.getLogger(__name__)

#: format version of the shards and the manifest
DATA_FORMAT = 1
#: tensors of a shard
SHARD_KEYS = ("xe0", "ref_start", "params", "t", "xe", "log_ratio", "x_ref")
MANIFEST = "manifest.json"


@dataclass(frozen=True)
class DensityDataConfig:
    """What :func:`generate_density_data` produces (defaults: the paper's sampling, ``docs/spec.md`` §5)."""

    #: total number of random references (training + validation)
    references: int = 32768
    #: initial errors (closed-loop trajectories) per reference. Many references with few samples each: the
    #: predictors must generalise over the 23 reference features (parameters, start heading and speed), which only
    #: new references teach, while the samples of all references together cover the five-dimensional error box
    samples: int = 8
    #: references per shard (one task, one batched Liouville integration of ``references_per_shard x samples``)
    references_per_shard: int = 256
    #: fraction of the shards (hence of the references) held out for validation (at least one shard)
    validation_fraction: float = 0.05
    #: seed; shard ``i`` uses a generator seeded from ``(seed, i)``
    seed: int = 0
    #: tracking controller: a name registered for the model set's system (the car: ``"c3m"``, the shipped weights
    #: of the set, or ``"analytic"``; KS: ``"analytic"``), ``"auto"`` (the set's default) or a C3M weights file.
    #: The default ``"c3m"`` means the set's default controller for a set of another system (written out)
    controller: str = "c3m"
    #: model set (``density-planner data density --system/--models``): the car's ``"paper"`` or ``"road"``, the
    #: kinematic single-track model's ``"ks"``; its system gives the state layout and boxes, its controllers the
    #: closed loop
    domain: str = "paper"
    #: reference parameters are ``clamp(param_scale N(0, 1))`` to the input bounds (one number or one per input).
    #: The default 2 is the paper's; for a system whose configuration names its own reference input scale (KS:
    #: ``reference_input_scale``, steering rates of 0.1 rad/s) it means that one (written out)
    param_scale: float | tuple[float, ...] = 2.0
    #: lower corner of the reference-start box (``nx`` entries; the car: ``(p_x, p_y, theta, v, bias)``);
    #: ``None``: the system's reference-start box (the car's of ``docs/spec.md`` §5: [-12, 12] x [-30, 10] m, theta
    #: in [0, 2 pi], v in [1, 8] m/s, bias 0). The default widens the paper set's heading and speed to the starts
    #: the planner meets (random scenes start with theta in [-2.1, -0.5] rad and v up to 9 m/s; the controller is
    #: not 2 pi-periodic in theta); for any other model set it means the system's reference-start box (written
    #: out, so the data's configuration records the box)
    start_low: tuple[float, ...] | None = (-12.0, -30.0, 0.0, 1.0, 0.0)
    #: upper corner of the reference-start box; ``None``: the system's box (default: as for ``start_low``)
    start_high: tuple[float, ...] | None = (12.0, 10.0, 2 * math.pi, 9.0, 0.0)
    #: initial errors are uniform in ``error_scale * XE0`` (the system's ``initial_error_max``; the car's
    #: +-(1 m, 1 m, 0.5 rad, 0.5 m/s, pi/16 rad)). The default 1.2 covers the offset of the planner's reference start
    #: (the mean of the initial law) from the centre of the XE0 box its samples are drawn in (below 20 % of the
    #: half-widths for 95 % of the paper's mixtures)
    error_scale: float = 1.2
    #: numerics of the exact propagation (default RK4 at 0.1 s, validated against fine solutions)
    liouville: LiouvilleConfig = field(default_factory=LiouvilleConfig)
    #: floating point precision of the propagation (shards are always stored in float32)
    dtype: Literal["float32", "float64"] = "float32"
    #: torch device of the propagation ("cpu", "cuda"); sampling stays on the CPU (same draws everywhere). Not part
    #: of the resume key: a run may continue on another device
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_seed("seed", self.seed)
        for name in ("references", "samples", "references_per_shard"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if not 0.0 <= self.validation_fraction < 1.0:
            raise ValueError(f"validation_fraction must be in [0, 1), got {self.validation_fraction!r}")
        if self.n_shards < 2 and self.validation_fraction > 0:
            raise ValueError(
                f"{self.references} references in shards of {self.references_per_shard} give one shard; a "
                "validation split needs at least two (lower references_per_shard or set validation_fraction = 0)"
            )
        scales = self.param_scale if isinstance(self.param_scale, tuple) else (self.param_scale,)
        if not scales or not all(v > 0 for v in scales):
            raise ValueError(f"param_scale must be > 0 (one number or one per input), got {self.param_scale!r}")
        if not self.error_scale > 0:
            raise ValueError(f"error_scale must be > 0, got {self.error_scale!r}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"dtype must be 'float32' or 'float64', got {self.dtype!r}")
        mset = self.model_set()
        system = mset.make_system()
        defaults = {f.name: f.default for f in fields(self)}
        if mset.name != "paper":  # the class defaults are the paper set's; other sets: their system's box
            cfg = getattr(system, "config", None)
            for name, attr in (("start_low", "reference_start_min"), ("start_high", "reference_start_max")):
                box = getattr(cfg, attr, None)
                if getattr(self, name) == defaults[name]:
                    object.__setattr__(self, name, None if box is None else tuple(float(v) for v in box))
        if mset.system != "car" and self.controller == defaults["controller"]:
            object.__setattr__(self, "controller", mset.default_controller)
        own_scale = getattr(getattr(system, "config", None), "reference_input_scale", None)
        if own_scale is not None and self.param_scale == defaults["param_scale"]:
            object.__setattr__(self, "param_scale", tuple(float(v) for v in own_scale))
        if isinstance(self.param_scale, tuple) and len(self.param_scale) not in (1, system.nu):
            raise ValueError(f"param_scale must be one number or {system.nu} (one per input), got {self.param_scale!r}")
        names = ", ".join(system.state_names)
        for name in ("start_low", "start_high"):
            v = getattr(self, name)
            if v is not None and len(v) != system.nx:
                raise ValueError(f"{name} must have {system.nx} entries ({names}) for the model set "
                                 f"{self.domain!r}, got {v!r}")

    def model_set(self):
        """The :class:`~density_planner.control.registry.ModelSet` named by :attr:`domain`."""
        from ..control.registry import model_set

        return model_set(self.domain)

    def make_system(self):
        """The model set's system (state layout, boxes, XE0)."""
        return self.model_set().make_system()

    @property
    def n_shards(self) -> int:
        return -(-self.references // self.references_per_shard)

    @property
    def n_validation_shards(self) -> int:
        if self.validation_fraction == 0:
            return 0
        return min(self.n_shards - 1, max(1, int(round(self.validation_fraction * self.n_shards))))

    def shard_split(self, index: int) -> str:
        """``"train"`` or ``"val"`` for shard ``index`` (the last shards are the validation references)."""
        return "val" if index >= self.n_shards - self.n_validation_shards else "train"

    def shard_references(self, index: int) -> int:
        return min(self.references_per_shard, self.references - index * self.references_per_shard)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def shard_seed(seed: int, index: int) -> int:
    """Seed of shard ``index``: independent streams for every ``(seed, index)`` (numpy ``SeedSequence``)."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1, dtype=np.uint64)[0] >> 1)


_CONTROLLERS: dict[str, Any] = {}


def _controller(spec: str, dtype: torch.dtype, domain: str = "paper"):
    """Controller ``spec`` of the model set ``domain`` (cached per process: workers load it once)."""
    key = f"{spec}|{dtype}|{domain}"
    if key not in _CONTROLLERS:
        from ..control.registry import load_controller

        _CONTROLLERS[key] = load_controller(spec, models=domain).to(dtype)
    return _CONTROLLERS[key]


def generate_shard(config: DensityDataConfig, index: int, controller=None) -> dict[str, Tensor]:
    """Propagate shard ``index`` of ``config``; returns the tensors listed in the module docstring (float32).

    ``controller`` overrides ``config.controller`` (for tests); by default it is loaded from its name.
    """
    from ..control.sampling import sample_feasible_references, sample_initial_errors
    from .liouville import propagate_density

    if not 0 <= index < config.n_shards:
        raise ValueError(f"shard index {index} out of range [0, {config.n_shards})")
    dtype = torch.float64 if config.dtype == "float64" else torch.float32
    system = config.make_system()
    controller = (controller.to(dtype) if controller is not None
                  else _controller(config.controller, dtype, config.domain))
    gen = torch.Generator().manual_seed(shard_seed(config.seed, index))
    b, n = config.shard_references(index), config.samples
    ref = sample_feasible_references(system, b, gen, param_scale=config.param_scale, start_low=config.start_low,
                                     start_high=config.start_high, dtype=dtype)
    box = [config.error_scale * v for v in system.initial_error_max]
    xe0 = sample_initial_errors(b * n, gen, box=box, dtype=dtype).reshape(b, n, system.nx)
    x0 = ref.start.unsqueeze(-2) + xe0
    device = torch.device(config.device)
    if device.type != "cpu":
        from ..control.reference import Reference

        ref = Reference(ref.params.to(device), ref.x.to(device), ref.u.to(device), ref.parameterization)
        x0, xe0, controller = x0.to(device), xe0.to(device), controller.to(device)
    with torch.no_grad():
        traj = propagate_density(system, controller, x0, ref, config=config.liouville)
    x_ref = ref.x_plan
    if traj.x.shape[-2] != x_ref.shape[-2]:
        raise ValueError(
            f"the Liouville output grid ({traj.x.shape[-2]} points) differs from the planning grid "
            f"({x_ref.shape[-2]} points); LiouvilleConfig.output_dt must equal the planning step"
        )
    f32 = torch.float32
    out = {
        "xe0": xe0.to(f32),
        "ref_start": ref.start.to(f32),
        "params": ref.params.to(f32),
        "t": traj.t.to(f32),
        "xe": (traj.x - x_ref.unsqueeze(-3)).to(f32),
        "log_ratio": (traj.log_rho - traj.log_rho0.unsqueeze(-1)).to(f32),
        "x_ref": x_ref.to(f32),
    }
    # own storage for every tensor (views such as the reference start would save the whole fine-grid reference)
    out = {k: v.cpu().contiguous().clone() for k, v in out.items()}
    if not all(bool(torch.isfinite(v).all()) for v in out.values()):
        raise FloatingPointError(f"shard {index}: non-finite values in the propagated trajectories")
    return out


def _shard_path(out: Path, index: int) -> Path:
    return out / f"shard_{index:05d}.pt"


def _read_shard(path: Path) -> dict[str, Any]:
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # corrupt files raise many types (RuntimeError, EOFError, pickle errors)
        raise DataError(f"shard {path} is corrupt or not a density data shard ({exc})") from exc
    if not isinstance(data, dict) or any(k not in data for k in SHARD_KEYS):
        raise DataError(f"shard {path} lacks some of the tensors {list(SHARD_KEYS)}")
    return data


def _shard_complete(path: Path, config: DensityDataConfig, index: int) -> bool:
    """Whether ``path`` holds shard ``index`` of ``config`` (shapes and meta data agree)."""
    if not path.is_file():
        return False
    try:
        data = _read_shard(path)
    except DataError:
        return False
    b, n = config.shard_references(index), config.samples
    return (
        data.get("index") == index
        and data.get("config_key") == _config_key(config)
        and tuple(data["xe0"].shape) == (b, n, config.make_system().nx)
        and data["xe"].shape[:2] == (b, n)
    )


def _config_key(config: DensityDataConfig) -> str:
    import hashlib
    import json

    d = config.to_dict()
    d.pop("device")
    # the scheme in force, whether configured or the system's own, and its tolerance; the error control's settings
    # only where they act (the keys of fixed-step data written before error control existed stay as they were,
    # hence resumable)
    system = config.make_system()
    d["liouville"]["integrator"] = config.liouville.scheme(system)
    pair = config.liouville.pair(system)
    if pair is None:
        d["liouville"].pop("tolerance", None)
        d["liouville"].pop("saturation_step", None)
        d["liouville"].pop("log_density_rule", None)
    else:
        d["liouville"]["tolerance"] = config.liouville.tolerance_of(pair)
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def _shard_task(task: tuple[dict[str, Any], int, str]) -> dict[str, Any]:
    """Worker: generate and write one shard (module level, so it pickles for joblib and Dask)."""
    from ..config import from_dict

    config_dict, index, out = task
    config = from_dict(DensityDataConfig, config_dict)
    t0 = time.perf_counter()
    data = generate_shard(config, index)
    wall = time.perf_counter() - t0
    meta = {"index": index, "config_key": _config_key(config), "wall_time_s": wall, "format": DATA_FORMAT}
    atomic_save_torch(_shard_path(Path(out), index), {**data, **meta})
    return {"index": index, "wall_time_s": wall, "references": int(data["xe0"].shape[0])}


def read_manifest(data_dir: str | Path) -> dict[str, Any]:
    """The manifest of a data directory (raises :class:`DataError` with a clear message if absent or invalid)."""
    import json

    path = Path(data_dir) / MANIFEST
    if not path.is_file():
        raise DataError(f"{path} not found: {data_dir} is not a density data directory "
                        "(generate one with `density-planner data density --out DIR`)")
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DataError(f"{path} is not valid JSON ({exc})") from exc
    if not isinstance(manifest, dict) or "config" not in manifest or "shards" not in manifest:
        raise DataError(f"{path} is not a density data manifest (no 'config'/'shards')")
    return manifest


def generate_density_data(
    config: DensityDataConfig,
    out: str | Path,
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = False,
    command: str | None = None,
    on_shard: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Generate (or complete) the data set of ``config`` in ``out``; returns the manifest.

    Shards that are already complete are skipped, so an interrupted run continues where it stopped. A directory
    that holds data of a different configuration is refused (use a new directory).

    Args:
        workers: local processes (default: the number of cores); ignored with ``scheduler``.
        scheduler: address of a Dask scheduler (``tcp://host:8786``).
        progress: progress bar over the shards.
        command: the command line, recorded in the manifest.
        on_shard: called with each finished shard's statistics.

    Raises:
        DataError: ``out`` holds another configuration's data, or some shards failed (after all others finished).
    """
    from ..parallel import run_tasks

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    key = _config_key(config)
    previous: dict[str, Any] = {}
    if (out / MANIFEST).is_file():
        previous = read_manifest(out)
        if previous.get("config_key") != key:
            raise DataError(
                f"{out} holds density data of another configuration (config_key {previous.get('config_key')} "
                f"vs {key}); use a new --out directory or the same settings to resume"
            )
    shards: list[dict[str, Any]] = [
        {"index": i, "file": _shard_path(out, i).name, "split": config.shard_split(i),
         "references": config.shard_references(i)}
        for i in range(config.n_shards)
    ]
    from .network import controller_fingerprint

    fingerprint = controller_fingerprint(_controller(config.controller, torch.float32, config.domain))
    if previous.get("controller_fingerprint") not in (None, fingerprint):
        raise DataError(
            f"{out} was generated with another controller {config.controller!r} (fingerprint "
            f"{previous['controller_fingerprint']}, now {fingerprint}); use a new --out directory"
        )
    manifest: dict[str, Any] = {
        "format": DATA_FORMAT,
        "config": config.to_dict(),
        "config_key": key,
        "controller_fingerprint": fingerprint,
        "complete": False,
        "shards": shards,
        "command": command or previous.get("command"),
        "wall_time_s": previous.get("wall_time_s", 0.0),
        "shard_time_s": previous.get("shard_time_s", {}),
    }
    atomic_write_json(out / MANIFEST, manifest)
    todo = [i for i in range(config.n_shards) if not _shard_complete(_shard_path(out, i), config, i)]
    logger.info("density data: %d of %d shards to generate in %s", len(todo), config.n_shards, out)
    config_dict = config.to_dict()
    t0 = time.perf_counter()
    errors = []
    times: dict[str, float] = dict(manifest["shard_time_s"])
    tasks = [(config_dict, i, str(out)) for i in todo]
    for outcome in run_tasks(_shard_task, tasks, workers=workers, scheduler=scheduler, progress=progress,
                             desc="shards"):
        if outcome.ok:
            times[str(outcome.value["index"])] = outcome.value["wall_time_s"]
            if on_shard is not None:
                on_shard(outcome.value)
        else:
            errors.append(f"shard {todo[outcome.index]}: {(outcome.error or 'failed').strip().splitlines()[-1]}")
            logger.error("shard %d failed:\n%s", todo[outcome.index], outcome.error)
    wall = time.perf_counter() - t0
    n_train = sum(s["references"] for s in shards if s["split"] == "train")
    n_val = sum(s["references"] for s in shards if s["split"] == "val")
    manifest.update({
        "complete": not errors,
        "wall_time_s": manifest["wall_time_s"] + wall,
        "shard_time_s": times,
        "shard_time_total_s": float(sum(times.values())),
        "workers": workers if scheduler is None else None,
        "scheduler": scheduler,
        "sizes": {
            "references_train": n_train,
            "references_val": n_val,
            "samples_per_reference": config.samples,
            "trajectories_train": n_train * config.samples,
            "trajectories_val": n_val * config.samples,
            "time_points": 101,
            "bytes": int(sum(_shard_path(out, i).stat().st_size for i in range(config.n_shards)
                             if _shard_path(out, i).is_file())),
        },
    })
    atomic_write_json(out / MANIFEST, manifest)
    if errors:
        raise DataError(f"{len(errors)} of {len(todo)} shards failed (run again to retry them): " + "; ".join(
            errors[:3]))
    return manifest


@dataclass
class DensityData:
    """Closed-loop trajectories of one split, flattened to one row per trajectory.

    Attributes:
        xe0: ``(M, nx)`` initial errors.
        ref_start: ``(M, nx)`` reference starts.
        params: ``(M, nu, S)`` reference parameters.
        t: ``(T,)`` times [s].
        xe: ``(M, T, nx)`` error trajectories.
        log_ratio: ``(M, T)`` log-density ratios ``log rho(t) - log rho0``.
        x_ref_heading: ``(M, T)`` heading of the reference on the time grid [rad] (zeros without heading).
        reference_id: ``(M,)`` global index of the reference of every row.
        system: the registered system of the states (its layout: :class:`~density_planner.density.network.
            DensityLayout`).
    """

    xe0: Tensor
    ref_start: Tensor
    params: Tensor
    t: Tensor
    xe: Tensor
    log_ratio: Tensor
    x_ref_heading: Tensor
    reference_id: Tensor
    system: str = "car"

    def __len__(self) -> int:
        return int(self.xe0.shape[0])

    @property
    def n_references(self) -> int:
        return int(torch.unique(self.reference_id).numel())

    def subset(self, index: Tensor | slice) -> DensityData:
        return DensityData(self.xe0[index], self.ref_start[index], self.params[index], self.t, self.xe[index],
                           self.log_ratio[index], self.x_ref_heading[index], self.reference_id[index], self.system)

    @classmethod
    def from_shards(cls, shards: Sequence[dict[str, Tensor]], first_reference: Sequence[int],
                    system: str = "car") -> DensityData:
        """Rows of ``shards`` (their first references' global indices ``first_reference``) of the registered
        ``system``."""
        from .network import system_layout

        heading = system_layout(system).heading
        parts: dict[str, list[Tensor]] = {k: [] for k in ("xe0", "ref_start", "params", "xe", "log_ratio", "head",
                                                       "rid")}
        t = None
        for data, r0 in zip(shards, first_reference):
            b, n = data["xe0"].shape[:2]
            if t is None:
                t = data["t"]
            elif data["t"].shape != t.shape or not torch.allclose(data["t"], t):
                raise DataError("shards have different time grids")
            parts["xe0"].append(data["xe0"].reshape(b * n, -1))
            parts["ref_start"].append(data["ref_start"].unsqueeze(1).expand(b, n, -1).reshape(b * n, -1))
            parts["params"].append(data["params"].unsqueeze(1).expand(b, n, *data["params"].shape[1:])
                                   .reshape(b * n, *data["params"].shape[1:]))
            parts["xe"].append(data["xe"].reshape(b * n, *data["xe"].shape[2:]))
            parts["log_ratio"].append(data["log_ratio"].reshape(b * n, -1))
            x_ref = data["x_ref"]
            head = x_ref.new_zeros(x_ref.shape[:-1]) if heading is None else x_ref[..., heading]
            parts["head"].append(head.unsqueeze(1).expand(b, n, -1).reshape(b * n, -1))
            parts["rid"].append((r0 + torch.arange(b)).repeat_interleave(n))
        if t is None:
            raise DataError("no shards to load")
        return cls(torch.cat(parts["xe0"]), torch.cat(parts["ref_start"]), torch.cat(parts["params"]), t,
                   torch.cat(parts["xe"]), torch.cat(parts["log_ratio"]), torch.cat(parts["head"]),
                   torch.cat(parts["rid"]), system)


def load_density_data(data_dir: str | Path, split: Literal["train", "val", "all"] = "train",
                      *, max_references: int | None = None) -> DensityData:
    """Load the shards of ``split`` from a directory written by :func:`generate_density_data`.

    Raises:
        DataError: no manifest, incomplete data set, missing or corrupt shard, no shard of that split.
    """
    if split not in ("train", "val", "all"):
        raise ValueError(f"split must be 'train', 'val' or 'all', got {split!r}")
    data_dir = Path(data_dir)
    manifest = read_manifest(data_dir)
    if not manifest.get("complete", False):
        raise DataError(f"{data_dir}: the data set is incomplete (run the generating command again to finish it)")
    per_shard = manifest["config"]["references_per_shard"]
    shards, firsts = [], []
    n_refs = 0
    for s in manifest["shards"]:
        if split != "all" and s["split"] != split:
            continue
        if max_references is not None and n_refs >= max_references:
            break
        data = _read_shard(data_dir / s["file"])
        shards.append(data)
        firsts.append(s["index"] * per_shard)
        n_refs += s["references"]
    if not shards:
        raise DataError(f"{data_dir}: no shards of split {split!r}")
    from ..control.registry import model_set

    try:
        system = model_set(manifest["config"].get("domain", "paper")).system
    except ValueError as exc:
        raise DataError(f"{data_dir}: {exc}") from exc
    return DensityData.from_shards(shards, firsts, system)

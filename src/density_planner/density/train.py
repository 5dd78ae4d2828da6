"""Training of the learned density predictors (:mod:`density_planner.density.network`).

Loss (on the normalised residual targets of the network, see the module docstring of ``network``)::

    loss = mean_{rows, times, error channels} l(net - z) + w_L * mean_{rows, times} l(net_L - z_L)

with ``l(d) = d^2`` (``loss = "mse"``, the default and the paper's) or ``l(d) = |d|`` (``loss = "l1"``). Both parts
are in units of the per-time residual standard deviation, so ``w_L = 1`` would weigh a typical log-density error
like a typical error of one state component; the default ``log_density_weight = 3`` puts more weight on the
log-density, the harder output (the paper used 5e-4 on raw, unnormalised outputs, where the log-density error is
~10^3 times larger). Where the position error's tail is the harder target, as on the road set, a weight below
one does better (docs/density.md, "The weight of the log-density"; the shipped road head's JSON file records its
weight).

The absolute loss is for heavy-tailed targets. On the road set's data, a few closed loops leave their reference by
metres at highway speed (true position errors: median 0.5 m, p95 8.7 m over all times). A squared loss spends the
network on those few, and the typical trajectory is fitted worse. The absolute loss fits the median instead.
docs/density.md has the measurements.

The trajectory head sees every training trajectory once per epoch (all ``T - 1`` times at once). The pointwise
net sees ``times_per_trajectory`` random time points of every trajectory per epoch (fresh draws each epoch; the
paper kept a fixed set of 10). Validation uses the held-out references of the data set (all times for the
trajectory head, a fixed seeded set of ``val_times`` points per trajectory for the pointwise net).

Adam with a cosine learning-rate decay, early stopping on the validation loss (``patience``), the best
validation state kept and restored at the end, an optional wall-time limit, seeded shuffling, a progress bar,
and a resumable checkpoint (``checkpoint.pt``, written atomically after every epoch).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor

from ..checks import check_seed
from ..errors import CheckpointError
from .data import DensityData
from .network import (
    DensityLayout,
    DensityNetArchitecture,
    DensityNetwork,
    errors_to_outputs,
    reference_features,
    sample_features,
)

__all__ = [
    "DensityTrainConfig",
    "DensityTrainResult",
    "fit_normalisation",
    "normalised_targets",
    "train_density",
    "architecture_from_config",
]

logger = logging.getLogger(__name__)

#: per-element losses of :attr:`DensityTrainConfig.loss`
_LOSSES: dict[str, Callable[[Tensor], Tensor]] = {"mse": torch.square, "l1": torch.abs}


@dataclass(frozen=True)
class DensityTrainConfig:
    """Settings of :func:`train_density`."""

    #: "trajectory" (whole horizon per evaluation) or "pointwise" (the paper's per-time MLP)
    arch: Literal["trajectory", "pointwise"] = "trajectory"
    #: hidden width / number of hidden layers / activation; ``None``: the architecture's default
    #: (trajectory 3 x 256 SiLU, pointwise 7 x 150 ReLU); a shipped head's JSON file records its own settings
    hidden: int | None = None
    layers: int | None = None
    activation: Literal["relu", "silu", "tanh"] | None = None
    #: maximum number of epochs (also the length of the cosine learning-rate decay)
    epochs: int = 60
    #: rows per batch: trajectories (trajectory head) or (trajectory, time) pairs (pointwise)
    batch_size: int = 256
    #: initial and final learning rate of the cosine decay
    lr: float = 2e-3
    lr_final: float = 2e-5
    #: Adam weight decay
    weight_decay: float = 0.0
    #: weight of the log-density part of the loss (see the module docstring); above one because the log-density
    #: is the harder output (its error, not the position error, is far from the paper's figure)
    log_density_weight: float = 3.0
    #: per-element loss on the normalised residuals: "mse" (squared, the paper's) or "l1" (absolute, for
    #: heavy-tailed targets such as the road set's; see the module docstring)
    loss: Literal["mse", "l1"] = "mse"
    #: pointwise only: random time points per trajectory and epoch
    times_per_trajectory: int = 10
    #: pointwise only: fixed time points per validation trajectory
    val_times: int = 20
    #: early stopping: stop after this many epochs without a lower validation loss
    patience: int = 15
    #: stop (keeping the best state) once training has run this long [s]; ``None``: no limit
    time_limit_s: float | None = None
    #: use at most this many training references (``None``: all)
    max_train_references: int | None = None
    #: ridge regularisation of the linear output baseline (relative to the number of rows)
    ridge: float = 1e-6
    #: seed of the initialisation, shuffling and time draws
    seed: int = 0
    #: torch device
    device: str = "cpu"

    def __post_init__(self) -> None:
        check_seed("seed", self.seed)
        for name in ("epochs", "batch_size", "times_per_trajectory", "val_times", "patience"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        for name in ("lr", "lr_final"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0, got {v!r}")
        for name in ("weight_decay", "log_density_weight", "ridge"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be >= 0, got {v!r}")
        if self.time_limit_s is not None and not self.time_limit_s > 0:
            raise ValueError(f"time_limit_s must be > 0, got {self.time_limit_s!r}")
        if self.loss not in _LOSSES:
            raise ValueError(f"loss must be one of {list(_LOSSES)}, got {self.loss!r}")
        if self.max_train_references is not None and self.max_train_references < 1:
            raise ValueError(f"max_train_references must be >= 1, got {self.max_train_references!r}")
        architecture_from_config(self)  # validates arch / hidden / layers / activation

    def resume_key(self) -> dict[str, Any]:
        """Settings that must agree to resume a run (``epochs``, ``patience`` and ``time_limit_s`` may change)."""
        d = asdict(self)
        for k in ("epochs", "patience", "time_limit_s", "device"):
            d.pop(k)
        return d


def architecture_from_config(config: DensityTrainConfig, n_times: int = 101, dt: float = 0.1,
                             nu: int = 2, n_segments: int = 10, system: str = "car") -> DensityNetArchitecture:
    base = DensityNetArchitecture.default(config.arch)
    return DensityNetArchitecture(
        arch=config.arch,
        hidden=config.hidden or base.hidden,
        layers=config.layers or base.layers,
        activation=config.activation or base.activation,
        n_times=n_times,
        dt=dt,
        nu=nu,
        n_segments=n_segments,
        system=system,
    )


@dataclass
class DensityTrainResult:
    """Outcome of :func:`train_density`: the best model (restored), history and timing."""

    model: DensityNetwork
    history: dict[str, list[float]]
    best_epoch: int
    best_val_loss: float
    epochs_run: int
    stopped: str
    wall_time: float
    normalisation_time: float
    n_train_trajectories: int
    n_val_trajectories: int
    extras: dict[str, Any] = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------- normalisation
def _outputs(data: DensityData, layout: DensityLayout) -> Tensor:
    """Learned outputs ``(M, T, O)``: error in the reference frame (the learned components) and log-density
    ratio."""
    return errors_to_outputs(data.xe, data.log_ratio, data.x_ref_heading, layout)


def _raw_features(data: DensityData, layout: DensityLayout) -> Tensor:
    return torch.cat([sample_features(data.xe0, data.ref_start, layout),
                      reference_features(data.ref_start, data.params, layout)], dim=-1)


@torch.no_grad()
def fit_normalisation(model: DensityNetwork, data: DensityData, *, ridge: float = 1e-6, chunk: int = 32768) -> None:
    """Set the input standardisation and the per-time linear output baseline and scale of ``model`` from
    ``data`` (the training split), in place."""
    a, lay = model.architecture, model.layout
    if data.xe.shape[1] != a.n_times:
        raise ValueError(f"data has {data.xe.shape[1]} time points, the architecture {a.n_times}")
    if data.xe.shape[-1] != lay.nx:
        raise ValueError(f"data has states of {data.xe.shape[-1]} components, the {a.system!r} network {lay.nx}")
    f_raw = _raw_features(data, lay).double()
    o = a.n_out
    mean = f_raw.mean(0)
    std = f_raw.std(0).clamp_min(1e-6)
    m, nf = f_raw.shape
    t = a.n_times
    gram = torch.zeros(nf + 1, nf + 1, dtype=torch.float64)
    xty = torch.zeros(nf + 1, t * o, dtype=torch.float64)
    for i in range(0, m, chunk):
        x = torch.cat([(f_raw[i:i + chunk] - mean) / std, torch.ones(min(chunk, m - i), 1, dtype=torch.float64)], 1)
        y = _outputs(data.subset(slice(i, i + chunk)), lay).reshape(x.shape[0], -1).double()
        gram += x.T @ x
        xty += x.T @ y
    reg = ridge * m * torch.eye(nf + 1, dtype=torch.float64)
    reg[-1, -1] = 0.0
    coef = torch.linalg.solve(gram + reg, xty)  # (F + 1, T * O)
    sq = torch.zeros(t * o, dtype=torch.float64)
    for i in range(0, m, chunk):
        x = torch.cat([(f_raw[i:i + chunk] - mean) / std, torch.ones(min(chunk, m - i), 1, dtype=torch.float64)], 1)
        y = _outputs(data.subset(slice(i, i + chunk)), lay).reshape(x.shape[0], -1).double()
        sq += ((y - x @ coef) ** 2).sum(0)
    res_std = (sq / max(m - 1, 1)).sqrt().reshape(t, o)
    floor = 1e-3 * res_std.max(0).values + 1e-8  # t = 0 is exact (residual 0); avoid dividing by ~0
    model.in_mean.copy_(mean.float())
    model.in_std.copy_(std.float())
    model.base_weight.copy_(coef[:-1].reshape(nf, t, o).permute(1, 0, 2).float())
    model.base_bias.copy_(coef[-1].reshape(t, o).float())
    model.out_scale.copy_(torch.maximum(res_std, floor).float())


@torch.no_grad()
def normalised_targets(model: DensityNetwork, data: DensityData, chunk: int = 32768) -> tuple[Tensor, Tensor, Tensor]:
    """Standardised features ``s (M, nx)``, ``r (M, R)`` and targets ``z (M, T - 1, O)`` of ``data``."""
    s_all, r_all, z_all = [], [], []
    for i in range(0, len(data), chunk):
        part = data.subset(slice(i, i + chunk))
        s, r = model.features(part.xe0, part.ref_start, part.params)
        base = model.baseline(s, r, model.base_weight[1:], model.base_bias[1:])
        z = (_outputs(part, model.layout)[:, 1:] - base) / model.out_scale[1:]
        s_all.append(s)
        r_all.append(r)
        z_all.append(z)
    return torch.cat(s_all), torch.cat(r_all), torch.cat(z_all)


# -------------------------------------------------------------------------------------------------------- loss
def _loss(pred: Tensor, target: Tensor, w_log: float, kind: str) -> tuple[Tensor, Tensor, Tensor]:
    d = _LOSSES[kind](pred - target)  # error channels, then the log-density ratio (the last channel)
    err = d[..., :-1].mean()
    log = d[..., -1].mean()
    return err + w_log * log, err, log


def _val_pairs(n_rows: int, n_times: int, k: int, seed: int) -> tuple[Tensor, Tensor]:
    g = torch.Generator().manual_seed(seed + 7919)
    rows = torch.arange(n_rows).repeat_interleave(k)
    times = torch.randint(1, n_times, (n_rows * k,), generator=g)
    return rows, times


class _Trainer:
    def __init__(self, model: DensityNetwork, config: DensityTrainConfig, train: tuple, val: tuple):
        self.model = model
        self.config = config
        self.s, self.r, self.z = train
        self.vs, self.vr, self.vz = val
        a = model.architecture
        self.t_grid = torch.arange(a.n_times, dtype=torch.float32) * a.dt
        self.scale = model.out_scale[1:].clone()
        if a.arch == "pointwise":
            self.val_rows, self.val_times = _val_pairs(self.vs.shape[0], a.n_times, config.val_times, config.seed)

    def _forward(self, s: Tensor, r: Tensor, k: Tensor | None) -> Tensor:
        if self.model.architecture.arch == "trajectory":
            return self.model.raw_trajectory(s, r)
        return self.model.raw_pointwise(s, r, self.t_grid[k])

    def epoch(self, opt: torch.optim.Optimizer, gen: torch.Generator) -> float:
        cfg, a = self.config, self.model.architecture
        self.model.train()
        m = self.s.shape[0]
        if a.arch == "trajectory":
            rows = torch.randperm(m, generator=gen)
            times = None
        else:
            rows = torch.arange(m).repeat(cfg.times_per_trajectory)
            times = torch.randint(1, a.n_times, rows.shape, generator=gen)
            perm = torch.randperm(rows.numel(), generator=gen)
            rows, times = rows[perm], times[perm]
        total, n = 0.0, 0
        for i in range(0, rows.numel(), cfg.batch_size):
            idx = rows[i:i + cfg.batch_size]
            if times is None:
                pred, target = self._forward(self.s[idx], self.r[idx], None), self.z[idx]
            else:
                k = times[i:i + cfg.batch_size]
                pred, target = self._forward(self.s[idx], self.r[idx], k), self.z[idx, k - 1]
            loss, _, _ = _loss(pred, target, cfg.log_density_weight, cfg.loss)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += float(loss.detach()) * idx.numel()
            n += idx.numel()
        return total / max(n, 1)

    @torch.no_grad()
    def validate(self, chunk: int = 8192) -> dict[str, float]:
        cfg, a = self.config, self.model.architecture
        self.model.eval()
        sums = {"loss": 0.0, "err": 0.0, "log": 0.0, "pos_sq": 0.0, "log_sq": 0.0}
        n = 0
        if a.arch == "trajectory":
            rows_all, times_all = torch.arange(self.vs.shape[0]), None
        else:
            rows_all, times_all = self.val_rows, self.val_times
        for i in range(0, rows_all.numel(), chunk):
            idx = rows_all[i:i + chunk]
            if times_all is None:
                pred, target, scale = self._forward(self.vs[idx], self.vr[idx], None), self.vz[idx], self.scale
            else:
                k = times_all[i:i + chunk]
                pred = self._forward(self.vs[idx], self.vr[idx], k)
                target, scale = self.vz[idx, k - 1], self.scale[k - 1]
            loss, err, log = _loss(pred, target, cfg.log_density_weight, cfg.loss)
            d = (pred - target) * scale  # physical units
            b = idx.numel()
            sums["loss"] += float(loss) * b
            sums["err"] += float(err) * b
            sums["log"] += float(log) * b
            sums["pos_sq"] += float((d[..., 0] ** 2 + d[..., 1] ** 2).mean()) * b
            sums["log_sq"] += float((d[..., -1] ** 2).mean()) * b
            n += b
        return {
            "val_loss": sums["loss"] / n,
            "val_loss_error": sums["err"] / n,
            "val_loss_log_density": sums["log"] / n,
            "val_position_rmse_m": math.sqrt(sums["pos_sq"] / n),
            "val_log_density_rmse": math.sqrt(sums["log_sq"] / n),
        }


def _cosine_lr(config: DensityTrainConfig, epoch: int) -> float:
    frac = min(epoch / max(config.epochs - 1, 1), 1.0)
    return config.lr_final + 0.5 * (config.lr - config.lr_final) * (1 + math.cos(math.pi * frac))


def train_density(
    config: DensityTrainConfig,
    train: DensityData,
    val: DensityData,
    out: str | Path | None = None,
    *,
    resume: bool = True,
    progress: bool = False,
    callback: Callable[[dict[str, float]], None] | None = None,
) -> DensityTrainResult:
    """Train a density predictor on ``train`` with early stopping on ``val`` (held-out references).

    Args:
        out: directory for the resumable ``checkpoint.pt`` (``None``: no checkpoint).
        resume: continue from ``out/checkpoint.pt`` if it exists (its settings must match ``config``).
        progress: progress bar over the epochs.
        callback: called with each epoch's record.

    Raises:
        CheckpointError: the checkpoint in ``out`` belongs to another configuration or is corrupt.
    """
    from ..io.checkpoint import load_training_state, save_training_state

    t_start = time.perf_counter()
    device = torch.device(config.device)
    torch.manual_seed(config.seed)
    if config.max_train_references is not None:
        ids = torch.unique(train.reference_id)[: config.max_train_references]
        train = train.subset(torch.isin(train.reference_id, ids))
    par_shape = tuple(train.params.shape[1:])
    arch = architecture_from_config(config, n_times=int(train.t.numel()),
                                    dt=round(float(train.t[1] - train.t[0]), 6), nu=par_shape[0],
                                    n_segments=par_shape[1], system=train.system)
    if val.system != train.system:
        raise ValueError(f"training data of the system {train.system!r}, validation data of {val.system!r}")
    model = DensityNetwork(arch)
    t0 = time.perf_counter()
    fit_normalisation(model, train, ridge=config.ridge)
    tr = normalised_targets(model, train)
    va = normalised_targets(model, val)
    t_norm = time.perf_counter() - t0
    model = model.to(device)
    tr = (tr[0].to(device), tr[1].to(device), tr[2].to(device))
    va = (va[0].to(device), va[1].to(device), va[2].to(device))
    trainer = _Trainer(model, config, tr, va)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    gen = torch.Generator().manual_seed(config.seed)

    history: dict[str, list[float]] = {}
    best_val, best_epoch, best_state, start_epoch, elapsed_before = math.inf, -1, None, 0, 0.0
    ckpt = Path(out) / "checkpoint.pt" if out is not None else None
    if ckpt is not None and resume and ckpt.is_file():
        state = load_training_state(ckpt)
        if state.get("resume_key") != config.resume_key():
            raise CheckpointError(f"{ckpt} was written with other training settings; use a new --out directory "
                                  "or --no-resume")
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        gen.set_state(state["generator"])
        history = state["history"]
        best_val, best_epoch = state["best_val"], state["best_epoch"]
        best_state = state["best_state"]
        start_epoch = state["epoch"] + 1
        elapsed_before = state["elapsed"]
        logger.info("resuming density training at epoch %d from %s", start_epoch, ckpt)

    from tqdm.auto import tqdm

    stopped = "epochs"
    t_loop = time.perf_counter()
    bar = tqdm(total=config.epochs, initial=start_epoch, desc=f"train {arch.arch}", disable=not progress,
               unit="epoch")
    epoch = start_epoch - 1
    try:
        if start_epoch > 0 and start_epoch - 1 - best_epoch >= config.patience:
            stopped = "early_stopping"
        for epoch in range(start_epoch, config.epochs if stopped == "epochs" else start_epoch):
            lr = _cosine_lr(config, epoch)
            for group in opt.param_groups:
                group["lr"] = lr
            train_loss = trainer.epoch(opt, gen)
            record = {"epoch": float(epoch), "lr": lr, "train_loss": train_loss, **trainer.validate()}
            record["wall_time_s"] = elapsed_before + time.perf_counter() - t_loop
            for k, v in record.items():
                history.setdefault(k, []).append(v)
            if record["val_loss"] < best_val:
                best_val, best_epoch = record["val_loss"], epoch
                best_state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
            bar.set_postfix(train=f"{train_loss:.3g}", val=f"{record['val_loss']:.3g}",
                            pos=f"{record['val_position_rmse_m']:.3f}m", best=best_epoch)
            bar.update()
            if callback is not None:
                callback(record)
            if ckpt is not None:
                save_training_state(ckpt, {
                    "model": model.state_dict(), "optimizer": opt.state_dict(), "generator": gen.get_state(),
                    "history": history, "best_val": best_val, "best_epoch": best_epoch, "best_state": best_state,
                    "epoch": epoch, "elapsed": record["wall_time_s"], "resume_key": config.resume_key(),
                })
            if epoch - best_epoch >= config.patience:
                stopped = "early_stopping"
                break
            if config.time_limit_s is not None and record["wall_time_s"] >= config.time_limit_s:
                stopped = "time_limit"
                break
    finally:
        bar.close()
    if best_state is not None:
        model.load_state_dict(best_state)
    model = model.cpu().eval()
    wall = elapsed_before + time.perf_counter() - t_loop
    return DensityTrainResult(
        model=model,
        history=history,
        best_epoch=best_epoch,
        best_val_loss=best_val,
        epochs_run=epoch + 1,
        stopped=stopped,
        wall_time=wall,
        normalisation_time=t_norm,
        n_train_trajectories=len(train),
        n_val_trajectories=len(val),
        extras={"total_time_s": time.perf_counter() - t_start},
    )


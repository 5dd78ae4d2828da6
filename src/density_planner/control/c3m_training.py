"""Training of the C3M controller and metric: penalties on violations of the contraction conditions.

Every optimisation step draws a fresh batch of tracking situations (:func:`~.sampling.sample_tracking_states`:
references in the state box, errors in the XE box, reference inputs in the input box, heading bias in
+-pi/8) from a seeded generator and minimises :func:`~.contraction.contraction_loss` with Adam and a cosine
learning-rate schedule. After every epoch the fraction of a fixed held-out set that satisfies the condition is
recorded. Checkpoints (model, optimiser, generator state, epoch, history) are written atomically every
``checkpoint_every`` epochs; a run started again with the same output directory resumes from the last one.
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

from ..checks import check_positive, check_seed
from ..errors import CheckpointError
from ..systems.car import CarConfig, car_domain
from .base import soft_clip
from .c3m import SHIPPED_C3M_WEIGHTS, C3MArchitecture, C3MModel, save_c3m_model
from .contraction import car_contraction_terms, condition_holds, contraction_loss, eigenvalues, max_eigenvalue
from .sampling import TrackingSamples, sample_tracking_states

__all__ = [
    "C3MTrainConfig",
    "TrainHistory",
    "C3MTrainResult",
    "train_c3m",
    "contraction_diagnostics",
    "CHECKPOINT_NAME",
]

logger = logging.getLogger(__name__)

#: file name of the resumable training checkpoint inside the output directory
CHECKPOINT_NAME = "checkpoint.pt"
_DTYPES = {"float32": torch.float32, "float64": torch.float64}


@dataclass(frozen=True)
class C3MTrainConfig:
    """Settings of :func:`train_c3m` (the shipped weights use the defaults)."""

    #: network shapes and metric lower bound
    architecture: C3MArchitecture = field(default_factory=C3MArchitecture)
    #: seed of the parameter initialisation and of the sample generator
    seed: int = 0
    #: number of epochs
    epochs: int = 60
    #: optimisation steps per epoch (each on a fresh batch)
    steps_per_epoch: int = 200
    #: samples per optimisation step
    batch_size: int = 2048
    #: initial Adam learning rate
    lr: float = 1e-3
    #: learning rate at the end of the cosine schedule
    lr_final: float = 1e-5
    #: contraction rate lambda of condition (CL) and (C1) [1/s]
    rate: float = 0.5
    #: margin of condition (CL): penalise lambda_max + margin > 0 (in 1/s if ``normalized``)
    margin: float = 0.4
    #: margin of condition (C1)
    margin_c1: float = 0.4
    #: weight of the (C1) penalty
    weight_c1: float = 1.0
    #: weight of the (C2) penalty (zero by construction of the metric; kept for completeness)
    weight_c2: float = 1.0
    #: penalise generalised eigenvalues of (C, W) (scale-invariant) instead of eigenvalues of C
    normalized: bool = True
    #: upper end of the contraction-rate band [1/s]: local rates above it are penalised (bounds the stiffness and
    #: the divergence of the closed loop, so that the density integrators stay accurate); 0 disables
    max_rate: float = 0.0
    #: weight of the rate-cap (or divergence-cap) penalty
    weight_max_rate: float = 1.0
    #: bound on the volume compression of the closed loop: penalise ``-tr(A_cl) > max_divergence`` [1/s] (keeps the
    #: Liouville density growth and the stiffness bounded); 0 disables; exclusive with ``max_rate``
    max_divergence: float = 15.0
    #: clip the gradient norm to this value (0 disables)
    grad_clip: float = 10.0
    #: size of the fixed held-out set checked after every epoch
    eval_samples: int = 20_000
    #: write a resumable checkpoint every this many epochs (and after the last)
    checkpoint_every: int = 5
    #: torch device ("cpu", "cuda", "cuda:N")
    device: str = "cpu"
    #: floating point precision of training
    dtype: Literal["float32", "float64"] = "float32"
    #: car domain whose boxes are sampled: "paper" (v in [0, 10] m/s) or "road" (v in [0, 40] m/s, smooth
    #: saturation, lateral-acceleration limit); see :data:`density_planner.systems.car.CAR_DOMAINS`
    domain: str = "paper"
    #: training samples have a true speed of at least this much [m/s] (0: the plain box). At standstill the lateral
    #: error is uncontrollable and the condition cannot hold for any metric (docs/controller.md), so samples there
    #: only waste the budget; the checks still sample the whole box
    min_speed: float = 0.0

    def __post_init__(self) -> None:
        for name in ("epochs", "steps_per_epoch", "batch_size", "eval_samples", "checkpoint_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"C3MTrainConfig.{name} must be a positive integer, got {value!r}")
        check_seed("C3MTrainConfig.seed", self.seed)
        check_positive("C3MTrainConfig.lr", self.lr)
        check_positive("C3MTrainConfig.lr_final", self.lr_final)
        check_positive("C3MTrainConfig.rate", self.rate, allow_zero=True)
        if self.max_rate and self.max_divergence:
            raise ValueError("C3MTrainConfig: set either max_rate or max_divergence, not both")
        if self.max_rate and (self.max_rate <= self.rate or not self.normalized):
            raise ValueError(
                f"C3MTrainConfig.max_rate ({self.max_rate}) must exceed rate ({self.rate}) and needs normalized=true"
            )
        for name in ("margin", "margin_c1", "weight_c1", "weight_c2", "grad_clip", "max_rate", "weight_max_rate",
                     "max_divergence"):
            check_positive(f"C3MTrainConfig.{name}", getattr(self, name), allow_zero=True)
        from ..systems.car import CAR_DOMAINS

        if self.domain not in CAR_DOMAINS:
            raise ValueError(f"C3MTrainConfig.domain must be one of {sorted(CAR_DOMAINS)}, got {self.domain!r}")
        check_positive("C3MTrainConfig.min_speed", self.min_speed, allow_zero=True)
        if self.dtype not in _DTYPES:
            raise ValueError(f"C3MTrainConfig.dtype must be one of {sorted(_DTYPES)}, got {self.dtype!r}")
        try:
            torch.device(self.device)
        except RuntimeError:
            raise ValueError(f"C3MTrainConfig.device {self.device!r} is not a torch device") from None

    def to_dict(self) -> dict[str, Any]:
        from ..config import to_dict

        return to_dict(self)

    def resume_key(self) -> dict[str, Any]:
        """Settings that must agree to resume a run (``epochs`` and ``device`` may change)."""
        d = self.to_dict()
        d.pop("epochs")
        d.pop("device")
        d.pop("checkpoint_every")
        for key, default in (("domain", "paper"), ("min_speed", 0.0)):
            if d.get(key) == default:
                d.pop(key)  # keys added later: checkpoints of paper runs written before them still resume
        return d


@dataclass
class TrainHistory:
    """Per-epoch training record (lists of equal length, one entry per completed epoch)."""

    epoch: list[int] = field(default_factory=list)
    #: mean training loss over the epoch's steps
    loss: list[float] = field(default_factory=list)
    #: mean (CL) and (C1) penalties over the epoch's steps
    loss_cl: list[float] = field(default_factory=list)
    loss_c1: list[float] = field(default_factory=list)
    #: fraction of training samples meeting (CL) with the margin
    train_frac_cl: list[float] = field(default_factory=list)
    #: fraction of the held-out set where (CL), resp. (C1), holds (no margin)
    eval_frac_cl: list[float] = field(default_factory=list)
    eval_frac_c1: list[float] = field(default_factory=list)
    #: learning rate at the end of the epoch
    lr: list[float] = field(default_factory=list)
    #: cumulative training wall time [s] (excluding checkpoint writing)
    wall_time: list[float] = field(default_factory=list)

    def to_dict(self) -> dict[str, list]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, list]) -> TrainHistory:
        return cls(**{k: list(v) for k, v in data.items()})


@dataclass
class C3MTrainResult:
    """What :func:`train_c3m` returns."""

    model: C3MModel
    history: TrainHistory
    #: ``.pt`` path of the final weights (the ``.json`` lies next to it)
    weights_path: Path
    #: diagnostics of the contraction condition on fresh samples (see :func:`contraction_diagnostics`)
    diagnostics: dict[str, Any]
    #: wall time of the optimisation over all (resumed) sessions [s]
    wall_time: float


def _lr_at(config: C3MTrainConfig, step: int) -> float:
    total = config.epochs * config.steps_per_epoch
    frac = min(step / max(total, 1), 1.0)
    return config.lr_final + 0.5 * (config.lr - config.lr_final) * (1.0 + math.cos(math.pi * frac))


def _terms(model: C3MModel, s: TrackingSamples, rate: float):
    return car_contraction_terms(model, s.x[:, :4], s.x_hat[:, :4], s.x_ref[:, :4], s.u_ref, rate)


@torch.no_grad()
def _eval_fractions(model: C3MModel, samples: TrackingSamples, rate: float, chunk: int = 10_000) -> tuple[float, float]:
    ok_cl, ok_c1 = 0, 0
    for i in range(0, len(samples), chunk):
        s = TrackingSamples(*(t[i:i + chunk] for t in (samples.x, samples.x_hat, samples.x_ref, samples.u_ref)))
        terms = _terms(model, s, rate)
        ok_cl += int((max_eigenvalue(terms.cl) < 0).sum())
        ok_c1 += int((max_eigenvalue(terms.c1) < 0).sum())
    return ok_cl / len(samples), ok_c1 / len(samples)


def _new_model(config: C3MTrainConfig, car: CarConfig | None) -> C3MModel:
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        model = C3MModel(config.architecture, car)
    return model


def train_c3m(
    config: C3MTrainConfig,
    out_dir: str | Path,
    *,
    progress: bool = True,
    resume: bool = True,
    car: CarConfig | None = None,
    callback: Callable[[int, TrainHistory], None] | None = None,
    diagnostics_samples: int = 100_000,
) -> C3MTrainResult:
    """Train the C3M controller and metric; writes ``out_dir/checkpoint.pt`` and ``out_dir/controller_c3m.{pt,json}``.

    Args:
        config: training settings.
        out_dir: output directory (created).
        progress: show a tqdm progress bar over the optimisation steps.
        resume: continue from ``out_dir/checkpoint.pt`` if it exists (its settings must match ``config`` except
            ``epochs``, ``device`` and ``checkpoint_every``); otherwise start from scratch.
        car: car boxes (default: the domain ``config.domain``).
        callback: called as ``callback(epoch, history)`` after every epoch.
        diagnostics_samples: fresh samples for the final :func:`contraction_diagnostics`.

    Returns:
        The trained model, the history, the weights path, the final diagnostics and the wall time.
    """
    from ..io.atomic import atomic_write_json
    from ..io.checkpoint import load_training_state, save_training_state

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    device = torch.device(config.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("C3MTrainConfig.device is cuda but no CUDA device is available")
    dtype = _DTYPES[config.dtype]
    car = car or car_domain(config.domain)

    model = _new_model(config, car).to(device=device, dtype=dtype)
    optimiser = torch.optim.Adam(model.parameters(), lr=config.lr)
    generator = torch.Generator().manual_seed(config.seed)
    history = TrainHistory()
    start_epoch, wall = 0, 0.0
    ckpt_path = out / CHECKPOINT_NAME
    if resume and ckpt_path.exists():
        state = load_training_state(ckpt_path)
        saved = state.get("config_key")
        if saved != config.resume_key():
            diff = sorted(k for k in set(saved or {}) | set(config.resume_key())
                          if (saved or {}).get(k) != config.resume_key().get(k))
            raise CheckpointError(
                f"{ckpt_path}: checkpoint was written with different settings ({', '.join(diff)}); use another "
                "--out directory or start afresh without resuming"
            )
        model.load_state_dict(state["model"])
        optimiser.load_state_dict(state["optimiser"])
        generator.set_state(state["generator"])
        history = TrainHistory.from_dict(state["history"])
        start_epoch, wall = int(state["epoch"]), float(state["wall_time"])
        logger.info("resuming from %s at epoch %d", ckpt_path, start_epoch)

    eval_gen = torch.Generator().manual_seed(config.seed + 1_000_003)
    eval_set = sample_tracking_states(config.eval_samples, eval_gen, car, dtype=dtype, device=device)

    def checkpoint(epoch: int) -> None:
        save_training_state(ckpt_path, {
            "model": model.state_dict(),
            "optimiser": optimiser.state_dict(),
            "generator": generator.get_state(),
            "epoch": epoch,
            "wall_time": wall,
            "history": history.to_dict(),
            "config_key": config.resume_key(),
            "config": config.to_dict(),
        })
        atomic_write_json(out / "history.json", history.to_dict())

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=config.epochs * config.steps_per_epoch, initial=start_epoch * config.steps_per_epoch,
                   desc="train C3M", unit="step", dynamic_ncols=True)
    model.train()
    try:
        for epoch in range(start_epoch, config.epochs):
            t0 = time.perf_counter()
            sums = torch.zeros(4, dtype=torch.float64)
            for step in range(config.steps_per_epoch):
                global_step = epoch * config.steps_per_epoch + step
                lr = _lr_at(config, global_step)
                for group in optimiser.param_groups:
                    group["lr"] = lr
                batch = sample_tracking_states(config.batch_size, generator, car, dtype=dtype, device=device,
                                               min_speed=config.min_speed)
                terms = _terms(model, batch, config.rate)
                loss = contraction_loss(
                    terms, margin=config.margin, margin_c1=config.margin_c1, weight_c1=config.weight_c1,
                    weight_c2=config.weight_c2, normalized=config.normalized, rate=config.rate,
                    max_rate=config.max_rate, weight_max_rate=config.weight_max_rate,
                    max_divergence=config.max_divergence,
                )
                optimiser.zero_grad(set_to_none=True)
                loss.total.backward()
                if config.grad_clip > 0:
                    torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
                optimiser.step()
                sums += torch.tensor([float(loss.total.detach()), loss.cl, loss.c1, loss.frac_cl], dtype=torch.float64)
                if bar is not None:
                    bar.update(1)
            model.eval()
            frac_cl, frac_c1 = _eval_fractions(model, eval_set, config.rate)
            model.train()
            wall += time.perf_counter() - t0
            mean = (sums / config.steps_per_epoch).tolist()
            history.epoch.append(epoch + 1)
            history.loss.append(mean[0])
            history.loss_cl.append(mean[1])
            history.loss_c1.append(mean[2])
            history.train_frac_cl.append(mean[3])
            history.eval_frac_cl.append(frac_cl)
            history.eval_frac_c1.append(frac_c1)
            history.lr.append(lr)
            history.wall_time.append(wall)
            logger.info("epoch %d/%d loss %.4g held-out (CL) %.4f (C1) %.4f", epoch + 1, config.epochs, mean[0],
                        frac_cl, frac_c1)
            if bar is not None:
                bar.set_postfix(loss=f"{mean[0]:.3g}", cl_ok=f"{frac_cl:.4f}", c1_ok=f"{frac_c1:.4f}")
            if (epoch + 1) % config.checkpoint_every == 0 or epoch + 1 == config.epochs:
                checkpoint(epoch + 1)
            if callback is not None:
                callback(epoch + 1, history)
    finally:
        if bar is not None:
            bar.close()
    model.eval()
    model.requires_grad_(False)
    cpu_model = model.to(device="cpu", dtype=torch.float32)
    diagnostics = contraction_diagnostics(cpu_model, n=diagnostics_samples, rate=config.rate,
                                          seed=config.seed + 2_000_003, car=car)
    diagnostics["train_wall_time_s"] = wall
    pt_path, _ = save_c3m_model(out / SHIPPED_C3M_WEIGHTS, cpu_model, config=config.to_dict(),
                                diagnostics={"contraction": diagnostics})
    return C3MTrainResult(cpu_model, history, pt_path, diagnostics, wall)


def _quantiles(x: torch.Tensor) -> dict[str, float]:
    """min, 1/5/50/95/99th percentiles, max and mean of ``x``."""
    x = x.double()
    out = {"min": float(x.min())}
    for q in (1, 5, 50, 95, 99):
        out[f"q{q:02d}"] = float(torch.quantile(x, q / 100))
    out["max"] = float(x.max())
    out["mean"] = float(x.mean())
    return out


@torch.no_grad()
def contraction_diagnostics(
    model: C3MModel,
    *,
    n: int = 100_000,
    rate: float = 0.5,
    seed: int = 12345,
    car: CarConfig | None = None,
    chunk: int = 10_000,
    return_samples: bool = False,
) -> dict[str, Any]:
    """Check the contraction conditions on ``n`` fresh samples (see :func:`~.sampling.sample_tracking_states`).

    Returns a JSON-friendly dict: fraction where (CL) holds, where (C1) holds, largest ``|C2|_F``, quantiles of
    ``lambda_max(C)`` and of the generalised ``lambda_max(C, W)`` (whose negative half is the certified rate in
    excess of ``rate``), the fraction per speed band, the largest local contraction rate ``rate - lambda_min(C, W)/2``
    [1/s] and the closed-loop divergence ``tr(A_cl)`` [1/s] of the unclipped law, and the fraction of samples whose
    unclipped input leaves the input bounds (where the clipped controller differs from the certified one). With
    ``return_samples`` the
    per-sample eigenvalues are included as tensors under ``"_samples"``.
    """
    car = car or getattr(model, "car", None) or CarConfig()
    gen = torch.Generator().manual_seed(seed)
    p = next(model.parameters())
    samples = sample_tracking_states(n, gen, car, dtype=p.dtype, device=p.device)
    holds, lam, lam_n, lam1, c2 = [], [], [], [], []
    clipped, lam_low, div, deep = [], [], [], []
    saturation = model.controller.saturation
    lo = torch.as_tensor(car.input_min, dtype=p.dtype, device=p.device)
    hi = torch.as_tensor(car.input_max, dtype=p.dtype, device=p.device)
    for i in range(0, n, chunk):
        s = TrackingSamples(*(t[i:i + chunk] for t in (samples.x, samples.x_hat, samples.x_ref, samples.u_ref)))
        terms = _terms(model, s, rate)
        h, l_raw, l_norm = condition_holds(terms)
        lam_low.append(eigenvalues(terms.cl, terms.w)[..., 0])
        _, k = model.controller.jacobian(s.x_hat, s.x_ref, s.u_ref)
        div.append(k[..., 0, 2] + k[..., 1, 3])  # tr(A_cl) = d omega / d theta + d a / d v (tr(da/dx) = 0)
        holds.append(h)
        lam.append(l_raw)
        lam_n.append(l_norm)
        lam1.append(max_eigenvalue(terms.c1))
        c2.append(terms.c2_norm())
        u = model.controller.raw(s.x_hat, s.x_ref, s.u_ref)
        if saturation is None:
            clipped.append(((u < lo) | (u > hi)).any(-1))
        else:
            # smooth saturation: "clipped" = the raw law leaves the reference box (the tanh tail is used);
            # "deep" = the saturation's slope is below 1/2 (the applied gain is less than half the certified one)
            k_lo, k_hi, c_lo, c_hi, _, _ = saturation._limits(u, s.x_hat)
            clipped.append(((u < k_lo) | (u > k_hi)).any(-1))
            deep.append((soft_clip(u, k_lo, k_hi, c_lo, c_hi)[1] < 0.5).any(-1))
    holds_t, lam_t, lam_n_t = torch.cat(holds), torch.cat(lam), torch.cat(lam_n)
    lam1_t, c2_t, clipped_t = torch.cat(lam1), torch.cat(c2), torch.cat(clipped)
    lam_low_t, div_t = torch.cat(lam_low), torch.cat(div)
    v = samples.x[:, 3]
    bands = {}
    v_top = car.speed_max + car.error_max[3]
    edges = [-car.error_max[3], 0.0, 0.5, 2.0] + ([10.0, 20.0, 30.0] if car.speed_max > 20 else []) + [v_top]
    for v0, v1 in zip(edges[:-1], edges[1:]):
        sel = (v >= v0) & (v < v1)
        if bool(sel.any()):
            bands[f"v_in_[{v0:g},{v1:g})"] = {"n": int(sel.sum()), "frac_holds": float(holds_t[sel].float().mean())}
    out: dict[str, Any] = {
        "n_samples": n,
        "rate": rate,
        "seed": seed,
        "frac_holds": float(holds_t.float().mean()),
        "frac_c1_holds": float((lam1_t < 0).float().mean()),
        "c2_max_frobenius": float(c2_t.max()),
        "lambda_max": _quantiles(lam_t),
        "lambda_max_generalised": _quantiles(lam_n_t),
        "frac_holds_by_speed": bands,
        "frac_holds_v_ge_0.5": float(holds_t[v >= 0.5].float().mean()),
        "max_local_rate": _quantiles(rate - 0.5 * lam_low_t),
        "divergence_unclipped": _quantiles(div_t),
        "frac_input_clipped": float(clipped_t.float().mean()),
        "frac_holds_where_not_clipped": float(holds_t[~clipped_t].float().mean()) if bool((~clipped_t).any())
        else None,
        "domain": car.domain,
    }
    if deep:
        out["frac_saturation_slope_below_half"] = float(torch.cat(deep).float().mean())
    if return_samples:
        out["_samples"] = {"lambda_max": lam_t, "lambda_max_generalised": lam_n_t, "v": v}
    return out

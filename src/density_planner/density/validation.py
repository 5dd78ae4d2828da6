"""Accuracy and speed of a density predictor against exact Liouville propagation on fresh references.

:func:`compare_with_exact` draws references and initial errors the same way as the training data (but with a
seed of its own; initial errors in the XE0 box by default), propagates them with both predictors and returns the
per-sample errors. :meth:`DensityComparison.summary` reduces them to the numbers of the validation report:

* per time: median and 95th percentile of the position error ``||p_NN(t) - p_LE(t)||`` [m] and of the absolute
  log-density error ``|log rho_NN(t) - log rho_LE(t)|``, and of the *relative* log-density error (the error
  minus its mean over the samples of the same reference and time: what the planner's per-time normalised sample
  weights see);
* overall (all samples and times): the mean squared error of the error state ``x - x_ref`` (all ``nx``
  components; for the car comparable with the paper's validation MSE 0.018) and the log-density RMSE (paper: about
  9.3);
* timing of both predictors.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ..control.reference import Reference
from .base import DensityPredictor
from .liouville import IntegratorName

__all__ = ["DensityComparison", "compare_with_exact", "fresh_references"]

#: edges of the reference start-speed bands of the accuracy reports [m/s]
SPEED_BANDS = (0.0, 5.0, 10.0, 20.0, 30.0, 41.0)
#: bands of a reference's highest speed [m/s] in :func:`liouville_accuracy`
_TOP_SPEED_BANDS = (0.0, 10.0, 15.0, 20.0, 25.0, 30.0, 45.0)

#: the paper's stored validation numbers of its density network (``docs/spec.md`` §6)
PAPER_ERROR_MSE = 0.0182
PAPER_LOG_DENSITY_RMSE = 9.3


def fresh_references(n: int, samples: int, seed: int, *, error_scale: float = 1.0,
                     start_low: Sequence[float] | None = None, start_high: Sequence[float] | None = None,
                     dtype: torch.dtype = torch.float32, domain: str = "paper") -> tuple[Reference, Tensor]:
    """``n`` random feasible references of the model set ``domain`` (the car's ``paper`` or ``road``, ``ks``, ...)
    and ``samples`` initial states per reference (errors uniform in ``error_scale * XE0``, the system's
    ``initial_error_max``): ``(reference (n,), x0 (n, samples, nx))``. The start box defaults to the data default
    for the paper's set and to the system's reference-start box for the others."""
    from ..control.registry import model_set
    from ..control.sampling import sample_feasible_references, sample_initial_errors
    from .data import DensityDataConfig

    system = model_set(domain).make_system()
    if domain == "paper":
        defaults = DensityDataConfig()
        start_low, start_high = start_low or defaults.start_low, start_high or defaults.start_high
    gen = torch.Generator().manual_seed(seed)
    ref = sample_feasible_references(system, n, gen, start_low=start_low, start_high=start_high, dtype=dtype)
    box = [error_scale * v for v in system.initial_error_max]
    xe0 = sample_initial_errors(n * samples, gen, box=box, dtype=dtype).reshape(n, samples, system.nx)
    return ref, ref.start.unsqueeze(-2) + xe0


@dataclass
class DensityComparison:
    """Per-sample errors of a predictor against exact Liouville: ``(R, N, T)`` tensors over references, samples
    and times, plus the error-state errors ``(R, N, T, 5)`` and wall times [s]."""

    t: Tensor
    position_error: Tensor
    log_density_error: Tensor
    state_error: Tensor
    time_exact: float
    time_predictor: float
    n_references: int
    n_samples: int
    #: reference start speeds ``(R,)`` [m/s] (for the per-speed-band summary)
    start_speed: Tensor | None = None
    #: indices of the system's hidden states (the car's heading bias), left out of the second error MSE
    hidden_states: tuple[int, ...] = (4,)

    def by_speed_band(self, edges: Sequence[float] = SPEED_BANDS) -> dict[str, dict]:
        """Position error [m] and |log-density error| (median, p95) per band of reference start speed."""
        if self.start_speed is None:
            return {}
        out = {}
        for lo, hi in zip(edges[:-1], edges[1:]):
            sel = (self.start_speed >= lo) & (self.start_speed < hi)
            if not bool(sel.any()):
                continue
            pe = self.position_error[sel].reshape(-1).double()
            le = self.log_density_error[sel].abs().reshape(-1).double()
            out[f"v0_in_[{lo:g},{hi:g})"] = {
                "n_references": int(sel.sum()),
                "position_error_m": {"median": float(pe.median()), "p95": float(torch.quantile(pe, 0.95))},
                "log_density_abs_error": {"median": float(le.median()), "p95": float(torch.quantile(le, 0.95))},
            }
        return out

    def summary(self) -> dict:
        pe, le = self.position_error, self.log_density_error
        rel = le - le.mean(dim=1, keepdim=True)
        ale, arel = le.abs(), rel.abs()

        def per_time(x: Tensor) -> dict[str, list[float]]:
            flat = x.permute(2, 0, 1).reshape(x.shape[2], -1).double()
            return {"median": flat.median(dim=1).values.tolist(),
                    "p95": torch.quantile(flat, 0.95, dim=1).tolist()}

        def overall(x: Tensor) -> dict[str, float]:
            flat = x.reshape(-1).double()
            if flat.numel() > 10_000_000:
                flat = flat[torch.randperm(flat.numel(), generator=torch.Generator().manual_seed(0))[:10_000_000]]
            return {"median": float(flat.median()), "p95": float(torch.quantile(flat, 0.95)),
                    "max": float(flat.max())}

        se = self.state_error.double()
        mse5 = float((se ** 2).mean())
        known = [i for i in range(se.shape[-1]) if i not in self.hidden_states]
        mse4 = float((se[..., known] ** 2).mean())
        lrmse = float((le.double() ** 2).mean().sqrt())
        rel_rmse = float((rel.double() ** 2).mean().sqrt())
        n_traj = self.n_references * self.n_samples
        return {
            "n_references": self.n_references,
            "samples_per_reference": self.n_samples,
            "t": self.t.tolist(),
            "position_error_m": {"per_time": per_time(pe), "overall": overall(pe)},
            "log_density_abs_error": {"per_time": per_time(ale), "overall": overall(ale)},
            "log_density_relative_abs_error": {"per_time": per_time(arel), "overall": overall(arel)},
            "error_state_mse": mse5,
            "error_state_mse_without_bias": mse4,
            "position_rmse_m": float((pe.double() ** 2).mean().sqrt()),
            "log_density_rmse": lrmse,
            "log_density_relative_rmse": rel_rmse,
            "paper": {"error_state_mse": PAPER_ERROR_MSE, "log_density_rmse": PAPER_LOG_DENSITY_RMSE,
                      "better_error_mse": mse5 < PAPER_ERROR_MSE,
                      "better_log_density_rmse": lrmse < PAPER_LOG_DENSITY_RMSE},
            "time_exact_s": self.time_exact,
            "time_predictor_s": self.time_predictor,
            "time_exact_per_500_trajectories_s": self.time_exact / n_traj * 500,
            "time_predictor_per_500_trajectories_s": self.time_predictor / n_traj * 500,
            "by_speed_band": self.by_speed_band(),
        }


@torch.no_grad()
def compare_with_exact(
    predictor: DensityPredictor,
    exact: DensityPredictor,
    reference: Reference,
    x0: Tensor,
    *,
    chunk: int = 32,
) -> DensityComparison:
    """Errors of ``predictor`` against ``exact`` for the initial states ``x0 (R, N, nx)`` of ``reference (R,)``,
    ``chunk`` references at a time (log rho0 = 0: only the log-density *ratio* is compared). Positions and speeds
    are read through ``exact.system`` (the car's layout when it has none)."""
    from ..systems.car import KinematicCar

    system = getattr(exact, "system", None) or KinematicCar()
    r, n = x0.shape[:2]
    pos, lde, se = [], [], []
    t_exact = t_pred = 0.0
    t = None
    for i in range(0, r, chunk):
        ref = reference.select(slice(i, i + chunk))
        x = x0[i:i + chunk]
        lr0 = torch.zeros(x.shape[:-1], dtype=x.dtype)
        t0 = time.perf_counter()
        ex = exact.predict(x, lr0, ref)
        t1 = time.perf_counter()
        pr = predictor.predict(x, lr0, ref)
        t2 = time.perf_counter()
        t_exact += t1 - t0
        t_pred += t2 - t1
        t = ex.t
        d = pr.x - ex.x
        pos.append(system.positions(d).norm(dim=-1))
        lde.append(pr.log_rho - ex.log_rho)
        se.append(d)
    assert t is not None
    speeds = system.speeds(reference.start)
    pe = torch.cat(pos)
    le = torch.cat(lde)
    if not (bool(torch.isfinite(pe).all()) and bool(torch.isfinite(le).all())):
        raise FloatingPointError("non-finite predictions in the density comparison")
    return DensityComparison(t=t, position_error=pe, log_density_error=le, state_error=torch.cat(se),
                             time_exact=t_exact, time_predictor=t_pred, n_references=r, n_samples=n,
                             start_speed=None if speeds is None else speeds.detach().cpu(),
                             hidden_states=tuple(system.hidden_states))



@torch.no_grad()
def liouville_accuracy(
    system,
    controller,
    *,
    n_references: int = 100,
    samples: int = 20,
    seed: int = 0,
    schemes: Sequence[tuple[IntegratorName, float]] = (("rk4", 0.1), ("rk4", 0.05), ("euler", 0.01)),
    reference_scheme: tuple[IntegratorName, float] = ("rk4", 0.005),
    dtype: torch.dtype = torch.float32,
    chunk: int = 25,
    default: bool = True,
) -> dict:
    """Accuracy of the exact Liouville integration on ``n_references`` random feasible references of ``system``'s
    domain (initial errors uniform in its XE0 box, heading bias included), against a converged float64 solution.

    The float64 reference uses ``reference_scheme``; its own convergence is reported as the largest difference to
    the same scheme at twice the step (``reference_self_error``). For every scheme (run in ``dtype``; each a fixed
    step) and, with ``default``, for the default :class:`~.liouville.LiouvilleConfig` (the system's scheme: for the
    road domain the error-controlled "rk43"; reported as ``"default"``): the largest and the median absolute
    log-density error over samples and times [nats], its 99th percentile, the largest position error [m], the wall
    time [s], and per band of the references' highest speed the largest log-density error (``by_top_speed``). A
    default equal to one of ``schemes`` is reported from that scheme's run. The references are integrated
    ``chunk`` at a time in the order of their highest speed (a chunk of similar references: an error-controlled
    scheme's call runs as long as its slowest row).
    """
    import copy

    from ..control.sampling import sample_feasible_references, sample_initial_errors
    from .liouville import LiouvilleConfig, propagate_density

    gen = torch.Generator().manual_seed(seed)
    ref64 = sample_feasible_references(system, n_references, gen, dtype=torch.float64)
    xe0 = sample_initial_errors(n_references * samples, gen, box=system.config.initial_error_max,
                                dtype=torch.float64).reshape(n_references, samples, system.nx)
    x064 = ref64.start.unsqueeze(-2) + xe0
    ctrl64 = copy.deepcopy(controller).to(torch.float64)
    ctrl = copy.deepcopy(controller).to(dtype)
    ref = ref64.select(slice(None))
    ref = type(ref)(ref.params.to(dtype), ref.x.to(dtype), ref.u.to(dtype), ref.parameterization)
    name, dt = reference_scheme
    speeds = system.speeds(ref64.x)
    top = speeds.abs().amax(dim=-1) if speeds is not None else None
    # references of similar top speed share a chunk: an error-controlled call lasts as long as its slowest row, and
    # the rows of fast references take more steps (a fixed step does not care)
    order = torch.argsort(top) if top is not None else torch.arange(n_references)
    inverse = torch.argsort(order)

    def run(controller_, x0, reference, config):
        x0, reference = x0[order], reference.select(order)
        outs = [propagate_density(system, controller_, x0[i:i + chunk], reference.select(slice(i, i + chunk)),
                                  config=config) for i in range(0, x0.shape[0], chunk)]
        return torch.cat([o.x for o in outs])[inverse], torch.cat([o.log_rho for o in outs])[inverse]

    fine_x, fine_lr = run(ctrl64, x064, ref64, LiouvilleConfig(name, dt))
    half_x, half_lr = run(ctrl64, x064, ref64, LiouvilleConfig(name, 2 * dt))
    report: dict = {
        "n_references": n_references, "samples_per_reference": samples, "seed": seed,
        "domain": getattr(system.config, "domain", None),
        "reference": {"integrator": name, "dt": dt, "dtype": "float64",
                      "reference_self_error": float((half_lr - fine_lr).abs().max())},
        "start_speed": {"min": float(ref64.start[:, 3].min()), "max": float(ref64.start[:, 3].max())},
        "max_speed": float(ref64.x[..., 3].max()),
        "schemes": {},
    }
    configs = {f"{integrator} {step:g}": LiouvilleConfig(integrator, step)
               for integrator, step in schemes}
    default_config = LiouvilleConfig(integrator=LiouvilleConfig().scheme(system)) if default else None
    if default_config is not None and default_config not in configs.values():
        configs["default"] = default_config
    for label, config in configs.items():
        t0 = time.perf_counter()
        x, lr = run(ctrl, x064.to(dtype), ref, config)
        wall = time.perf_counter() - t0
        err = (lr.double() - fine_lr).abs()
        pos = (x[..., :2].double() - fine_x[..., :2]).norm(dim=-1)
        bands = {}
        if top is not None:
            per_ref = err.amax(dim=(-1, -2))
            for lo, hi in zip(_TOP_SPEED_BANDS[:-1], _TOP_SPEED_BANDS[1:]):
                sel = (top >= lo) & (top < hi)
                if bool(sel.any()):
                    bands[f"[{lo:g},{hi:g})"] = {"n_references": int(sel.sum()),
                                                 "max_abs_log_density_error": float(per_ref[sel].max())}
        report["schemes"][label] = {
            "max_abs_log_density_error": float(err.max()),
            "median_abs_log_density_error": float(err.median()),
            "p99_abs_log_density_error": float(torch.quantile(err.flatten()[:: max(1, err.numel() // 1_000_000)],
                                                              0.99)),
            "max_position_error_m": float(pos.max()),
            "wall_time_s": wall,
            "by_top_speed": bands,
        }
        if config == default_config:
            report["schemes"]["default"] = report["schemes"][label]
    return report

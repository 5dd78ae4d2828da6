"""Initial-state distributions: Gaussian, Gaussian mixture (optionally truncated to a box), uniform box and
weighted samples (a Gaussian kernel density estimate).

Every distribution has ``sample(n, generator)`` returning ``(n, dim)`` and ``log_prob(x)`` for ``x (*batch, dim)``,
a normalised log-density (it integrates to one over the state space). Parameters are stored in float64; samples
and log-densities come back in the requested (or the input's) dtype and device.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor

from ..checks import check_tensor

__all__ = [
    "InitialDistribution",
    "Gaussian",
    "GaussianMixture",
    "UniformBox",
    "WeightedSamples",
    "Conditioned",
    "paper_gaussian_mixture",
    "rejection_sample",
]

_LOG_2PI = math.log(2 * math.pi)


def _f64(name: str, value, **kw) -> Tensor:
    return check_tensor(name, value, dtype=torch.float64, device="cpu", **kw)


def _norm_cdf(z: Tensor) -> Tensor:
    return torch.special.ndtr(z)


def _norm_pdf(z: Tensor) -> Tensor:
    return torch.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)


class InitialDistribution(ABC):
    """A probability density over the state space (dimension :attr:`dim`)."""

    dim: int

    @abstractmethod
    def _sample(self, n: int, generator: torch.Generator | None) -> Tensor:
        """``(n, dim)`` float64 samples on the CPU."""

    @abstractmethod
    def _log_prob(self, x: Tensor) -> Tensor:
        """log-density of float64 ``x (*batch, dim)``."""

    @property
    @abstractmethod
    def mean(self) -> Tensor:
        """``(dim,)`` mean (float64)."""

    @property
    def support(self) -> tuple[Tensor, Tensor] | None:
        """Bounding box ``(low, high)`` of the support, or ``None`` when unbounded."""
        return None

    def sample(
        self,
        n: int,
        generator: torch.Generator | None = None,
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> Tensor:
        """``n`` independent samples, shape ``(n, dim)``; deterministic given ``generator``'s seed."""
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"number of samples n must be a positive integer, got {n!r}")
        out = self._sample(n, generator)
        return out.to(dtype=dtype or torch.get_default_dtype(), device=device)

    def log_prob(self, x: Tensor) -> Tensor:
        """Normalised log-density at ``x (*batch, dim)`` (``-inf`` outside the support)."""
        x = check_tensor("x", x, last_dims=(self.dim,))
        return self._log_prob(x.to(torch.float64).cpu()).to(dtype=x.dtype, device=x.device)


class Gaussian(InitialDistribution):
    """Multivariate normal ``N(mean, cov)``."""

    def __init__(self, mean: Sequence[float] | Tensor, cov: Sequence[Sequence[float]] | Tensor):
        self._mean = _f64("mean", mean, ndim=1)
        self.dim = self._mean.numel()
        cov = _f64("cov", cov)
        if cov.ndim == 1:
            cov = torch.diag(cov)
        if cov.shape != (self.dim, self.dim):
            raise ValueError(f"cov must have shape ({self.dim}, {self.dim}) or ({self.dim},), got {tuple(cov.shape)}")
        if not torch.allclose(cov, cov.T):
            raise ValueError("cov must be symmetric")
        try:
            self._chol = torch.linalg.cholesky(cov)
        except RuntimeError:
            raise ValueError("cov must be positive definite") from None
        self.cov = cov

    @property
    def mean(self) -> Tensor:
        return self._mean

    def _sample(self, n, generator):
        z = torch.randn(n, self.dim, dtype=torch.float64, generator=generator)
        return self._mean + z @ self._chol.T

    def _log_prob(self, x):
        d = (x - self._mean).unsqueeze(-1)
        chol = self._chol.expand(*d.shape[:-2], self.dim, self.dim)
        z = torch.linalg.solve_triangular(chol, d, upper=False).squeeze(-1)
        half_logdet = torch.log(torch.diagonal(self._chol)).sum()
        return -0.5 * (z * z).sum(-1) - half_logdet - 0.5 * self.dim * _LOG_2PI


class UniformBox(InitialDistribution):
    """Uniform density on the box ``[low, high]`` (all widths > 0)."""

    def __init__(self, low: Sequence[float] | Tensor, high: Sequence[float] | Tensor):
        self.low = _f64("low", low, ndim=1)
        self.high = _f64("high", high, ndim=1)
        if self.low.shape != self.high.shape:
            raise ValueError(f"low and high must have the same shape, got {tuple(self.low.shape)} and "
                             f"{tuple(self.high.shape)}")
        if not bool((self.high > self.low).all()):
            raise ValueError("UniformBox needs high > low in every dimension")
        self.dim = self.low.numel()
        self._log_volume = torch.log(self.high - self.low).sum()

    @property
    def mean(self) -> Tensor:
        return 0.5 * (self.low + self.high)

    @property
    def support(self):
        return self.low, self.high

    def _sample(self, n, generator):
        u = torch.rand(n, self.dim, dtype=torch.float64, generator=generator)
        return self.low + u * (self.high - self.low)

    def _log_prob(self, x):
        inside = ((x >= self.low) & (x <= self.high)).all(-1)
        return torch.where(inside, -self._log_volume, torch.full_like(inside, -math.inf, dtype=torch.float64))


class GaussianMixture(InitialDistribution):
    """Mixture of Gaussians, optionally truncated to (and renormalised on) the box ``[low, high]``.

    Args:
        weights: ``(K,)`` non-negative component weights (normalised internally).
        means: ``(K, dim)``.
        covs: ``(K, dim)`` diagonal variances or ``(K, dim, dim)`` full covariances.
        low, high: optional truncation box (needs diagonal covariances; the normaliser is then exact).
    """

    def __init__(
        self,
        weights: Sequence[float] | Tensor,
        means: Sequence[Sequence[float]] | Tensor,
        covs: Tensor | Sequence,
        *,
        low: Sequence[float] | Tensor | None = None,
        high: Sequence[float] | Tensor | None = None,
    ):
        w = _f64("weights", weights, ndim=1)
        if bool((w < 0).any()) or float(w.sum()) <= 0:
            raise ValueError("weights must be non-negative with a positive sum")
        self.weights = w / w.sum()
        self.means = _f64("means", means, ndim=2)
        k, self.dim = self.means.shape
        if self.weights.numel() != k:
            raise ValueError(f"weights has {self.weights.numel()} entries but means has {k} components")
        covs = _f64("covs", covs)
        self.diagonal = covs.ndim == 2
        if self.diagonal:
            if covs.shape != (k, self.dim) or bool((covs <= 0).any()):
                raise ValueError(f"diagonal covs must have shape ({k}, {self.dim}) with positive entries")
            self.std = covs.sqrt()
            self._chol = torch.diag_embed(self.std)
        else:
            if covs.shape != (k, self.dim, self.dim):
                raise ValueError(f"covs must have shape ({k}, {self.dim}) or ({k}, {self.dim}, {self.dim})")
            try:
                self._chol = torch.linalg.cholesky(covs)
            except RuntimeError:
                raise ValueError("every covariance must be positive definite") from None
        self.low = self.high = None
        if (low is None) != (high is None):
            raise ValueError("give both low and high for a truncated mixture, or neither")
        if low is not None:
            if not self.diagonal:
                raise ValueError("truncation to a box needs diagonal covariances")
            self.low = _f64("low", low, last_dims=(self.dim,), ndim=1)
            self.high = _f64("high", high, last_dims=(self.dim,), ndim=1)
            if not bool((self.high > self.low).all()):
                raise ValueError("truncation box needs high > low in every dimension")
            alpha = (self.low - self.means) / self.std
            beta = (self.high - self.means) / self.std
            mass_d = (_norm_cdf(beta) - _norm_cdf(alpha)).clamp_min(1e-300)  # (K, dim)
            self._alpha, self._beta, self._mass_d = alpha, beta, mass_d
            mass = mass_d.prod(-1)  # probability of the box under each component
            z = (self.weights * mass).sum()
            if float(z) <= 1e-12:
                raise ValueError("the truncation box carries (numerically) no probability mass")
            self._log_z = torch.log(z)
            self._trunc_weights = self.weights * mass / z  # component probabilities of the truncated law
        self._half_logdet = torch.log(torch.diagonal(self._chol, dim1=-2, dim2=-1)).sum(-1)  # (K,)

    @property
    def truncated(self) -> bool:
        return self.low is not None

    @property
    def support(self):
        return (self.low, self.high) if self.truncated else None

    @property
    def mean(self) -> Tensor:
        if not self.truncated:
            return (self.weights[:, None] * self.means).sum(0)
        shift = self.std * (_norm_pdf(self._alpha) - _norm_pdf(self._beta)) / self._mass_d
        return (self._trunc_weights[:, None] * (self.means + shift)).sum(0)

    def _component_log_prob(self, x: Tensor) -> Tensor:
        d = x.unsqueeze(-2) - self.means  # (*batch, K, dim)
        if self.diagonal:
            z = d / self.std
        else:
            chol = self._chol.expand(*d.shape[:-1], self.dim)
            z = torch.linalg.solve_triangular(chol, d.unsqueeze(-1), upper=False).squeeze(-1)
        return -0.5 * (z * z).sum(-1) - self._half_logdet - 0.5 * self.dim * _LOG_2PI

    def _log_prob(self, x):
        lp = torch.logsumexp(torch.log(self.weights) + self._component_log_prob(x), dim=-1)
        if not self.truncated:
            return lp
        inside = ((x >= self.low) & (x <= self.high)).all(-1)
        return torch.where(inside, lp - self._log_z, torch.full_like(lp, -math.inf))

    def _sample(self, n, generator):
        probs = self._trunc_weights if self.truncated else self.weights
        comp = torch.multinomial(probs, n, replacement=True, generator=generator)
        if not self.truncated:
            z = torch.randn(n, self.dim, dtype=torch.float64, generator=generator)
            return self.means[comp] + (self._chol[comp] @ z.unsqueeze(-1)).squeeze(-1)
        # inverse-CDF sampling of each truncated normal coordinate
        u = torch.rand(n, self.dim, dtype=torch.float64, generator=generator)
        lo = _norm_cdf(self._alpha[comp])
        hi = _norm_cdf(self._beta[comp])
        p = (lo + u * (hi - lo)).clamp(1e-15, 1 - 1e-15)
        x = self.means[comp] + self.std[comp] * torch.special.ndtri(p)
        return torch.maximum(torch.minimum(x, self.high), self.low)


class Conditioned(InitialDistribution):
    """``base`` conditioned on an event of the state, ``A = {x : accept(x)}``: ``rho(x) = base(x) 1_A(x) / Z``,
    ``Z = P_base(A)`` (e.g. the car's initial law given that its body is on the road: a localisation prior combined
    with the map).

    ``accept(x (N, dim) float64) -> (N,) bool`` (tensor or array) must be vectorised. ``Z`` and the mean are
    Monte-Carlo estimates from ``n_estimate`` draws of ``base`` with a fixed seed (deterministic); sampling is by
    rejection from ``base``.
    The support box is ``base``'s.

    Raises:
        ValueError: ``Z`` below ``min_acceptance`` (the event is (almost) impossible under ``base``; the message
        names ``description``).
    """

    def __init__(self, base: InitialDistribution, accept: Callable[[Tensor], Any], *, description: str = "",
                 n_estimate: int = 8192, min_acceptance: float = 1e-3):
        self.base, self.accept, self.description = base, accept, description
        self.dim = base.dim
        draws = base.sample(n_estimate, torch.Generator().manual_seed(0), dtype=torch.float64)
        ok = self.accepts(draws)
        self.acceptance = float(ok.double().mean())
        if self.acceptance < min_acceptance:
            raise ValueError(f"the initial law gives the event {description or 'accept(x)'} a probability of "
                             f"{self.acceptance:.2g} (< {min_acceptance:g}): it cannot be conditioned on it")
        self._log_z = math.log(self.acceptance)
        self._mean = draws[ok].mean(0)

    def accepts(self, x: Tensor) -> Tensor:
        """``(N,)`` bool: which states ``x (N, dim)`` lie in the event."""
        out = torch.as_tensor(self.accept(x.to(torch.float64).cpu().reshape(-1, self.dim)), dtype=torch.bool)
        return out.reshape(x.shape[:-1]).to(x.device)

    @property
    def mean(self) -> Tensor:
        return self._mean

    @property
    def support(self):
        return self.base.support

    def _log_prob(self, x):
        lp = self.base._log_prob(x) - self._log_z
        return torch.where(self.accepts(x), lp, torch.full_like(lp, -math.inf))

    def _sample(self, n, generator):
        x, _ = rejection_sample(lambda k: self.base._sample(k, generator), self.accepts, n,
                                lambda missing: max(2 * missing, int(1.5 * missing / self.acceptance) + 8),
                                max_rounds=1000, what=f"the initial law given {self.description or 'its event'}")
        return x  # max_rounds is unreachable for acceptance >= min_acceptance


def rejection_sample(propose: Callable[[int], Tensor], accepts: Callable[[Tensor], Tensor], n: int,
                     batch: Callable[[int], int], *, max_rounds: int, what: str) -> tuple[Tensor, float]:
    """The first ``n`` proposals ``propose(k) -> (k, dim)`` that ``accepts (k, dim) -> (k,) bool`` keeps, drawing
    ``batch(missing)`` at a time, and the accepted fraction of all draws. Raises ``RuntimeError`` (naming
    ``what``) when ``max_rounds`` draws are not enough."""
    out, have, drawn = [], 0, 0
    for _ in range(max_rounds):
        draws = propose(batch(n - have))
        drawn += draws.shape[0]
        draws = draws[accepts(draws)]
        have += draws.shape[0]
        out.append(draws)
        if have >= n:
            return torch.cat(out)[:n], have / drawn
    raise RuntimeError(f"rejection sampling of {what} did not finish: {have} of {n} in {drawn} draws")


class WeightedSamples(InitialDistribution):
    """A weighted point cloud smoothed by a Gaussian kernel (kernel density estimate).

    ``sample`` resamples points by weight and adds kernel noise; ``log_prob`` is the normalised KDE. The
    per-dimension kernel width defaults to Scott's rule ``std_d * n_eff^(-1/(dim + 4))``.
    """

    def __init__(
        self,
        points: Tensor | Sequence[Sequence[float]],
        weights: Tensor | Sequence[float] | None = None,
        bandwidth: Tensor | Sequence[float] | float | None = None,
    ):
        self.points = _f64("points", points, ndim=2)
        n, self.dim = self.points.shape
        if n < 1:
            raise ValueError("points must contain at least one sample")
        w = torch.ones(n, dtype=torch.float64) if weights is None else _f64("weights", weights, ndim=1)
        if w.numel() != n:
            raise ValueError(f"weights has {w.numel()} entries but there are {n} points")
        if bool((w < 0).any()) or float(w.sum()) <= 0:
            raise ValueError("weights must be non-negative with a positive sum")
        self.weights = w / w.sum()
        if bandwidth is None:
            n_eff = 1.0 / float((self.weights**2).sum())
            mu = (self.weights[:, None] * self.points).sum(0)
            var = (self.weights[:, None] * (self.points - mu) ** 2).sum(0)
            std = var.sqrt().clamp_min(1e-6)
            self.bandwidth = std * n_eff ** (-1.0 / (self.dim + 4))
        else:
            bw = _f64("bandwidth", bandwidth)
            self.bandwidth = bw.expand(self.dim).clone()
            if bool((self.bandwidth <= 0).any()):
                raise ValueError("bandwidth must be positive")

    @property
    def mean(self) -> Tensor:
        return (self.weights[:, None] * self.points).sum(0)

    def _sample(self, n, generator):
        idx = torch.multinomial(self.weights, n, replacement=True, generator=generator)
        z = torch.randn(n, self.dim, dtype=torch.float64, generator=generator)
        return self.points[idx] + z * self.bandwidth

    def _log_prob(self, x):
        z = (x.unsqueeze(-2) - self.points) / self.bandwidth  # (*batch, n, dim)
        lk = -0.5 * (z * z).sum(-1) - torch.log(self.bandwidth).sum() - 0.5 * self.dim * _LOG_2PI
        return torch.logsumexp(torch.log(self.weights) + lk, dim=-1)


def paper_gaussian_mixture(
    center: Sequence[float] | Tensor,
    half_width: Sequence[float] | Tensor,
    generator: torch.Generator | None = None,
    *,
    n_components: int = 5,
    mean_std: float = 0.3,
    variance_scale: float = 5.0,
    bounds: tuple[Sequence[float] | Tensor, Sequence[float] | Tensor] | None = None,
) -> GaussianMixture:
    """The paper's default initial distribution (``docs/spec.md`` §7) around ``center``.

    ``bounds = (low, high)`` (e.g. the system's state box) cuts the truncation box further, so that no initial state
    lies outside the model (a vehicle standing still has no negative speeds in its law).

    ``n_components`` Gaussians with weights ``U(0, 1)`` (normalised), means ``center + mean_std N(0, I)`` and
    diagonal variances ``variance_scale U(0, 1)``, truncated to the box ``center +- half_width`` (the XE0 box of
    the car). The original code cut the density off at the larger XE box but drew its samples in XE0; here the
    law itself lives on XE0, so samples, weights and true initial states all come from the same distribution.
    """
    c = _f64("center", center, ndim=1)
    hw = _f64("half_width", half_width, ndim=1)
    if hw.shape != c.shape:
        raise ValueError(f"half_width must have shape {tuple(c.shape)}, got {tuple(hw.shape)}")
    d = c.numel()
    w = torch.rand(n_components, dtype=torch.float64, generator=generator)
    means = c + mean_std * torch.randn(n_components, d, dtype=torch.float64, generator=generator)
    var = variance_scale * torch.rand(n_components, d, dtype=torch.float64, generator=generator)
    low, high = c - hw, c + hw
    if bounds is not None:
        low = torch.maximum(low, _f64("bounds[0]", bounds[0], ndim=1))
        high = torch.minimum(high, _f64("bounds[1]", bounds[1], ndim=1))
        if not bool((low < high).all()):
            raise ValueError(f"the initial-error box around {c.tolist()} lies outside the bounds {bounds}: the start "
                             "is outside the model's state box")
    return GaussianMixture(w.clamp_min(1e-3), means, var.clamp_min(1e-4), low=low, high=high)

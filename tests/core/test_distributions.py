"""Initial distributions: moments of samples, normalisation of log_prob, truncation, errors."""

from __future__ import annotations

import math

import pytest
import torch

from density_planner.density.distributions import (
    Gaussian,
    GaussianMixture,
    UniformBox,
    WeightedSamples,
    paper_gaussian_mixture,
)

N = 200_000


def _grid_integral(dist, lo, hi, n=601):
    """Trapezoid integral of exp(log_prob) over the 2-D box [lo, hi]."""
    xs = torch.linspace(lo[0], hi[0], n, dtype=torch.float64)
    ys = torch.linspace(lo[1], hi[1], n, dtype=torch.float64)
    gx, gy = torch.meshgrid(xs, ys, indexing="ij")
    p = torch.exp(dist.log_prob(torch.stack([gx, gy], -1)))
    return float(torch.trapezoid(torch.trapezoid(p, ys, dim=1), xs))


def _moment_check(samples, mean, cov):
    n = samples.shape[0]
    se = (torch.diagonal(cov).sqrt() / math.sqrt(n))
    # sample mean within 5 standard errors per coordinate (false-failure probability ~1e-6)
    assert ((samples.mean(0) - mean).abs() < 5 * se).all(), (samples.mean(0), mean)
    emp = torch.cov(samples.T)
    # covariance entries: relative/absolute 3 % at n = 2e5 (standard error ~ sqrt(2/n) ~ 0.3 %)
    assert torch.allclose(emp, cov, rtol=0.03, atol=0.03 * float(torch.diagonal(cov).max())), (emp, cov)


def test_gaussian_moments_and_normalisation(gen):
    cov = torch.tensor([[1.0, 0.6], [0.6, 2.0]], dtype=torch.float64)
    d = Gaussian([0.5, -1.0], cov)
    s = d.sample(N, gen, dtype=torch.float64)
    _moment_check(s, torch.tensor([0.5, -1.0], dtype=torch.float64), cov)
    # trapezoid over +-8 sigma on a 601^2 grid: discretisation error < 1e-4
    assert abs(_grid_integral(d, (-9.0, -12.0), (10.0, 10.0)) - 1.0) < 1e-3
    # closed-form log density at the mean
    expected = -math.log(2 * math.pi) - 0.5 * math.log(float(torch.linalg.det(cov)))
    assert abs(float(d.log_prob(torch.tensor([0.5, -1.0]).double())) - expected) < 1e-12


def test_uniform_box(gen):
    d = UniformBox([-1.0, 0.0], [1.0, 4.0])
    s = d.sample(N, gen, dtype=torch.float64)
    assert (s >= d.low).all() and (s <= d.high).all()
    _moment_check(s, torch.tensor([0.0, 2.0], dtype=torch.float64),
                  torch.diag(torch.tensor([4 / 12, 16 / 12], dtype=torch.float64)))
    assert abs(_grid_integral(d, (-1.0, 0.0), (1.0, 4.0)) - 1.0) < 1e-9
    assert d.log_prob(torch.tensor([2.0, 1.0])) == -math.inf


def test_gaussian_mixture_untruncated(gen):
    w = torch.tensor([0.2, 0.8], dtype=torch.float64)
    means = torch.tensor([[-2.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    var = torch.tensor([[0.5, 1.0], [1.0, 0.3]], dtype=torch.float64)
    d = GaussianMixture(w, means, var)
    s = d.sample(N, gen, dtype=torch.float64)
    mean = (w[:, None] * means).sum(0)
    second = (w[:, None, None] * (torch.diag_embed(var) + means[:, :, None] * means[:, None, :])).sum(0)
    _moment_check(s, mean, second - mean[:, None] * mean[None, :])
    assert abs(_grid_integral(d, (-8.0, -6.0), (7.0, 7.0)) - 1.0) < 1e-3


def test_truncated_mixture_is_normalised_and_mean_is_exact(gen):
    d = GaussianMixture([1.0, 2.0], [[0.0, 0.0], [0.8, -0.5]], [[1.0, 4.0], [0.3, 0.5]],
                        low=[-1.0, -0.5], high=[1.0, 0.5])
    s = d.sample(N, gen, dtype=torch.float64)
    assert (s >= d.low).all() and (s <= d.high).all()
    # the truncated density integrates to one on its box (trapezoid error of a smooth density on 601^2 points)
    assert abs(_grid_integral(d, (-1.0, -0.5), (1.0, 0.5)) - 1.0) < 1e-4
    se = s.std(0) / math.sqrt(N)
    assert ((s.mean(0) - d.mean).abs() < 5 * se).all(), (s.mean(0), d.mean)
    assert d.log_prob(torch.tensor([1.5, 0.0])) == -math.inf


def test_weighted_samples_kde(gen):
    pts = torch.tensor([[0.0, 0.0], [2.0, 1.0], [-1.0, 3.0]], dtype=torch.float64)
    w = torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64)
    d = WeightedSamples(pts, w, bandwidth=0.4)
    s = d.sample(N, gen, dtype=torch.float64)
    mean = (w[:, None] * pts).sum(0)
    cov = (w[:, None, None] * ((pts - mean)[:, :, None] * (pts - mean)[:, None, :])).sum(0) + 0.16 * torch.eye(2)
    _moment_check(s, mean, cov.double())
    assert abs(_grid_integral(d, (-4.0, -3.0), (5.0, 6.0)) - 1.0) < 1e-3
    torch.testing.assert_close(d.mean, mean)


def test_paper_mixture_on_xe0_box(gen):
    center = torch.tensor([0.0, -28.0, 1.5, 3.0, 0.0], dtype=torch.float64)
    hw = torch.tensor([1.0, 1.0, 0.5, 0.5, math.pi / 16], dtype=torch.float64)
    d = paper_gaussian_mixture(center, hw, gen)
    assert d.weights.numel() == 5
    s = d.sample(5000, gen, dtype=torch.float64)
    assert ((s - center).abs() <= hw + 1e-12).all()
    assert torch.isfinite(d.log_prob(s)).all()
    # deterministic given the seed
    d2 = paper_gaussian_mixture(center, hw, torch.Generator().manual_seed(1234))
    torch.testing.assert_close(d2.means, d.means)


def test_samples_are_deterministic_per_seed():
    d = Gaussian([0.0], [[1.0]])
    a = d.sample(10, torch.Generator().manual_seed(5))
    b = d.sample(10, torch.Generator().manual_seed(5))
    assert torch.equal(a, b)


@pytest.mark.parametrize(
    "factory,match",
    [
        (lambda: Gaussian([0.0, 0.0], [[1.0, 2.0], [2.0, 1.0]]), "positive definite"),
        (lambda: Gaussian([0.0, float("nan")], [[1.0, 0.0], [0.0, 1.0]]), "mean"),
        (lambda: UniformBox([0.0, 1.0], [1.0, 1.0]), "high > low"),
        (lambda: GaussianMixture([1.0], [[0.0, 0.0], [1.0, 1.0]], [[1.0, 1.0], [1.0, 1.0]]), "weights"),
        (lambda: GaussianMixture([-1.0, 2.0], [[0.0], [1.0]], [[1.0], [1.0]]), "non-negative"),
        (lambda: GaussianMixture([1.0], [[0.0]], [[1.0]], low=[40.0], high=[41.0]), "no probability mass"),
        (lambda: WeightedSamples(torch.zeros(0, 2)), "at least one"),
    ],
)
def test_bad_distribution_parameters(factory, match):
    with pytest.raises(ValueError, match=match):
        factory()


def test_bad_sample_count_and_shape():
    d = UniformBox([0.0], [1.0])
    with pytest.raises(ValueError, match="number of samples"):
        d.sample(0)
    with pytest.raises(ValueError, match="x must have trailing shape"):
        d.log_prob(torch.zeros(3, 2))


def test_paper_mixture_is_cut_to_the_models_state_box():
    """A car standing still (v = 0) has no negative speeds in its initial law: the truncation box is the XE0 box cut
    by ``bounds``; inside the bounds nothing changes; a start outside the bounds is an error."""
    center, half = [0.0, 0.0, 0.3, 0.0, 0.0], [0.5, 0.5, 0.05, 0.3, 0.2]
    lo, hi = [-1e3, -1e3, -10.0, 0.0, -0.4], [1e3, 1e3, 10.0, 40.0, 0.4]
    law = paper_gaussian_mixture(center, half, torch.Generator().manual_seed(0), bounds=(lo, hi))
    low, high = law.support
    assert low[3] == 0.0 and high[3] == pytest.approx(0.3)
    x = law.sample(2000, torch.Generator().manual_seed(1), dtype=torch.float64)
    assert bool((x[:, 3] >= 0).all()) and bool((x[:, 3] <= 0.3).all())
    free = paper_gaussian_mixture(center, half, torch.Generator().manual_seed(0))
    inside = paper_gaussian_mixture([0.0, 0.0, 0.3, 5.0, 0.0], half, torch.Generator().manual_seed(0), bounds=(lo, hi))
    same = paper_gaussian_mixture([0.0, 0.0, 0.3, 5.0, 0.0], half, torch.Generator().manual_seed(0))
    assert torch.equal(inside.support[0], same.support[0]) and torch.equal(inside.support[1], same.support[1])
    assert free.support[0][3] == pytest.approx(-0.3)
    with pytest.raises(ValueError, match="outside the model's state box"):
        paper_gaussian_mixture([0.0, 0.0, 0.3, -1.0, 0.0], half, bounds=(lo, hi))


def test_conditioned_law_is_the_truncated_base(gen):
    """N(0, 1) in 2-D given x0 > 0: the half-normal mean sigma sqrt(2/pi) in x0, acceptance 1/2, density doubled on
    the event and 0 off it, every sample in it; an (almost) impossible event is refused."""
    from density_planner.density.distributions import Conditioned

    base = Gaussian([0.0, 0.0], [1.0, 1.0])
    law = Conditioned(base, lambda x: x[:, 0] > 0, description="x0 > 0", n_estimate=20000)
    se = math.sqrt(0.25 / 20000)
    assert abs(law.acceptance - 0.5) < 4 * se
    assert abs(float(law.mean[0]) - math.sqrt(2 / math.pi)) < 4 * 0.6 / math.sqrt(10000)
    x = law.sample(5000, gen, dtype=torch.float64)
    assert x.shape == (5000, 2) and bool((x[:, 0] > 0).all())
    pts = torch.tensor([[0.5, 0.1], [-0.5, 0.1]], dtype=torch.float64)
    lp = law.log_prob(pts)
    assert float(lp[0]) == pytest.approx(float(base.log_prob(pts[:1])[0]) - math.log(law.acceptance))
    assert lp[1] == -math.inf
    with pytest.raises(ValueError, match="x0 > 5 a probability of .* cannot be conditioned"):
        Conditioned(base, lambda x: x[:, 0] > 5, description="x0 > 5")


def test_rejection_sample_keeps_the_first_accepted_and_counts_the_acceptance():
    from density_planner.density.distributions import rejection_sample

    stream = iter(torch.arange(100.0).reshape(-1, 1).split(10))
    x, acc = rejection_sample(lambda k: next(stream), lambda d: d[:, 0] % 2 == 0, 12, lambda missing: 10,
                              max_rounds=5, what="even numbers")
    assert x[:, 0].tolist() == [0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0, 20.0, 22.0]
    assert acc == pytest.approx(15 / 30)  # three batches of 10 drawn, 15 accepted
    with pytest.raises(RuntimeError, match="rejection sampling of nothing did not finish: 0 of 3 in 20 draws"):
        rejection_sample(lambda k: torch.zeros(k, 1), lambda d: d[:, 0] > 0, 3, lambda missing: 10, max_rounds=2,
                         what="nothing")

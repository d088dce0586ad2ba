"""Priors in the sampler's coordinates against their stated distributions (scipy.stats)."""

from __future__ import annotations

import numpy as np
import pytest

from fitmedia.inference.params import ParameterSpace


def _marginal_cdf(space: ParameterSpace, k: int, grid: np.ndarray) -> np.ndarray:
    """CDF along coordinate k of exp(log_prior) (others fixed: the prior factorises)."""
    u0 = 0.5 * (space.lower + space.upper)
    dens = np.array([np.exp(space.log_prior(np.r_[u0[:k], x, u0[k + 1:]])) for x in grid])
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    return cdf / cdf[-1]


def test_albedo_prior_is_the_stated_mixture():
    """The albedo prior (docs/inference.md) is an equal mixture of flat in logit albedo and
    uniform in albedo on the same bounds.  Against the analytic CDF of that mixture in logit
    albedo, 0.5 (u - lo) / (hi - lo) + 0.5 (a(u) - a(lo)) / (a(hi) - a(lo)), by numerical
    integration of exp(log_prior); and the prior is flat in log kappa_t."""
    space = ParameterSpace()
    lo, hi = space.lower[1], space.upper[1]
    grid = np.linspace(lo, hi, 200001)
    cdf = _marginal_cdf(space, 1, grid)
    a = 1 / (1 + np.exp(-grid))
    ref = 0.5 * (grid - lo) / (hi - lo) + 0.5 * (a - a[0]) / (a[-1] - a[0])
    assert np.max(np.abs(cdf - ref)) < 1e-6
    # the normalisation is the prior's own (no free constant): density integrates to 1
    dens = np.exp([space.log_albedo_prior(x) for x in grid[::100]])
    assert abs(np.trapezoid(dens, grid[::100]) - 1.0) < 1e-4
    u0 = 0.5 * (space.lower + space.upper)
    lp = [space.log_prior(np.r_[x, u0[1:]]) for x in np.linspace(space.lower[0], space.upper[0], 50)]
    assert np.ptp(lp) == 0.0


def test_albedo_prior_on_a_users_range():
    """With `priors.albedo: [0.3, 0.99]` the same mixture lives on the user's bounds: the
    albedo's prior mass in [0.3, 0.6] is 0.5 x (its share in logit) + 0.5 x (its share in
    albedo), by Monte Carlo draws from the two components (accept-reject free) against the
    numerically integrated prior."""
    space = ParameterSpace(priors={"albedo": [0.3, 0.99]})
    logit = lambda p: np.log(p / (1 - p))  # noqa: E731
    lo, hi = logit(0.3), logit(0.99)
    assert np.isclose(space.lower[1], lo) and np.isclose(space.upper[1], hi)
    rng = np.random.default_rng(11)
    n = 200_000
    flat = rng.uniform(lo, hi, n)
    unif = logit(rng.uniform(0.3, 0.99, n))
    draws = np.where(rng.random(n) < 0.5, unif, flat)
    mc = np.mean((draws > logit(0.3)) & (draws < logit(0.6)))
    grid = np.linspace(lo, hi, 100001)
    cdf = _marginal_cdf(space, 1, grid)
    num = np.interp(logit(0.6), grid, cdf)
    assert abs(mc - num) < 4 * np.sqrt(num * (1 - num) / n)


def test_g_prior_is_uniform():
    """atanh g's prior density maps to a uniform g on the prior's range."""
    space = ParameterSpace(priors={"g": [-0.5, 0.99]})
    grid = np.linspace(space.lower[2], space.upper[2], 200001)
    cdf = _marginal_cdf(space, 2, grid)
    ref = (np.tanh(grid) + 0.5) / 1.49
    assert np.max(np.abs(cdf - ref)) < 1e-6


@pytest.mark.parametrize("albedo_range", [None, [0.3, 0.99]])
def test_uniform_albedo_weights_turn_the_mixture_into_its_uniform_half(albedo_range):
    """Draws from the albedo mixture (``draw_logit_albedo``) weighted by
    ``uniform_albedo_weights`` follow the mixture's uniform-in-albedo half alone: against the
    analytic uniform CDF of the albedo on the prior's bounds (default and a user's range), the
    weighted empirical CDF is within a few standard errors of a weighted sample of its
    effective size."""
    space = ParameterSpace(priors={"albedo": albedo_range} if albedo_range else None)
    rng = np.random.default_rng(5)
    u = space.draw_logit_albedo(rng, 400_000)
    w = space.uniform_albedo_weights(u)
    assert np.mean(w) == pytest.approx(1.0)
    a = 1 / (1 + np.exp(-u))
    a_lo, a_hi = (1 / (1 + np.exp(-b)) for b in (space.lower[1], space.upper[1]))
    grid = np.linspace(a_lo, a_hi, 41)[1:-1]
    cdf = np.array([np.sum(w * (a <= x)) / np.sum(w) for x in grid])
    ref = (grid - a_lo) / (a_hi - a_lo)
    ess = np.sum(w) ** 2 / np.sum(w ** 2)
    assert np.max(np.abs(cdf - ref) / np.sqrt(ref * (1 - ref) / ess)) < 4.5
    # and without the weights the draws are not uniform in the albedo (the test can fail)
    plain = np.array([np.mean(a <= x) for x in grid])
    assert np.max(np.abs(plain - ref)) > 0.1

"""Priors in the sampler's coordinates against their stated distributions (scipy.stats)."""

from __future__ import annotations

import numpy as np
from scipy import stats
from scipy.special import expit

from fitmedia.inference.params import ParameterSpace


def _marginal_cdf(space: ParameterSpace, k: int, grid: np.ndarray) -> np.ndarray:
    """CDF along coordinate k of exp(log_prior) (others fixed: the prior factorises)."""
    u0 = 0.5 * (space.lower + space.upper)
    dens = np.array([np.exp(space.log_prior(np.r_[u0[:k], x, u0[k + 1:]])) for x in grid])
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    return cdf / cdf[-1]


def test_albedo_prior_is_jeffreys_beta_half_half():
    """The density of logit albedo, mapped to the albedo, is Beta(1/2, 1/2) (scipy's CDF),
    truncated to the logit bounds [-15, 15]: the reference is independent of our formula."""
    space = ParameterSpace()
    lo, hi = space.lower[1], space.upper[1]
    grid = np.linspace(lo, hi, 200001)
    cdf = _marginal_cdf(space, 1, grid)
    beta = stats.beta(0.5, 0.5)
    ref = (beta.cdf(expit(grid)) - beta.cdf(expit(lo))) / (beta.cdf(expit(hi)) - beta.cdf(expit(lo)))
    assert np.max(np.abs(cdf - ref)) < 1e-6


def test_g_prior_is_uniform():
    """atanh g's prior density maps to a uniform g on the prior's range."""
    space = ParameterSpace(priors={"g": [-0.5, 0.99]})
    grid = np.linspace(space.lower[2], space.upper[2], 200001)
    cdf = _marginal_cdf(space, 2, grid)
    ref = (np.tanh(grid) + 0.5) / 1.49
    assert np.max(np.abs(cdf - ref)) < 1e-6


def test_albedo_prior_does_not_pile_up_at_zero_absorption():
    """The choice documented in docs/inference.md: under the prior, the mass with
    kappa_a / kappa_t below 1e-5 is ~0.2 % (Beta(1/2, 1/2)), where a flat prior in logit albedo
    on the same bounds would put (15 - logit(1 - 1e-5)) / 30 = 12 % there."""
    space = ParameterSpace()
    grid = np.linspace(space.lower[1], space.upper[1], 200001)
    cdf = _marginal_cdf(space, 1, grid)
    edge = np.log((1 - 1e-5) / 1e-5)
    tail = 1.0 - np.interp(edge, grid, cdf)
    flat_tail = (space.upper[1] - edge) / (space.upper[1] - space.lower[1])
    assert tail < 0.005 < 0.1 < flat_tail

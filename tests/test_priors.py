"""Priors in the sampler's coordinates against their stated distributions (scipy.stats)."""

from __future__ import annotations

import numpy as np
from scipy import stats

from fitmedia.inference.params import ParameterSpace


def _marginal_cdf(space: ParameterSpace, k: int, grid: np.ndarray) -> np.ndarray:
    """CDF along coordinate k of exp(log_prior) (others fixed: the prior factorises)."""
    u0 = 0.5 * (space.lower + space.upper)
    dens = np.array([np.exp(space.log_prior(np.r_[u0[:k], x, u0[k + 1:]])) for x in grid])
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens[1:] + dens[:-1]) * np.diff(grid))])
    return cdf / cdf[-1]


def test_albedo_prior_makes_kappa_a_and_kappa_s_log_uniform():
    """Flat in (log kappa_t, logit albedo) = independent log-uniform kappa_a and kappa_s
    (docs/inference.md): Monte Carlo draws from the prior, mapped to kappa_a, kappa_s, match
    scipy's loguniform inside the region where the box does not cut (KS test), and the two
    are uncorrelated there."""
    space = ParameterSpace()
    rng = np.random.default_rng(3)
    n = 400_000
    u = rng.uniform(space.lower[:2], space.upper[:2], size=(n, 2))
    lp = np.array([space.log_prior(np.r_[x, 0.5]) for x in u[:2000]])
    assert np.ptp(lp) == 0.0  # flat in these two coordinates
    kt, alb = np.exp(u[:, 0]), 1 / (1 + np.exp(-u[:, 1]))
    ks, ka = kt * alb, kt * (1 - alb)
    lo, hi = 1e-3, 1e-1  # a square in (kappa_a, kappa_s) far inside the box's image
    sel = (ka > lo) & (ka < hi) & (ks > lo) & (ks < hi)
    assert sel.sum() > 1000
    for v in (ka[sel], ks[sel]):
        assert stats.kstest(v, stats.loguniform(lo, hi).cdf).pvalue > 1e-3
    assert abs(np.corrcoef(np.log(ka[sel]), np.log(ks[sel]))[0, 1]) < 0.05


def test_g_prior_is_uniform():
    """atanh g's prior density maps to a uniform g on the prior's range."""
    space = ParameterSpace(priors={"g": [-0.5, 0.99]})
    grid = np.linspace(space.lower[2], space.upper[2], 200001)
    cdf = _marginal_cdf(space, 2, grid)
    ref = (np.tanh(grid) + 0.5) / 1.49
    assert np.max(np.abs(cdf - ref)) < 1e-6

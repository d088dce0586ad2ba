"""The round-trip grid's pass criterion (fitmedia.validate.grid_verdict) against its analytic
pass probability, for calibrated, too narrow and biased posteriors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binom, norm

from fitmedia.validate import Score, grid_verdict, is_degenerate, normal_score

N_VALUES = 45  # the grid of tests/test_roundtrip.py: 5 media x 3 channels x 3 quantities


def analytic_pass_probability(n: int, bias: float, spread: float) -> float:
    """P(a grid passes) when each of n independent values has normal score ~ N(bias, spread^2):
    no value beyond the Bonferroni limit and at most K beyond the 99 % limit, K the 99 %
    quantile of Binomial(n, 0.01).  Multinomial over the three bands |z| <= 2.576,
    2.576 < |z| <= limit, |z| > limit."""
    z_lim, z99 = norm.isf(0.01 / (2 * n)), norm.isf(0.005)

    def beyond(z):
        return norm.sf(z, bias, spread) + norm.cdf(-z, bias, spread)

    p_far, p_out = beyond(z_lim), beyond(z99)
    p_mid = p_out - p_far
    k_max = int(binom.ppf(0.99, n, 0.01))
    return float(sum(binom.pmf(k, n, p_mid / (1 - p_far)) * (1 - p_far) ** n
                     for k in range(k_max + 1)))


def simulated_grid(rng, bias: float, spread: float) -> list[Score]:
    """Scores of normal posteriors in atanh g: sd 0.05, median = truth + 0.05 * z."""
    truth = np.arctanh(0.9)
    z = bias + spread * rng.standard_normal(N_VALUES)
    medians, pits = np.tanh(truth + 0.05 * z), norm.cdf(-z)
    return [Score("m", (8.0,), "R", "g", 0.9, float(m), 0.05, float(p), None, float(e))
            for m, p, e in zip(medians, pits, z)]


@pytest.mark.parametrize("bias, spread, expected_at_least, expected_at_most", [
    (0.0, 1.0, 0.985, 1.0),        # calibrated: passes 98.9 % of grids
    (0.0, 1 / 0.7, 0.0, 0.5),      # intervals 0.7x the true spread: passes 45 %
    (0.0, 1 / 0.6, 0.0, 0.15),     # 0.6x: passes 10 %
    (1.0, 1.0, 0.0, 0.7),          # biased by one posterior sd: passes 66 %
])
def test_grid_verdict_pass_rate_matches_analytic(rng, bias, spread, expected_at_least,
                                                 expected_at_most):
    """Second model: 3000 simulated grids of 45 independent values pass at the rate the
    multinomial formula gives (within 4 binomial standard errors), and that rate is high for
    calibrated posteriors and low for narrow or biased ones.  The old criterion (every value
    inside its own 99 % interval) passes calibrated grids at 0.99^45 = 0.64 only."""
    p = analytic_pass_probability(N_VALUES, bias, spread)
    assert expected_at_least <= p <= expected_at_most, p
    n_grids = 3000
    rate = np.mean([grid_verdict(simulated_grid(rng, bias, spread)).passed
                    for _ in range(n_grids)])
    assert abs(rate - p) <= 4 * np.sqrt(p * (1 - p) / n_grids) + 1e-3, (rate, p)


def test_grid_verdict_limits_and_failures():
    """The limits for 45 values (Bonferroni z 3.692, Binomial(45, 0.01)'s 99 % quantile 3);
    one value past the limit fails the grid, as do four 99 % misses; NaN never passes; a
    score without a normal score falls back to the PIT (a truth outside every sample fails)."""
    def score(z, pit=None):
        return Score("m", (8.0,), "R", "g", 0.9, 0.9, 0.01,
                     float(norm.cdf(-z)) if pit is None else pit, None, z)

    ok = [score(0.0)] * N_VALUES
    v = grid_verdict(ok)
    assert v.passed and v.z_limit == pytest.approx(3.6923, abs=1e-4) and v.max_misses_99 == 3
    assert not grid_verdict(ok[:-1] + [score(3.70)]).passed
    assert grid_verdict(ok[:-1] + [score(-3.68)]).passed
    assert grid_verdict(ok[:-3] + [score(3.0)] * 3).passed
    assert not grid_verdict(ok[:-4] + [score(3.0)] * 4).passed
    assert not grid_verdict(ok[:-1] + [score(float("nan"), pit=0.5)]).passed
    no_normal = Score("m", (8.0,), "R", "g", 0.9, 0.9, 0.01, 0.0)  # truth below every sample
    v = grid_verdict(ok[:-1] + [no_normal])
    assert not v.passed and v.worst is no_normal


def test_normal_score_against_analytic(rng):
    """normal_score of log-normal and tanh-normal samples equals (median - truth) / sd in the
    transformed coordinate (known exactly: the samples are a transformed normal); undefined
    cases give None."""
    x = rng.standard_normal(200_000)
    kappa = np.exp(np.log(0.02) + 0.1 * x)  # log kappa ~ N(log 0.02, 0.1^2)
    assert normal_score(kappa, 0.02 * np.exp(-0.25), "kappa_t") == pytest.approx(2.5, abs=0.02)
    g = np.tanh(np.arctanh(0.9) + 0.05 * x)
    assert normal_score(g, np.tanh(np.arctanh(0.9) + 0.1), "g") == pytest.approx(-2.0, abs=0.02)
    assert normal_score(kappa, 0.0, "kappa_s") is None
    assert normal_score(np.full(10, 0.5), 0.4, "g") is None


@pytest.mark.parametrize("quantity, value", [("g", 0.5), ("g", 0.0), ("kappa_t", 0.02),
                                             ("kappa_s", 1.0)])
def test_equal_samples_have_no_normal_score(rng, quantity, value):
    """Equal samples give None however their sum rounds: exactly equal, and equal up to a
    perturbation of 1e-16 relative (np.std of such samples is ~1e-16, which an exact test
    ``sd > 0`` turned into a score of ~1e15 on some CPUs).  Independent check: samples with a
    real spread (1e-6 relative, far above rounding) keep their analytic score."""
    exact = np.full(10, value)
    assert normal_score(exact, 0.4, quantity) is None
    bumped = exact * (1.0 + 1e-16 * rng.standard_normal(10)) + 1e-300
    assert normal_score(bumped, 0.4, quantity) is None
    assert is_degenerate(exact) and is_degenerate(bumped)
    if value != 0.0:
        f = np.arctanh if quantity == "g" else np.log
        h = f(value) + 1e-6 * np.array([-1.0, 1.0] * 5)  # sd 1e-6, median f(value)
        x = np.tanh(h) if quantity == "g" else np.exp(h)
        expected = (f(value) - f(0.4)) / np.std(h)
        assert normal_score(x, 0.4, quantity) == pytest.approx(expected, rel=1e-6)
        assert not is_degenerate(x)


def test_report_gives_no_digits_to_a_rounding_width():
    """The report's table (format_estimate) shows a posterior whose 68 % width is rounding
    error (1e-16) to 3 significant digits, as it shows an exactly zero width, instead of
    12 decimals; a real width (2e-3) still sets the decimals (second case: independent, by
    hand)."""
    from fitmedia.report.html import format_estimate

    def entry(width):
        return {"map": 0.5, "median": 0.5, "q05": 0.5 - width, "q16": 0.5 - width / 2,
                "q84": 0.5 + width / 2, "q95": 0.5 + width}

    assert format_estimate(entry(0.0))["estimate"] == "0.500"
    assert format_estimate(entry(1e-16))["estimate"] == "0.500"
    assert format_estimate(entry(2e-3))["estimate"] == "0.5000"

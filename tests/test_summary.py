"""Parameter summaries (inference/summary.py) and their envelope over the albedo prior's
halves, against numpy's percentiles and against validate's coverage test of the same
intervals."""

from __future__ import annotations

import numpy as np
import pytest

from fitmedia.inference.summary import QUANTILES, summarise, weighted_percentiles
from fitmedia.validate import Score, envelope_pit


def test_weighted_percentiles_against_numpy():
    """Equal weights give numpy's (linear) percentiles exactly; integer weights agree with the
    percentiles of the samples repeated that many times to within the gap between neighbouring
    samples (the two place a repeated sample's copies differently)."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=501)
    assert np.array_equal(weighted_percentiles(x, np.ones_like(x)), np.percentile(x, QUANTILES))
    # all the weight on the largest sample (a degenerate reweighting): equal weights' positions
    spike = np.r_[np.zeros(x.size - 1), 1.0][np.argsort(np.argsort(x))]
    assert np.array_equal(weighted_percentiles(x, spike), np.percentile(x, QUANTILES))
    k = rng.integers(0, 4, size=x.size)
    ref = np.percentile(np.repeat(x, k), QUANTILES)
    gap = np.max(np.diff(np.sort(x)))
    assert np.max(np.abs(weighted_percentiles(x, k.astype(float)) - ref)) < gap


def test_envelope_never_narrows_and_holds_both_intervals():
    """With weights the 68 % and 90 % intervals are the envelope of the plain and the weighted
    ones: never narrower than the plain (the samples' own) interval; median, mean and std the
    samples' own."""
    rng = np.random.default_rng(4)
    x = rng.lognormal(size=4000)
    w = np.exp(0.8 * np.log(x))  # weights that favour the upper tail
    plain, env = summarise(x, 1.0), summarise(x, 1.0, w)
    qw = weighted_percentiles(x, w)
    for key in ("median", "mean", "std"):
        assert env[key] == plain[key]
    assert env["q05"] == plain["q05"] <= qw[0] and env["q16"] == plain["q16"] <= qw[1]
    assert env["q84"] == qw[3] > plain["q84"] and env["q95"] == qw[4] > plain["q95"]


@pytest.mark.parametrize("skew", [-0.8, 0.0, 0.8])
def test_validate_coverage_reads_the_envelope(skew):
    """``Score.inside`` with ``envelope_pit`` is true exactly where results.json's interval
    (``summarise`` with the same weights) holds the truth: over 400 truths across the
    posterior, at 68 % and 90 %, apart from truths within one sample of a bound (where the
    two quantile conventions may round differently)."""
    rng = np.random.default_rng(6)
    x = rng.normal(size=3000)
    w = np.exp(skew * x)
    summ = summarise(x, 0.0, w)
    xs = np.sort(x)
    for t in rng.uniform(-3.5, 3.5, 400):
        s = Score("m", (1.0,), "G", "kappa_t", float(t), 0.0, 1.0, float(np.mean(x < t)),
                  pit_envelope=envelope_pit(x, float(t), w))
        for level, (lo, hi) in ((0.68, ("q16", "q84")), (0.90, ("q05", "q95"))):
            near = min(abs(np.searchsorted(xs, summ[b]) - np.searchsorted(xs, t))
                       for b in (lo, hi)) <= 1
            if not near:
                assert s.inside(level) == (summ[lo] <= t <= summ[hi])

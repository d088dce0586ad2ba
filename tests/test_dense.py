"""kappa_s' = kappa_s (1 - g) and the verdict "kappa_s and g not separately measured"
(fitmedia.trust, docs/results.md "trust")."""

from __future__ import annotations

import numpy as np
import pytest

from fitmedia import trust


def test_similarity_ridge_is_not_separable(rng):
    """Samples on the similarity ridge (kappa_s (1 - g) = 1 +- 1 %, g spread over 0.3-0.95,
    as the diffusion regime allows): kappa_s' tight, kappa_s and g not separable.  Samples
    with kappa_s and g independently measured (kappa_s 10 +- 1 %, g 0.9 +- 0.005): separable,
    and kappa_s' then less well known than kappa_s."""
    n = 20000
    g = rng.uniform(0.3, 0.95, n)
    ks = np.exp(rng.normal(0, 0.01, n)) / (1 - g)
    red, ratio = trust.reduced_from_samples(ks, g, float(np.median(ks)), 0.6)
    assert ratio < 0.1 and trust.separable(ratio, False) is False
    assert red["median"] == pytest.approx(1.0, rel=0.005)
    assert red["q05"] == pytest.approx(np.exp(-1.645 * 0.01), rel=2e-3)  # lognormal quantile
    note = trust.not_separable_note("G", red)
    assert "not separately measured" in note and f"{red['median']:.4g}" in note
    g = rng.normal(0.9, 0.005, n)
    ks = 10 * np.exp(rng.normal(0, 0.01, n))
    red, ratio = trust.reduced_from_samples(ks, g, 10.0, 0.9)
    assert ratio > 1 and trust.separable(ratio, False) is True
    assert red["map"] == pytest.approx(1.0)
    assert trust.separable(ratio, True) is None  # kappa_s consistent with 0: not applicable


@pytest.mark.parametrize("corr", [0.99, 0.0])
def test_laplace_against_samples(rng, corr):
    """The linearised Laplace interval of kappa_s' (reduced_from_laplace) against samples
    drawn from the same normal in (log kappa_t, logit albedo, atanh g) and pushed through the
    exact map (reduced_from_samples): quantiles within 2 %, width ratios within 5 %; with a
    correlation of 0.99 between log kappa_t and atanh g, along the similarity ridge
    (d log kappa_t = (1 + g) d atanh g), both say not separable; without it, separable."""
    names = ["log_kappa_t", "logit_albedo", "atanh_g", "log_brightness"]
    x = np.array([np.log(12.0), 6.0, np.arctanh(0.8), 0.0])
    sd = np.array([0.144, 0.3, 0.08, 0.01])  # 0.144 = (1 + g) x 0.08: the ridge's slope
    c = np.eye(4)
    c[0, 2] = c[2, 0] = corr
    cov = c * np.outer(sd, sd)
    u = rng.multivariate_normal(x, cov, size=40000)
    albedo = 1 / (1 + np.exp(-u[:, 1]))
    ks, g = np.exp(u[:, 0]) * albedo, np.tanh(u[:, 2])
    map_ks, map_g = float(np.exp(x[0]) / (1 + np.exp(-x[1]))), float(np.tanh(x[2]))
    lap, r_lap = trust.reduced_from_laplace(x, cov, names, map_ks, map_g)
    smp, r_smp = trust.reduced_from_samples(ks, g, map_ks, map_g)
    for q in ("q05", "q16", "q84", "q95"):
        assert lap[q] == pytest.approx(smp[q], rel=0.02), q
    assert r_lap == pytest.approx(r_smp, rel=0.05)
    assert trust.separable(r_lap, False) is trust.separable(r_smp, False) is (corr == 0.0)
    assert trust.reduced_from_laplace(x, None, names, map_ks, map_g)[1] is None


def test_cli_line_prints_kappa_s_reduced_when_not_separable():
    """`fitmedia fit`'s line for a channel: kappa_s and g with their 90 % intervals when
    separable; kappa_t and kappa_s' with their intervals and the plain-words caveat, and no
    kappa_s, g or kappa_a value (kappa_a = kappa_t - kappa_s moves with g too), when not."""
    entry = {"map": 2.0, "median": 2.1, "q05": 1.0, "q95": 3.0}
    res = {"channels": ["G"],
           "parameters": {q: {"G": dict(entry)} for q in ("kappa_a", "kappa_s", "g")},
           "diagnostics": {"channels": {"G": {"kappa_s_g_separable": True}}}}
    res["parameters"]["kappa_s_reduced"] = {"G": {"map": 0.5, "median": 0.51, "q05": 0.49,
                                                  "q95": 0.53, "source": "samples"}}
    line = trust.value_line(res, "G")
    assert "kappa_s=2.1 [1, 3]" in line and "g=2.100 [1.000, 3.000]" in line
    res["diagnostics"]["channels"]["G"]["kappa_s_g_separable"] = False
    res["parameters"]["kappa_t"] = {"G": {"map": 7.0, "median": 7.1, "q05": 6.9, "q95": 7.3}}
    line = trust.value_line(res, "G")
    assert "kappa_s'=kappa_s(1-g)=0.51 (90 %: 0.49 - 0.53)" in line
    assert "kappa_t=7.1 [6.9, 7.3]" in line
    assert "not separately measured" in line and "kappa_s=" not in line and " g=" not in line
    assert "kappa_a=" not in line


def test_cli_line_prints_an_unresolved_kappa_a_as_an_upper_limit():
    """Where kappa_a is not resolved (``kappa_a_upper_limit_only``: its median is the prior's),
    `fitmedia fit`'s line gives kappa_a as its 95 % upper limit and kappa_t with its interval,
    not a median that reads like a measurement; resolved, kappa_a's median and interval."""
    res = {"channels": ["B"],
           "parameters": {"kappa_a": {"B": {"map": 0.02, "median": 1.5e-4, "q05": 4e-7,
                                            "q95": 0.066}},
                          "kappa_s": {"B": {"map": 0.74, "median": 0.742, "q05": 0.727,
                                            "q95": 0.757}},
                          "g": {"B": {"map": 0.57, "median": 0.566, "q05": 0.549, "q95": 0.583}},
                          "kappa_t": {"B": {"map": 0.77, "median": 0.745, "q05": 0.729,
                                            "q95": 0.818}}},
           "diagnostics": {"channels": {"B": {"kappa_a_upper_limit_only": True}}}}
    line = trust.value_line(res, "B")
    assert "kappa_a<0.066 (95 % upper limit; kappa_t=0.745 [0.729, 0.818])" in line
    assert "kappa_a=" not in line and "0.00015" not in line
    res["diagnostics"]["channels"]["B"]["kappa_a_upper_limit_only"] = False
    line = trust.value_line(res, "B")
    assert "kappa_a=0.00015 [4e-07, 0.066]" in line and "upper limit" not in line

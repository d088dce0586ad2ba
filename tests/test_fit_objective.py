"""What the fitter maximises: the posterior (prior x likelihood), not the likelihood.

A stub forward model whose image *is* the unconstrained parameter vector makes the
likelihood an exact Gaussian in (log kappa_t, logit albedo, atanh g) centred on the
data; the priors of docs/inference.md (flat in log kappa_t, the albedo mixture, uniform
in g) then move the posterior mode by a known amount.  The reference mode is computed
here from the priors as the docs write them (not from ``ParameterSpace``), by 1-D
minimisation per coordinate (the problem separates).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import geometry_dict
from scipy.optimize import minimize_scalar
from scipy.special import expit, logit

from fitmedia.inference.fit import FitOptions, fit_channel
from fitmedia.spec import parse_spec

N_PIX = 10           # pixels per coordinate
SIGMA2 = 2.0         # read variance: precision N_PIX / SIGMA2 = 5 per coordinate
TRUTH = np.array([np.log(5e-3), logit(0.7), np.arctanh(0.6)])  # where the data put the likelihood


class _StubModel:
    """Image rows: log kappa_t, logit albedo = log(kappa_s / kappa_a), atanh g (each N_PIX wide)."""

    channels = ("G",)
    shape = (3, N_PIX)
    support = np.ones((3, N_PIX), bool)

    def render(self, kappa_a, kappa_s, g, brightness):
        ka, ks, gg = (float(np.ravel(v)[0]) for v in (kappa_a, kappa_s, g))
        rows = [np.log(ka + ks), np.log(ks) - np.log(ka), np.arctanh(gg)]
        return np.repeat(np.array(rows)[:, None, None], N_PIX, axis=1)


def _reference_mode() -> np.ndarray:
    """Posterior mode of each coordinate: Gaussian likelihood (precision N_PIX / SIGMA2) times
    the prior density in the unconstrained coordinate (docs/inference.md): flat in log kappa_t;
    for logit albedo u on [-15, 15] the equal mixture of flat (1/30) and uniform in the albedo
    (a (1 - a) / (expit(15) - expit(-15))); uniform g on [-0.9, 0.995]: sech^2(u)."""
    prec = N_PIX / SIGMA2
    log_prior = [lambda u: 0.0,
                 lambda u: np.log(0.5 / 30 + 0.5 * expit(u) * expit(-u) / (expit(15) - expit(-15))),
                 lambda u: -2 * np.log(np.cosh(u))]
    out = []
    for k, lp in enumerate(log_prior):
        res = minimize_scalar(lambda u: 0.5 * prec * (u - TRUTH[k]) ** 2 - lp(u),
                              bracket=(TRUTH[k] - 1, TRUTH[k]), tol=1e-12)
        out.append(res.x)
    return np.array(out)


def test_fitter_maximises_the_posterior_not_the_likelihood():
    """Independent reference: the analytic posterior mode (_reference_mode).  The MAP of
    fit_channel agrees within 2e-4 in every coordinate, and the priors move the albedo and g
    coordinates away from the likelihood's maximum by more than 0.02 (so an optimizer of the
    likelihood fails this test)."""
    ref = _reference_mode()
    assert np.all(np.abs(ref[1:] - TRUTH[1:]) > 0.02), ref - TRUTH
    d = geometry_dict(width=N_PIX, height=3, light={"type": "spot", "position": [0, 0, 0],
                                                    "direction": [0, 0, 1], "cutoff_deg": 30})
    d["images"] = [{"path": "stub.tif", "exposure_s": 1.0, "concentration": 1.0}]
    spec = parse_spec(d, require_images=False)
    data = [_StubModel().render(np.exp(TRUTH[0]) * expit(-TRUTH[1]),
                                np.exp(TRUTH[0]) * expit(TRUTH[1]), np.tanh(TRUTH[2]), 1.0)[..., 0]]
    np.testing.assert_allclose(data[0][:, 0], TRUTH, rtol=1e-12)
    # the stub as a forward model of one's own: fitted as it is (no multiple-scattering term
    # is traced with it; since stop 25 a spot's would be, as a bulb's)
    out = fit_channel(spec, "G", data, [np.ones((3, N_PIX), bool)], 1.0, None, (0.0, SIGMA2),
                      FitOptions(mcmc=False, progress=False, global_evals=200),
                      forward=lambda *a, **k: _StubModel())
    np.testing.assert_allclose(out["x_map"], ref, rtol=0, atol=2e-4)
    assert out["map"]["g"] == pytest.approx(np.tanh(ref[2]), abs=2e-4)


def test_parameter_vector_maps_to_the_physical_values():
    """Definitions (docs/inference.md), written out here: kappa_t = e^u0, albedo = 1 / (1 +
    e^-u1), kappa_s = kappa_t albedo, kappa_a = kappa_t (1 - albedo), g = tanh u2, brightness
    e^u3; its prior normal in u3 around the calibration (sd = the relative error): one sd away
    costs 1/2 in log density."""
    from fitmedia.inference.params import ParameterSpace

    space = ParameterSpace(free_brightness=True, brightness_guess=2.0, brightness_rel_sd=0.1)
    u = np.array([[np.log(0.02), 1.3, 0.7, np.log(2.5)], [np.log(5.0), -2.0, -0.4, np.log(1.9)]])
    kt, alb = np.exp(u[:, 0]), 1 / (1 + np.exp(-u[:, 1]))
    ref = {"kappa_t": kt, "albedo": alb, "kappa_s": kt * alb, "kappa_a": kt * (1 - alb),
           "g": np.tanh(u[:, 2]), "brightness": np.exp(u[:, 3])}
    phys = space.physical_samples(u)
    for q, v in ref.items():
        np.testing.assert_allclose(phys[q], v, rtol=1e-12, err_msg=q)
    p = space.to_params(u[0])
    np.testing.assert_allclose([p.kappa_t, p.albedo, p.kappa_s, p.kappa_a, p.g, p.brightness],
                               [ref[q][0] for q in ("kappa_t", "albedo", "kappa_s", "kappa_a",
                                                    "g", "brightness")], rtol=1e-12)
    np.testing.assert_allclose(space.to_vector(p), u[0], rtol=1e-12)
    at = np.array([np.log(0.02), 1.3, 0.7, np.log(2.0)])
    off = at + np.array([0, 0, 0, 0.1])
    assert space.log_prior(off) - space.log_prior(at) == pytest.approx(-0.5, rel=1e-12)


def test_gaussian_log_likelihood_is_the_normal_density():
    """Independent reference: scipy's normal log density with the noise model's variance at the
    model (gain * model + read_var), summed over the pixels, equals the problem's Gaussian log
    likelihood up to the constant N log(2 pi) / 2 -- at two parameter points, so that a term
    dropped from the variance's normalisation shows."""
    from scipy.stats import norm

    from fitmedia.inference.likelihood import ChannelProblem, Observation
    from fitmedia.inference.params import ParameterSpace

    stub = _StubModel()
    rng = np.random.default_rng(3)
    data = 1.0 + rng.random((3, N_PIX))
    gain, read = 0.3, 0.05
    problem = ChannelProblem([Observation(stub, data, np.ones((3, N_PIX), bool), 1.0)],
                             ParameterSpace(), 1.0, (gain, read))
    for u in (np.array([np.log(5.0), 1.3, 0.7]), np.array([np.log(3.0), 0.4, 1.1])):
        kt, alb = np.exp(u[0]), 1 / (1 + np.exp(-u[1]))
        m = stub.render(kt * (1 - alb), kt * alb, np.tanh(u[2]), 1.0)[..., 0]
        assert np.all(m > 0)
        ref = norm.logpdf(data, m, np.sqrt(gain * m + read)).sum() + 0.5 * m.size * np.log(2 * np.pi)
        assert problem.log_likelihood(u) == pytest.approx(ref, rel=1e-12, abs=1e-9)

"""The term's Monte Carlo variance in the residuals (inference/likelihood.py:
``ChannelProblem.log_likelihood``; forward/multiple.py: ``FullTransport.render_with_variance``).

A model with a Monte Carlo part adds, on average, its variance s^2(u) to every squared
residual; where s^2 depends on the parameters, the plain likelihood prefers the parameters at
which the model is least noisy.  The likelihood takes that excess out (relative to the local
model's refresh point).  Tested against independent computations: the excess's formula
against numpy's covariances of the same batches, and the bias it removes on a stub model whose
exact term is known (a synthetic round trip over many realisations of the noise).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import make_spec
from fitmedia.forward.multiple import FullTransport
from fitmedia.forward.single import SingleScattering
from fitmedia.inference.likelihood import ChannelProblem, Observation
from fitmedia.inference.params import ChannelParams, ParameterSpace


@pytest.mark.parametrize("bin", [1, 2, 4])
def test_excess_is_the_terms_variance_and_its_covariance_with_each_step(rng, bin):
    """``ms_part(excess=True)`` against numpy: at a point (dk, dg) from the refresh point, the
    variance of the mean of the batches' term plus twice its covariance with each finite
    difference times its step (the finite differences' own variance left out), at the camera's
    pixels: each batch's images interpolated there first (numpy's covariances of those).  At
    bin 1 at the refresh point it is the variance ``ms_part`` states.  Mutants caught: the
    factor 2 on the covariances, the finite differences' variance included, the variance
    interpolated instead of the batches (at bin 2)."""
    spec = make_spec(width=8 * bin, height=6 * bin)
    ft = FullTransport(spec, None, channels=("G",), bin=bin, n_paths=16, batches=16)
    n, orders, npix = 16, 5, 48
    base = rng.gamma(2.0, 1.0, (n, orders, npix))
    d_kt = 0.5 * base + rng.normal(0.0, 0.3, base.shape)  # correlated with the term, as photons
    d_g = -0.2 * base + rng.normal(0.0, 0.3, base.shape)
    kt, g, albedo = 0.02, 0.8, 0.9
    ft._local = [{"kt": kt, "eta": math.atanh(g), "batches": base, "d_kt": d_kt, "d_g": d_g}]
    dk, dg = 0.1, -0.05
    kt1, g1 = kt * math.exp(dk), math.tanh(math.atanh(g) + dg)
    img, var, exc = ft.ms_part([kt1 * (1 - albedo)], [kt1 * albedo], [g1], [1.0], excess=True)
    pw = albedo ** np.arange(orders)
    pw[0] = 0.0
    # the values' upsampler (bilinear sharpened at bin 2), dense: independent of the sparse code
    up = ft.ms._up_mean.toarray() * ft.ms._cover[:, None]  # (H*W, h*w)
    t, d1, d2 = (np.tensordot(x, pw, axes=([1], [0])) @ up.T for x in (base, d_kt, d_g))
    want = np.array([np.var(t[:, i], ddof=1) + 2 * dk * np.cov(t[:, i], d1[:, i])[0, 1]
                     + 2 * dg * np.cov(t[:, i], d2[:, i])[0, 1] for i in range(t.shape[1])]) / n
    np.testing.assert_allclose(exc[..., 0].ravel(), want, rtol=1e-9, atol=1e-15)
    _, var0, exc0 = ft.ms_part([kt * (1 - albedo)], [kt * albedo], [g], [1.0], excess=True)
    if bin == 1:
        np.testing.assert_allclose(exc0, var0, rtol=1e-9, atol=1e-15)


class NoisyStub:
    """A full-transport stand-in whose term has a known exact value and a Monte Carlo error of
    known size: 0.8 x albedo x the analytic order-1 glow, times (1 + the mean of ``batches``
    fixed per-pixel relative errors), so that its variance grows with the term (as the real
    term's grows with the albedo).  ``corrected``: it offers ``render_with_variance``, and the
    likelihood takes the excess out; else the plain likelihood."""

    def __init__(self, single: SingleScattering, noise: np.ndarray, corrected: bool):
        self.single, self.shape, self.support = single, single.shape, single.support
        self.channels, self.noise = single.channels, noise
        self.ms = type("Ms", (), {"bin": 1})()
        self._var0 = None
        if corrected:
            self.render_with_variance = self._render_with_variance

    def exact(self, kappa_a, kappa_s, g, brightness):
        ka, ks = np.asarray(kappa_a, float), np.asarray(kappa_s, float)
        glow = self.single.render(ka, ks, g, brightness) - \
            self.single.render(ka + ks, np.zeros_like(ks), g, brightness)
        return 0.8 * (ks / (ka + ks)) * glow

    def refresh(self, kappa_a, kappa_s, g, brightness=None) -> None:
        self._var0 = self.ms_part(kappa_a, kappa_s, g, 1.0 if brightness is None else brightness)[1]

    def ms_part(self, kappa_a, kappa_s, g, brightness):
        t = self.exact(kappa_a, kappa_s, g, brightness)[..., 0]
        per = t[None] * (1.0 + self.noise)
        mean, var = per.mean(axis=0), per.var(axis=0, ddof=1) / len(per)
        return mean[..., None], var[..., None]

    def render(self, kappa_a, kappa_s, g, brightness):
        return self.single.render(kappa_a, kappa_s, g, brightness) + \
            self.ms_part(kappa_a, kappa_s, g, brightness)[0]

    def _render_with_variance(self, kappa_a, kappa_s, g, brightness):
        img, var = self.ms_part(kappa_a, kappa_s, g, brightness)
        return self.single.render(kappa_a, kappa_s, g, brightness) + img, var - self._var0


def test_corrected_likelihood_is_unbiased_for_the_exact_terms():
    """A synthetic check against the exact term: on a 32 x 24 G capture rendered with the
    stub's exact term (camera noise of constant variance), the change of the log likelihood
    from the truth to a point with half the albedo (so a term half as large, with a quarter of
    its Monte Carlo variance), averaged over 200 realisations of the term's error (16 batches,
    100 % relative error per batch and pixel: 25 % per pixel), against the same change with
    the exact term.
    The plain likelihood is off by about half the drop of sum s^2 / var (it prefers the less
    noisy point by that much, more than 5 standard errors of the mean); with the excess taken
    out it agrees within 3 standard errors.  Both with the same variance in the likelihood."""
    spec = make_spec(width=32, height=24)
    ka, ks, g, b = 0.0004, 0.012, 0.85, 1.0
    single = SingleScattering(spec, None, channels=("G",))
    single.freeze_nodes([ka + ks], [g])
    exact = NoisyStub(single, np.zeros((2, 24, 32)), False)
    clean = exact.render([ka], [ks], [g], [b])[..., 0]
    data = clean + np.random.default_rng(3).normal(0.0, np.sqrt(2e-5 * clean.max()), clean.shape)
    noise = (0.0, 2e-5 * float(clean.max()))  # constant variance: log var does not move
    space = ParameterSpace(free_brightness=False, brightness_guess=b)
    kt = ka + ks
    truth = space.to_vector(ChannelParams(kt, ks / kt, g, None))
    half = space.to_vector(ChannelParams(kt, 0.5 * ks / kt, g, None))

    def change(model, model_var=None) -> tuple[float, np.ndarray]:
        problem = ChannelProblem([Observation(model, data, single.support, 1.0)], space, b, noise)
        problem.refresh_models(truth)
        if model_var is not None:  # the exact term, with the noisy one's variance in ``var``
            problem._model_var[0] = model_var
        return problem.log_likelihood(half) - problem.log_likelihood(truth), problem._model_var[0]

    got = {False: [], True: []}
    for r in range(200):
        err = np.random.default_rng([7, r]).normal(0.0, 1.0, (16, 24, 32))
        for corrected in (False, True):
            value, model_var = change(NoisyStub(single, err, corrected))
            got[corrected].append(value - change(exact, model_var)[0])
    se = {c: np.std(v, ddof=1) / math.sqrt(len(v)) for c, v in got.items()}
    off = {c: np.mean(v) for c, v in got.items()}
    print(f"plain off by {off[False]:+.3f} +- {se[False]:.3f}; corrected "
          f"off by {off[True]:+.3f} +- {se[True]:.3f}")
    assert off[False] > 5 * se[False]
    assert abs(off[True]) < 3 * se[True]

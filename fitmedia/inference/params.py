"""Named parameters of one colour channel, their unconstrained coordinates and priors.

Per channel the sampler sees

* ``log_kappa_t``: log of the undiluted liquid's extinction (1/mm),
* ``logit_albedo``: logit of the single-scattering albedo, well conditioned at
  0.9999 (milk) where it equals ~ -log(1 - albedo) = -log(kappa_a / kappa_t),
* ``atanh_g``: atanh of the HG anisotropy,
* ``log_brightness`` (only when the light's brightness is not calibrated).

Priors (docs/inference.md): log-uniform in kappa_t; for the albedo an equal mixture
of flat in logit albedo (with log-uniform kappa_t, the same as independent
log-uniform kappa_a and kappa_s: right for liquids that hardly absorb, milk) and
uniform in the albedo (right for absorbing liquids whose kappa_a a thin dilution
does not resolve), both on the same bounds (ALBEDO_UNIFORM_WEIGHT); uniform in g on
[G_MIN, G_MAX]; the brightness either normal in log around the clear-water
calibration (with the calibration's standard error) or log-uniform.  Flat vectors exist only at
the optimizer / sampler boundary.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import expit, logit

LOG_KT_BOUNDS = (np.log(1e-5), np.log(1e3))  # undiluted kappa_t, 1/mm
LOGIT_ALBEDO_BOUNDS = (-15.0, 15.0)
G_MIN, G_MAX = -0.9, 0.995
ATANH_G_BOUNDS = (float(np.arctanh(G_MIN)), float(np.arctanh(G_MAX)))
#: weight of the uniform-in-albedo component of the albedo prior (the rest is flat in logit)
ALBEDO_UNIFORM_WEIGHT = 0.5
LOG_BRIGHTNESS_SPAN = 12.0  # +-12 e-folds around the initial guess


@dataclass(frozen=True)
class ChannelParams:
    """Physical values of one channel (undiluted liquid), 1/mm."""

    kappa_t: float
    albedo: float
    g: float
    brightness: float | None = None
    background: float = 0.0  # additive offset, image units

    @property
    def kappa_s(self) -> float:
        return self.kappa_t * self.albedo

    @property
    def kappa_a(self) -> float:
        return self.kappa_t * (1.0 - self.albedo)


class ParameterSpace:
    """Maps between :class:`ChannelParams` and the flat unconstrained vector."""

    def __init__(self, *, free_brightness: bool = False, brightness_guess: float = 1.0,
                 brightness_rel_sd: float | None = None, background_sd: float | None = None,
                 priors: dict | None = None):
        """``free_brightness``: the brightness is a parameter; with ``brightness_rel_sd`` its
        prior is normal in log brightness around ``brightness_guess`` (a calibration with that
        relative standard error), else log-uniform within +-12 e-folds of the guess.
        ``background_sd``: add a background offset (image units) with a normal prior of that
        standard deviation.  ``priors``: the spec's `priors` (ranges of kappa_t in 1/mm for the
        undiluted liquid, of the albedo and of g) replacing the default bounds."""
        priors = priors or {}
        self.free_brightness = free_brightness
        self.names = ["log_kappa_t", "logit_albedo", "atanh_g"]
        kt = priors.get("kappa_t")
        alb = priors.get("albedo")
        g = priors.get("g")
        self.g_range = (float(g[0]), float(g[1])) if g else (G_MIN, G_MAX)
        bounds = [(np.log(kt[0]), np.log(kt[1])) if kt else LOG_KT_BOUNDS,
                  (float(logit(alb[0])), float(logit(alb[1]))) if alb else LOGIT_ALBEDO_BOUNDS,
                  (float(np.arctanh(self.g_range[0])), float(np.arctanh(self.g_range[1])))]
        self.log_b0 = float(np.log(brightness_guess))
        self.b_sd = brightness_rel_sd
        if free_brightness:
            c = self.log_b0
            span = LOG_BRIGHTNESS_SPAN if brightness_rel_sd is None else 10 * brightness_rel_sd
            self.names.append("log_brightness")
            bounds.append((c - span, c + span))
        self.background_sd = background_sd
        if background_sd is not None:
            self.names.append("background")
            bounds.append((-10 * background_sd, 10 * background_sd))
        self.lower = np.array([b[0] for b in bounds])
        self.upper = np.array([b[1] for b in bounds])
        lo, hi = self.lower[1], self.upper[1]
        # albedo mixture, density in logit albedo u: w a (1 - a) / (a(hi) - a(lo)) from the
        # uniform-in-albedo part (da/du = a (1 - a)), (1 - w) / (hi - lo) from the flat part
        self._alb_flat = (1.0 - ALBEDO_UNIFORM_WEIGHT) / (hi - lo)
        self._alb_unif = ALBEDO_UNIFORM_WEIGHT / (expit(hi) - expit(lo))

    @property
    def ndim(self) -> int:
        return len(self.names)

    def to_params(self, u: np.ndarray) -> ChannelParams:
        b = float(np.exp(u[3])) if self.free_brightness else None
        bg = float(u[-1]) if self.background_sd is not None else 0.0
        return ChannelParams(float(np.exp(u[0])), float(expit(u[1])), float(np.tanh(u[2])), b, bg)

    def to_vector(self, p: ChannelParams) -> np.ndarray:
        u = [np.log(p.kappa_t), logit(np.clip(p.albedo, 1e-12, 1 - 1e-12)), np.arctanh(p.g)]
        if self.free_brightness:
            u.append(np.log(p.brightness))
        if self.background_sd is not None:
            u.append(p.background)
        return np.clip(np.array(u, float), self.lower, self.upper)

    def log_prior(self, u: np.ndarray) -> float:
        if np.any(u < self.lower) or np.any(u > self.upper) or not np.all(np.isfinite(u)):
            return -np.inf
        lp = self.log_albedo_prior(u[1])
        # uniform in g: density in atanh g is 1 - tanh^2 = sech^2
        lp -= 2.0 * np.log(np.cosh(u[2]))
        if self.free_brightness and self.b_sd is not None:
            lp -= 0.5 * ((u[3] - self.log_b0) / self.b_sd) ** 2
        if self.background_sd is not None:
            lp -= 0.5 * (u[-1] / self.background_sd) ** 2
        return float(lp)

    def log_albedo_prior(self, u1):
        """log density (normalised on the bounds) of the albedo prior in logit albedo."""
        a = expit(u1)
        return np.log(self._alb_flat + self._alb_unif * a * (1.0 - a))

    def uniform_albedo_weights(self, u1) -> np.ndarray:
        """Importance weights that turn samples drawn under the albedo mixture
        (:meth:`log_albedo_prior`) into samples under its uniform-in-albedo half alone (flat in
        kappa_a at a given kappa_t): that half's density over the mixture's, at logit albedo
        ``u1``; normalised to mean 1 over ``u1``."""
        a = expit(np.asarray(u1, float))
        unif = self._alb_unif * a * (1.0 - a)
        w = unif / (self._alb_flat + unif)
        mean = float(np.mean(w)) if w.size else 0.0
        return w / mean if mean > 0 else w

    def draw_logit_albedo(self, random, n: int) -> np.ndarray:
        """``n`` draws of logit albedo from its prior (the mixture of :meth:`log_albedo_prior`)
        with ``random`` (a numpy RandomState or Generator)."""
        lo, hi = self.lower[1], self.upper[1]
        flat = random.uniform(lo, hi, n)
        unif = logit(random.uniform(expit(lo), expit(hi), n))
        return np.clip(np.where(random.uniform(0.0, 1.0, n) < ALBEDO_UNIFORM_WEIGHT, unif, flat),
                       lo, hi)

    def physical_samples(self, u: np.ndarray) -> dict[str, np.ndarray]:
        """Samples (..., ndim) -> dict of physical arrays (1/mm)."""
        kt = np.exp(u[..., 0])
        alb = expit(u[..., 1])
        out = {"kappa_t": kt, "albedo": alb, "g": np.tanh(u[..., 2]),
               "kappa_s": kt * alb, "kappa_a": kt * expit(-u[..., 1])}
        if self.free_brightness:
            out["brightness"] = np.exp(u[..., 3])
        if self.background_sd is not None:
            out["background"] = u[..., -1]
        return out

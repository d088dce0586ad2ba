"""The log-posterior of one colour channel: the one function that both the
nlopt optimizer and the emcee sampler call.

Noise model (CAPTURE_SPEC.md): variance = gain * mean + read_var, in the units
of the exposure-normalised images, evaluated at the model's mean; per pixel where the
images give it (brackets, subtracted darks, binned RAW: ``LoadedImage.variance_maps``).
The read variance is floored at the data's quantisation variance (step^2 / 12; for float
data the type's spacing at the largest value), so that a read variance of 0 never makes
a zero-valued pixel's weight infinite (docs/spec.md, "Noise").  Saturated,
masked and out-of-tank pixels are excluded; the count of excluded pixels is
reported.  Optionally a Student-t likelihood (nu = 4) for outliers.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from ..forward.base import ForwardModel
from .params import ParameterSpace

STUDENT_NU = 4.0
#: ``ChannelProblem.tabulated``: the table's box spans the first of these many Laplace sd
#: either side of the MAP in log kappa_t and atanh g whose table passes the check below (a
#: Gaussian posterior's walkers stay within 8 sd but for ~1e-15; renders outside the box are
#: computed, not interpolated) ...
TABLE_REACH_SD = (16.0, 8.0, 4.0)
#: ... and the tables are used only where the log likelihood they give differs from the
#: computed one by less than this at every test point (the box's corners, edges' midpoints
#: and centre, and the points halfway to them, where the interpolation errs most): the
#: posterior density is then right to 1 % wherever the sampler goes
TABLE_LOGL_TOL = 0.01
#: the test points' offsets from the MAP, in units of the box's half-width, per axis
TABLE_TEST_T = (-1.0, -0.5, 0.0, 0.5, 1.0)
#: ``ChannelProblem._term_box``: the values of logit albedo, evenly across the box, at which
#: the term's tables are checked (each at 5 points in log kappa_t and atanh g)
TERM_TEST_POINTS = 9


@dataclass
class Observation:
    """One image of one channel.

    model : forward model for this image, built for this one channel
    data : (H, W) exposure-normalised image
    valid : (H, W) bool, pixels used
    concentration : the image's concentration (the medium's values scale with it)
    gain, read_var : (H, W) per-pixel noise model, optional (else the problem's own)
    """

    model: ForwardModel
    data: np.ndarray
    valid: np.ndarray
    concentration: float
    gain: np.ndarray | None = None
    read_var: np.ndarray | None = None

    def __post_init__(self):
        self.flat_idx = np.flatnonzero(self.valid.ravel())
        self.values = self.data.ravel()[self.flat_idx]
        if not np.all(np.isfinite(self.values)):
            raise ValueError("non-finite data in valid pixels")  # images.io masks these
        pick = (lambda a: None if a is None else
                np.broadcast_to(np.asarray(a, float), self.data.shape).ravel()[self.flat_idx])
        self.gain_v, self.read_v = pick(self.gain), pick(self.read_var)


def quantisation_var(values: np.ndarray) -> float:
    """The read-variance floor of data with no known step: the float64 spacing at the
    largest absolute value, squared, over 12 (positive even for all-zero data)."""
    top = float(np.max(np.abs(values))) if np.size(values) else 0.0
    return max(float(np.spacing(top)) ** 2 / 12.0, np.finfo(float).tiny)


@dataclass
class TableUse:
    """What ``ChannelProblem.tabulated`` did: the largest log-likelihood difference at its
    test points (None: no tables, every image computed) and the tables themselves."""

    logl_error: float | None
    tables: list
    #: the same for the multiple-scattering term's tables (``ms_table.TermTable``)
    term_logl_error: float | None = None
    term_tables: list = field(default_factory=list)

    @property
    def share(self) -> float | None:
        """The share of the renders since the tables were built that they served (None:
        no tables, or no renders)."""
        return _share(self.tables)

    @property
    def term_share(self) -> float | None:
        """``share`` for the term's tables."""
        return _share(self.term_tables)


def _can_tabulate_term(model) -> bool:
    """Whether ``model`` can tabulate its multiple-scattering term now
    (``FullTransport.can_tabulate_term``; False for a model without one)."""
    return bool(getattr(model, "can_tabulate_term", lambda: False)())


def _share(tables: list) -> float | None:
    n = sum(t.used + t.outside for t in tables)
    return sum(t.used for t in tables) / n if n else None


class ChannelProblem:
    """Posterior of one channel's parameters given its observations.

    Parameters
    ----------
    observations : list of Observation
    space : ParameterSpace
    brightness : float or None
        The light's calibrated brightness; None when it is a free parameter.
    noise : (gain, read_var)
        Used for observations without per-pixel maps; read_var floored (module docstring).
    robust : bool
        Student-t (nu = 4) instead of Gaussian residuals.
    water_kappa_a : float
        Absorption of the clear water itself (1/mm), added at every concentration.
    """

    def __init__(self, observations: list[Observation], space: ParameterSpace,
                 brightness: float | None, noise: tuple[float, float], *, robust: bool = False,
                 water_kappa_a: float = 0.0):
        if brightness is None and not space.free_brightness:
            raise ValueError("brightness must be given or free")
        self.obs = observations
        self.space = space
        self.brightness = brightness
        self.gain, self.read_var = noise
        self.robust = robust
        self.water_kappa_a = float(water_kappa_a)  # clear water's own absorption, 1/mm (fixed)
        self.n_pixels = int(sum(len(o.values) for o in observations))
        self._noise = []  # per observation: (gain, read variance) per used pixel, floored
        for o in observations:
            g = o.gain_v if o.gain_v is not None else np.full(len(o.values), float(self.gain))
            r = o.read_v if o.read_v is not None else np.full(len(o.values), float(self.read_var))
            self._noise.append((g, np.maximum(r, quantisation_var(o.values))))
        # per observation: the forward model's own (Monte Carlo) variance per used pixel,
        # set by refresh_models (0 for the analytic model)
        self._model_var: list[np.ndarray | float] = [0.0] * len(observations)

    def variance(self, k: int, m: np.ndarray) -> np.ndarray:
        """Noise variance of observation ``k``'s used pixels at model values ``m``."""
        g, r = self._noise[k]
        return g * np.maximum(m, 0.0) + r + self._model_var[k]

    @contextmanager
    def models_kept(self):
        """Within the block the observations' forward models may be replaced and refreshed;
        afterwards (also after an error) every observation has its model back, with the local
        model it had (a full-transport model's ``_local``, which ``refresh`` replaces) and the
        Monte Carlo variance that model had (``seed_shift``: a second realisation of the term;
        the sampler of a second mode of g, refreshed there)."""
        models, var = [o.model for o in self.obs], list(self._model_var)
        local = [(getattr(m, "_local", None), getattr(m, "_var0", None)) for m in models]
        try:
            yield self
        finally:
            for o, m, (loc, var0) in zip(self.obs, models, local):
                o.model = m
                if hasattr(m, "_local"):
                    m._local, m._var0 = loc, var0
            self._model_var = var

    @contextmanager
    def tabulated(self, x: np.ndarray, cov: np.ndarray | None):
        """Within the block every observation's analytic image (single scattering, or a full
        model's analytic part) is interpolated from a table over a box of ``TABLE_REACH_SD``
        Laplace sd (``cov``) around ``x`` in log kappa_t and atanh g
        (``SingleScattering.tabulate``), where the log likelihood it gives is within
        ``TABLE_LOGL_TOL`` of the computed one at every test point; else, or without a
        covariance, frozen quadrature or one-channel models, nothing changes.  For the
        sampler, which evaluates the posterior 10^4-10^5 times within a few sd of the MAP
        (measured: docs/inference.md, "The sampler's table").  Yields the largest
        log-likelihood difference found at the test points and the share of renders the
        tables served (:class:`TableUse`)."""
        models = [getattr(o.model, "single", o.model) for o in self.obs]
        use = TableUse(None, [])
        x = np.asarray(x, float)
        try:
            use.logl_error = self._tabulate(models, x, cov)
            use.tables = [m._table for m in models if getattr(m, "_table", None) is not None]
            use.term_logl_error = self._tabulate_terms(x, cov, TABLE_LOGL_TOL - (
                use.logl_error or 0.0))
            use.term_tables = [o.model._term_table for o in self.obs
                               if getattr(o.model, "_term_table", None) is not None]
            yield use
        finally:
            for m in models:
                if hasattr(m, "untabulate"):
                    m.untabulate()
            self._untabulate_terms()

    def _tabulate(self, models: list, x: np.ndarray, cov: np.ndarray | None) -> float | None:
        """``tabulated``'s tables, built and checked; the largest difference, or None."""
        ok = all(hasattr(m, "tabulate") and len(m.channels) == 1 and m._frozen is not None
                 for m in models)
        if not ok or cov is None or not np.all(np.isfinite(np.diag(cov))):
            return None
        for reach in TABLE_REACH_SD:
            worst = self._tabulate_box(models, x, reach * np.sqrt(np.diag(cov)[[0, 2]]))
            if worst is not None:
                return worst
        return None

    def _tabulate_box(self, models: list, x: np.ndarray, half: np.ndarray) -> float | None:
        """Tables over ``x`` +- ``half`` in (log kappa_t, atanh g), kept where they pass
        ``tabulated``'s check: the largest log-likelihood difference, or None."""
        lo = np.maximum(x[[0, 2]] - half, self.space.lower[[0, 2]])
        hi = np.minimum(x[[0, 2]] + half, self.space.upper[[0, 2]])
        if not np.all(hi > lo):
            return None
        tests = []
        for tu in TABLE_TEST_T:
            for tv in TABLE_TEST_T:
                u = x.copy()
                u[[0, 2]] = 0.5 * (lo + hi) + 0.5 * (hi - lo) * np.array([tu, tv])
                tests.append(u)
        exact = [self.log_likelihood(u) for u in tests]
        for o, m in zip(self.obs, models):
            kt = [o.concentration * np.exp(e) + self.water_kappa_a for e in (lo[0], hi[0])]
            m.tabulate((np.log(kt[0]), np.log(kt[1])), (lo[1], hi[1]))
        worst = max(abs(self.log_likelihood(u) - e) for u, e in zip(tests, exact))
        if not worst < TABLE_LOGL_TOL:  # (NaN too)
            for m in models:
                m.untabulate()
            return None
        return float(worst)

    def _tabulate_terms(self, x: np.ndarray, cov: np.ndarray | None, tol: float
                        ) -> float | None:
        """``tabulated``'s tables of the full-transport models' terms (``tabulate_term``),
        over the albedos of a box of ``TABLE_REACH_SD`` Laplace sd around ``x`` (the first
        that passes), kept where the log likelihood they give is within ``tol`` of the one
        computed without them at every test point (``_term_box``); the largest difference,
        or None (no tables)."""
        if not any(_can_tabulate_term(o.model) for o in self.obs):
            return None
        if cov is None or not np.all(np.isfinite(np.diag(cov))) or not tol > 0:
            return None
        for reach in TABLE_REACH_SD:
            worst = self._term_box(x, reach * np.sqrt(np.diag(cov)), tol)
            if worst is not None:
                return worst
        return None

    def _term_box(self, x: np.ndarray, half: np.ndarray, tol: float) -> float | None:
        """Term tables for the albedos of ``x`` +- ``half`` (every coordinate, within the
        bounds), kept where they pass ``_tabulate_terms``'s check at the test points:
        ``TERM_TEST_POINTS`` values of logit albedo across the box, each at the box's centre
        and corners in (log kappa_t, atanh g), the other coordinates at ``x`` (the steps in
        log kappa_t and atanh g enter the term exactly; the albedo is interpolated).
        The largest log-likelihood difference, or None."""
        lo, hi = np.maximum(x - half, self.space.lower), np.minimum(x + half, self.space.upper)
        if not hi[1] > lo[1]:
            return None
        tests = []
        for ta in np.linspace(lo[1], hi[1], TERM_TEST_POINTS):
            for tu, tv in ((0, 0), (-1, -1), (-1, 1), (1, -1), (1, 1)):
                u = x.copy()
                u[1] = ta
                for i, t in ((0, tu), (2, tv)):
                    u[i] = 0.5 * (lo[i] + hi[i]) + 0.5 * t * (hi[i] - lo[i])
                tests.append(u)
        exact = [self.log_likelihood(u) for u in tests]
        corners = []
        for e0 in (lo[0], hi[0]):
            for e1 in (lo[1], hi[1]):
                u = x.copy()
                u[0], u[1] = e0, e1
                corners.append(self._medium(u)[0])
        built = 0
        for k, o in enumerate(self.obs):
            if not _can_tabulate_term(o.model):  # no term, no local model, a spot's term
                continue
            albedo = [ks / (ka + ks) if ka + ks > 0 else 0.0
                      for ka, ks, _, _ in (c[k] for c in corners)]
            try:
                o.model.tabulate_term((min(albedo), max(albedo)))
                built += 1
            except ValueError:  # an empty albedo interval
                continue
        if not built:
            return None
        worst = max(abs(self.log_likelihood(u) - e) for u, e in zip(tests, exact))
        if not worst < tol:  # (NaN too)
            self._untabulate_terms()
            return None
        return float(worst)

    def _untabulate_terms(self) -> None:
        for o in self.obs:
            if hasattr(o.model, "untabulate_term"):
                o.model.untabulate_term()

    def refresh_models(self, u: np.ndarray) -> None:
        """Rebuild the local model of every Monte Carlo forward model (``refresh``, as
        :class:`fitmedia.forward.multiple.FullTransport` has) at the parameters ``u``, and
        take its Monte Carlo variance there into the likelihood.  That variance is inflated by
        the camera pixels per traced sample pixel (``bin**2``): they share one error, which
        independent per-pixel variances would count that many times (inference/full.py)."""
        args, _ = self._medium(u)
        for k, (o, medium) in enumerate(zip(self.obs, args)):
            refresh = getattr(o.model, "refresh", None)
            if refresh is None:
                continue
            refresh(*medium)
            _, var = o.model.ms_part(*medium)
            self._model_var[k] = var[..., 0].ravel()[o.flat_idx] * o.model.ms.bin ** 2

    def adapt(self, u: np.ndarray) -> None:
        """Tune the forward models' quadrature to the parameters ``u`` (and keep it fixed).

        Models without this ability (Monte Carlo) are left alone.
        """
        p = self.space.to_params(u)
        for o in self.obs:
            # a full-transport model's quadrature is that of its analytic part
            freeze = getattr(getattr(o.model, "single", o.model), "freeze_nodes", None)
            if freeze is not None:
                freeze(o.concentration * p.kappa_t + self.water_kappa_a, p.g)

    def _medium(self, u: np.ndarray):
        """Per observation, its forward model's arguments (kappa_a, kappa_s, g, brightness) at
        ``u``; and the background."""
        p = self.space.to_params(u)
        b = p.brightness if self.space.free_brightness else self.brightness
        return [(o.concentration * p.kappa_a + self.water_kappa_a, o.concentration * p.kappa_s,
                 p.g, b) for o in self.obs], p.background

    def render(self, u: np.ndarray) -> list[np.ndarray]:
        """Model images (H, W) for the parameter vector ``u``."""
        args, background = self._medium(u)
        return [o.model.render(*a)[..., 0] + background for o, a in zip(self.obs, args)]

    def _images(self, u: np.ndarray) -> list[tuple[np.ndarray, np.ndarray | None]]:
        """Per observation: its used pixels' model values and, for a model with a Monte Carlo
        part (``render_with_variance``), how much that part's variance at ``u`` exceeds its
        variance at the local model's refresh point (else None)."""
        args, background = self._medium(u)
        out = []
        for o, a in zip(self.obs, args):
            with_var = getattr(o.model, "render_with_variance", None)
            img, mc = with_var(*a) if with_var is not None else (o.model.render(*a), None)
            out.append((img[..., 0].ravel()[o.flat_idx] + background,
                        None if mc is None else mc[..., 0].ravel()[o.flat_idx]))
        return out

    def log_likelihood(self, u: np.ndarray) -> float:
        """Gaussian (or, ``robust``, Student-t) log likelihood of the images at ``u``.

        Where a model's Monte Carlo part has variance s^2(u) per pixel, its realisation adds
        s^2(u) to every squared residual on average, and s^2 grows with the albedo (the
        higher orders) and moves with kappa_t and g: the plain likelihood would prefer the
        parameters at which the model is least noisy (measured: kappa_t 10 % low and the
        albedo pulled off its plateau, for milk at 256 paths per sample pixel; docs/
        inference.md, "The term's variance in the residuals").  The Gaussian likelihood
        therefore adds back sum (s^2(u) - s^2(u0)) / var, the batches' estimate of that
        excess relative to the refresh point u0 (``render_with_variance``): the slope of its
        expectation over the realisations is that of the likelihood with the exact term, and
        at u0 it is the plain likelihood, so that values at different refresh points compare
        as before (a noisier point gains nothing); the model caps it per pixel
        (``render_with_variance``)."""
        total = 0.0
        for k, (o, (m, mc)) in enumerate(zip(self.obs, self._images(u))):
            var = self.variance(k, m)
            r2 = (o.values - m) ** 2 / var
            if self.robust:
                total += float(np.sum(-0.5 * (STUDENT_NU + 1) * np.log1p(r2 / STUDENT_NU)
                                      - 0.5 * np.log(var)))
            else:
                excess = 0.0 if mc is None else float(np.sum(mc / var))
                total += float(-0.5 * (np.sum(r2 + np.log(var)) - excess))
        return total

    def log_posterior(self, u: np.ndarray) -> float:
        """log prior + log likelihood (up to a constant); -inf outside the bounds."""
        u = np.asarray(u, float)
        lp = self.space.log_prior(u)
        if not np.isfinite(lp):
            return -np.inf
        ll = self.log_likelihood(u)
        return lp + ll if np.isfinite(ll) else -np.inf

    __call__ = log_posterior

    def chi2_images(self, u: np.ndarray) -> list[tuple[float, int]]:
        """Per image: sum of squared standardised residuals and the number of pixels."""
        out = []
        for k, (o, img) in enumerate(zip(self.obs, self.render(u))):
            m = img.ravel()[o.flat_idx]
            out.append((float(np.sum((o.values - m) ** 2 / self.variance(k, m))), len(m)))
        return out

    def variance_images(self, u: np.ndarray) -> list[np.ndarray]:
        """Per image (H, W): the likelihood's variance at the model for ``u`` (camera noise per
        pixel plus the forward model's Monte Carlo variance); NaN at pixels the fit does not use."""
        out = []
        for k, (o, img) in enumerate(zip(self.obs, self.render(u))):
            v = np.full(img.size, np.nan)
            v[o.flat_idx] = self.variance(k, img.ravel()[o.flat_idx])
            out.append(v.reshape(img.shape))
        return out

    def chi2(self, u: np.ndarray) -> tuple[float, int]:
        """Sum of squared standardised residuals over all images and the number of pixels."""
        per = self.chi2_images(u)
        return sum(c for c, _ in per), sum(n for _, n in per)

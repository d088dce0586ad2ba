"""Estimating the camera's Poisson-Gaussian noise from one smooth image.

The model (CAPTURE_SPEC.md, ``noise``) is ``variance = gain * value + read_var``
in the units of the exposure-normalised images (file units per second).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter
from scipy.optimize import nnls

from ..errors import InputError
from ..spec import ImageEntry
from ..util import make_rng
from .io import LoadedImage, linearise, read_frame

#: Fewest usable pixel samples :func:`estimate_noise` accepts.
MIN_SAMPLES = 1000
_MAD_TO_SIGMA = 1.4826
# the residual 2 (N + S + E + W) - (NE + NW + SE + SW) - 4 x vanishes for any quadratic signal
# (x - mean of 4 neighbours leaves a glow's curvature in); for white noise its variance is
# (4 * 4 + 4 * 1 + 16) var(x) = 36 var(x)
_RESIDUAL_GAIN = 36.0
#: a bin's variance is that of its residuals within CLIP_SIGMAS (MAD) sigmas of the median:
#: relative error sqrt(2 / n) (the MAD's own is sqrt(5.4 / n)); a normal distribution cut at
#: +-4 sigma keeps this fraction of its variance
CLIP_SIGMAS = 4.0
_CLIP_VAR_KEPT = 0.99893
_CLIPPED_VAR_FACTOR = 2.0
#: side of the box (pixels) whose mean is a pixel's signal level in :func:`fit_noise`
LEVEL_BOX = 5
#: a bin further than this many sampling errors from the fit is dropped (:func:`_fit_bins`)
OUTLIER_Z = 4.0
#: a bin whose highest level is over this many times its lowest (> 0) is not used: the top
#: bin of a tank image spans the bulb's edge, 4e-4 to 0.5, and its mean (0.01) fits no pixel
WIDE_BIN = 4.0


def _shifted(a: np.ndarray, di: int, dj: int) -> np.ndarray:
    """The interior ``a[1:-1, 1:-1]`` moved by (di, dj) pixels."""
    h, w = a.shape[:2]
    return a[1 + di:h - 1 + di, 1 + dj:w - 1 + dj]


def estimate_noise(data: np.ndarray, valid: np.ndarray, *,
                   rng: np.random.Generator | int | None = None, n_bins: int = 30,
                   max_samples: int = 500_000) -> tuple[float, float]:
    """(gain, read_var) of :func:`fit_noise` (which see)."""
    fit = fit_noise(data, valid, rng=rng, n_bins=n_bins, max_samples=max_samples)
    return fit.gain, fit.read_var


def fit_noise(data: np.ndarray, valid: np.ndarray, *,
              rng: np.random.Generator | int | None = None, n_bins: int = 30,
              max_samples: int = 500_000, dark: tuple[float, int] | None = None) -> "NoiseFit":
    """Fit ``variance = gain * value + read_var`` to the noise of one image.

    Assumes the signal is smooth, i.e. locally quadratic over 3x3 pixels, as the
    tank images are except at edges and the bulb, and that the noise of
    neighbouring pixels is independent (demosaicing or denoising correlates it
    and biases the estimate low).  For each interior pixel the residual
    ``r = 2 (N + S + E + W) - (NE + NW + SE + SW) - 4 x`` removes any quadratic
    signal and has variance ``36 var(x)``.  Samples are binned by their level
    (a ``LEVEL_BOX`` x ``LEVEL_BOX`` mean over valid pixels; a 3x3 mean is so
    noisy that it sorts read-noise pixels by their noise) into ``n_bins``
    equally populated bins; bins spanning levels over ``WIDE_BIN`` apart are
    not used.  A bin's variance is that of its residuals within ``CLIP_SIGMAS``
    robust sigmas of the median, over 36.  ``gain`` and ``read_var`` (both
    >= 0) follow by non-negative least squares over the bins, weighted by the
    inverse model variance and the bins' sampling errors (sqrt(2 / n)); bins
    more than ``OUTLIER_Z`` errors off are dropped one at a time.  Standard
    errors from the weighted fit, scaled by its reduced chi^2 when above 1
    (over 24 synthetic tank images, 240x180: the gain's 0.85x its scatter, the read
    variance's 1.06x).
    The image must span a range of signal levels for gain and read_var to be
    told apart.

    Parameters
    ----------
    data : ndarray of shape (H, W, C) or (H, W)
        Exposure-normalised image, any units; channels are pooled.
    valid : ndarray of bool, same shape as ``data``
        False for pixels to ignore (saturated, masked).
    rng : numpy.random.Generator or int, optional
        Used only to draw ``max_samples`` samples when there are more.
    n_bins : int
        Number of signal-level bins.
    max_samples : int
        Largest number of pixel samples used.
    dark : (float, int), optional
        A read variance measured on a dark frame (in the units of ``data`` squared) and
        its number of samples: one more bin at level 0, weighed by its sampling error.

    Returns
    -------
    NoiseFit
        ``gain`` in units of ``data`` (variance per unit value), ``read_var`` in units
        of ``data`` squared, their standard errors and the range of levels seen.

    Raises
    ------
    InputError
        Mismatched shapes, or fewer than ``MIN_SAMPLES`` samples (pixel and
        channel pairs) whose pixel and 8 neighbours are valid and finite.
    """
    r, m = _residuals(data, valid, rng, max_samples)
    return _fit_bins(r, m, n_bins, dark)


def read_variance(data: np.ndarray, valid: np.ndarray, *,
                  rng: np.random.Generator | int | None = None) -> tuple[float, int]:
    """The noise variance of a flat image (a dark frame): the clipped variance of the
    residuals of :func:`fit_noise` over 36, which remove a smooth offset but not
    pixel-to-pixel fixed pattern (it counts as noise here)."""
    r, _m = _residuals(data, valid, rng, 500_000)
    med = np.median(r)
    r = r[np.abs(r - med) <= CLIP_SIGMAS * _MAD_TO_SIGMA * np.median(np.abs(r - med))]
    return float(np.var(r)) / _CLIP_VAR_KEPT / _RESIDUAL_GAIN, int(r.size)


def _residuals(data: np.ndarray, valid: np.ndarray, rng, max_samples: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """Residuals (:func:`fit_noise`) and levels at usable pixels."""
    x = np.asarray(data, dtype=float)
    v = np.asarray(valid, dtype=bool)
    if x.shape != v.shape or x.ndim not in (2, 3):
        raise InputError(f"estimate_noise: data {x.shape} and valid {v.shape} must have the same "
                         "shape (H, W) or (H, W, C)")
    if x.ndim == 2:
        x, v = x[..., None], v[..., None]
    v = v & np.isfinite(x)
    x = np.where(v, x, 0.0)
    cross = [(-1, 0), (1, 0), (0, -1), (0, 1)]
    diag = [(-1, -1), (-1, 1), (1, -1), (1, 1)]
    ok = _shifted(v, 0, 0).copy()
    for d in cross + diag:
        ok &= _shifted(v, *d)
    n = int(np.count_nonzero(ok))
    if n < MIN_SAMPLES:
        raise InputError(f"estimate_noise: only {n} usable pixel samples (a valid pixel with 8 "
                         f"valid neighbours); at least {MIN_SAMPLES} are needed")
    resid = (2.0 * sum(_shifted(x, *d) for d in cross) - sum(_shifted(x, *d) for d in diag)
             - 4.0 * _shifted(x, 0, 0))
    # the level: a LEVEL_BOX x LEVEL_BOX mean over valid pixels; a 3x3 mean is so noisy that
    # binning by it sorts read-noise pixels by their noise (a 160x120 tank image: gain 0.6x)
    wsum = uniform_filter(v.astype(float), size=(LEVEL_BOX, LEVEL_BOX, 1), mode="constant")
    xsum = uniform_filter(x, size=(LEVEL_BOX, LEVEL_BOX, 1), mode="constant")
    local = _shifted(xsum / np.maximum(wsum, 1e-12), 0, 0)
    r, m = resid[ok], local[ok]
    if n > max_samples:
        pick = make_rng(rng).choice(n, size=max_samples, replace=False)
        r, m = r[pick], m[pick]
    return r, m


@dataclass(frozen=True)
class NoiseFit:
    """``variance = gain * value + read_var`` fitted to an image, with standard errors.

    ``gain_se`` and ``read_se`` come from the bins' sampling errors (a clipped variance of
    n samples has relative error sqrt(2 / n)), scaled up by the fit's reduced chi^2 when
    above 1.  ``level_lo`` and ``level_hi`` are the lowest and highest bins' mean values.
    """

    gain: float
    read_var: float
    gain_se: float
    read_se: float
    level_lo: float
    level_hi: float


def _fit_bins(r: np.ndarray, m: np.ndarray, n_bins: int,
              dark: tuple[float, int] | None) -> NoiseFit:
    """Bin residuals ``r`` by level ``m`` and fit the linear variance model to the bins;
    ``dark`` (a read variance and its number of samples) is one more bin at level 0.

    Bins that disagree with the fit by more than ``OUTLIER_Z`` of their sampling errors
    (levels blurred across the tank's edges, or a top bin spanning the bulb's edge) are
    dropped one at a time, the worst first, at most a third of them."""
    order = np.argsort(m, kind="stable")
    means, variances, counts = [], [], []
    for idx in np.array_split(order, max(2, min(int(n_bins), m.size // 30))):
        lo, hi = m[idx[0]], m[idx[-1]]
        if 0 < lo and hi > WIDE_BIN * lo:  # its mean level stands for none of its pixels
            continue
        rb = r[idx]
        med = np.median(rb)
        sigma = _MAD_TO_SIGMA * np.median(np.abs(rb - med))
        rb = rb[np.abs(rb - med) <= CLIP_SIGMAS * sigma]  # outliers (edges, hot pixels) out
        means.append(m[idx].mean())
        variances.append(float(np.var(rb)) / _CLIP_VAR_KEPT / _RESIDUAL_GAIN)
        counts.append(idx.size)
    if dark is not None:
        means.append(0.0)
        variances.append(dark[0])
        counts.append(dark[1])
    if len(means) < 3:
        raise InputError("estimate_noise: the image's levels are too spread out to bin (fewer "
                         "than 3 bins of similar level)")
    y, rel = np.asarray(variances), np.sqrt(_CLIPPED_VAR_FACTOR / np.asarray(counts))
    a = np.column_stack([means, np.ones(len(means))])
    tiny = max(float(np.abs(y).max()), 1e-300) * 1e-6
    keep = np.ones(len(y), bool)
    while True:
        coef, sd = _weighted_fit(a[keep], y[keep], rel[keep], tiny)
        z = np.abs(y - a @ coef) / np.maximum(a @ coef, tiny) / rel
        z[~keep] = 0.0
        if z.max() <= OUTLIER_Z or np.count_nonzero(~keep) >= len(y) // 3:
            break
        keep[int(np.argmax(z))] = False
    aw = a[keep] / sd[:, None]
    cov = np.linalg.pinv(aw.T @ aw)
    chi2 = float(np.sum(((y[keep] - a[keep] @ coef) / sd) ** 2)) / max(
        np.count_nonzero(keep) - a.shape[1], 1)
    se = np.sqrt(np.diag(cov) * max(chi2, 1.0))
    means = np.asarray(means)[keep]
    return NoiseFit(float(coef[0]), float(coef[1]), float(se[0]), float(se[1]),
                    float(means.min()), float(means.max()))


def _weighted_fit(a: np.ndarray, y: np.ndarray, rel: np.ndarray, tiny: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Non-negative least squares of ``y`` on ``a`` weighted by the inverse model variance
    times the bins' relative errors ``rel`` (two passes); the coefficients and the bins'
    standard errors at the fit."""
    weight = 1.0 / (np.maximum(np.abs(y), tiny) * rel)
    for _ in range(2):
        coef, _res = nnls(a * weight[:, None], y * weight)
        model = np.maximum(a @ coef, tiny)
        weight = 1.0 / (model * rel)
    return coef, model * rel


#: A noise parameter that may carry at least this share of the variance at some level seen
#: in the image (its estimate plus two standard errors) must be determined ...
NEEDED_SHARE = 0.1
#: ... to this relative standard error (a 10 % error is then 3 standard errors), else the
#: estimate is refused
NOISE_REL_SE = 0.033


@dataclass(frozen=True)
class SensorNoise:
    """The camera's noise for one image entry: ``variance = a * signal + b`` for one stored
    sample of one frame, in file units (DN) and DN^2, per channel R, G, B (NaN for channels
    not used), and where it comes from."""

    a: np.ndarray
    b: np.ndarray
    source: str


def spec_sensor_noise(gain: float, read_var: float, exposure_s: float | None,
                      entry: ImageEntry, where: str) -> SensorNoise:
    """The spec's ``noise`` block (normalised units at ``exposure_s``, by default the entry's
    own single exposure) as the noise of one stored sample in file units.

    Raises
    ------
    InputError
        A bracket of different exposures and no ``noise.exposure_s``.
    """
    if exposure_s is None:
        if len(set(entry.exposures)) > 1:
            raise InputError(f"noise: {where} is an exposure bracket; add noise.exposure_s (the "
                             "exposure at which gain and read_var hold) so that each frame's "
                             "variance follows from its own exposure")
        exposure_s = entry.exposures[0]
    return SensorNoise(np.full(3, gain * exposure_s), np.full(3, read_var * exposure_s ** 2),
                       "spec")


def estimate_sensor_noise(img: LoadedImage, entry: ImageEntry, channels: tuple[int, ...],
                          where: str, *, rng: int = 0) -> SensorNoise:
    """The camera's noise estimated from one loaded image entry, per channel.

    The fit (:func:`fit_noise`) uses the pixels merged from the most common set of frames
    (same summed exposure T and reads N), where the variance of the normalised image is
    ``a / (n T) * value + N b / (n T^2)`` (``LoadedImage.variance_maps``).  With a dark
    frame, its own noise variance (:func:`read_variance`) is one more bin at level 0.  A
    flat field's division is undone first (the noise is the sensor's).

    Raises
    ------
    InputError
        Too few usable pixels, or a parameter that matters (``NEEDED_SHARE``) determined
        worse than ``NOISE_REL_SE``: asks for a ``noise`` block or a dark frame.
    """
    a, b = np.full(3, np.nan), np.full(3, np.nan)
    dark = None
    if entry.darks:
        dark = linearise(read_frame(entry.darks[0]), entry.response, entry.darks[0],
                         entry.response_curve).data
    for ci in channels:
        ch = "RGB"[ci]
        t_map, n_map, v = img.exposure[..., ci], img.reads[..., ci], img.valid[..., ci]
        pairs, counts = np.unique(np.stack([t_map[v], n_map[v]]), axis=1, return_counts=True)
        if counts.size == 0:
            raise InputError(f"{where}: no usable pixels in channel {ch} to estimate the noise "
                             "from; give a `noise` block (gain, read_var)")
        t, nr = pairs[:, int(np.argmax(counts))]
        n = float(img.samples[ci])
        known = None  # the dark frame's read variance in the image's units, and its samples
        if dark is not None:
            b_dark, n_dark = read_variance(dark[..., ci], np.ones(dark.shape[:2], bool), rng=rng)
            known = (nr * max(b_dark * n, img.quant_var) / (n * t * t), n_dark)
        signal = img.data[..., ci] * (1.0 if img.flat is None else img.flat[..., ci])
        try:
            fit = fit_noise(signal, v & (t_map == t) & (n_map == nr), rng=rng,
                            dark=known)
        except InputError as exc:
            raise InputError(f"{where}: the noise cannot be estimated in channel {ch} ({exc}); "
                             "give a `noise` block (gain, read_var) or a dark frame") from None
        top = float(np.max(signal[v]))  # the brightest pixel the fit will weigh
        _check_support(fit, where, ch, max(top, fit.level_hi))
        a[ci], b[ci] = fit.gain * n * t, fit.read_var * n * t * t / nr
    src = "estimated from this image" + ("" if dark is None else
                                         f" and its dark frame {entry.darks[0].name}")
    return SensorNoise(a, b, src)


def _check_support(fit: NoiseFit, where: str, ch: str, top: float) -> None:
    """Refuse a fit whose parameters that matter, at any level from the fit's lowest to the
    image's brightest ``top`` (the bulb: levels the bins may not reach), are not determined
    well enough."""
    var_hi = fit.gain * max(top, 0.0) + fit.read_var
    var_lo = fit.gain * max(fit.level_lo, 0.0) + fit.read_var
    checks = [("gain", fit.gain, fit.gain_se,
               (fit.gain + 2 * fit.gain_se) * max(top, 0.0) >= NEEDED_SHARE * var_hi)]
    checks.append(("read variance", fit.read_var, fit.read_se,
                   fit.read_var + 2 * fit.read_se >= NEEDED_SHARE * var_lo))
    for name, val, se, needed in checks:
        if needed and not se <= NOISE_REL_SE * val:
            rel = f"{100 * se / val:.0f} %" if val > 0 else "all of it"
            raise InputError(f"{where}: the data cannot support a noise estimate in channel {ch}: "
                             f"the {name} is {val:.3g} +- {se:.2g} (standard error {rel}, more "
                             f"than {100 * NOISE_REL_SE:.1f} %); give a `noise` block (gain, "
                             "read_var) or a dark frame (`dark`)")


def noise_summary(noise: SensorNoise, img: LoadedImage, maps: tuple[np.ndarray, np.ndarray],
                  channels: tuple[int, ...]) -> dict:
    """results.json's record of one entry's noise: its source and, per channel, the camera's
    ``gain_file_units`` / ``read_var_file_units2`` (one stored sample of one frame) and the
    median over usable pixels of the per-pixel ``gain`` / ``read_var`` of the exposure-
    normalised image (exact for a single frame without a dark)."""
    per = {}
    for ci in channels:
        v = img.valid[..., ci]
        per["RGB"[ci]] = {
            "gain_file_units": float(noise.a[ci]), "read_var_file_units2": float(noise.b[ci]),
            "gain": float(np.median(maps[0][..., ci][v])) if v.any() else None,
            "read_var": float(np.median(maps[1][..., ci][v])) if v.any() else None}
    return {"source": noise.source, "per_channel": per}


def entry_noise(spec_noise: tuple[float, float] | None, noise_exposure: float | None,
                entry: ImageEntry, img: LoadedImage, channels: tuple[int, ...], where: str,
                fallback: tuple[str, SensorNoise] | None = None) -> SensorNoise:
    """One entry's camera noise: from the spec's ``noise`` block when given, else estimated
    from the entry itself; where that is refused and ``fallback`` (another entry's name and
    noise, same camera) is given, that one.  The clear-water photo uses the first image as
    fallback: it shows the bulb on black, with no range of levels to tell the gain from."""
    if spec_noise is not None:
        return spec_sensor_noise(*spec_noise, noise_exposure, entry, where)
    try:  # a binned image's noise from its pixels before binning (independent, more of them)
        return estimate_sensor_noise(img.unbinned or img, entry, channels, where)
    except InputError as exc:
        if fallback is None:
            raise
        name, other = fallback
        return SensorNoise(other.a, other.b, f"the camera noise of {name} (its own estimate "
                                             f"was refused: {str(exc).split(': ', 1)[1]})")

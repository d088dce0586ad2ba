"""Estimating the camera's Poisson-Gaussian noise from one smooth image.

The model (CAPTURE_SPEC.md, ``noise``) is ``variance = gain * value + read_var``
in the units of the exposure-normalised images (file units per second).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import nnls

from ..errors import InputError
from ..util import make_rng

#: Fewest usable pixel samples :func:`estimate_noise` accepts.
MIN_SAMPLES = 1000
_MAD_TO_SIGMA = 1.4826
_RESIDUAL_GAIN = 1.25  # var(x - mean of 4 neighbours) = (1 + 4/16) var(x) for white noise


def _shifted(a: np.ndarray, di: int, dj: int) -> np.ndarray:
    """The interior ``a[1:-1, 1:-1]`` moved by (di, dj) pixels."""
    h, w = a.shape[:2]
    return a[1 + di:h - 1 + di, 1 + dj:w - 1 + dj]


def estimate_noise(data: np.ndarray, valid: np.ndarray, *,
                   rng: np.random.Generator | int | None = None, n_bins: int = 30,
                   max_samples: int = 500_000) -> tuple[float, float]:
    """Fit ``variance = gain * value + read_var`` to the noise of one image.

    Assumes the signal is smooth, i.e. locally linear over 3x3 pixels, as the
    tank images are except near a bright light, and that the noise of
    neighbouring pixels is independent (demosaicing or denoising correlates it
    and biases the estimate low).  For each interior pixel the residual
    ``r = x - mean(4 neighbours)`` removes a locally linear signal and has
    variance ``1.25 * var(x)``.  Samples are binned by their local mean (3x3
    box over valid pixels) into ``n_bins`` equally populated bins; the
    variance of each bin is ``(1.4826 * MAD(r))**2 / 1.25``, robust to the few
    pixels where the signal is not smooth.  ``gain`` and ``read_var`` (both
    >= 0) follow by non-negative least squares over the bins, weighted by the
    inverse model variance (relative errors), in two passes.  The image must
    span a range of signal levels for gain and read_var to be told apart.

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

    Returns
    -------
    gain : float
        In units of ``data`` (variance per unit value).
    read_var : float
        In units of ``data`` squared.

    Raises
    ------
    InputError
        Mismatched shapes, or fewer than ``MIN_SAMPLES`` samples (pixel and
        channel pairs) whose pixel and 4 neighbours are valid and finite.
    """
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
    ok = _shifted(v, 0, 0).copy()
    for d in cross:
        ok &= _shifted(v, *d)
    n = int(np.count_nonzero(ok))
    if n < MIN_SAMPLES:
        raise InputError(f"estimate_noise: only {n} usable pixel samples (a valid pixel with 4 "
                         f"valid neighbours); at least {MIN_SAMPLES} are needed")
    resid = _shifted(x, 0, 0) - 0.25 * sum(_shifted(x, *d) for d in cross)
    box = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1)]
    wsum = sum(_shifted(v, *d).astype(float) for d in box)
    local = sum(_shifted(x, *d) for d in box) / np.maximum(wsum, 1.0)
    r, m = resid[ok], local[ok]
    if n > max_samples:
        pick = make_rng(rng).choice(n, size=max_samples, replace=False)
        r, m = r[pick], m[pick]
    order = np.argsort(m, kind="stable")
    means, variances = [], []
    for idx in np.array_split(order, max(2, min(int(n_bins), m.size // 30))):
        rb = r[idx]
        mad = np.median(np.abs(rb - np.median(rb)))
        means.append(m[idx].mean())
        variances.append((_MAD_TO_SIGMA * mad) ** 2 / _RESIDUAL_GAIN)
    a = np.column_stack([means, np.ones(len(means))])
    y = np.asarray(variances)
    tiny = max(float(y.max()), 1e-300) * 1e-6
    weight = 1.0 / np.maximum(y, tiny)
    for _ in range(2):
        coef, _res = nnls(a * weight[:, None], y * weight)
        weight = 1.0 / np.maximum(a @ coef, tiny)
    return float(coef[0]), float(coef[1])

"""A parameter's summary in results.json (``map``, ``median``, ``mean``, ``std``, ``q05``,
``q16``, ``q84``, ``q95``) from posterior samples, and its intervals' envelope over the albedo
prior's halves (docs/inference.md, "The intervals: an envelope over the albedo prior's
halves")."""

from __future__ import annotations

import numpy as np

#: the quantiles results.json gives, percent
QUANTILES = (5, 16, 50, 84, 95)


def kish_ess(w: np.ndarray) -> float:
    """Kish's effective sample size of importance weights ``w``: (sum w)^2 / sum w^2."""
    w = np.asarray(w, float)
    return float(w.sum() ** 2 / np.sum(w ** 2))


def _weighted_positions(x: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The samples ``x`` sorted, and each one's position in (0, 1) with importance weights
    ``w``: the weight of those below it over the weight of all but the largest, so that equal
    weights give numpy's (linear) percentile positions k / (n - 1)."""
    x, w = np.asarray(x, float), np.asarray(w, float)
    i = np.argsort(x, kind="stable")
    below = np.r_[0.0, np.cumsum(w[i])[:-1]]
    if not below[-1] > 0:  # no weight below the largest sample: equal weights instead
        below = np.arange(x.size, dtype=float)
    return x[i], below / below[-1]


def weighted_percentiles(x: np.ndarray, w: np.ndarray, pct=QUANTILES) -> np.ndarray:
    """Percentiles ``pct`` of samples ``x`` with importance weights ``w``
    (:func:`_weighted_positions`; equal weights give numpy's ``percentile`` exactly)."""
    if np.size(x) < 2:
        return np.full(len(pct), np.ravel(x)[0] if np.size(x) else np.nan)
    xs, pos = _weighted_positions(x, w)
    return np.interp(np.asarray(pct, float) / 100.0, pos, xs)


def weighted_cdf(x: np.ndarray, w: np.ndarray, t: float) -> float:
    """The inverse of :func:`weighted_percentiles`: the position of ``t`` among the weighted
    samples, 0 below the smallest and 1 above the largest."""
    if np.size(x) < 2:
        return float(np.mean(np.asarray(x) < t))
    xs, pos = _weighted_positions(x, w)
    return float(np.interp(t, xs, pos, left=0.0, right=1.0))


def summarise(samples: np.ndarray | None, map_value: float,
              weights: np.ndarray | None = None) -> dict:
    """A parameter's summary: ``map``; with ``samples`` their median, mean, std and the
    bounds of the central 68 % and 90 % intervals.  With ``weights`` (the albedo prior's
    uniform half, :meth:`ParameterSpace.uniform_albedo_weights`) each interval is the
    envelope of the samples' own and the reweighted samples' (docs/inference.md, "The
    intervals: an envelope over the albedo prior's halves"); median, mean and std stay the
    samples' own."""
    out = {"map": float(map_value)}
    if samples is not None and len(samples):
        q = np.percentile(samples, QUANTILES)
        if weights is not None:
            qw = weighted_percentiles(samples, weights)
            q = np.r_[np.minimum(q[:2], qw[:2]), q[2], np.maximum(q[3:], qw[3:])]
        out.update(median=float(q[2]), mean=float(np.mean(samples)), std=float(np.std(samples)),
                   q05=float(q[0]), q16=float(q[1]), q84=float(q[3]), q95=float(q[4]))
    return out

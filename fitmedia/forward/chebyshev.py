"""Chebyshev points and barycentric Lagrange weights, shared by the sampler's tables: the
analytic image's (``single._ImageTable``, in log kappa_t and atanh g) and the
multiple-scattering term's (``ms_table.TermTable``, in the albedo).

Interpolation at the n Chebyshev points of the first kind is exact for polynomials of degree
below n, and for a smooth function its error falls geometrically with n (Trefethen,
Approximation Theory and Approximation Practice, ch. 5 and 8).
"""

from __future__ import annotations

import numpy as np


def chebyshev_points(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The n Chebyshev points of the first kind in (-1, 1) and their barycentric weights."""
    j = np.arange(int(n))
    return np.cos(np.pi * (j + 0.5) / n), (-1.0) ** j * np.sin(np.pi * (j + 0.5) / n)


def lagrange_weights(x: np.ndarray, w: np.ndarray, t: float) -> np.ndarray:
    """The weights that interpolate values at the points ``x`` (barycentric weights ``w``)
    to ``t`` (in the points' interval): sum 1, exact at the points."""
    d = t - x
    at = np.flatnonzero(d == 0.0)
    if len(at):
        out = np.zeros(len(x))
        out[at[0]] = 1.0
        return out
    q = w / d
    return q / q.sum()

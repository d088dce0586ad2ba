"""The sampler's table of the multiple-scattering term (``FullTransport.tabulate_term``).

Between refreshes a full-transport model's term comes from its local model: per order k,
per batch b of paths and per sample pixel, the images at the refresh point and their
finite differences in log kappa_t and atanh g (``FullTransport``).  At albedo a and steps
h = (1, dlog kappa_t, d atanh g) the term's image is the upsampled batch mean of

    per_b = sum_s h_s sum_k a^k X[k, s, b],

and the likelihood's excess variance (``FullTransport.ms_part``, ``excess``) is
Q(dev_0, dev_0 + 2 h_1 dev_1 + 2 h_2 dev_2) / (n (n - 1)), with dev_s the batches'
deviations from their mean of sum_k a^k X[k, s, b], Q the upsampled pair products
(``MultipleScattering.upsampled_products``, bilinear) and n the batches.  Both are exact in
h; a posterior evaluation formed them from the whole local model (K x 3 x batches x sample
pixels) every time: 5.6 of its 6.5 ms at 200 x 150 px (cProfile of the bench's channel R,
docs/inference.md, "The term's table").  Here

* the mean is exact: the batch means of every order and part are kept (smoothed, as the
  term is), and the image is one product of K x 3 weights with them;
* the excess is E_0(a) + 2 h_1 E_1(a) + 2 h_2 E_2(a), each E_s(a) = Q(dev_0(a), dev_s(a)) a
  polynomial in a of degree 2 (K - 1), tabulated at Chebyshev points of an albedo interval and
  interpolated there (barycentric Lagrange weights); outside the interval, for a model
  whose local model was replaced, or with a batch left out (the jackknife), nothing is
  served and the model computes the term as before.

What the interpolation costs in accuracy is for the caller to check
(``ChannelProblem.tabulated``).  Measured on the bench capture's G (18 orders, 16 batches,
a 50 x 38 sample grid at 200 x 150 px), with the interval the whole of [0, 1]: at most
7e-5 log-likelihood units at 16 points, 0.03 at 12, 4 at 8; over [0.5, 1], 1e-8 at 16.
"""

from __future__ import annotations

import math

import numpy as np

from .chebyshev import chebyshev_points, lagrange_weights

#: Chebyshev points in the albedo (``TermTable``; measured above)
TERM_TABLE_POINTS = 16


class TermTable:
    """One channel's term from one local model, for albedos in ``albedo`` (low, high).

    ``loc``: the local model (``FullTransport._local[0]``), whose refresh point (``kt``,
    ``eta``) the steps are taken from; ``stack``: its order-major array (K, 3, batches, h*w);
    ``ms``: the ``MultipleScattering`` that traced it (smoothing, upsampling); ``shape``: the
    camera image's (H, W)."""

    def __init__(self, loc: dict, stack: np.ndarray, ms, shape: tuple[int, int],
                 albedo: tuple[float, float], n: int | None = None):
        n = TERM_TABLE_POINTS if n is None else int(n)
        lo, hi = (float(v) for v in albedo)
        if not (0.0 <= lo < hi <= 1.0):
            raise ValueError(f"tabulate_term: albedo interval {albedo} is empty or not in "
                             "[0, 1]")
        self.loc, self.ms, self.shape = loc, ms, shape
        self.kt, self.eta = loc["kt"], loc["eta"]
        k, parts, b, hw = stack.shape
        self.orders = k
        self.mid, self.half = 0.5 * (lo + hi), 0.5 * (hi - lo)
        self.x, self.w = chebyshev_points(n)
        self.used = self.outside = 0  # renders from the table, renders it did not serve
        # the batch means of every order and part, smoothed as the term is: (K * 3, h*w)
        self.means = ms.smoothed(stack.mean(axis=2).reshape(k * parts, hw))
        rows = []
        flat = stack.reshape(k, -1)
        for a in self.mid + self.half * self.x:
            per = [ms.smoothed(p) for p in (self._powers(a) @ flat).reshape(parts, b, hw)]
            dev = [p - p.mean(axis=0) for p in per]
            rows.extend(ms.upsampled_products(dev[0], d) for d in dev)
        # row 3 j + s: E_s at the j-th point, over n (n - 1)
        self.excess = np.array(rows) / (b * (b - 1))

    def _powers(self, a: float) -> np.ndarray:
        pw = a ** np.arange(self.orders)
        pw[0] = 0.0
        return pw

    def parts(self, loc: dict, kt: float, ks: float, g: float, br: float
              ) -> tuple[np.ndarray, np.ndarray] | None:
        """The term's image and its excess variance, each (H, W), at one channel's extinction
        ``kt``, scattering ``ks``, anisotropy ``g`` and brightness ``br``, given the model's
        local model ``loc`` now; None where the table does not serve (another local model,
        no scattering, an albedo outside its interval)."""
        if loc is not self.loc or not (ks > 0.0 and kt > 0.0):
            self.outside += 1
            return None
        t = (ks / kt - self.mid) / self.half
        if not abs(t) <= 1.0 + 1e-12:
            self.outside += 1
            return None
        self.used += 1
        steps = np.array([1.0, math.log(kt / self.kt), math.atanh(g) - self.eta])
        mean = np.outer(self._powers(ks / kt), steps).ravel() @ self.means
        img = self.ms.upsample(np.clip(mean, 0.0, None)) * br
        coef = np.outer(lagrange_weights(self.x, self.w, min(max(t, -1.0), 1.0)),
                        steps * np.array([1.0, 2.0, 2.0])).ravel()
        exc = (coef @ self.excess) * br * br
        return img.reshape(self.shape), exc.reshape(self.shape)

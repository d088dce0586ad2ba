"""The bulb's visible cap: the phase function averaged over the cap of directions
from which a point in the water sees the bulb, with the attenuation across it
(see ``single.py``'s module docstring for where it enters the image).

``cap_table()`` tabulates log pbar once on a parameter-independent grid; forward
models read it through sparse interpolation matrices.  ``cap_average`` is the
direct quadrature the table interpolates, kept for tests.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
from scipy import sparse

try:  # y += A x into an existing array (no temporary); falls back to A @ x
    from scipy.sparse._sparsetools import csr_matvec as _csr_matvec
except ImportError:  # pragma: no cover - private scipy API
    _csr_matvec = None


def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w  # on [0, 1]


# ------------------------------------------------------------- the bulb's visible cap
# The cap average pbar(theta_c, alpha; g, a) of the phase function over the bulb's
# visible cap, with the attenuation weight exp(a psi) / E(a) (a = kappa_t r), tabulated
# on a grid that depends on the geometry only.
#
# theta_c: angle between the direction of travel from the bulb's centre and the
# direction to the camera; alpha = asin(r/d) the cap's half-angle.  A ray with closest
# approach h has sin(alpha) = rho sin(theta_c), rho = r/h, at every point, so the table
# is indexed by (theta_c, rho) for rho < 1 and by (theta_c, alpha - theta_c) for rays
# that hit the bulb (the cap holds the forward peak).
#
# psi = kappa_t (d - l) / (kappa_t r) with l(beta) = d cos(beta) - sqrt(r^2 - d^2
# sin^2 beta) the path from the surface in the direction at angle beta from the
# centre's: psi = (1 - cos beta)/sin(alpha) + sqrt(1 - sin^2 beta / sin^2 alpha).
# log(cap average of p exp(a psi)) - log E(a) is expanded in the cumulants of psi
# under the phase-weighted cap measure minus those of the far field (psi = z with
# density 2z on [0, 1]: E(a) is its moment generating function):
#
#   log pbar = log <p> + sum_n a^n (kappa_n - kappa_n^far) / n!,   n <= 4,
#
# exact in the far field; truncation error of log pbar 1e-11 at a = 0.06 (diluted milk,
# r = 6 mm), 5e-7 at a = 0.5, 1e-4 at a = 1.4, 7e-4 at a = 2, 5e-3 at a = 3.
#
# Radial quadrature: u = 1 - cos(beta) = u_alpha (1 - tau^2) removes the square root of
# psi at the cap's edge (domega = 2 u_alpha tau dtau dphi); Gauss-Legendre in tau with a
# sinh map towards the ring nearest the forward peak (width _EG: all |g| <= 0.995).
# Azimuth: int_0^2pi (A - B cos phi)^(-3/2) dphi = 4 E(m) / ((A - B) sqrt(A + B)),
# m = 2B / (A + B), with A -+ B = 1 + g^2 - 2 g cos(theta_c -+ beta).

_TH0 = 0.005                          # theta grid: uniform in _theta_x, fine near 0 and pi
_XPI = float(np.log((np.pi + _TH0) / _TH0))
_NX = 409                             # theta columns (step 0.035 in log units)
_DX = 2 * _XPI / (_NX - 1)
_RHO_A = np.arange(31) * 0.02                                  # 0 .. 0.6, uniform in rho
_ETA = 1e-3
_RHO_B = 1.0 - 0.4 * (_ETA / 0.4) ** (np.arange(1, 31) / 30)  # 1 - rho geometric to 1e-3
_RHO_ROWS = np.concatenate([_RHO_A, _RHO_B, [1.0]])
_DZ = 0.08                            # hitting rays: z = asinh((alpha - theta_c)/_TH0)
_EG = 0.004                           # clustering width of the radial nodes
_NTAU = 16
_DT = 0.05                            # table slices every 0.05 in atanh(g), cubic in between
_ALPHA_MIN = 1e-7
_FAR_CUMULANTS = (2.0 / 3.0, 1.0 / 18.0, -1.0 / 135.0, -1.0 / 540.0)
_MAX_SLICES = 96                     # all of |g| <= 0.995: 0.7 MB each
# A&S 17.3.35: E(m) with m1 = 1 - m, |error| < 2e-8
_EA = (0.44325141463, 0.06260601220, 0.04757383546, 0.01736506451)
_EB = (0.24998368310, 0.09200180037, 0.04069697526, 0.00526449639)


def _ellipe_1m(m1: np.ndarray) -> np.ndarray:
    """Complete elliptic integral of the second kind E(m) of m = 1 - m1 (0 < m1 <= 1)."""
    a1, a2, a3, a4 = _EA
    b1, b2, b3, b4 = _EB
    pa = 1.0 + m1 * (a1 + m1 * (a2 + m1 * (a3 + m1 * a4)))
    pb = m1 * (b1 + m1 * (b2 + m1 * (b3 + m1 * b4)))
    return pa - pb * np.log(m1)


def _theta_x(theta):
    """Table coordinate of theta_c (in units of the grid step): log((theta + th0) /
    (pi - theta + th0)), uniform in theta within th0 of 0 and pi, in log theta beyond."""
    return (np.log((theta + _TH0) / ((np.pi + _TH0) - theta)) + _XPI) / _DX


def _rho_y(rho):
    """Table coordinate of rho = r/h in [0, 1]: rho up to 0.6, then log(1 - rho)."""
    rho = np.asarray(rho, float)
    yb = 0.6 + 0.6 * np.log(0.4 / np.maximum(1.0 - rho, _ETA)) / np.log(0.4 / _ETA)
    return np.where(rho <= 0.6, rho, np.where(rho < 1.0 - _ETA, yb,
                                               1.2 + 0.6 * (rho - (1.0 - _ETA)) / _ETA))


#: Largest kappa_t r for the cap table (its attenuation is a polynomial in a); beyond it the
#: phase function is taken in the direction of the bulb's centre (far-field treatment).
CAP_A_MAX = 3.0  # truncation error of the table 5e-3 there (docs/physics.md)
A_OPAQUE = 600.0


def log_cap_attenuation(a: float) -> float:
    """log E(a), E(a) = 2 ((a - 1) e^a + 1) / a^2 = int_0^1 2 z e^(a z) dz."""
    a = float(a)
    if a < 1e-3:
        return float(np.log1p(2 * a / 3 + a * a / 4 + a**3 / 15))
    return float(a + np.log(2 * ((a - 1) + np.exp(-a)) / (a * a)))


def _cap_nodes(theta: np.ndarray, alpha: np.ndarray, inside: bool, n: int = _NTAU,
               eg: float = _EG):
    """Radial quadrature of the cap average for cells (theta, alpha), alpha > 0.

    Returns sin^2((theta -+ beta)/2), psi and weights W (each (N, n) outside the peak,
    (N, 2n) when theta < alpha) with  pbar = sum W e^(a psi) ring(beta) / E(a),
    ring = (1 - g^2)/pi E(m) / ((A - B) sqrt(A + B)).
    """
    x01, w01 = _gauss_legendre(n)
    sa = np.sin(alpha)
    ua = 2 * np.sin(0.5 * alpha) ** 2
    if inside:  # the forward peak at tau_p; split there, nodes clustered on both sides
        up = 2 * np.sin(0.5 * theta) ** 2
        taup = np.sqrt(np.clip(1 - up / ua, 0.0, 1.0))
        uw = eg * np.hypot(np.sin(theta), 0.5 * eg)
        eps = np.minimum(uw / np.maximum(2 * ua * taup, 1e-300), np.sqrt(uw / ua))
        segs = ((np.zeros_like(taup), taup, True), (taup, np.ones_like(taup), False))
    else:  # the ring nearest the peak is the edge, tau = 0
        eps = np.sqrt(np.hypot(eg, theta - alpha) * sa / ua)
        segs = ((np.zeros_like(theta), np.ones_like(theta), False),)
    eps = np.clip(eps, 1e-7, 1.0)[:, None]
    taus, jacs = [], []
    for lo, hi, at_hi in segs:
        span = np.arcsinh((hi - lo)[:, None] / eps)
        et = np.exp(span * x01)
        d = 0.5 * eps * (et - 1 / et)
        jacs.append(0.5 * eps * (et + 1 / et) * span * w01)
        taus.append(hi[:, None] - d if at_hi else lo[:, None] + d)
    tau = np.concatenate(taus, axis=1)
    jac = np.concatenate(jacs, axis=1)
    u = ua[:, None] * (1 - tau * tau)
    beta = 2 * np.arcsin(np.sqrt(np.clip(0.5 * u, 0.0, 1.0)))
    sm = np.sin(0.5 * (theta[:, None] - beta)) ** 2
    sp = np.sin(0.5 * (theta[:, None] + beta)) ** 2
    root = np.sqrt(np.clip(ua[:, None] * (2 - u - ua[:, None]), 0.0, None))
    psi = (u + tau * root) / sa[:, None]
    return sm, sp, psi, tau * jac / np.pi


def _cap_cumulants(nodes, g: float, chunk: int = 2048) -> np.ndarray:
    """(5, N): log <p> and the cumulants 1..4 of psi under the phase-weighted cap measure."""
    sm_all, sp_all, psi_all, w_all = nodes
    c0, c1 = (1 - g) ** 2, 4 * g
    out = np.empty((5, len(sm_all)))
    for s in range(0, len(sm_all), chunk):
        sl = slice(s, s + chunk)
        am = c1 * sm_all[sl]
        am += c0
        ap = c1 * sp_all[sl]
        ap += c0
        lo, hi = np.minimum(am, ap), np.maximum(am, ap)  # A - |B|, A + |B|
        wr = _ellipe_1m(lo / hi)
        lo *= np.sqrt(hi)
        wr /= lo
        wr *= w_all[sl]
        m0 = wr.sum(axis=1)
        psi = psi_all[sl]
        k1 = np.einsum("ij,ij->i", wr, psi) / m0
        d = psi - k1[:, None]
        wr *= d
        wd2 = wr * d
        m2 = wd2.sum(axis=1) / m0
        wd2 *= d
        m3 = wd2.sum(axis=1) / m0
        m4 = np.einsum("ij,ij->i", wd2, d) / m0
        out[0, sl] = np.log(m0 * ((1 - g * g) / np.pi))
        out[1, sl], out[2, sl], out[3, sl], out[4, sl] = k1, m2, m3, m4 - 3 * m2 * m2
    return out


def _log_hg(theta: np.ndarray, g: float) -> np.ndarray:
    d = (1 - g) ** 2 + 4 * g * np.sin(0.5 * theta) ** 2
    return np.log((1 - g * g) / (4 * np.pi)) - 1.5 * np.log(d)


class _CapTable:
    """log pbar on a fixed (theta_c, rho) grid; slices in g are computed on demand and cached.

    Cells: block AB (theta column i, rho row j) for rays with rho = r/h < 1, and block C
    (every other theta column, z row) for rays that hit the bulb.  A slice holds, per cell,
    log <p> and (kappa_n - kappa_n^far)/n! for n = 1..4 (float32); a render blends four
    slices around atanh(g) (cubic Lagrange) and sums the cumulant series in a.
    """

    def __init__(self):
        xs = np.arange(_NX, dtype=float)
        lo, hi = np.zeros(_NX), np.full(_NX, np.pi)  # invert _theta_x by bisection
        for _ in range(64):
            mid = 0.5 * (lo + hi)
            big = _theta_x(mid) > xs
            lo, hi = np.where(big, lo, mid), np.where(big, mid, hi)
        th = 0.5 * (lo + hi)
        th[0], th[-1] = 0.0, np.pi
        self.nrow = len(_RHO_ROWS)
        self.y_rows = _rho_y(_RHO_ROWS)
        tab, rab = np.meshgrid(th, _RHO_ROWS, indexing="ij")
        alpha_ab = np.arcsin(np.clip(rab * np.sin(tab), 0.0, 1.0))
        # block C: theta <= pi/2 (every other column), alpha = theta + _TH0 sinh(z)
        ncx = int(np.searchsorted(th[::2], np.pi / 2)) + 2
        self.ncx = ncx
        self.nz = int(np.ceil(np.arcsinh(np.pi / 2 / _TH0) / _DZ)) + 2
        tc, zc = np.meshgrid(th[::2][:ncx], np.arange(self.nz) * _DZ, indexing="ij")
        alpha_c = tc + _TH0 * np.sinh(zc)
        feasible = (tc + _TH0 * np.sinh(np.maximum(zc - _DZ, 0.0))) <= np.pi / 2
        self.nab = tab.size
        theta = np.concatenate([tab.ravel(), tc.ravel()])
        alpha = np.concatenate([alpha_ab.ravel(), np.minimum(alpha_c, np.pi / 2).ravel()])
        compute = np.concatenate([np.ones(tab.size, bool), feasible.ravel()])
        self.size = theta.size
        self.theta = theta
        self.point = compute & (alpha < _ALPHA_MIN)      # pbar = p_HG(theta)
        cap = compute & ~self.point
        self.outside = cap & (theta >= alpha)
        self.inside = cap & (theta < alpha)
        # cells beyond alpha = pi/2 (not reached) repeat the last one of their column
        cidx = np.arange(self.nab, self.size).reshape(tc.shape)
        src = np.maximum.accumulate(np.where(feasible, cidx, -1), axis=1)
        self.source = np.concatenate([np.arange(self.nab), src.ravel()])
        self.nodes_out = _cap_nodes(theta[self.outside], alpha[self.outside], False)
        self.nodes_in = _cap_nodes(theta[self.inside], alpha[self.inside], True)
        self._slices: OrderedDict[int, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ values
    def slice_at(self, k: int) -> np.ndarray:
        """(5, size) float32 for g = tanh(k _DT): log <p>, (kappa_n - kappa_n^far)/n!."""
        with self._lock:
            if k in self._slices:
                self._slices.move_to_end(k)
                return self._slices[k]
        g = float(np.tanh(k * _DT))
        out = np.zeros((5, self.size))
        out[0, self.point] = _log_hg(self.theta[self.point], g)
        for mask, nodes in ((self.outside, self.nodes_out), (self.inside, self.nodes_in)):
            out[:, mask] = _cap_cumulants(nodes, g)
        cap = self.outside | self.inside
        for n, (far, fact) in enumerate(zip(_FAR_CUMULANTS, (1.0, 2.0, 6.0, 24.0)), start=1):
            out[n, cap] = (out[n, cap] - far) / fact
        out = out[:, self.source].astype(np.float32)
        with self._lock:
            self._slices[k] = out
            while len(self._slices) > _MAX_SLICES:
                self._slices.popitem(last=False)
        return out

    def table(self, g: float, a: float, cells: np.ndarray | None = None,
              cache: OrderedDict | None = None) -> np.ndarray:
        """log pbar (float64) for anisotropy g and a = kappa_t r: per cell, or on ``cells``
        only (with a per-caller ``cache`` of the four slices restricted to them, in float64,
        which keeps the result smooth in g and a)."""
        t = float(np.arctanh(np.clip(g, -0.9999, 0.9999))) / _DT
        k = int(np.floor(t))
        f = t - k
        # cubic Lagrange weights on slices k-1 .. k+2, times the powers of a
        lag = np.array([-f * (f - 1) * (f - 2) / 6, (f + 1) * (f - 1) * (f - 2) / 2,
                        -(f + 1) * f * (f - 2) / 2, (f + 1) * f * (f - 1) / 6])
        coef = lag[:, None] * np.array([1.0, a, a * a, a**3, a**4])[None, :]
        if cells is None:  # float32 products: an adaptive render's nodes move with g anyway
            out = np.zeros(self.size, dtype=np.float32)
            for dk, c in zip((-1, 0, 1, 2), coef.astype(np.float32)):
                out += c @ self.slice_at(k + dk)
            return out.astype(np.float64)
        block = cache.get(k)
        if block is None:
            block = cache[k] = np.concatenate([self.slice_at(k + dk)[:, cells]
                                               for dk in (-1, 0, 1, 2)], axis=0, dtype=np.float64)
            while len(cache) > 6:
                cache.popitem(last=False)
        else:
            cache.move_to_end(k)
        return coef.ravel() @ block

    # ------------------------------------------------------------------ nodes
    def rows(self, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row index and fraction in block AB of rays with r/h = ``rho`` (clipped to 1)."""
        y = _rho_y(np.minimum(rho, 1.0))
        j = np.clip(np.searchsorted(self.y_rows, y, side="right") - 1, 0, self.nrow - 2)
        return j, np.clip((y - self.y_rows[j]) / (self.y_rows[j + 1] - self.y_rows[j]), 0.0, 1.0)

    def matrix(self, theta: np.ndarray, sin_alpha: np.ndarray, row: np.ndarray,
               row_frac: np.ndarray, hit: np.ndarray, work: dict | None = None
               ) -> sparse.csr_matrix:
        """Sparse bilinear interpolation from the cells to the nodes of m rays.

        ``theta``, ``sin_alpha``: (m, n) node angles; ``row``, ``row_frac``: (m,) from
        :meth:`rows`; ``hit``: (m,) rays whose nodes go to block C (lower half, r/h >= 1).
        Rows of the matrix follow the nodes in C order.  ``work``: arrays reused from call to
        call (the matrix then shares them: for a matrix used before the next call only).
        """
        m, n = theta.shape
        size = m * n
        if work is None or work.get("size") != size:
            work = {} if work is None else work
            work.clear()
            work.update(size=size, cols=np.empty(4 * size, dtype=np.int32),
                        w=np.empty(4 * size), base=np.empty(size, dtype=np.int32),
                        fx=np.empty(size), fy=np.empty(size), gx=np.empty(size),
                        gy=np.empty(size),
                        indptr=np.arange(0, 4 * size + 1, 4, dtype=np.int32))
        base, fx, fy, gx, gy = (work[k] for k in ("base", "fx", "fy", "gx", "gy"))
        x = _theta_x(theta).ravel()  # the grid is x = 0, 1, ..., _NX - 1
        np.minimum(x, _NX - 2, out=fx)
        np.floor(fx, out=gx)
        base[:] = gx
        np.subtract(x, gx, out=fx)
        base *= self.nrow
        base.reshape(m, n)[:] += row.astype(np.int32)[:, None]
        fy.reshape(m, n)[:] = row_frac[:, None]
        step = self.nrow
        if hit.any():  # block C: every other theta column, z = asinh((alpha - theta)/_TH0)
            h = (np.flatnonzero(hit)[:, None] * n + np.arange(n)).ravel()
            xh = 0.5 * x[h]
            ic = np.minimum(xh.astype(np.int32), self.ncx - 2)
            fx[h] = np.minimum(xh - ic, 1.0)
            dz = np.arcsin(sin_alpha.ravel()[h]) - theta.ravel()[h]
            z = np.arcsinh(np.maximum(dz, 0.0) / _TH0) / _DZ
            iz = np.minimum(z.astype(np.int32), self.nz - 2)
            fy[h] = np.minimum(z - iz, 1.0)
            base[h] = self.nab + ic * self.nz + iz
            step = np.full(size, self.nrow, dtype=np.int32)
            step[h] = self.nz
        cols, w = work["cols"], work["w"]
        cols[0::4] = base
        np.add(base, 1, out=cols[1::4])
        base += step
        cols[2::4] = base
        np.add(base, 1, out=cols[3::4])
        np.subtract(1.0, fx, out=gx)
        np.subtract(1.0, fy, out=gy)
        np.multiply(gx, gy, out=w[0::4])
        np.multiply(gx, fy, out=w[1::4])
        np.multiply(fx, gy, out=w[2::4])
        np.multiply(fx, fy, out=w[3::4])
        return sparse.csr_matrix((w, cols, work["indptr"]), shape=(size, self.size))


def _matvec_add(mat: sparse.csr_matrix, x: np.ndarray, y: np.ndarray) -> None:
    """y += mat @ x (y contiguous float64)."""
    if _csr_matvec is not None and mat.indices.dtype == np.int32:
        _csr_matvec(mat.shape[0], mat.shape[1], mat.indptr, mat.indices, mat.data, x, y)
    else:
        y += mat @ x


_CAP_TABLE: _CapTable | None = None
_CAP_LOCK = threading.Lock()


def cap_table() -> _CapTable:
    """The module's cap table (built on first use, ~0.1 s)."""
    global _CAP_TABLE
    with _CAP_LOCK:
        if _CAP_TABLE is None:
            _CAP_TABLE = _CapTable()
        return _CAP_TABLE


def cap_average(theta, alpha, g: float, a: float = 0.0, *, n: int = 24) -> np.ndarray:
    """pbar: the cap average of p_HG weighted by exp(a psi) / E(a), by direct quadrature.

    ``theta`` (theta_c) and ``alpha`` (the cap's half-angle) broadcast; radians.  The table
    interpolates this function; it is exposed for tests and checks.
    """
    theta, alpha = (np.ravel(v).astype(float) for v in np.broadcast_arrays(theta, alpha))
    out = np.exp(_log_hg(theta, g))
    for inside in (False, True):
        sel = (alpha >= _ALPHA_MIN) & ((theta < alpha) == inside)
        if sel.any():
            sm, sp, psi, w = _cap_nodes(theta[sel], alpha[sel], inside, n=n)
            c0, c1 = (1 - g) ** 2, 4 * g
            am, ap = c0 + c1 * sm, c0 + c1 * sp
            lo, hi = np.minimum(am, ap), np.maximum(am, ap)
            ring = _ellipe_1m(lo / hi) / (lo * np.sqrt(hi))
            val = np.einsum("ij,ij->i", w * np.exp(a * (psi - 1)), ring) * ((1 - g * g) / np.pi)
            out[sel] = val * np.exp(a - log_cap_attenuation(a)) if a else val
    return out

"""Analytic single-scattering forward model (orders 0 and 1).

For each camera ray in the water, p(s) = p0 + s v, 0 <= s <= S, the radiance
scattered once towards the camera is

    L1 = int I(d) kappa_s p_HG(cos theta) exp(-kappa_t (d + s)) / d^2 ds,

with d = |p(s) - c| the distance to the light.  With the closest approach
s0 = (c - p0).v and h = |p(s0) - c|, the equiangular substitution
s = s0 + h tan(phi) gives ds / d^2 = dphi / h, cos(theta) = -sin(phi) and
d + s = s0 + h tan(phi/2 + pi/4), so

    L1 = (I kappa_s / h) int p_HG(-sin phi) exp(-kappa_t (s0 + h tan(phi/2 + pi/4))) dphi.

Both the forward peak of the phase function and the attenuation peak sit at
phi = -pi/2 (points between the light and the camera).  The interval is split
at phi = 0 and each half is mapped with w = eps sinh(t) around its end
(w = distance of phi from -pi/2 or +pi/2), with eps the width of the peak;
a Gauss–Legendre rule in t is then accurate with a few nodes.

The bulb (a Lambertian sphere of radiance L_b and radius r) lights a point at
distance d from within the cap of directions of half-angle alpha = asin(r/d)
around the direction of its centre, with uniform radiance L_b attenuated over
the path l(beta) from its surface:

    int_cap p_HG(omega . omega_out) exp(-kappa_t l) domega
        = Omega exp(-kappa_t d) E(kappa_t r) pbar,

Omega = 2 pi (1 - cos alpha), E(a) = 2 ((a - 1) e^a + 1) / a^2 the far-field cap
average of exp(kappa_t (d - l)), and pbar the cap average of p_HG weighted by
exp(kappa_t (d - l)) / E.  pbar -> p_HG(cos theta_c) far from the bulb, but for a
forward-peaked phase function it differs by percents within a few radii (the
phase function varies across the cap) and it stays finite where the cap holds
the forward peak.  pbar is tabulated once on a parameter-independent grid in
(theta_c, r/h) (see _CapTable): the azimuthal integral over each ring of the
cap is closed-form (complete elliptic integral E), the radial one a
Gauss-Legendre rule; the attenuation enters through the cumulants of
kappa_t (d - l) / (kappa_t r) over the phase-weighted cap.  Each quadrature node
reads log pbar from the table by bilinear interpolation (a sparse matrix fixed
with the node positions).  Rays that hit the bulb see it attenuated,
L_b exp(-kappa_t s_hit), and stop there.  Pixels near the bulb's silhouette are
supersampled so that the direct view is integrated over the pixel footprint;
elsewhere the footprint average is the sample value plus the midpoint rule's
second-order term (laplacian / 24), taken from the image itself.

The spot is a point source of intensity I inside a cone; each ray's
integration range is clipped to the (convex) cone analytically.
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

from ..geometry import WaterRays, pixel_grid, trace_to_water
from ..spec import Camera, Spec

_HALF_PI = 0.5 * np.pi
HALO_FOOTPRINTS = 8.0  # the bulb's halo: pixels whose ray passes within r + 8 footprints
HALO_SUB = 4


def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w  # on [0, 1]


def _cone_interval(u: np.ndarray, v: np.ndarray, axis: np.ndarray, cutoff_deg: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Interval [s_in, s_out] of s where c + u + s v lies inside the spot's cone.

    ``u`` = p0 - c (N, 3), ``v`` unit ray directions (N, 3), ``axis`` unit (3,).
    The forward nappe of a cone with half-angle <= 90 deg is convex, so the set
    is one interval (empty: s_in > s_out).
    """
    ua, va = u @ axis, v @ axis
    n = len(ua)
    big = 1e30
    if cutoff_deg >= 90.0:  # half-space (p - c).axis >= 0
        with np.errstate(divide="ignore", invalid="ignore"):
            r = -ua / va
        s_in = np.where(va > 0, r, np.where(va < 0, -big, np.where(ua >= 0, -big, big)))
        s_out = np.where(va < 0, r, np.where(va > 0, big, np.where(ua >= 0, big, -big)))
        return s_in, s_out
    k = np.cos(np.radians(cutoff_deg)) ** 2
    a = va * va - k
    b = ua * va - k * np.einsum("ij,ij->i", u, v)
    c = ua * ua - k * np.einsum("ij,ij->i", u, u)
    s_in = np.full(n, big)
    s_out = np.full(n, -big)
    disc = b * b - a * c
    has = disc >= 0
    sq = np.sqrt(np.where(has, disc, 0.0))
    lin = np.abs(a) < 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(lin, -c / (2 * b), (-b - sq) / a)
        r2 = np.where(lin, -c / (2 * b), (-b + sq) / a)
    lo, hi = np.minimum(r1, r2), np.maximum(r1, r2)
    on_lo = has & np.isfinite(lo) & (ua + lo * va >= 0)
    on_hi = has & np.isfinite(hi) & (ua + hi * va >= 0) & ~lin
    cosang = va  # cosine between the ray and the axis
    ahead = cosang > np.sqrt(k)  # far along the ray: inside
    both = on_lo & on_hi
    s_in = np.where(both, lo, s_in)
    s_out = np.where(both, hi, s_out)
    one = on_lo ^ on_hi
    root = np.where(on_lo, lo, hi)
    s_in = np.where(one & ahead, root, np.where(one, -big, s_in))
    s_out = np.where(one & ahead, big, np.where(one, root, s_out))
    return s_in, s_out


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


class SingleScattering:
    """Analytic single-scattering image of one capture (see module docstring).

    Parameters
    ----------
    spec : Spec
        The capture spec (geometry only is used).
    image_index : int or None
        Which image's camera/light overrides to use; None for the spec's base
        camera and light (the clear-water photo).
    channels : tuple of str, optional
        Channels rendered, default ``spec.channels``.
    nodes : int
        Gauss–Legendre nodes on the half-interval with the forward peak (phi < 0).
    nodes_upper : int
        Nodes on the smooth half (phi > 0) when every g >= 0 (else ``nodes``).
    supersample : int
        ``n`` gives n x n samples per pixel everywhere (1: pixel centres).
    bulb_supersample : int
        Samples per pixel side for pixels near the bulb's silhouette.
    halo_supersample : int
        Samples per pixel side in the bulb's halo (within 8 pixel footprints).
    box_filter : bool
        Average over each pixel's footprint (True) or return the value at the samples.
    """

    def __init__(self, spec: Spec, image_index: int | None = 0, *, channels: tuple[str, ...] | None = None,
                 nodes: int = 8, nodes_upper: int = 8, supersample: int = 1,
                 bulb_supersample: int = 8, halo_supersample: int = HALO_SUB,
                 box_filter: bool = True):
        self.spec = spec
        use = image_index is not None and spec.images
        self.camera: Camera = spec.camera_for(image_index) if use else spec.camera
        self.light = spec.light_for(image_index) if use else spec.light
        self.channels = tuple(channels or spec.channels)
        self.shape = (self.camera.height, self.camera.width)
        self.nodes, self.nodes_upper = int(nodes), int(nodes_upper)
        self._rules = {n: _gauss_legendre(n) for n in {self.nodes, self.nodes_upper}}
        self._frozen: list | None = None
        self._cap_cells: np.ndarray | None = None
        self._freezing = False
        self._work = threading.local()  # arrays reused by the adaptive renders' cap matrices
        self.box_filter = box_filter
        self._build(int(supersample), int(bulb_supersample), int(halo_supersample))

    def __getstate__(self):
        state = self.__dict__.copy()
        del state["_work"]  # per-thread scratch arrays
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._work = threading.local()

    # ----------------------------------------------------------------- set-up
    def _rays(self, sub: int, mask: np.ndarray | None = None):
        x, y = pixel_grid(self.camera, sub=sub)
        pix = np.broadcast_to(np.arange(x.shape[0] * x.shape[1]).reshape(x.shape[:2])[..., None],
                              x.shape)
        if mask is not None:
            x, y, pix = x[mask], y[mask], pix[mask]
        rays = trace_to_water(self.camera, self.spec.tank, self.spec.medium_ior,
                              np.ravel(x), np.ravel(y))
        return rays, np.ravel(pix), np.full(np.size(pix), 1.0 / sub**2)

    def _build(self, sub: int, bulb_sub: int, halo_sub: int) -> None:
        c = self.light.position
        # samples per pixel side: `sub` everywhere; near the bulb's silhouette `bulb_sub`
        # (the direct view is a discontinuity); in its halo 4 (the glow of a forward-peaked
        # phase function curves too fast for the second-order footprint correction)
        sub_map = np.full(self.shape, sub)
        zone = np.zeros(self.shape, bool)
        if self.light.type == "bulb":
            centre, _, _ = self._rays(1)
            h_c = self._closest(centre, c)[1].reshape(self.shape)
            footprint = np.linalg.norm(c - self.camera.position) / min(self.camera.fx, self.camera.fy)
            zone = h_c < self.light.radius + HALO_FOOTPRINTS * footprint
            sub_map[zone] = max(sub, halo_sub)
            sub_map[h_c < self.light.radius + 2.0 * footprint] = max(sub, bulb_sub)
        parts = []
        for n in np.unique(sub_map):
            sel = np.broadcast_to((sub_map == n)[..., None], (*self.shape, n * n))
            parts.append(self._rays(int(n), sel))
        rays = WaterRays(*(np.concatenate([getattr(p[0], f) for p in parts])
                           for f in ("origin", "direction", "length", "factor")))
        pix = np.concatenate([p[1] for p in parts])
        wts = np.concatenate([p[2] for p in parts])
        live = rays.factor > 0
        # pixels where the box filter is applied as centre value + laplacian / (24 sub^2):
        # sampled on the regular grid, fully inside the tank's face, neighbours alike
        regular = (sub_map == sub) & ~zone
        full = np.bincount(pix[live], weights=wts[live], minlength=regular.size).reshape(self.shape)
        regular &= np.isclose(full, 1.0)
        ok = regular.copy()
        ok[1:-1, 1:-1] &= (regular[:-2, 1:-1] & regular[2:, 1:-1] & regular[1:-1, :-2]
                           & regular[1:-1, 2:])
        ok[[0, -1], :] = False
        ok[:, [0, -1]] = False
        self._smooth, self._lap_scale = ok, 1.0 / (24.0 * sub * sub)
        self._pix, self._wts = pix[live], wts[live] * rays.factor[live]
        o, v, length = rays.origin[live], rays.direction[live], rays.length[live]
        s0, h = self._closest(WaterRays(o, v, length, rays.factor[live]), c)
        lo, hi = np.zeros_like(s0), length.copy()
        self._hit = np.zeros(len(s0), bool)
        self._s_hit = np.zeros(len(s0))
        if self.light.type == "bulb":
            r = self.light.radius
            s_hit = s0 - np.sqrt(np.clip(r * r - h * h, 0.0, None))
            self._hit = (h < r) & (s_hit > 0) & (s_hit < length)
            self._s_hit = np.where(self._hit, s_hit, 0.0)
            hi = np.where(self._hit, s_hit, hi)
        else:
            s_in, s_out = _cone_interval(o - c, v, self.light.direction, self.light.cutoff_deg)
            lo, hi = np.maximum(lo, s_in), np.minimum(hi, s_out)
        hfloor = 1e-9 * max(self.spec.tank.inner_size)
        h = np.maximum(h, hfloor)
        self._s0, self._h = s0, h
        if self.light.type == "bulb":  # the rays' rows in the cap table
            self._rho = self.light.radius / h
            self._cap_row, self._cap_frac = cap_table().rows(self._rho)
            self._cap_hit = self._rho >= 1.0
        empty = hi <= lo
        self._phi_a = np.where(empty, 0.0, np.arctan2(lo - s0, h))
        self._phi_b = np.where(empty, 0.0, np.arctan2(hi - s0, h))

    @staticmethod
    def _closest(rays: WaterRays, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = c - rays.origin
        s0 = np.einsum("ij,ij->i", u, rays.direction)
        h = np.linalg.norm(u - s0[:, None] * rays.direction, axis=1)
        return s0, h

    # ----------------------------------------------------------------- render
    def _panel_nodes(self, sel, w_a, w_b, eps, n: int, upper: bool, from_end: bool,
                     r_bulb: float):
        """Nodes of one half for rays ``sel``: w in [w_a, w_b] from -pi/2 (lower) or +pi/2 (upper).

        The nodes follow w = w_a + eps sinh(t) (or w_b - eps sinh(t)), which resolves a peak
        of width ``eps`` at that end of the interval and is near-logarithmic beyond it.

        Returns (path length d + s, sin^2(w/2), weight including the Jacobian and the bulb's
        solid-angle factor, and for the bulb the sparse matrix that interpolates log pbar
        from the cap table, else None), the arrays of shape (len(sel), n).
        """
        x01, w01 = self._rules[n]
        span = np.arcsinh((w_b - w_a) / eps)[:, None]
        et = np.exp(span * x01[None, :])
        inv = 1.0 / et
        e2 = 0.5 * eps[:, None]
        dw = e2 * (et - inv)  # sinh map anchored at w_a (or at w_b when from_end)
        if from_end.any():
            w = np.where(from_end[:, None], w_b[:, None] - dw, w_a[:, None] + dw)
        else:
            w = dw
            w += w_a[:, None]
        et += inv
        et *= e2 * span * w01[None, :]
        weight = et
        t = np.tan(0.5 * w)  # one tan instead of sin and cos of w/2 (numpy's are 8x slower)
        t2 = t * t
        h, s0 = self._h[sel][:, None], self._s0[sel][:, None]
        with np.errstate(divide="ignore"):
            path = s0 + (h / t if upper else h * t)
        mat = None
        if r_bulb > 0:  # exact solid angle of the sphere instead of pi r^2 / d^2
            sin_alpha = np.minimum(self._rho[sel][:, None] * (2 * t / (1 + t2)), 1.0)  # r/d
            # Omega / (pi r^2 / d^2) = 2 (1 - cos alpha) / sin^2 alpha = 2 / (1 + cos alpha)
            weight *= 2.0 / (1.0 + np.sqrt(1.0 - sin_alpha * sin_alpha))
            hit = self._cap_hit[sel] & (not upper)
            if not hasattr(self._work, "by_half"):
                self._work.by_half = {}
            work = None if self._freezing else self._work.by_half.setdefault(upper, {})
            mat = cap_table().matrix(np.pi - w if upper else w, sin_alpha, self._cap_row[sel],
                                     self._cap_frac[sel], hit, work)
        return path, t2 / (1 + t2), weight, mat

    def _nodes(self, kt: np.ndarray, g: np.ndarray) -> list[tuple]:
        """Quadrature nodes of every ray for channels with extinction ``kt`` and anisotropy ``g``.

        Returns panels (sel, upper, path, sin^2(w/2), weight, cap matrix or None); the node
        positions are shared by the channels (the narrowest peak width wins).
        """
        pa, pb = self._phi_a, self._phi_b
        r = self.light.radius if self.light.type == "bulb" else 0.0
        eps_g = np.clip((1 - np.abs(g)) / np.sqrt(np.abs(g) + 1e-3), 1e-4, 1.0)
        kth = np.max(kt) * self._h + 1e-300
        fwd, back = g >= 0, g < 0
        eg_fwd = eps_g[fwd].min() if fwd.any() else 1.0
        eg_back = eps_g[back].min() if back.any() else 1.0
        panels = []
        for upper, sel in ((False, np.flatnonzero(pa < 0)), (True, np.flatnonzero(pb > 0))):
            if not len(sel):
                continue
            if upper:  # w = pi/2 - phi; attenuation falls towards w = 0 with scale 1/(kt h)
                w_a, w_b = _HALF_PI - pb[sel], _HALF_PI - np.maximum(pa[sel], 0.0)
                if back.any():  # backward HG peak at w = 0
                    eps, n = np.minimum(np.hypot(eg_back, w_a), 1.0), self.nodes
                    from_end = np.zeros(len(sel), bool)
                else:
                    # thin (kt h < 1/2): the integrand switches on near w ~ 2 kt h and varies on
                    # the scale of w itself; thick: it grows like exp(-kt h cot(w/2)) towards w_b
                    k = kth[sel]
                    from_end = k > 0.5
                    eps = np.clip(np.where(from_end, 1.0 / k, np.maximum(2 * k, w_a)), 1e-4, 1.0)
                    n = self.nodes_upper
            else:  # w = phi + pi/2; forward HG peak and attenuation peak at w = 0
                w_a, w_b = pa[sel] + _HALF_PI, np.minimum(pb[sel], 0.0) + _HALF_PI
                eps = np.clip(np.minimum(np.hypot(eg_fwd, w_a), 2.0 / kth[sel]), 1e-4, 1.0)
                n, from_end = self.nodes, np.zeros(len(sel), bool)
            panels.append((sel, upper) + self._panel_nodes(sel, w_a, w_b, eps, n, upper, from_end, r))
        return panels

    def freeze_nodes(self, kappa_t, g) -> None:
        """Fix the quadrature nodes at the values suited to (kappa_t, g) (arrays of shape (C,)).

        Later renders reuse them: about 5x faster.  Any node placement is a valid quadrature;
        this one is accurate for parameters near those given (a fit freezes them at the MAP).
        """
        kt = np.broadcast_to(np.asarray(kappa_t, float), (len(self.channels),))
        gg = np.broadcast_to(np.asarray(g, float), (len(self.channels),))
        self._freezing = True  # the node set is kept: no shared work arrays
        try:
            panels = self._nodes(kt, gg)
        finally:
            self._freezing = False
        self._cap_cells = None
        if self.light.type == "bulb":  # restrict the cap table to the cells the nodes read
            cells = np.unique(np.concatenate([p[5].indices for p in panels]))
            panels = [p[:5] + (sparse.csr_matrix(
                (p[5].data, np.searchsorted(cells, p[5].indices).astype(np.int32), p[5].indptr),
                shape=(p[5].shape[0], len(cells))),) for p in panels]
            self._cap_cells, self._cap_cache = cells, OrderedDict()
        self._frozen = panels

    def unfreeze_nodes(self) -> None:
        self._frozen = None
        self._cap_cells = None

    def _line_integrals(self, kt: np.ndarray, g: np.ndarray) -> np.ndarray:
        """int p exp(-kt (d+s)) (source factor) dphi per ray and channel, shape (N, C).

        For the bulb p is the cap average pbar (log pbar from the cap table)."""
        panels = self._frozen if self._frozen is not None else self._nodes(kt, g)
        total = np.zeros((len(self._h), len(kt)))
        tables = None
        need = max((p[2].size for p in panels), default=0)
        buf = getattr(self._work, "buf", None)
        if buf is None or buf.size < need:
            buf = self._work.buf = np.empty(need)
        if self.light.type == "bulb":
            r = self.light.radius
            cells = self._cap_cells if self._frozen is not None else None
            tables = [cap_table().table(gk, ktk * r, cells, getattr(self, "_cap_cache", None))
                      if ktk * r <= CAP_A_MAX else None for ktk, gk in zip(kt, g)]
        for sel, upper, path, sin2, weight, mat in panels:
            rows = slice(None) if len(sel) == len(total) else sel  # all rays: no scatter
            for k, (ktk, gk) in enumerate(zip(kt, g)):
                if mat is not None and ktk * self.light.radius <= CAP_A_MAX:
                    expo = np.multiply(path, -ktk, out=buf[: path.size].reshape(path.shape))
                    _matvec_add(mat, tables[k], expo.reshape(-1))  # log pbar - kt (d + s)
                    total[rows, k] += np.einsum("ij,ij->i", np.exp(expo, out=expo), weight)
                    continue
                # HG with cos(theta) = +-cos w written without cancellation near the peak
                denom = ((1 + gk) ** 2 - 4 * gk * sin2) if upper else ((1 - gk) ** 2 + 4 * gk * sin2)
                f = np.exp(-ktk * path) / (denom * np.sqrt(denom))
                total[rows, k] += (1 - gk * gk) / (4 * np.pi) * np.einsum("ij,ij->i", f, weight)
        return total

    def render(self, kappa_a, kappa_s, g, brightness) -> np.ndarray:
        """Image (H, W, C) of the radiance at the camera; see ForwardModel."""
        ka, ks, gg, br = (np.broadcast_to(np.asarray(a, float), (len(self.channels),))
                          for a in (kappa_a, kappa_s, g, brightness))
        kt = ka + ks
        n_pix = self.shape[0] * self.shape[1]
        out = np.empty((*self.shape, len(self.channels)))
        scat = ks > 0
        lines = np.zeros((len(self._h), len(kt)))
        if scat.any():
            lines[:, scat] = self._line_integrals(kt[scat], gg[scat])
        for k in range(len(self.channels)):
            if self.light.type == "bulb":
                r = self.light.radius
                a = kt[k] * r
                # a > A_OPAQUE: the light is attenuated by < e^-600 over one bulb radius, and the
                # camera is farther than that from the bulb: no glow reaches it
                e_cap = 0.0 if a > A_OPAQUE else np.exp(log_cap_attenuation(a))
                intensity = np.pi * r * r * br[k] * e_cap
            else:
                intensity = br[k]
            rad = intensity * ks[k] / self._h * lines[:, k]
            if self.light.type == "bulb":
                rad = rad + np.where(self._hit, br[k] * np.exp(-kt[k] * self._s_hit), 0.0)
            out[..., k] = np.bincount(self._pix, weights=self._wts * rad,
                                      minlength=n_pix).reshape(self.shape)
        return self._box_filter(out) if self.box_filter else out

    def _box_filter(self, img: np.ndarray) -> np.ndarray:
        """Pixel-footprint average from the samples: midpoint rule + its second-order term.

        The composite midpoint rule with n x n samples errs by (1 / (24 n^2)) times the
        laplacian in pixel units; the laplacian is taken from the image itself, on pixels
        whose neighbours are regular samples (elsewhere the footprint is sampled finely).
        """
        lap = np.zeros_like(img)
        lap[1:-1, 1:-1] = (img[:-2, 1:-1] + img[2:, 1:-1] + img[1:-1, :-2] + img[1:-1, 2:]
                           - 4 * img[1:-1, 1:-1])
        return img + np.where(self._smooth[..., None], self._lap_scale * lap, 0.0)

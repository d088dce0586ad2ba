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
from scipy import ndimage, sparse

from ..geometry import WaterRays, pixel_angle, pixel_grid, trace_to_water
from ..medium import hg_phase_half_angle
from ..spec import Camera, Spec
from .base import check_render_args
from .bulb_cap import (
    A_OPAQUE,
    CAP_A_MAX,
    _gauss_legendre,
    _matvec_add,
    cap_table,
    log_cap_attenuation,
)
from .chebyshev import chebyshev_points, lagrange_weights

_HALF_PI = 0.5 * np.pi
HALO_FOOTPRINTS = 8.0  # the bulb's halo: pixels whose ray passes within r + 8 footprints
HALO_SUB = 4
#: a spot's pixels sampled more finely (``_build``): those whose ray passes within this many
#: footprints of the point source (glow ~ 1/h), with SPOT_APEX_SUB samples per side, and the
#: cone's silhouette (a pixel whose centre ray meets the cone next to one whose does not),
#: with SPOT_EDGE_SUB.  Measured on capture_specs/spot.yaml, Lowfat Milk 16 ml (docs/physics.md,
#: "The spot"): pixel centres alone gave 0.079 chi2/pixel of model error and +26 % of the glow
SPOT_APEX_FOOTPRINTS = 8.0
SPOT_APEX_SUB = 16
SPOT_EDGE_SUB = 8
#: ``SingleScattering.tabulate``: Chebyshev points per axis of (log kappa_t, atanh g)
TABLE_POINTS = 7


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
    spot_supersample : (int, int)
        A spot's samples per pixel side near its apex (the point source) and on its cone's
        silhouette (``SPOT_APEX_SUB``, ``SPOT_EDGE_SUB``; 1, 1: the regular samples).
    """

    def __init__(self, spec: Spec, image_index: int | None = 0, *, channels: tuple[str, ...] | None = None,
                 nodes: int = 8, nodes_upper: int = 8, supersample: int = 1,
                 bulb_supersample: int = 8, halo_supersample: int = HALO_SUB,
                 box_filter: bool = True,
                 spot_supersample: tuple[int, int] = (SPOT_APEX_SUB, SPOT_EDGE_SUB)):
        self.spec = spec
        use = image_index is not None and spec.images
        self.camera: Camera = spec.camera_for(image_index) if use else spec.camera
        self.light = spec.light_for(image_index) if use else spec.light
        self.channels = tuple(channels or spec.channels)
        self.shape = (self.camera.height, self.camera.width)
        self.nodes, self.nodes_upper = int(nodes), int(nodes_upper)
        self._rules = {n: _gauss_legendre(n) for n in {self.nodes, self.nodes_upper}}
        self._frozen: list | None = None
        self._table: _ImageTable | None = None  # tabulate()
        self._cap_cells: np.ndarray | None = None
        self._freezing = False
        self._work = threading.local()  # arrays reused by the adaptive renders' cap matrices
        self.box_filter = box_filter
        self._spot_sub = tuple(int(n) for n in spot_supersample)
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
        # phase function curves too fast for the second-order footprint correction); a spot's
        # silhouette and apex: ``spot_supersample``.  `zone`: pixels sampled finely
        sub_map = np.full(self.shape, sub)
        centre, _, _ = self._rays(1)
        h_c = self._closest(centre, c)[1].reshape(self.shape)
        footprint = np.linalg.norm(c - self.camera.position) * pixel_angle(self.camera)
        if self.light.type == "bulb":
            zone = h_c < self.light.radius + HALO_FOOTPRINTS * footprint
            sub_map[zone] = max(sub, halo_sub)
            sub_map[h_c < self.light.radius + 2.0 * footprint] = max(sub, bulb_sub)
        else:  # a spot: its cone's silhouette and its apex (a point source, glow ~ 1/h)
            s_in, s_out = _cone_interval(centre.origin - c, centre.direction,
                                         self.light.direction, self.light.cutoff_deg)
            meets = ((np.minimum(centre.length, s_out) > np.maximum(s_in, 0.0))
                     & (centre.factor > 0)).reshape(self.shape)
            edge = ndimage.binary_dilation(meets) & ndimage.binary_dilation(~meets)
            apex = h_c < SPOT_APEX_FOOTPRINTS * footprint
            zone = edge | apex
            sub_map[edge] = max(sub, self._spot_sub[1])
            sub_map[apex] = max(sub, self._spot_sub[0])
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
        self.support = (np.bincount(self._pix, minlength=self.shape[0] * self.shape[1])
                        .reshape(self.shape) > 0)
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
        buf = self._scratch(upper, (len(sel), n))
        span = np.arcsinh((w_b - w_a) / eps)
        e2 = 0.5 * eps
        et = np.multiply(span[:, None], x01[None, :], out=buf["weight"])
        np.exp(et, out=et)
        inv = np.divide(1.0, et, out=buf["t"])
        w = np.subtract(et, inv, out=buf["w"])
        w *= e2[:, None]  # sinh map anchored at w_a (or at w_b when from_end)
        if from_end.any():
            w[:] = np.where(from_end[:, None], w_b[:, None] - w, w_a[:, None] + w)
        else:
            w += w_a[:, None]
        et += inv
        et *= (e2 * span)[:, None]
        et *= w01[None, :]
        weight = et
        t = np.multiply(w, 0.5, out=inv)
        np.tan(t, out=t)  # one tan instead of sin and cos of w/2 (numpy's are 8x slower)
        t2 = np.multiply(t, t, out=buf["sin2"])
        tmp = buf["tmp"]
        path = buf["path"]
        all_rays = len(sel) == len(self._h)
        h, s0 = ((self._h, self._s0) if all_rays else (self._h[sel], self._s0[sel]))
        with np.errstate(divide="ignore"):
            (np.divide if upper else np.multiply)(h[:, None], t, out=path)
        path += s0[:, None]
        mat = None
        if r_bulb > 0:  # exact solid angle of the sphere instead of pi r^2 / d^2
            rho = self._rho if all_rays else self._rho[sel]
            sin_alpha = np.add(1.0, t2, out=tmp)  # r/d = rho sin(w) = rho 2t / (1 + t^2)
            np.divide(t, sin_alpha, out=sin_alpha)
            sin_alpha *= 2.0 * rho[:, None]
            np.minimum(sin_alpha, 1.0, out=sin_alpha)
            # Omega / (pi r^2 / d^2) = 2 (1 - cos alpha) / sin^2 alpha = 2 / (1 + cos alpha)
            cos_alpha = np.multiply(sin_alpha, sin_alpha, out=t)  # t is not needed any more
            np.subtract(1.0, cos_alpha, out=cos_alpha)
            np.sqrt(cos_alpha, out=cos_alpha)
            cos_alpha += 1.0
            np.divide(2.0, cos_alpha, out=cos_alpha)
            weight *= cos_alpha
            hit = self._cap_hit[sel] & (not upper)
            if not hasattr(self._work, "by_half"):
                self._work.by_half = {}
            work = None if self._freezing else self._work.by_half.setdefault(upper, {})
            if upper:
                np.subtract(np.pi, w, out=w)  # theta_c = pi - w
            mat = cap_table().matrix(w, sin_alpha, self._cap_row[sel], self._cap_frac[sel], hit,
                                     work)
        sin2 = np.add(1.0, t2, out=tmp)
        np.divide(t2, sin2, out=t2)  # sin^2(w/2) = t^2 / (1 + t^2)
        return path, t2, weight, mat

    def _scratch(self, upper: bool, shape: tuple[int, int]) -> dict:
        """Arrays of ``shape`` for one half's nodes, reused from render to render (new ones
        while freezing: the frozen node set keeps them)."""
        names = ("weight", "t", "w", "sin2", "tmp", "path")
        if self._freezing:
            return {k: np.empty(shape) for k in names}
        if not hasattr(self._work, "nodes"):
            self._work.nodes = {}
        buf = self._work.nodes.get(upper)
        if buf is None or buf["w"].shape != shape:
            buf = self._work.nodes[upper] = {k: np.empty(shape) for k in names}
        return buf

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
        self._table = None

    def unfreeze_nodes(self) -> None:
        self._frozen = None
        self._cap_cells = None
        self._table = None

    def _line_integrals(self, kt: np.ndarray, g: np.ndarray, nodes_for: int | None = None
                        ) -> np.ndarray:
        """int p exp(-kt (d+s)) (source factor) dphi per ray and channel, shape (N, C).

        For the bulb p is the cap average pbar (log pbar from the cap table).  Unless frozen,
        the nodes suit every channel (the narrowest peak's), or only channel ``nodes_for``
        (the camera paths' points: the first one's value is then that of it alone)."""
        sel = slice(None) if nodes_for is None else slice(nodes_for, nodes_for + 1)
        panels = self._frozen if self._frozen is not None else self._nodes(kt[sel], g[sel])
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
                # HG at cos(theta) = +-cos w: sin^2(theta/2) = sin^2(w/2) on the lower half,
                # 1 - sin^2(w/2) on the upper one (no cancellation near the forward peak)
                f = np.exp(-ktk * path)
                f *= hg_phase_half_angle(1.0 - sin2 if upper else sin2, gk)
                total[rows, k] += np.einsum("ij,ij->i", f, weight)
        return total

    def render(self, kappa_a, kappa_s, g, brightness) -> np.ndarray:
        """Image (H, W, C) of the radiance at the camera; see ForwardModel.  Within the box of a
        table (``tabulate``) the image is interpolated from it."""
        ka, ks, gg, br = check_render_args(len(self.channels), kappa_a, kappa_s, g, brightness)
        kt = ka + ks
        table = getattr(self, "_table", None)  # (_line_model's copies have none)
        if table is not None:
            img = table.image(kt, ks, gg, br)
            if img is not None:
                return img
        scattered, direct = self._parts(kt, gg, ks > 0)
        out = scattered * (ks * br)
        return out if direct is None else out + direct * br

    def _parts(self, kt: np.ndarray, gg: np.ndarray, scat: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray | None]:
        """Per unit brightness, (H, W, C) each: the scattered light per unit kappa_s (0 where
        not ``scat``) and the bulb seen directly through the liquid (None for a spot), so
        that the image is brightness * (kappa_s * scattered + direct).  Box-filtered (the
        filter is linear)."""
        n_pix = self.shape[0] * self.shape[1]
        lines = np.zeros((len(self._h), len(kt)))
        if scat.any():
            lines[:, scat] = self._line_integrals(kt[scat], gg[scat])
        bulb = self.light.type == "bulb"
        scattered = np.empty((*self.shape, len(kt)))
        direct = np.zeros((*self.shape, len(kt))) if bulb else None
        hit = np.flatnonzero(self._hit)
        for k in range(len(kt)):
            intensity = 1.0
            if bulb:
                r = self.light.radius
                a = kt[k] * r
                # a > A_OPAQUE: the light is attenuated by < e^-600 over one bulb radius, and the
                # camera is farther than that from the bulb: no glow reaches it
                e_cap = 0.0 if a > A_OPAQUE else np.exp(log_cap_attenuation(a))
                intensity = np.pi * r * r * e_cap
                direct[..., k] = np.bincount(
                    self._pix[hit], weights=self._wts[hit] * np.exp(-kt[k] * self._s_hit[hit]),
                    minlength=n_pix).reshape(self.shape)
            scattered[..., k] = np.bincount(self._pix, weights=self._wts * (intensity / self._h)
                                            * lines[:, k], minlength=n_pix).reshape(self.shape)
        if self.box_filter:
            scattered = self._box_filter(scattered)
            direct = None if direct is None else self._box_filter(direct)
        return scattered, direct

    def tabulate(self, log_kt: tuple[float, float], atanh_g: tuple[float, float],
                 points: int = TABLE_POINTS) -> None:
        """Tabulate the image of this one-channel model on ``points`` x ``points`` Chebyshev
        points over the box ``log_kt`` x ``atanh_g`` (log of the extinction at this image,
        atanh of g; each a (low, high) pair); later renders inside the box interpolate the
        table (barycentric Lagrange interpolation, exact at the points), renders outside it
        compute the image.  The quadrature must be frozen (``freeze_nodes``); freezing,
        unfreezing or ``untabulate`` drop the table.  What it costs in accuracy is for the
        caller to check (``ChannelProblem.tabulated``)."""
        if len(self.channels) != 1 or self._frozen is None:
            raise ValueError("tabulate: one channel and frozen quadrature nodes only")
        self._table = _ImageTable(self, log_kt, atanh_g, int(points))

    def untabulate(self) -> None:
        self._table = None

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


class _ImageTable:
    """A one-channel model's image per unit brightness on a tensor grid of Chebyshev points
    (first kind) in (log kappa_t, atanh g): the scattered part per unit kappa_s at every grid
    point, the bulb seen directly (a function of kappa_t alone) at every log kappa_t point.
    ``image`` interpolates both with barycentric Lagrange weights (exact at the grid
    points; for the smooth dependence on the two coordinates the error falls geometrically
    with the points per axis, Trefethen, Approximation Theory and Approximation Practice,
    ch. 8)."""

    def __init__(self, model: SingleScattering, log_kt: tuple[float, float],
                 atanh_g: tuple[float, float], n: int):
        box = np.array([log_kt, atanh_g], float)
        if not (np.all(np.isfinite(box)) and np.all(box[:, 1] > box[:, 0]) and n >= 2):
            raise ValueError(f"tabulate: empty or non-finite box {box.tolist()}, {n} points")
        self.x, self.w = chebyshev_points(n)  # in (-1, 1); barycentric weights
        self.mid, self.half = box.mean(axis=1), 0.5 * (box[:, 1] - box[:, 0])
        self.shape = model.shape
        self.used = self.outside = 0  # renders from the table, renders outside its box
        u, v = self.mid[:, None] + self.half[:, None] * self.x
        rows, direct = [], []
        for i in range(n):
            for k in range(n):
                s, d = model._parts(np.array([np.exp(u[i])]), np.array([np.tanh(v[k])]),
                                    np.array([True]))
                rows.append(s.ravel())
                if k == 0:
                    direct.append(None if d is None else d.ravel())
        self.scattered = np.array(rows)  # (n * n, H * W), row i * n + k
        self.d_idx = None
        if direct[0] is not None:
            d = np.array(direct)
            self.d_idx = np.flatnonzero(np.any(d != 0.0, axis=0))
            self.direct = np.ascontiguousarray(d[:, self.d_idx])

    def _lagrange(self, t: float) -> np.ndarray:
        return lagrange_weights(self.x, self.w, t)

    def image(self, kt: np.ndarray, ks: np.ndarray, g: np.ndarray, br: np.ndarray
              ) -> np.ndarray | None:
        """The image (H, W, 1) at these one-channel values, or None outside the box."""
        if not (kt[0] > 0 and abs(g[0]) < 1):
            self.outside += 1
            return None
        t = (np.array([np.log(kt[0]), np.arctanh(g[0])]) - self.mid) / self.half
        if not np.all(np.abs(t) <= 1.0 + 1e-9):  # (the box's edges, after rounding)
            self.outside += 1
            return None
        self.used += 1
        lu, lv = self._lagrange(t[0]), self._lagrange(t[1])
        img = (np.outer(lu, lv).ravel() @ self.scattered) * (ks[0] * br[0])
        if self.d_idx is not None:
            img[self.d_idx] += br[0] * (lu @ self.direct)
        return img.reshape(*self.shape, 1)

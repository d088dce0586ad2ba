"""Light tracing from the bulb: the multiple-scattering term's higher orders.

Photons leave the bulb (a unit-radiance Lambertian sphere: power pi * 4 pi r^2, a uniform
point on the sphere and a cosine-weighted direction), fly the free-flight distance of the
medium (analog: no forcing, no guiding), scatter by Henyey–Greenstein, reflect at the front
wall (the Fresnel choice of ``PathTracer._walls``: its water/glass face, or through the
glass off its outer face), and end at a black wall or the bulb, or by Russian roulette at the
render's albedo.  Every collision is connected to the camera exactly: the ray from the
collision to the pinhole through the plane front wall is found by Newton's method, and the
collision's intensity I = power * p_HG(in, towards the camera) lands in the pixel it is seen
in as irradiance at the pinhole, I T exp(-kappa_t l) sin(theta_w) / (rho rho'(theta_a) n_w
cos(theta_w)), divided by the pixel's solid angle and by the fraction of it that sees the
water (the camera tracer's units, ``MultipleScattering.orders``).

Why: the camera tracer's per-pixel contributions are heavy-tailed (docs/multiple_scattering.md,
"Heavy tails per pixel"); a photon's contribution here is bounded (the camera is outside the
tank, the phase function is bounded), so the per-pixel error falls as photons^(-1/2) and is
not skewed.  ``MultipleScattering`` takes orders >= ``LIGHT_FROM_ORDER`` from here and the
lower ones (segment connections: smooth, cheap) from the camera tracer.

Finite differences come from the same photons reweighted (``variants``): a path traced at
(kappa_t, g) has, at (kappa_t', g'), the weight prod (kappa_t'/kappa_t) exp(-(kappa_t' -
kappa_t) s) over its flights (s the whole flight, before and after a reflection) times prod
p_HG(g') / p_HG(g) over its scatterings; its connections are evaluated at (kappa_t', g').
Unbiased for any (kappa_t', g'), and the images at the three points share every photon, so
the differences carry no pixel-to-pixel decorrelation.

Units and albedo as ``PathTracer.trace``: per order, albedo 1, a unit-radiance bulb.
"""

from __future__ import annotations

import numpy as np

from ..geometry import camera_rays, fresnel_transmittance, project
from ..medium import hg_phase
from .ms_paths import RR_MIN, PathTracer, around, box_exit, sample_hg, sphere_hit, uniforms

#: orders from this one up come from the photons (below: from the camera paths)
LIGHT_FROM_ORDER = 3
LIGHT_SALT = 0x5DEECE66D  # photons' random numbers: another stream than the camera paths'
PHOTON_CHUNK = 1 << 18
NEWTON_STEPS = 40  # at most; they stop once every angle moved by less than NEWTON_TOL
#: radians: Newton converges quadratically near the root, so the step after one this small
#: is at rounding (``LightTracer._chief``; 12 fixed steps were 18 % of a photon trace)
NEWTON_TOL = 1e-12


def pixel_solid_angles(camera, sub: int = 8) -> np.ndarray:
    """Solid angle (sr) of each pixel at the pinhole, (H*W,): ``sub`` x ``sub`` quads per
    pixel from the camera's rays at their corners (distortion included)."""
    xs = np.linspace(0.0, camera.width, camera.width * sub + 1)
    ys = np.linspace(0.0, camera.height, camera.height * sub + 1)
    d = camera_rays(camera, *np.meshgrid(xs, ys))
    area = 0.5 * np.linalg.norm(np.cross(d[1:, 1:] - d[:-1, :-1], d[:-1, 1:] - d[1:, :-1]), axis=-1)
    return area.reshape(camera.height, sub, camera.width, sub).sum(axis=(1, 3)).ravel()


class LightTracer:
    """Photons from a bulb, connected to the (low-resolution) camera of ``tracer``.

    ``cover``: the fraction of each sample pixel that sees the water (H*W,).
    """

    def __init__(self, tracer: PathTracer, cover: np.ndarray):
        if tracer.spot:
            raise ValueError("LightTracer: a bulb only (a spot's term is the camera tracer's)")
        self.tr, self.cam = tracer, tracer.camera
        omega = pixel_solid_angles(self.cam)
        self.norm = np.where(cover > 0, 1.0 / (omega * np.maximum(cover, 1e-12)), 0.0)
        self.o = np.asarray(self.cam.position, float)
        w = tracer.wall
        self.hz, self.t, self.nw, self.ng = tracer.half[2], w.thickness, w.n_water, w.n_glass

    # ------------------------------------------------------------------ camera
    def _chief(self, y: np.ndarray):
        """The ray from ``y`` (in the water) to the pinhole through the front wall: angle in
        the air theta_a, the water depth above ``y``, the lateral distance rho to the camera's
        axis through ``y`` and the unit lateral direction.

        Newton's method on u = tan theta_a: rho(u) = D u + t h_g(u) + a h_w(u), with
        h_n(u) = tan theta_n = u / sqrt(n^2 + (n^2 - 1) u^2) (Snell).  Each h_n is concave
        and increasing with slope 1/n at 0, so rho(u) is concave, the paraxial root
        rho / (D + t / n_g + a / n_w) is below the root, and from there Newton's iterates rise
        monotonically to it (no overshoot).  Until 2026-12-05 (stop 38) the iteration was on
        theta_a itself, where rho is convex: from the same start the first step overshot, and
        where it overshot past 90 degrees (the clip) 12 fixed steps had not come back; with
        a camera 14 mm from the glass, 78 of 4000 points in the tank ended up to 0.17 rad off
        (all outside that camera's view; none at the canonical 900 mm)."""
        a = self.hz - y[:, 2]
        far = self.o[2] - (self.hz + self.t)
        hvec = self.o[None, :2] - y[:, :2]
        rho = np.linalg.norm(hvec, axis=1)
        g2, w2 = self.ng * self.ng, self.nw * self.nw
        u = rho / (far + self.t / self.ng + a / self.nw)  # paraxial: below the root
        for _ in range(NEWTON_STEPS):
            u2 = u * u
            qg, qw = g2 + (g2 - 1.0) * u2, w2 + (w2 - 1.0) * u2
            rg, rw = 1.0 / np.sqrt(qg), 1.0 / np.sqrt(qw)
            f = u * (far + self.t * rg + a * rw) - rho
            df = far + self.t * g2 * rg / qg + a * w2 * rw / qw
            step = f / df
            u -= step
            if np.max(np.abs(step) / (1.0 + u * u), initial=0.0) < NEWTON_TOL:
                break
        th = np.arctan(u)
        hu = np.where(rho[:, None] > 0, hvec / np.maximum(rho, 1e-300)[:, None], 0.0)
        return th, a, rho, hu

    def toward_camera(self, y: np.ndarray) -> np.ndarray:
        """Unit directions in the water from ``y`` along the ray that reaches the pinhole."""
        th, _, _, hu = self._chief(y)
        sw = np.sin(th) / self.nw
        return np.column_stack([sw[:, None] * hu, np.sqrt(1 - sw * sw)])

    def connect(self, y: np.ndarray):
        """Per point: (pixel index or -1, unit direction in the water towards the camera,
        water path to the wall, irradiance factor T sin(theta_w) / (rho rho' n_w cos theta_w)
        times the pixel's 1 / (solid angle x water cover))."""
        th, a, rho, hu = self._chief(y)
        s, c = np.sin(th), np.cos(th)
        sg, sw = s / self.ng, s / self.nw
        cg, cw = np.sqrt(1 - sg * sg), np.sqrt(1 - sw * sw)
        df = (self.o[2] - self.hz - self.t) / (c * c) + self.t * c / (self.ng * cg**3) \
            + a * c / (self.nw * cw**3)
        w = np.column_stack([sw[:, None] * hu, cw])
        lw = a / cw
        s_over_rho = np.where(rho > 1e-9, sw / np.maximum(rho, 1e-300), 1.0 / (self.nw * df))
        trans = (fresnel_transmittance(c, 1.0, self.ng) * fresnel_transmittance(cg, self.ng, self.nw)
                 if self.t > 0 else fresnel_transmittance(c, 1.0, self.nw))
        px, py, front = project(self.cam, self.o - np.column_stack([s[:, None] * hu, c]))
        width, height = self.cam.width, self.cam.height
        with np.errstate(invalid="ignore"):
            ok = front & (px >= 0) & (px < width) & (py >= 0) & (py < height)
        ok &= self.tr._in_face(y + lw[:, None] * w) & (sphere_hit(y, w, self.tr.c, self.tr.r) > lw)
        pix = np.where(ok, np.floor(np.where(ok, py, 0)).astype(int) * width
                       + np.floor(np.where(ok, px, 0)).astype(int), -1)
        fac = np.where(ok, trans * s_over_rho / (df * self.nw * cw) * self.norm[np.maximum(pix, 0)], 0.0)
        return pix, w, lw, fac

    # ------------------------------------------------------------------- trace
    def trace(self, kt: float, g: float, n_photons: int, seed: int, batches: int,
              max_order: int = 400, rr_albedo: float = 1.0, from_order: int = LIGHT_FROM_ORDER,
              variants: tuple[tuple[float, float], ...] = ()) -> list[np.ndarray]:
        """Per-batch, per-order mean radiance at the sample pixels, (batches, max_order + 2,
        H*W) each, for orders >= ``from_order``, at (kt, g) and at each of ``variants``
        ((kappa_t, g) pairs) from the same photons reweighted.  Order 1 here is all of it:
        the analytic model's and the part lit through a front-wall reflection (a test's
        comparison with the analytic model; ``MultipleScattering`` takes orders >= 3)."""
        if from_order < 1:
            raise ValueError(f"from_order {from_order}: orders start at 1")
        points = ((float(kt), float(g)),) + tuple((float(a), float(b)) for a, b in variants)
        accs = [np.zeros((batches, max_order + 2, self.tr.n_pix)) for _ in points]
        for lo in range(0, n_photons, PHOTON_CHUNK):
            pid = np.arange(lo, min(n_photons, lo + PHOTON_CHUNK))
            self._trace_chunk(accs, points, pid, n_photons, seed, batches, max_order,
                              rr_albedo, from_order)
        return accs

    def _emit(self, pid: np.ndarray, seed: int):
        """Points on the bulb (just outside it) and cosine-weighted directions around its normal."""
        u = uniforms(seed + LIGHT_SALT, 0, pid, 4)
        zc = 1.0 - 2.0 * u[:, 0]
        ph = 2.0 * np.pi * u[:, 1]
        sz = np.sqrt(np.clip(1.0 - zc * zc, 0.0, None))
        nrm = np.column_stack([sz * np.cos(ph), sz * np.sin(ph), zc])
        x = self.tr.c + nrm * self.tr.r * (1.0 + 1e-9)
        return x, around(nrm, np.sqrt(u[:, 2]), 2.0 * np.pi * u[:, 3])

    def _fly(self, x, v, kt, u):
        """One free flight (analog, through a front-wall reflection): which photons collide,
        which of them without a reflection, where, their direction there and the whole
        flight's length."""
        s = -np.log1p(-u[:, 0]) / kt
        stop, (i, xi, vi, d2) = self.tr._walls(x, v, u[:, 1])
        coll = s < stop
        direct = coll.copy()
        rest = s[i] - stop[i]
        after = ~coll[i] & (rest < d2)  # reflected, and colliding before the next wall
        x = x + np.minimum(s, stop)[:, None] * v
        v = v.copy()
        j = i[after]
        x[j] = xi[after] + rest[after, None] * vi[after]
        v[j] = vi[after]
        coll[j] = True
        return coll, direct, x, v, s

    def _splat(self, accs, points, order, logr, cell, wgt, w_in, w_cam, lw, fac, extra=None):
        """Add one connection per photon to every point's image: weight x exp(log ratio) x
        p_HG(w_in . w_cam) at that point's g x exp(-kappa_t lw) x ``fac`` (x ``extra``, per
        point, where given), into order ``order`` at ``cell`` = batch * pixels + pixel."""
        cos_c = np.einsum("ij,ij->i", w_in, w_cam)
        for j, (acc, (ktj, gj)) in enumerate(zip(accs, points)):
            val = wgt * np.exp(logr[:, j] - ktj * lw) * hg_phase(cos_c, gj) * fac
            if extra is not None:
                val = val * extra[j]
            acc[:, order, :] += np.bincount(cell, weights=val, minlength=acc.shape[0] * acc.shape[2]
                                            ).reshape(acc.shape[0], acc.shape[2])

    def _trace_chunk(self, accs, points, pid, n_photons, seed, batches, max_order, rr_albedo,
                     from_order):  # long: one loop over the orders, its state in locals
        """The photons ``pid``: at every collision of order >= ``from_order``, two
        connections combined by the balance heuristic over the direction of the flight that
        led there: the photon's own (drawn from the phase function at the last scattering,
        pdf p1) and a second flight from that scattering drawn around the direction towards
        the camera (the same Henyey–Greenstein lobe, pdf p2).  Without the second, a photon
        that happens to fly towards the camera carries p_HG's peak into one pixel (33x
        the mean phase value for g = 0.93: a heavy tail per pixel); with it each connection
        is about the mean of the lobe's product.  Flights through a front-wall reflection
        only the first strategy makes: weight 1."""
        kt, g = points[0]
        n_pix = self.tr.n_pix
        q = float(np.clip(rr_albedo, RR_MIN, 1.0))
        x, v = self._emit(pid, seed)
        wgt = np.full(len(pid), np.pi * 4.0 * np.pi * self.tr.r ** 2 * batches / n_photons)
        logr = np.zeros((len(pid), len(points)))  # log of each point's weight over (kt, g)'s
        kts = np.array([p[0] for p in points])
        gs = [p[1] for p in points]
        mis = np.ones(len(pid))  # p1 / (p1 + p2) of the last flight's direction
        ids = pid
        for order in range(1, max_order + 1):
            if not len(ids):
                break
            u = uniforms(seed + LIGHT_SALT, order, ids, 8)
            coll, direct, x, v, s = self._fly(x, v, kt, u)
            ids, x, v, wgt, logr, s, u = ids[coll], x[coll], v[coll], wgt[coll], logr[coll], s[coll], u[coll]
            mis = np.where(direct[coll], mis[coll], 1.0)
            logr += np.log(kts / kt)[None, :] - s[:, None] * (kts - kt)[None, :]
            w_cam = None
            if order >= from_order and len(ids):
                pix, w_cam, lw, fac = self.connect(x)
                on = pix >= 0
                self._splat(accs, points, order, logr[on], (ids[on] % batches) * n_pix + pix[on],
                            wgt[on] * mis[on], v[on], w_cam[on], lw[on], fac[on])
            alive = u[:, 2] < q
            ids, x, v, wgt, logr, u = ids[alive], x[alive], v[alive], wgt[alive] / q, logr[alive], u[alive]
            v_new = sample_hg(v, g, u[:, 3], u[:, 4])
            cos_s = np.einsum("ij,ij->i", v, v_new)
            p1 = hg_phase(cos_s, g)
            mis = np.ones(len(ids))  # the next flight's; set below where it will connect
            if order + 1 >= from_order and len(ids):
                w0 = w_cam[alive] if w_cam is not None else self.toward_camera(x)
                mis = p1 / (p1 + hg_phase(np.einsum("ij,ij->i", w0, v_new), g))
                self._second_flight(accs, points, ids, x, v, w0, wgt, logr, u, order + 1, batches)
            for j in range(1, len(points)):
                if gs[j] != g:
                    logr[:, j] += np.log(hg_phase(cos_s, gs[j]) / p1)
            v = v_new

    def _second_flight(self, accs, points, ids, x, v_in, w0, wgt, logr, u, order, batches):
        """The second strategy of :meth:`_trace_chunk` at scattering points ``x`` (incoming
        ``v_in``, camera direction ``w0``): a direction from the phase lobe around ``w0``, a
        free flight (no reflection: else nothing), and the connection there, weighted
        F / (p1 + p2) for each point (its phase functions and kappa_t; the pdfs the base's)."""
        kt, g = points[0]
        v2 = sample_hg(w0, g, u[:, 5], u[:, 6])
        s2 = -np.log1p(-u[:, 7]) / kt
        d_box, _ = box_exit(x, v2, self.tr.half)
        ok = s2 < np.minimum(d_box, sphere_hit(x, v2, self.tr.c, self.tr.r))
        if not ok.any():
            return
        x2 = x[ok] + s2[ok, None] * v2[ok]
        pix, w_cam, lw, fac = self.connect(x2)
        on = pix >= 0
        sel = np.flatnonzero(ok)[on]
        cos_in = np.einsum("ij,ij->i", v_in[sel], v2[sel])
        denom = hg_phase(cos_in, g) + hg_phase(np.einsum("ij,ij->i", w0[sel], v2[sel]), g)
        extra = [hg_phase(cos_in, gj) / denom * (ktj / kt) * np.exp(-(ktj - kt) * s2[sel])
                 for ktj, gj in points]
        self._splat(accs, points, order, logr[sel], (ids[sel] % batches) * self.tr.n_pix + pix[on],
                    wgt[sel], v2[sel], w_cam[on], lw[on], fac[on], extra)

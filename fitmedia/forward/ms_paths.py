"""Vectorised numpy path tracer for the light the analytic model leaves out.

Paths start at the camera (through the front wall, ``geometry.trace_to_water``)
and random-walk in the tank: every vertex is forced onto its segment (the camera
ray's first two from a mixture of free flight, equiangular and forward-peak
sampling towards the bulb, later ones by free flight), directions come from a
mixture of Henyey–Greenstein and a guide towards the bulb, the five black walls
and the bulb end a segment, the front wall reflects it (Fresnel; total internal
reflection at the glass/air face beyond ~49 degrees in the water), and paths end
by Russian roulette.  The bulb's light is connected explicitly (a spot's likewise: its
analytic single scattering along the segments, clipped to its cone, and exact point-source
connections through the front wall, ``PathTracer._mirror_point``):

* along every segment after the first vertex: the single scattering towards the
  segment's start, by the analytic model's line integral (exact cap average);
* at a quarter of the vertices (weight 4), through one reflection at the
  water/glass face (the bulb's mirror image is an exact sphere: cap sampling,
  weight R_wg) and through the glass and one reflection at its outer face (a
  cone around the chief ray, found by Newton's method, wide enough to hold the
  shifted image; each sampled ray is traced exactly; weight
  T_wg^2 R_ga / (1 - R_wg R_ga), the internal reflections summed with the first
  one's lateral shift).

The weights carry no albedo: a contribution of order k is stored per order and
multiplied by albedo^k later, so one trace gives the image for every albedo.
Random numbers are a hash of (seed, order, path, dimension) (common random
numbers): a fixed seed makes the estimate a smooth function of kappa_t and g
except where a path changes its fate (wall, bulb, roulette).  See
docs/multiple_scattering.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import threading

from ..geometry import WaterRays, fresnel_transmittance, trace_to_water
from ..medium import hg_phase
from ..spec import Camera, Light, Tank
from .bulb_cap import A_OPAQUE, cap_table, log_cap_attenuation

#: Half-angle of the slab-mirror cone, as a multiple of asin(r / water path).
SLAB_CONE_MARGIN = 1.3
RR_MIN = 0.05  # lowest survival probability of the roulette
MIRROR_FRACTION = 0.25  # share of vertices that connect to the bulb through the front wall
N_UNIFORMS = 12  # random numbers per path and order
#: paths traced at once (PathTracer.trace): ~1 GB of temporaries; a loop's usual trace (256
#: paths on a 48 x 36 grid, 442 368 paths) is one chunk
TRACE_CHUNK = 1 << 20
MIX_FRACTION = 1.0 / 3.0  # vertices: free flight, equiangular, forward peak, a third each
MIX_ORDERS = 2  # vertices before this order use the mixture, later ones free flight only (its
# weights multiply: at milk 64 ml the batch spread was 1.99 with it at every order, 1.13 so)
GUIDE_ORDERS = 400  # scatterings up to this order draw towards the bulb too
GUIDE_FRACTION = 0.5  # share of scattering directions drawn towards the bulb (one-sample MIS)
#: a spot's direction guide and its vertices' equiangular sampling aim at its apex as at a bulb
#: of this radius (mm; the canonical bulb's): any width is unbiased, this one only steers
SPOT_GUIDE_RADIUS = 6.0


def frame(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors completing the unit vectors ``w`` (N, 3) to orthonormal frames
    (Duff et al. 2017, branchless)."""
    s = np.where(w[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (s + w[:, 2])
    b = w[:, 0] * w[:, 1] * a
    t = np.stack([1.0 + s * w[:, 0] ** 2 * a, s * b, -s * w[:, 0]], axis=1)
    bb = np.stack([b, s + w[:, 1] ** 2 * a, -w[:, 1]], axis=1)
    return t, bb


def around(w: np.ndarray, cos_t: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Unit directions at angle acos(cos_t) from ``w`` and azimuth ``phi``."""
    t, b = frame(w)
    sin_t = np.sqrt(np.clip(1.0 - cos_t * cos_t, 0.0, None))
    return (cos_t[:, None] * w + (sin_t * np.cos(phi))[:, None] * t
            + (sin_t * np.sin(phi))[:, None] * b)


def sample_hg(v: np.ndarray, g: float, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """New directions of travel after a Henyey–Greenstein scattering of ``v``."""
    if abs(g) < 1e-4:
        cos_t = 1.0 - 2.0 * u1
    else:
        q = (1.0 - g * g) / (1.0 - g + 2.0 * g * u1)
        cos_t = np.clip((1.0 + g * g - q * q) / (2.0 * g), -1.0, 1.0)
    return around(v, cos_t, 2.0 * np.pi * u2)


def guide_to(x: np.ndarray, c: np.ndarray, r: float, u1: np.ndarray, u2: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Directions drawn around the bulb's direction from x with density in solid angle
    p(theta) = K theta / ((theta^2 + alpha^2) sin theta), alpha = asin(r / d), on theta in
    [0, pi] (theta^2 = alpha^2 ((1 + pi^2 / alpha^2)^u - 1)): the 1/theta rise of the glow
    seen from x towards the bulb.  Returns (directions, axis, alpha, log(1 + pi^2 / alpha^2))."""
    dc = c - x
    d = np.linalg.norm(dc, axis=1)
    axis = dc / d[:, None]
    alpha = np.arcsin(np.minimum(r / d, 1.0))
    span = np.log1p((np.pi / alpha) ** 2)
    theta = alpha * np.sqrt(np.expm1(u1 * span))
    return around(axis, np.cos(np.minimum(theta, np.pi)), 2.0 * np.pi * u2), axis, alpha, span


def guide_pdf(w: np.ndarray, axis: np.ndarray, alpha: np.ndarray, span: np.ndarray) -> np.ndarray:
    """Density in solid angle of ``guide_to``'s directions ``w``."""
    cos_t = np.clip(np.einsum("ij,ij->i", w, axis), -1.0, 1.0)
    theta = np.arccos(cos_t)
    sin_t = np.sqrt(1.0 - cos_t * cos_t)
    ratio = np.where(theta > 1e-6, theta / np.maximum(sin_t, 1e-300), 1.0)
    return ratio / ((theta * theta + alpha * alpha) * np.pi * span)


def _as_points(kt, g) -> tuple[np.ndarray, np.ndarray, bool]:
    """(kappa_t, g) as 1-D arrays of the points to evaluate at, and whether both were scalars
    (the connections then return (N,) instead of (N, points))."""
    kts, gs = np.atleast_1d(np.asarray(kt, float)), np.atleast_1d(np.asarray(g, float))
    return kts, gs, np.ndim(kt) == 0 and np.ndim(g) == 0


def _per_point(val: np.ndarray, scalar: bool) -> np.ndarray:
    """``val`` (N, points) as the caller asked: (N,) for one scalar point."""
    return val[:, 0] if scalar else val


def sphere_hit(o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    """Distance along unit rays (o, d) to the first hit of the sphere (c, r); inf if none."""
    oc = c - o
    b = np.einsum("ij,ij->i", oc, d)
    h2 = np.einsum("ij,ij->i", oc, oc) - b * b
    disc = r * r - h2
    with np.errstate(invalid="ignore"):
        s = b - np.sqrt(disc)
    return np.where((disc > 0) & (s > 0), s, np.inf)


def box_exit(o: np.ndarray, d: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance to the tank's inner box along rays from inside, and whether the exit face
    is the front wall (z = +half_z)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = np.where(d > 0, half, -half)
        dist = np.where(d != 0, (bound - o) / d, np.inf)
    dist = np.clip(dist, 0.0, None)
    face = np.argmin(dist, axis=1)
    s = dist[np.arange(len(o)), face]
    return s, (face == 2) & (d[:, 2] > 0)


@dataclass(frozen=True)
class Wall:
    """The front wall seen from the water: indices and thickness."""

    n_water: float
    n_glass: float
    thickness: float

    def reflectances(self, cos_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R1, R2): reflection at the water/glass face, and through the glass off its outer
        face with the internal reflections summed; ``cos_w`` the cosine in the water."""
        if self.thickness <= 0:
            return 1.0 - fresnel_transmittance(cos_w, self.n_water, 1.0), np.zeros_like(cos_w)
        r_wg = 1.0 - fresnel_transmittance(cos_w, self.n_water, self.n_glass)
        sin_g = self.n_water / self.n_glass * np.sqrt(np.clip(1.0 - cos_w * cos_w, 0.0, 1.0))
        r_ga = 1.0 - fresnel_transmittance(np.sqrt(1.0 - sin_g * sin_g), self.n_glass, 1.0)
        t = 1.0 - r_wg
        return r_wg, t * t * r_ga / np.maximum(1.0 - r_wg * r_ga, 1e-12)

    def shift(self, d: np.ndarray) -> np.ndarray:
        """Lateral displacement (N, 3) of a ray of direction ``d`` (d_z > 0) that crosses the
        glass, reflects off its outer face and comes back: 2 t tan(theta_glass) outward."""
        sin_w = np.hypot(d[:, 0], d[:, 1])
        sin_g = self.n_water / self.n_glass * sin_w
        tan_g = sin_g / np.sqrt(1.0 - sin_g * sin_g)
        with np.errstate(invalid="ignore", divide="ignore"):
            k = np.where(sin_w > 0, 2.0 * self.thickness * tan_g / sin_w, 0.0)
        out = np.zeros_like(d)
        out[:, 0], out[:, 1] = k * d[:, 0], k * d[:, 1]
        return out

    def chief_angle(self, rho: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Angle theta in the water of the ray that reaches lateral offset ``rho`` after going
        down ``depth`` = (a + b) of water and back through the glass: Newton's method on
        depth tan(theta) + 2 t tan(theta_g) = rho, from the thin-wall root (convex, increasing
        function: the iterates decrease monotonically to the root)."""
        th = np.arctan2(rho, depth)
        m = self.n_water / self.n_glass
        for _ in range(5):
            s, c = np.sin(th), np.cos(th)
            sg = m * s
            cg = np.sqrt(1.0 - sg * sg)
            f = depth * s / c + 2 * self.thickness * sg / cg - rho
            df = depth / (c * c) + 2 * self.thickness * m * c / cg**3
            th = np.clip(th - f / df, 0.0, 0.5 * np.pi - 1e-9)
        return th


_M1, _M2 = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)


def uniforms(seed: int, order: int, ids: np.ndarray, n_dims: int) -> np.ndarray:
    """Counter-based uniforms in [0, 1) of shape (len(ids), n_dims): a function of (seed,
    order, path index, dimension) only (splitmix64's finaliser), so a path draws the same
    numbers whichever other paths are alive (common random numbers at a cost per live path)."""
    base = (ids.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
            + np.uint64((seed * 1_000_003 + order * 64) % (1 << 63)))
    z = base[:, None] + np.arange(n_dims, dtype=np.uint64)[None, :] * np.uint64(0xD1B54A32D192ED03)
    z ^= z >> np.uint64(30)
    z *= _M1
    z ^= z >> np.uint64(27)
    z *= _M2
    z ^= z >> np.uint64(31)
    return (z >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


class PathTracer:
    """The estimator for one camera (the low-resolution one), tank and light (bulb or spot).

    ``trace`` returns per batch, order and pixel the sum of path contributions for a
    unit-radiance bulb (a unit-intensity spot) and albedo 1 (multiply order k by albedo^k).
    """

    def __init__(self, camera: Camera, tank: Tank, water_ior: float, light: Light, single):
        from ..util import keep_freed_memory

        keep_freed_memory()  # its large temporaries: ~25 % of a trace in page faults otherwise
        self.camera, self.tank, self.light = camera, tank, light
        self.half = tank.half
        self.c = np.asarray(light.position, float)
        self.spot = light.type == "spot"
        # a spot (a point source in a cone) occludes nothing; its guide is as wide as a bulb
        # of SPOT_GUIDE_RADIUS (the beam near its apex, where the light is brightest)
        self.r = 0.0 if self.spot else float(light.radius)
        self.r_guide = SPOT_GUIDE_RADIUS if self.spot else self.r
        if self.spot:
            self.axis = np.asarray(light.direction, float)
            self.cos_cut = float(np.cos(np.radians(light.cutoff_deg)))
        self.wall = Wall(water_ior, tank.wall_ior, tank.wall_thickness)
        self.n_pix = camera.width * camera.height
        self.water_ior = water_ior
        self._single = single  # a SingleScattering of the same light: its line integrals

    # ------------------------------------------------------------ connections
    def _cap(self, x, centre, u1, u2):
        """Sample the cap of the sphere (centre, r) seen from x: (directions, solid angle,
        distance to the sphere along them)."""
        dc = centre - x
        d = np.linalg.norm(dc, axis=1)
        sin_a = np.minimum(self.r / d, 1.0)
        one_m_cos = sin_a * sin_a / (1.0 + np.sqrt(1.0 - sin_a * sin_a))
        cos_b = 1.0 - u1 * one_m_cos
        w = around(dc / d[:, None], cos_b, 2.0 * np.pi * u2)
        sin2_b = 1.0 - cos_b * cos_b
        ell = d * cos_b - np.sqrt(np.clip(self.r**2 - d * d * sin2_b, 0.0, None))
        return w, 2.0 * np.pi * one_m_cos, ell

    def _occluder(self, o, d):
        """Distance along unit rays (o, d) to the bulb (inf if missed); a spot occludes nothing."""
        return np.full(len(o), np.inf) if self.spot else sphere_hit(o, d, self.c, self.r)

    def _in_face(self, q):
        return (np.abs(q[:, 0]) < self.half[0]) & (np.abs(q[:, 1]) < self.half[1])

    def nee_mirror(self, x, v, kt, g, u):
        """Both one-reflection connections to the bulb through the front wall; ``kt``, ``g``
        scalars ((N,)) or arrays of points ((N, points): the geometry is shared, only the
        attenuation and the phase function are evaluated per point)."""
        if self.spot:
            return self._mirror_point(x, v, kt, g, 0.0) + (
                self._mirror_point(x, v, kt, g, self.wall.thickness)
                if self.wall.thickness > 0 else 0.0)
        kts, gs, scalar = _as_points(kt, g)
        hz = self.half[2]
        img = self.c.copy()
        img[2] = 2 * hz - img[2]
        # 1: the water/glass face, an exact plane mirror
        w, omega, ell = self._cap(x, np.broadcast_to(img, x.shape), u[:, 0], u[:, 1])
        s_q = (hz - x[:, 2]) / w[:, 2]
        q = x + s_q[:, None] * w
        r1, _ = self.wall.reflectances(w[:, 2])
        ok = self._in_face(q) & (sphere_hit(x, w, self.c, self.r) > s_q)
        cos_v = np.einsum("ij,ij->i", w, v)
        out = np.where(ok[:, None], (omega * r1)[:, None] * hg_phase(cos_v[:, None], gs[None, :])
                       * np.exp(-np.outer(ell, kts)), 0.0)
        if self.wall.thickness > 0:
            out = out + self._slab(x, v, kts, gs, u[:, 2], u[:, 3])
        return _per_point(out, scalar)

    def _mirror_point(self, x, v, kt, g, thickness):
        """A spot's light at ``x`` after one reflection at the front wall: at its water/glass
        face (``thickness`` 0, weight R1) or, through the glass, at its outer face (weight R2).
        Every interface is a plane parallel to the wall, so the ray from the apex to ``x`` is
        found exactly (Newton, ``Wall.chief_angle``) and the irradiance of a point source along
        it is I sin(theta) / (cos(theta) rho drho/dtheta), rho(theta) = depth tan(theta) +
        2 t tan(theta_glass) the lateral offset reached at polar angle theta in the water
        (rho = L sin(theta) and I / L^2 without the glass)."""
        hz = self.half[2]
        hvec = self.c[None, :2] - x[:, :2]
        rho = np.linalg.norm(hvec, axis=1)
        depth = (hz - x[:, 2]) + (hz - self.c[2])
        wall = Wall(self.wall.n_water, self.wall.n_glass, thickness)
        th = wall.chief_angle(rho, depth)
        s, c = np.sin(th), np.cos(th)
        m = wall.n_water / wall.n_glass
        cg = np.sqrt(1.0 - (m * s) ** 2)
        drho = depth / (c * c) + 2 * thickness * m * c / cg**3
        # sin(theta) / rho, with its limit 1 / drho(0) on the wall's normal through the apex
        s_over_rho = np.where(rho > 1e-9 * depth, s / np.maximum(rho, 1e-300), 1.0 / drho)
        irr = s_over_rho / (c * drho)
        hu = np.where(rho[:, None] > 0, hvec / np.maximum(rho, 1e-300)[:, None], 0.0)
        w = np.column_stack([s[:, None] * hu, c])  # from x towards the wall
        q1 = x + ((hz - x[:, 2]) / c)[:, None] * w
        q_back = q1 + wall.shift(w) if thickness > 0 else q1  # where it leaves the glass again
        emit = np.column_stack([-s[:, None] * hu, c])  # from the apex towards the wall
        ok = (self._in_face(q1) & self._in_face(q_back) & (emit @ self.axis >= self.cos_cut)
              & (x[:, 2] < hz) & (self.c[2] < hz))
        r1, r2 = self.wall.reflectances(c)  # the real wall's faces (``wall``: the geometry)
        refl = r2 if thickness > 0 else r1
        kts, gs, scalar = _as_points(kt, g)
        with np.errstate(invalid="ignore", over="ignore"):
            val = ((irr * refl)[:, None] * hg_phase(np.einsum("ij,ij->i", w, v)[:, None], gs[None, :])
                   * np.exp(-np.outer(depth / c, kts)))
        return _per_point(np.where(ok[:, None], val, 0.0), scalar)

    def _slab(self, x, v, kt, g, u1, u2):
        hz = self.half[2]
        hvec = self.c[None, :2] - x[:, :2]
        rho = np.linalg.norm(hvec, axis=1)
        depth = (hz - x[:, 2]) + (hz - self.c[2])
        th = self.wall.chief_angle(rho, depth)
        hu = np.where(rho[:, None] > 0, hvec / np.maximum(rho, 1e-300)[:, None], 0.0)
        chief = np.column_stack([np.sin(th)[:, None] * hu, np.cos(th)])
        water = depth / np.cos(th)
        sin_a = np.minimum(SLAB_CONE_MARGIN * self.r / water, 1.0)
        one_m_cos = sin_a * sin_a / (1.0 + np.sqrt(1.0 - sin_a * sin_a))
        w = around(chief, 1.0 - u1 * one_m_cos, 2.0 * np.pi * u2)
        up = w[:, 2] > 1e-9
        s_q = np.where(up, (hz - x[:, 2]) / np.where(up, w[:, 2], 1.0), 0.0)
        q1 = x + s_q[:, None] * w
        q2 = q1 + self.wall.shift(np.where(up[:, None], w, chief))
        wr = w * np.array([1.0, 1.0, -1.0])
        ell = sphere_hit(q2, wr, self.c, self.r)
        ok = (up & self._in_face(q1) & self._in_face(q2) & np.isfinite(ell)
              & (sphere_hit(x, w, self.c, self.r) > s_q))
        _, r2 = self.wall.reflectances(np.clip(w[:, 2], 0.0, 1.0))
        kts, gs, scalar = _as_points(kt, g)
        with np.errstate(invalid="ignore", over="ignore"):
            val = ((2 * np.pi * one_m_cos * r2)[:, None]
                   * hg_phase(np.einsum("ij,ij->i", w, v)[:, None], gs[None, :])
                   * np.exp(-np.outer(s_q + ell, kts)))
        return _per_point(np.where(ok[:, None], val, 0.0), scalar)

    # ------------------------------------------------------------------ segments
    def _segment_lines(self, o, v, length, kt, g):
        """Single scattering towards ``o`` along each ray (o, v, length) from a unit bulb,
        per unit albedo: the analytic model's line integral (exact cap average, sinh-mapped
        Gauss-Legendre nodes) run on arbitrary rays.  ``kt``, ``g``: scalars ((N,)) or
        arrays of points ((N, points), one set of nodes for all of them, the first point's:
        its value is that of it alone, bit for bit)."""
        kts, gs, scalar = _as_points(kt, g)
        out = np.zeros((len(o), len(kts)))
        live = length > 0
        if not live.any():
            return _per_point(out, scalar)
        seg = _line_model(self._single, o[live], v[live], length[live])
        lines = seg._line_integrals(kts, gs, nodes_for=0)
        if self.spot:  # a unit-intensity point source: SingleScattering.render's spot factor
            out[live] = kts[None, :] / seg._h[:, None] * lines
            return _per_point(out, scalar)
        a = kts * self.r
        e_cap = np.array([0.0 if ak > A_OPAQUE else np.exp(log_cap_attenuation(ak)) for ak in a])
        out[live] = (np.pi * self.r**2 * e_cap * kts)[None, :] / seg._h[:, None] * lines
        return _per_point(out, scalar)

    def _walls(self, x, v, u_r):
        """Where each ray from x along v meets the tank: distance to the first wall or the
        bulb, and for rays that reach the front wall and are reflected (Fresnel choice by
        ``u_r``): their index, restart point, reflected direction and free length."""
        d_box, front = box_exit(x, v, self.half)
        d_b = self._occluder(x, v)
        i = np.flatnonzero(front & (d_b > d_box))
        xi, vi = x[i] + d_box[i, None] * v[i], v[i].copy()
        r1, r2 = self.wall.reflectances(vi[:, 2])
        one = u_r[i] < r1
        two = ~one & (u_r[i] < r1 + r2)
        xi = xi + np.where(two[:, None], self.wall.shift(vi), 0.0)
        vi[:, 2] = -vi[:, 2]
        ok = (one | two) & self._in_face(xi)
        i, xi, vi = i[ok], xi[ok], vi[ok]
        d2 = np.minimum(box_exit(xi, vi, self.half)[0], self._occluder(xi, vi))
        return np.minimum(d_box, d_b), (i, xi, vi, d2)

    def _scatter(self, x, v, g, u, u_pick, guide=GUIDE_FRACTION):
        """New directions, from the phase function or towards the bulb (one-sample mixture),
        and their weights p_HG / p_mixture."""
        w_hg = sample_hg(v, g, u[:, 0], u[:, 1])
        w_gd, axis, alpha, span = guide_to(x, self.c, self.r_guide, u[:, 0], u[:, 1])
        w = np.where((u_pick < guide)[:, None], w_gd, w_hg)
        p_hg = hg_phase(np.einsum("ij,ij->i", w, v), g)
        if guide <= 0:
            return w, np.ones(len(w))
        p_mix = (1 - guide) * p_hg + guide * guide_pdf(w, axis, alpha, span)
        return w, p_hg / p_mix

    def _collide(self, x, v, kt, eps, u_s, u_pick, stop, refl, mix=MIX_FRACTION):
        """Forced next vertex on the segment (and its reflected part): a one-sample mixture,
        in equal parts, of the free-flight density truncated to the segment, equiangular
        sampling towards the bulb on the first part, and a sinh map of the angle to the bulb
        around its forward direction (width ``eps``).  Returns (alive, x, weight kt T(s) /
        p_mixture(s), the distance s flown to x)."""
        n = len(x)
        i, xi, vi, d2 = refl
        tail = np.zeros(n)
        tail[i] = d2
        total = stop + tail
        alive = total > 0
        p_col = -np.expm1(-kt * total)
        s_exp = -np.log1p(-u_s * p_col) / kt
        oc = self.c - x
        s0 = np.einsum("ij,ij->i", oc, v)
        h = np.maximum(np.sqrt(np.clip(np.einsum("ij,ij->i", oc, oc) - s0 * s0, 0.0, None)), 1e-9)
        th_a, th_b = np.arctan2(-s0, h), np.arctan2(stop - s0, h)
        # equiangular: phi uniform on [th_a, th_b]; forward: w = phi + pi/2 on a sinh map from
        # its low end (the bulb ahead: the phase function's forward peak, width eps)
        w_a, w_b = th_a + 0.5 * np.pi, th_b + 0.5 * np.pi
        span = np.arcsinh((w_b - w_a) / eps)
        phi = np.where(u_pick < 1 - mix, th_a + u_s * (th_b - th_a),
                       w_a + eps * np.sinh(u_s * span) - 0.5 * np.pi)
        s_ang = np.clip(s0 + h * np.tan(np.clip(phi, -0.5 * np.pi + 1e-12, 0.5 * np.pi - 1e-12)),
                        0.0, stop)
        s = np.where(u_pick < 1 - 2 * mix, s_exp, s_ang)
        dens = kt * np.exp(-kt * s)
        with np.errstate(divide="ignore", invalid="ignore"):
            p_e = np.where(alive, dens / p_col, 0.0)
            on = (s <= stop) & (th_b > th_a)
            jac = h / (h * h + (s - s0) ** 2)  # dphi / ds
            p_q = np.where(on, jac / (th_b - th_a), 0.0)
            w_s = np.arctan2(s - s0, h) + 0.5 * np.pi
            p_f = np.where(on, jac / (np.sqrt(eps * eps + (w_s - w_a) ** 2) * span), 0.0)
            wgt = np.where(alive, dens / ((1 - 2 * mix) * p_e + mix * (p_q + p_f)), 0.0)
        x = x + np.minimum(s, stop)[:, None] * v
        if len(i):
            past = s[i] > stop[i]
            x[i] = np.where(past[:, None], xi + (s[i] - stop[i])[:, None] * vi, x[i])
        return alive & (wgt > 0), x, wgt, s

    def _segment_nee(self, x, v, kts, gs, stop, refl):
        """Order-(k+1) light along the next segment (and its reflected part), (N, points)."""
        c = self._segment_lines(x, v, stop, kts, gs)
        i, xi, vi, d2 = refl
        if len(i):
            c[i] += np.exp(-np.outer(stop[i], kts)) * self._segment_lines(xi, vi, d2, kts, gs)
        return c

    # -------------------------------------------------------------------- trace
    def trace(self, kt: float, g: float, n_per_pixel: int, seed: int, batches: int,
              max_order: int = 400, rr_albedo: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Sums of contributions (batches, max_order + 1, H * W) and samples that entered the
        water per pixel (H * W,); index 0 of the order axis is unused.

        The paths are traced in chunks of at most ``TRACE_CHUNK`` (their random numbers are
        drawn by path id, so the chunks change only the order of the sums): the memory of a
        trace is bounded whatever the paths per pixel (measured: 11.7 GB peak RSS at 4096 paths
        on a 45 x 60 grid in one piece, 1.7 GB in chunks)."""
        accs, entered = self.trace_at(((kt, g),), n_per_pixel, seed, batches, max_order,
                                      rr_albedo)
        return accs[0], entered

    def trace_at(self, points, n_per_pixel: int, seed: int, batches: int,
                 max_order: int = 400, rr_albedo: float = 1.0
                 ) -> tuple[list[np.ndarray], np.ndarray]:
        """:meth:`trace` at each (kappa_t, g) of ``points`` from the paths of the first one
        reweighted (as the photons are, ``ms_light``): a path sampled at (kt, g) has at
        (kt', g') the weight prod (kt'/kt) exp(-(kt' - kt) s) over its flights (s the distance
        flown to each vertex) times prod p_HG(g') / p_HG(g) over its scatterings, and its
        connections are evaluated at (kt', g').  Unbiased at any point; the points share every
        path and the geometry of every connection (one set of quadrature nodes per segment,
        the first point's), so their differences carry no path-to-path noise, at about a
        third of the cost of tracing each point.  Returns one sum per point and the samples
        that entered the water."""
        points = tuple((float(a), float(b)) for a, b in points)
        n = self.n_pix * n_per_pixel
        accs = [np.zeros((batches, max_order + 1, self.n_pix)) for _ in points]
        entered = np.zeros(self.n_pix)
        for lo in range(0, n, TRACE_CHUNK):
            entered += self._trace_chunk(accs, points, np.arange(lo, min(n, lo + TRACE_CHUNK)),
                                         n_per_pixel, seed, batches, max_order, rr_albedo)
        return accs, entered

    def _trace_chunk(self, accs: list[np.ndarray], points: tuple, pid: np.ndarray,
                     n_per_pixel: int, seed: int, batches: int, max_order: int,
                     rr_albedo: float) -> np.ndarray:  # long: one loop over the orders
        """:meth:`trace_at` for the paths ``pid`` (global ids): adds to ``accs``, returns the
        samples of these paths that entered the water per pixel."""
        kt, g = points[0]
        kts, gs = np.array([p[0] for p in points]), np.array([p[1] for p in points])
        moved_g = [j for j in range(1, len(points)) if gs[j] != g]
        pix = pid // n_per_pixel
        batch = pid % n_per_pixel % batches
        u0 = uniforms(seed, 0, pid, 4)
        cam = self.camera
        rays = trace_to_water(cam, self.tank, self.water_ior, pix % cam.width + u0[:, 0],
                              pix // cam.width + u0[:, 1])
        entered = np.bincount(pix, weights=(rays.factor > 0).astype(float), minlength=self.n_pix)
        length = np.minimum(rays.length, self._occluder(rays.origin, rays.direction))
        ids = np.flatnonzero((rays.factor > 0) & (length > 0))
        none = (np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
        v = rays.direction[ids]
        eps = float(np.clip((1 - abs(g)) / np.sqrt(abs(g) + 1e-3), 1e-3, 1.0))
        alive, x, wgt, s = self._collide(rays.origin[ids], v, kt, eps, u0[ids, 2], u0[ids, 3],
                                         length[ids], none)
        wgt = wgt * rays.factor[ids]
        w_ref = np.where(alive, wgt, 0.0)
        # each point's weight over the first one's (1 for the first: its sums are those of a
        # trace at that point alone, bit for bit)
        ratio = np.ones((len(ids), len(points)))
        ratio[:, 1:] = _flight_ratio(kts, kt, s)[:, 1:]
        ids, x, v, wgt, w_ref, ratio = ids[alive], x[alive], v[alive], wgt[alive], w_ref[alive], ratio[alive]
        a_rr = float(np.clip(rr_albedo, 0.0, 1.0))

        def add(order, values):  # values (paths, points)
            cell = batch[ids] * self.n_pix + pix[ids]
            for j, acc in enumerate(accs):
                w = wgt * ratio[:, j] * values[:, j]  # ratio[:, 0] is 1: as a lone trace
                acc[:, order, :] += np.bincount(cell, weights=w, minlength=batches * self.n_pix
                                                ).reshape(batches, -1)

        for k in range(1, max_order + 1):
            if not len(ids):
                break
            u = uniforms(seed, k, pid[ids], N_UNIFORMS)
            # the front-wall connections (~3e-4 of milk's term) for a random quarter of the
            # paths, weighted 4x: unbiased, and a fifth of the cost saved
            sel = np.flatnonzero(u[:, 0] < MIRROR_FRACTION)
            mirror = np.zeros((len(ids), len(points)))
            mirror[sel] = self.nee_mirror(x[sel], v[sel], kts, gs, u[sel, 2:6]) / MIRROR_FRACTION
            add(k, mirror)
            if k == max_order:  # the next segment's light would be of order max_order + 1
                break
            v_old = v
            v, f = self._scatter(x, v, g, u[:, 6:8], u[:, 11],
                                 GUIDE_FRACTION if k <= GUIDE_ORDERS else 0.0)
            wgt = wgt * f
            if moved_g:
                cos_s = np.einsum("ij,ij->i", v_old, v)
                p0 = hg_phase(cos_s, g)
                for j in moved_g:
                    ratio[:, j] *= hg_phase(cos_s, gs[j]) / p0
            stop, refl = self._walls(x, v, u[:, 9])
            add(k + 1, self._segment_nee(x, v, kts, gs, stop, refl))
            alive, x, f, s = self._collide(x, v, kt, eps, u[:, 8], u[:, 1], stop, refl,
                                           MIX_FRACTION if k < MIX_ORDERS else 0.0)
            wgt = wgt * f
            ratio[:, 1:] *= _flight_ratio(kts, kt, s)[:, 1:]
            # roulette on the weight the next order would carry at albedo rr_albedo
            q = np.clip(wgt * a_rr ** k / w_ref, RR_MIN, 1.0)
            alive &= u[:, 10] < q
            wgt = wgt / q
            ids, x, v, wgt, w_ref, ratio = ids[alive], x[alive], v[alive], wgt[alive], w_ref[alive], ratio[alive]
        return entered


def _flight_ratio(kts: np.ndarray, kt: float, s: np.ndarray) -> np.ndarray:
    """(paths, points): the density of a collision after a flight of ``s`` at each point's
    kappa_t over its density at ``kt``, (kt'/kt) exp(-(kt' - kt) s)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return (kts / kt)[None, :] * np.exp(-np.outer(s, kts - kt))


def _line_model(tpl, o, v, length):
    """A SingleScattering whose rays are (o, v, length) instead of the camera's, for its line
    integrals (the per-ray set-up of ``SingleScattering._build``)."""
    from .single import SingleScattering, _cone_interval

    seg = object.__new__(SingleScattering)
    seg.__dict__.update({k: tpl.__dict__[k] for k in ("light", "nodes", "nodes_upper", "_rules")})
    seg._frozen, seg._cap_cells, seg._freezing = None, None, False
    seg._work = threading.local()
    c, r = tpl.light.position, tpl.light.radius
    s0, h = SingleScattering._closest(WaterRays(o, v, length, length), c)
    if tpl.light.type == "spot":  # the rays clipped to the cone; no cap table
        s_in, s_out = _cone_interval(o - c, v, tpl.light.direction, tpl.light.cutoff_deg)
        lo, hi = np.maximum(s_in, 0.0), np.minimum(length, s_out)
        seg._s0, seg._h = s0, np.maximum(h, 1e-9 * max(tpl.spec.tank.inner_size))
        empty = hi <= lo
        seg._phi_a = np.where(empty, 0.0, np.arctan2(lo - s0, seg._h))
        seg._phi_b = np.where(empty, 0.0, np.arctan2(hi - s0, seg._h))
        return seg
    s_hit = s0 - np.sqrt(np.clip(r * r - h * h, 0.0, None))
    hit = (h < r) & (s_hit > 0) & (s_hit < length)
    hi = np.where(hit, s_hit, length)
    h = np.maximum(h, 1e-9 * max(tpl.spec.tank.inner_size))
    seg._s0, seg._h, seg._rho = s0, h, r / h
    seg._cap_row, seg._cap_frac = cap_table().rows(seg._rho)
    seg._cap_hit = seg._rho >= 1.0
    empty = hi <= 0
    seg._phi_a = np.where(empty, 0.0, np.arctan2(-s0, h))
    seg._phi_b = np.where(empty, 0.0, np.arctan2(hi - s0, h))
    return seg

"""Full light transport with Mitsuba 3 (all scattering orders, or a chosen depth).

The scene is built from the capture spec in millimetres (see ``docs/mitsuba.md``):

* camera: Mitsuba's ``perspective`` sensor at ``camera.position`` looking at
  ``camera.look_at`` with ``camera.up``; horizontal field of view
  2 atan(W / (2 fx)) and principal point offsets (0.5 - cx/W, 0.5 - cy/H) in
  film fractions, which reproduces the pinhole of CAPTURE_SPEC.md (x to the
  right, y down, pixel (i, j) centred at (j + 0.5, i + 0.5)); a ``box``
  reconstruction filter so each pixel integrates its own footprint.  Mitsuba's
  perspective camera has square pixels: fx and fy must agree to 1e-3.
  With ``camera.distortion`` (which the perspective sensor cannot do) the sensor
  is a distortion-free pinhole (:func:`pinhole_cover`) at DISTORTION_OVERSAMPLE
  (3) times the camera's resolution whose image covers every ray of the camera's
  pixels, and each camera pixel is an area sample of that render over its
  undistorted footprint (:func:`resampler`; error measured in
  tests/test_distortion.py and docs/spec.md, "Lens distortion").
* front wall: two smooth ``dielectric`` rectangles the size of the tank's
  front face, air/glass at z = depth/2 + thickness and glass/water at
  z = depth/2 (one air/water rectangle when the thickness is 0).
* the other five walls: rectangles with a black ``diffuse`` BSDF (all light
  that reaches them is lost).
* the water: the six wall rectangles bound it; the glass/water rectangle
  carries the ``homogeneous`` medium (``hg`` phase function) as its interior,
  so camera rays enter the medium there.  sigma_t = kappa_t (1/mm, the scene is
  in mm), albedo = kappa_s / kappa_t.
* bulb: a ``sphere`` ``area`` emitter of radiance 1 with a black BSDF in the
  water; spot: a ``spot`` emitter of intensity 1 with
  ``cutoff_angle = beam_width = cutoff_deg`` (constant inside the cone).

Images are rendered per channel with a mono variant (unit light, then scaled
by the brightness), in the units of the ForwardModel interface: Mitsuba's
``dielectric`` scales transmitted radiance by (n_out / n_in)^2, so a pixel that
sees the bulb through clear water reads L_b T_air/glass T_glass/water / n_water^2.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from ..errors import InputError
from ..geometry import pixel_grid, trace_to_water, undistorted
from ..spec import Camera, Light, Spec
from .base import check_render_args

log = logging.getLogger(__name__)

#: Largest number of Monte Carlo samples (pixels x spp) traced in one wavefront.
MAX_SAMPLES_PER_PASS = 1 << 22
INTEGRATORS = ("volpath", "prbvolpath")
#: with lens distortion: pinhole render pixels per camera pixel side (at the principal point)
DISTORTION_OVERSAMPLE = 3
#: with lens distortion: cells per camera pixel side whose footprints are area-sampled
DISTORTION_SUB = 2


def _edge_midpoints(cam: Camera, scale: int, sub: int) -> tuple[np.ndarray, ...]:
    """Each camera pixel split into ``sub x sub`` cells: the undistorted midpoints of the cells'
    left, right, top and bottom edges (u0, u1, v0, v1, each (H*sub, W*sub)) in the pixel units
    of a pinhole with focal lengths ``scale`` fx, ``scale`` fy and principal point (0, 0)."""
    xe = np.arange(cam.width * sub + 1) / sub      # cell edges
    ye = np.arange(cam.height * sub + 1) / sub
    xc, yc = 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1])  # cell centres
    gx, gy = np.meshgrid(xe, yc)                  # midpoints of the vertical edges
    u, _ = undistorted(cam, gx, gy)
    gx, gy = np.meshgrid(xc, ye)                  # midpoints of the horizontal edges
    _, v = undistorted(cam, gx, gy)
    u, v = u * (scale * cam.fx), v * (scale * cam.fy)
    return u[:, :-1], u[:, 1:], v[:-1, :], v[1:, :]


def pinhole_cover(cam: Camera, scale: int = DISTORTION_OVERSAMPLE,
                  sub: int = DISTORTION_SUB) -> Camera:
    """A distortion-free camera at ``cam``'s pose, focal lengths ``scale`` times ``cam``'s,
    whose image covers the undistorted footprints of all of ``cam``'s pixels with a margin
    of 2 pixels."""
    import dataclasses

    u0, u1, v0, v1 = _edge_midpoints(cam, scale, sub)
    x0, y0 = math.floor(min(u0.min(), u1.min())) - 2, math.floor(min(v0.min(), v1.min())) - 2
    x1, y1 = math.ceil(max(u0.max(), u1.max())) + 2, math.ceil(max(v0.max(), v1.max())) + 2
    return dataclasses.replace(cam, width=x1 - x0, height=y1 - y0, fx=scale * cam.fx,
                               fy=scale * cam.fy, cx=float(-x0), cy=float(-y0), distortion=None)


def _overlaps(a: np.ndarray, b: np.ndarray, size: int) -> tuple[list, list]:
    """Pixel indices and the shares of the interval [a, b] (a < b) that pixels [k, k+1] hold."""
    first = np.floor(a).astype(int)
    n = int(np.ceil(np.max(b - a))) + 1
    idx = [first + k for k in range(n)]
    share = [np.clip(np.minimum(b, k + 1) - np.maximum(a, k), 0.0, None) / (b - a) for k in idx]
    return [np.clip(k, 0, size - 1) for k in idx], share


def resampler(cam: Camera, cover: Camera, scale: int = DISTORTION_OVERSAMPLE,
              sub: int = DISTORTION_SUB):
    """Sparse (H*W, h*w) matrix from the ``cover`` pinhole image (h, w) to ``cam``'s pixels,
    an area sample: each camera pixel is split into ``sub x sub`` cells, each cell's
    undistorted footprint is taken as the axis-aligned rectangle through its edges'
    midpoints, and the pinhole pixels are weighted by the exact share of that rectangle
    they hold (without distortion: each camera pixel the mean of its scale x scale pixels)."""
    from scipy import sparse

    u0, u1, v0, v1 = _edge_midpoints(cam, scale, sub)
    cols_j, wx = _overlaps(u0 + cover.cx, u1 + cover.cx, cover.width)
    rows_i, wy = _overlaps(v0 + cover.cy, v1 + cover.cy, cover.height)
    pix = np.arange(cam.height * cam.width).reshape(cam.height, cam.width)
    pix = np.repeat(np.repeat(pix, sub, axis=0), sub, axis=1)
    rows, cols, vals = [], [], []
    for i, a in zip(rows_i, wy):
        for j, b in zip(cols_j, wx):
            w = (a * b).ravel()
            keep = w > 0
            rows.append(pix.ravel()[keep])
            cols.append((i * cover.width + j).ravel()[keep])
            vals.append(w[keep] / sub**2)
    return sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(cam.height * cam.width, cover.height * cover.width))


def single_scattering_depth(spec: Spec) -> int:
    """Mitsuba ``max_depth`` that renders scattering orders 0 and 1 exactly.

    Every surface crossing counts as one bounce in Mitsuba's path depth, so a
    camera path is: camera -> air/glass (1) -> glass/water (2) -> scattering
    point (3) -> light (4).  With a front wall of thickness 0 there is one
    interface less.  ``single_scattering_depth(spec) - 1`` renders order 0
    only (the bulb seen directly).  Verified in ``tests/test_mitsuba_forward.py``.
    """
    return 4 if spec.tank.wall_thickness > 0 else 3


def _geometry_of(spec: Spec, image_index: int | None) -> tuple[Camera, Light]:
    """Camera and light of image ``image_index``; None (or a spec without images):
    the spec's base camera and light (the clear-water photo)."""
    if image_index is None or not spec.images:
        if image_index not in (None, 0):
            raise InputError(f"image_index: got {image_index}, the spec has no images (use 0)")
        return spec.camera, spec.light
    if not 0 <= image_index < len(spec.images):
        raise InputError(f"image_index: got {image_index}, the spec has {len(spec.images)} "
                         f"image(s) (0 .. {len(spec.images) - 1})")
    return spec.camera_for(image_index), spec.light_for(image_index)


def _sensor_dict(mi, cam: Camera) -> dict:
    if abs(cam.fx - cam.fy) > 1e-3 * cam.fx:
        raise InputError(f"camera.fy: got {cam.fy:g} with fx {cam.fx:g}: Mitsuba's perspective "
                         f"camera needs square pixels (fx == fy to 1e-3)")
    fov = math.degrees(2.0 * math.atan(0.5 * cam.width / cam.fx))
    return {
        "type": "perspective", "fov": fov, "fov_axis": "x",
        "principal_point_offset_x": 0.5 - cam.cx / cam.width,
        "principal_point_offset_y": 0.5 - cam.cy / cam.height,
        "near_clip": 1e-2, "far_clip": 1e7,
        "to_world": mi.ScalarTransform4f().look_at(origin=cam.position.tolist(),
                                                   target=cam.look_at.tolist(), up=cam.up.tolist()),
        "sampler": {"type": "independent"},
        "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height,
                 "rfilter": {"type": "box"}, "pixel_format": "luminance",
                 "component_format": "float32"},
    }


def _rect(mi, center, axis: int, sign: float, half_a: float, half_b: float) -> dict:
    """A rectangle centred at ``center`` with normal ``sign * e_axis``.

    Its half-extents are (half_a, half_b) along the two other axes, in order.
    """
    T = mi.ScalarTransform4f
    if axis == 2:
        rot = T() if sign > 0 else T().rotate([0, 1, 0], 180)
    elif axis == 0:
        rot = T().rotate([0, 1, 0], 90 * sign)   # +z -> +-x; local x -> -+z, y -> y
        half_a, half_b = half_b, half_a           # local x spans z, local y spans y
    else:
        rot = T().rotate([1, 0, 0], -90 * sign)  # +z -> +-y; local y spans z
    return {"type": "rectangle",
            "to_world": T().translate(list(map(float, center))) @ rot @ T().scale([half_a, half_b, 1])}


def _light_dict(mi, light: Light) -> dict:
    black = {"type": "diffuse", "reflectance": 0.0}
    if light.type == "bulb":
        return {"type": "sphere", "center": light.position.tolist(), "radius": light.radius,
                "emitter": {"type": "area", "radiance": 1.0}, "bsdf": black}
    d = np.asarray(light.direction, float)
    up = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    return {"type": "spot", "intensity": 1.0, "cutoff_angle": float(light.cutoff_deg),
            "beam_width": float(light.cutoff_deg),
            "to_world": mi.ScalarTransform4f().look_at(
                origin=light.position.tolist(), target=(light.position + d).tolist(),
                up=up.tolist())}


def scene_dict(mi, spec: Spec, image_index: int | None = 0, *, max_depth: int = -1,
               integrator: str = "volpath", sensor: Camera | None = None) -> dict:
    """The Mitsuba scene dictionary of one image of ``spec`` (unit light, clear medium).

    The medium has id ``water`` (parameters ``water.sigma_t.value.value``,
    ``water.albedo.value.value``, ``water.phase_function.g``), the light id ``light``.
    ``sensor``: the camera rendered (default the image's; with lens distortion
    :func:`pinhole_cover` of it).
    """
    if integrator not in INTEGRATORS:
        raise InputError(f"integrator: got {integrator!r}, expected one of {', '.join(INTEGRATORS)}")
    cam, light = _geometry_of(spec, image_index)
    if sensor is not None:
        cam = sensor
    elif cam.distortion is not None:
        cam = pinhole_cover(cam)
    hx, hy, hz = spec.tank.half
    t = spec.tank.wall_thickness
    n_w, n_g = spec.medium_ior, spec.tank.wall_ior
    black = {"type": "diffuse", "reflectance": 0.0}
    d: dict = {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": int(max_depth)},
        "sensor": _sensor_dict(mi, cam),
        "water": {"type": "homogeneous", "sigma_t": 0.0, "albedo": 0.0, "scale": 1.0,
                  "phase": {"type": "hg", "g": 0.0}},
        "light": _light_dict(mi, light),
    }
    inner = _rect(mi, (0, 0, hz), 2, +1, hx, hy)
    if t > 0:
        d["wall_air_glass"] = {**_rect(mi, (0, 0, hz + t), 2, +1, hx, hy),
                               "bsdf": {"type": "dielectric", "int_ior": n_g, "ext_ior": 1.0}}
        d["wall_glass_water"] = {**inner, "bsdf": {"type": "dielectric", "int_ior": n_w,
                                                   "ext_ior": n_g},
                                 "interior": {"type": "ref", "id": "water"}}
    else:
        d["wall_air_water"] = {**inner, "bsdf": {"type": "dielectric", "int_ior": n_w,
                                                 "ext_ior": 1.0},
                               "interior": {"type": "ref", "id": "water"}}
    # the five black walls, normals pointing out of the water
    d["wall_back"] = {**_rect(mi, (0, 0, -hz), 2, -1, hx, hy), "bsdf": black}
    d["wall_left"] = {**_rect(mi, (-hx, 0, 0), 0, -1, hy, hz), "bsdf": black}
    d["wall_right"] = {**_rect(mi, (hx, 0, 0), 0, +1, hy, hz), "bsdf": black}
    d["wall_bottom"] = {**_rect(mi, (0, -hy, 0), 1, -1, hx, hz), "bsdf": black}
    d["wall_top"] = {**_rect(mi, (0, hy, 0), 1, +1, hx, hz), "bsdf": black}
    return d


class MitsubaModel:
    """Monte Carlo image of one capture with Mitsuba 3 (ForwardModel interface).

    Parameters
    ----------
    spec : Spec
        The capture spec (geometry only).
    image_index : int or None
        Which image's camera/light overrides to use; None for the spec's base
        camera and light (the clear-water photo).
    spp : int
        Samples per pixel per channel.
    max_depth : int
        Mitsuba's longest path (-1: unlimited); see :func:`single_scattering_depth`.
    seed : int
        Seed of the sampler; the same seed gives the same image (and the same
        random numbers for every channel and every parameter value).
    integrator : {"volpath", "prbvolpath"}
    channels : tuple of str, optional
        Channels rendered, default ``spec.channels``.
    variant : str, optional
        Mitsuba variant; default: :func:`fitmedia.mitsuba_env.choose_variant`.
    oversample : int
        Only with ``camera.distortion``: pinhole render pixels per camera pixel side
        (:func:`pinhole_cover`, :func:`resampler`); ``spp`` stays per camera pixel.
    """

    def __init__(self, spec: Spec, image_index: int | None = 0, *, spp: int = 256, max_depth: int = -1,
                 seed: int = 0, integrator: str = "volpath",
                 channels: tuple[str, ...] | None = None, variant: str | None = None,
                 oversample: int = DISTORTION_OVERSAMPLE):
        from ..mitsuba_env import import_mitsuba

        if int(spp) < 1:
            raise InputError(f"spp: got {spp}, expected a positive number of samples per pixel")
        if int(max_depth) < -1 or int(max_depth) == 0:
            raise InputError(f"max_depth: got {max_depth}, expected -1 (unlimited) or >= 1")
        self.spec = spec
        self.camera, self.light = _geometry_of(spec, image_index)
        self.channels = tuple(channels or spec.channels)
        self.shape = (self.camera.height, self.camera.width)
        x, y = pixel_grid(self.camera, sub=2)  # pixels whose footprint sees the water
        rays = trace_to_water(self.camera, spec.tank, spec.medium_ior, np.ravel(x), np.ravel(y))
        self.support = np.any(rays.factor.reshape(x.shape) > 0, axis=-1)
        self.spp, self.max_depth, self.seed = int(spp), int(max_depth), int(seed)
        sensor, self._resample = self.camera, None
        self._oversample = int(oversample)
        if self.camera.distortion is not None:  # a pinhole render, resampled (module docstring)
            if self._oversample < 1:
                raise InputError(f"oversample: got {oversample}, expected a positive integer")
            sensor = pinhole_cover(self.camera, self._oversample)
            self._resample = resampler(self.camera, sensor, self._oversample)
        self._render_shape = (sensor.height, sensor.width)
        self._mi = import_mitsuba(variant)
        self.variant = self._mi.variant()
        self._scene = self._mi.load_dict(scene_dict(self._mi, spec, image_index,
                                                    max_depth=self.max_depth, integrator=integrator,
                                                    sensor=sensor))
        self._params = self._mi.traverse(self._scene)
        self._state: tuple[float, float, float] | None = None

    # ------------------------------------------------------------------ core
    def _set_medium(self, kt: float, albedo: float, g: float) -> None:
        if self._state == (kt, albedo, g):
            return
        p = self._params
        p["water.sigma_t.value.value"] = kt
        p["water.albedo.value.value"] = albedo
        p["water.phase_function.g"] = g
        p.update()
        self._state = (kt, albedo, g)

    def _pass_plan(self, spp: int) -> list[int]:
        per = max(1, MAX_SAMPLES_PER_PASS // (self._render_shape[0] * self._render_shape[1]))
        n = -(-spp // per)
        base, extra = divmod(spp, n)
        return [base + (1 if k < extra else 0) for k in range(n)]

    def _seeds(self, n: int, stream: int = 0) -> list[int]:
        ss = np.random.SeedSequence([self.seed, stream])
        return [int(s) for s in ss.generate_state(n, dtype=np.uint32)]

    def _render_unit(self, kt: float, albedo: float, g: float, spp: int, seed: int) -> np.ndarray:
        """Mean over ``spp`` samples per camera pixel of the unit-light image (H, W), float64.
        With distortion the pinhole render has oversample^2 pixels per camera pixel at the
        centre, each with spp / oversample^2 samples (rounded up)."""
        self._set_medium(kt, albedo, g)
        if self._resample is not None:
            spp = -(-spp // self._oversample**2)
        plan = self._pass_plan(spp)
        seeds = [seed] if len(plan) == 1 else self._seeds(len(plan), seed)
        acc = np.zeros(self._render_shape)
        for n, s in zip(plan, seeds):
            img = np.asarray(self._mi.render(self._scene, spp=n, seed=s), dtype=np.float64)
            acc += n * (img[..., 0] if img.ndim == 3 else img)
        if self._resample is None:
            return acc / spp
        return (self._resample @ (acc / spp).ravel()).reshape(self.shape)

    def _batches(self, kappa_a, kappa_s, g, brightness, batches: int) -> np.ndarray:
        """Images of ``batches`` independent batches, shape (batches, H, W, C)."""
        ka, ks, gg, br = check_render_args(len(self.channels), kappa_a, kappa_s, g, brightness)
        spp_b = max(1, -(-self.spp // batches))
        seeds = [self.seed] if batches == 1 else self._seeds(batches, 1)
        out = np.empty((batches, *self.shape, len(self.channels)))
        t0 = time.perf_counter()
        units: dict[tuple, np.ndarray] = {}  # channels with the same medium share a render
        for k in range(len(self.channels)):
            kt = float(ka[k] + ks[k])
            key = (kt, float(ks[k] / kt) if kt > 0 else 0.0, float(gg[k]))
            if key not in units:
                units[key] = np.stack([self._render_unit(*key, spp_b, s) for s in seeds])
            out[..., k] = units[key] * br[k]
        log.debug("mitsuba render %s x %d spp x %d channels in %.2f s", self.shape, self.spp,
                  len(self.channels), time.perf_counter() - t0)
        return out

    # ------------------------------------------------------------------- API
    def render(self, kappa_a, kappa_s, g, brightness) -> np.ndarray:
        """Image (H, W, C) float64 of the radiance at the camera (ForwardModel).

        ``kappa_a``, ``kappa_s`` in 1/mm, ``g`` unitless, ``brightness`` the
        bulb's radiance in the water (spot: its intensity), arrays of shape (C,).
        """
        return self._batches(kappa_a, kappa_s, g, brightness, 1)[0]

    def render_with_error(self, kappa_a, kappa_s, g, brightness, *, batches: int = 8
                          ) -> tuple[np.ndarray, np.ndarray]:
        """Mean image and its Monte Carlo standard error, both (H, W, C).

        ``spp`` is split into ``batches`` independent batches (different
        seeds); the error is the standard deviation of the batch images over
        sqrt(batches).
        """
        if int(batches) < 2:
            raise InputError(f"batches: got {batches}, need at least 2 to estimate an error")
        imgs = self._batches(kappa_a, kappa_s, g, brightness, int(batches))
        return imgs.mean(axis=0), imgs.std(axis=0, ddof=1) / math.sqrt(imgs.shape[0])

"""Camera rays, refraction and Fresnel transmittance at the flat front wall,
and the in-water segment of each ray up to the black walls.

Frame and pixel conventions are those of CAPTURE_SPEC.md.  Lengths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .spec import Camera, Tank


def pixel_grid(camera: Camera, *, sub: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Image coordinates of ``sub x sub`` stratified samples in every pixel.

    Returns ``x, y`` of shape (H, W, sub*sub); pixel (i, j) spans
    [j, j+1] x [i, i+1] and its centre is (j + 0.5, i + 0.5).
    """
    off = (np.arange(sub) + 0.5) / sub
    ox, oy = np.meshgrid(off, off)
    j = np.arange(camera.width)[None, :, None] + ox.ravel()[None, None, :]
    i = np.arange(camera.height)[:, None, None] + oy.ravel()[None, None, :]
    return np.broadcast_to(j, (camera.height, camera.width, sub * sub)), \
        np.broadcast_to(i, (camera.height, camera.width, sub * sub))


def undistorted(camera: Camera, x, y) -> tuple[np.ndarray, np.ndarray]:
    """Normalised pinhole coordinates ((x - cx)/fx, (y - cy)/fy) of the ray that the camera
    records at image point (x, y), y down: through ``camera.distortion`` when it has one
    (fitmedia.distortion.undistort; OpenCV's normalised coordinates are the same, y down).
    Points beyond a fold (possible only outside the image, which the spec checks) keep
    Newton's last iterate."""
    xn = (np.asarray(x, float) - camera.cx) / camera.fx
    yn = (np.asarray(y, float) - camera.cy) / camera.fy
    if camera.distortion is None:
        return xn, yn
    from .distortion import undistort

    xu, yu, _ = undistort(camera.distortion, xn, yn)
    return xu, yu


def camera_rays(camera: Camera, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Unit directions (..., 3) of the camera's rays through image points (x, y): the pinhole
    of CAPTURE_SPEC.md, through the lens distortion when the camera has one."""
    f, r, u = camera.frame()
    xn, yn = undistorted(camera, x, y)
    d = f + xn[..., None] * r - yn[..., None] * u
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def project(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Image points (x, y) where the camera (distortion included) records points (..., 3)
    seen in a straight line (no refraction), and whether each is in front of the camera.
    (x, y) are NaN for a direction beyond the distortion's fold (far outside the image:
    the polynomial would bring it back in), found as one whose :func:`undistorted` differs."""
    f, r, u = camera.frame()
    d = np.asarray(points, float) - camera.position
    depth = d @ f
    with np.errstate(divide="ignore", invalid="ignore"):
        xn, yn = (d @ r) / depth, -(d @ u) / depth
    if camera.distortion is not None:
        from .distortion import distort, undistort

        with np.errstate(all="ignore"):  # far outside the image the polynomial may overflow
            xd, yd = distort(camera.distortion, xn, yn)
            xu, yu, ok = undistort(camera.distortion, xd, yd)
            ok &= np.hypot(xu - xn, yu - yn) <= 1e-9 * (1.0 + np.hypot(xn, yn))
        xn, yn = np.where(ok, xd, np.nan), np.where(ok, yd, np.nan)
    return camera.cx + camera.fx * xn, camera.cy + camera.fy * yn, depth > 0


def pixel_angle(camera: Camera) -> float:
    """Largest angle (radians, small-angle) one pixel spans anywhere in the image: 1/min(fx, fy)
    for the pinhole (at the principal point); with distortion, the largest over the image of
    the undistorted coordinates' step per pixel (a 17 x 17 grid, steps of 1/4 pixel)."""
    base = 1.0 / min(camera.fx, camera.fy)
    if camera.distortion is None:
        return base
    gx, gy = np.meshgrid(np.linspace(0, camera.width - 0.25, 17),
                         np.linspace(0, camera.height - 0.25, 17))
    x0, y0 = undistorted(camera, gx, gy)
    x1, _ = undistorted(camera, gx + 0.25, gy)
    _, y1 = undistorted(camera, gx, gy + 0.25)
    return max(base, 4.0 * float(np.max(np.abs(x1 - x0))), 4.0 * float(np.max(np.abs(y1 - y0))))


def fresnel_transmittance(cos_i: np.ndarray, n1: float, n2: float) -> np.ndarray:
    """Unpolarised Fresnel power transmittance from index n1 into n2.

    ``cos_i`` is the cosine of the angle of incidence (>= 0).  Returns 0 under
    total internal reflection.
    """
    cos_i = np.clip(np.asarray(cos_i, dtype=float), 0.0, 1.0)
    sin_t2 = (n1 / n2) ** 2 * (1.0 - cos_i**2)
    tir = sin_t2 >= 1.0
    cos_t = np.sqrt(np.clip(1.0 - sin_t2, 0.0, 1.0))
    rs = ((n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)) ** 2
    rp = ((n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)) ** 2
    return np.where(tir, 0.0, 1.0 - 0.5 * (rs + rp))


def refract_z(d: np.ndarray, n1: float, n2: float) -> np.ndarray:
    """Refract directions (..., 3) travelling towards -z through a plane z = const.

    The interface normal is +z; the tangential component scales by n1/n2.
    No total internal reflection can occur for n2 >= n1 (our case: air -> glass -> water).
    """
    eta = n1 / n2
    t = d * eta
    tz2 = 1.0 - t[..., 0] ** 2 - t[..., 1] ** 2
    t[..., 2] = -np.sqrt(np.clip(tz2, 0.0, None))
    return t


@dataclass(frozen=True)
class WaterRays:
    """Camera rays after the front wall, in the water.

    Attributes (N = number of rays)
    ----------
    origin : (N, 3) entry point on the inner face z = depth/2 (mm)
    direction : (N, 3) unit direction in the water (towards -z)
    length : (N,) distance to the black wall where the ray leaves the water (mm)
    factor : (N,) radiance factor water -> camera: T_air/glass * T_glass/water / n_water**2;
        0 for rays that miss the tank's front face
    """

    origin: np.ndarray
    direction: np.ndarray
    length: np.ndarray
    factor: np.ndarray


def trace_to_water(camera: Camera, tank: Tank, water_ior: float, x: np.ndarray,
                   y: np.ndarray) -> WaterRays:
    """Trace the pinhole rays through image points (x, y) (any shape) into the water."""
    shape = np.shape(x)
    d = camera_rays(camera, x, y).reshape(-1, 3)
    o = camera.position
    half = tank.half
    z_out = half[2] + tank.wall_thickness
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (z_out - o[2]) / d[:, 2]
    ok = (d[:, 2] < 0) & (lam > 0)
    q = o + np.where(ok, lam, 0.0)[:, None] * d
    cos_air = -d[:, 2]
    if tank.wall_thickness > 0:
        n_g = tank.wall_ior
        dg = refract_z(d.copy(), 1.0, n_g)
        factor = fresnel_transmittance(cos_air, 1.0, n_g)
        q = q + (tank.wall_thickness / -dg[:, 2])[:, None] * dg
        dw = refract_z(dg.copy(), n_g, water_ior)
        factor = factor * fresnel_transmittance(-dg[:, 2], n_g, water_ior)
    else:
        dw = refract_z(d.copy(), 1.0, water_ior)
        factor = fresnel_transmittance(cos_air, 1.0, water_ior)
    inside = ok & (np.abs(q[:, 0]) < half[0]) & (np.abs(q[:, 1]) < half[1])
    factor = np.where(inside, factor / water_ior**2, 0.0)
    q[:, 2] = half[2]
    # exit distance through the other five faces of the interior box
    with np.errstate(divide="ignore", invalid="ignore"):
        dist = []
        for ax in (0, 1):
            bound = np.where(dw[:, ax] > 0, half[ax], -half[ax])
            dist.append(np.where(dw[:, ax] != 0, (bound - q[:, ax]) / dw[:, ax], np.inf))
        dist.append((-half[2] - q[:, 2]) / dw[:, 2])
    length = np.where(inside, np.clip(np.min(dist, axis=0), 0.0, None), 0.0)
    return WaterRays(q.reshape(*shape, 3), dw.reshape(*shape, 3), length.reshape(shape),
                     factor.reshape(shape))

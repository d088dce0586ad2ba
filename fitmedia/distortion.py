"""Lens distortion: OpenCV's Brown-Conrady model on normalised image coordinates.

A point of the ideal pinhole image with normalised coordinates (x, y) (x right, y down,
as OpenCV's) is recorded by the camera at the distorted normalised point

    r2 = x^2 + y^2,   R = 1 + k1 r2 + k2 r2^2 + k3 r2^3
    xd = x R + 2 p1 x y + p2 (r2 + 2 x^2)
    yd = y R + p1 (r2 + 2 y^2) + 2 p2 x y

and at pixel (cx + fx xd, cy + fy yd).  The coefficients are the spec's
``camera.distortion`` in the order :data:`KEYS` (OpenCV's distCoeffs order).  The camera's
rays (``geometry.camera_rays``) need the inverse, :func:`undistort`: Newton's method on
the map above (its Jacobian is exact and symmetric), to :data:`TOLERANCE`.

numpy only: imported by ``spec`` (the monotonicity check) and ``geometry``.
"""

from __future__ import annotations

import numpy as np

#: the spec's keys, in OpenCV's distCoeffs order
KEYS = ("k1", "k2", "p1", "p2", "k3")

#: largest |distort(undistort(p)) - p| accepted, normalised units (x fx: ~1e-9 px)
TOLERANCE = 1e-12


def distort(coeffs, x, y) -> tuple[np.ndarray, np.ndarray]:
    """Distorted normalised coordinates of the pinhole's normalised (x, y)."""
    k1, k2, p1, p2, k3 = coeffs
    x, y = np.asarray(x, float), np.asarray(y, float)
    r2 = x * x + y * y
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (x * rad + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
            y * rad + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y)


def jacobian(coeffs, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The distortion's Jacobian at (x, y): (dxd/dx, dxd/dy = dyd/dx, dyd/dy)."""
    k1, k2, p1, p2, k3 = coeffs
    x, y = np.asarray(x, float), np.asarray(y, float)
    r2 = x * x + y * y
    rad = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # dR / d(r2)
    off = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
    return (rad + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x, off,
            rad + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x)


def undistort(coeffs, xd, yd, *, max_iter: int = 60
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pinhole's normalised (x, y) that :func:`distort` maps to (xd, yd).

    Damped Newton from (xd, yd): a step that does not lower the residual is halved.
    Returns ``x, y, converged``; ``converged`` is false where the residual stayed above
    :data:`TOLERANCE` or the Jacobian is not positive there (a point beyond a fold: the
    spec refuses distortions with such points in the image, ``check_monotonic``).
    """
    with np.errstate(all="ignore"):  # absurd coefficients overflow: not converged, no warning
        return _newton(coeffs, np.asarray(xd, float), np.asarray(yd, float), max_iter)


def _newton(coeffs, xd: np.ndarray, yd: np.ndarray, max_iter: int):
    x, y = xd.copy(), yd.copy()
    ex, ey = (a - b for a, b in zip(distort(coeffs, x, y), (xd, yd)))
    err = np.hypot(ex, ey)
    for _ in range(max_iter):
        todo = err > TOLERANCE
        if not np.any(todo):
            break
        a, b, d = jacobian(coeffs, x, y)
        det = a * d - b * b
        dx = np.where(todo, -(d * ex - b * ey) / det, 0.0)
        dy = np.where(todo, -(a * ey - b * ex) / det, 0.0)
        dx, dy = np.nan_to_num(dx), np.nan_to_num(dy)
        t = np.ones_like(x)
        for _ in range(40):
            nx, ny = x + t * dx, y + t * dy
            nex, ney = (p - q for p, q in zip(distort(coeffs, nx, ny), (xd, yd)))
            nerr = np.hypot(nex, ney)
            worse = todo & ~(nerr < err)
            if not np.any(worse):
                break
            t = np.where(worse, 0.5 * t, t)
        keep = nerr < err
        x, y = np.where(keep, nx, x), np.where(keep, ny, y)
        ex, ey, err = np.where(keep, nex, ex), np.where(keep, ney, ey), np.where(keep, nerr, err)
    a, b, d = jacobian(coeffs, x, y)
    return x, y, (err <= TOLERANCE) & (a * d - b * b > 0)


def check_monotonic(coeffs, width: int, height: int, fx: float, fy: float, cx: float,
                    cy: float, *, steps: int = 64) -> str | None:
    """Why the distortion is not one-to-one over the image [0, width] x [0, height], or None.

    The image's border (a point per pixel, at most 1025 per side) and a 33 x 33 grid inside
    it are undistorted; each must have a preimage, and the Jacobian's determinant must stay
    positive along the straight segment from the principal point's preimage (0, 0) to it
    (``steps`` points): where it reaches 0 the map folds back (the distorted radius stops
    growing).
    """
    n = min(max(width, height), 1024) + 1
    edge = np.linspace(0.0, 1.0, n)
    zero, one = np.zeros(n), np.ones(n)
    ux = np.concatenate([edge, edge, zero, one, np.repeat(np.linspace(0, 1, 33), 33)])
    uy = np.concatenate([zero, one, edge, edge, np.tile(np.linspace(0, 1, 33), 33)])
    px, py = ux * width, uy * height
    x, y, ok = undistort(coeffs, (px - cx) / fx, (py - cy) / fy)
    if not np.all(ok):
        k = int(np.argmin(ok))
        return (f"no undistorted direction reaches pixel ({px[k]:.0f}, {py[k]:.0f}): the "
                "distortion folds back before the image's edge")
    t = np.linspace(0.0, 1.0, steps + 1)[1:, None]
    with np.errstate(all="ignore"):
        a, b, d = jacobian(coeffs, t * x, t * y)
        bad = ~(a * d - b * b > 0)
        s, k = np.unravel_index(int(np.argmax(bad)), bad.shape)
        qx, qy = distort(coeffs, t[s, 0] * x[k], t[s, 0] * y[k])
    if np.any(bad):
        return (f"the distortion folds back near pixel ({cx + fx * qx:.0f}, {cy + fy * qy:.0f}) "
                "inside the image (its Jacobian's determinant reaches 0 there)")
    return None

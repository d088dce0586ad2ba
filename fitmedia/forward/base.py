"""The interface every forward model implements."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ..errors import InputError


class ForwardModel(Protocol):
    """Render one image of a capture spec for given medium parameters.

    A model is built for one spec and one image index (camera, light), and
    precomputes whatever depends only on geometry.  ``render`` takes the
    medium *in the tank* (already scaled by concentration) per channel and
    the light's brightness per channel, and returns the radiance arriving at
    the camera, in the same units as the brightness:

    * bulb: brightness = the bulb's radiance in the water, L_b; a pixel that
      sees the bulb through clear water reads L_b * T_fresnel / n_water**2.
    * spot: brightness = radiant intensity in the water (L_b units x mm^2).
    """

    channels: tuple[str, ...]
    shape: tuple[int, int]  # (H, W)
    support: np.ndarray  # (H, W) bool: pixels whose footprint sees the tank's water

    def render(self, kappa_a: np.ndarray, kappa_s: np.ndarray, g: np.ndarray,
               brightness: np.ndarray) -> np.ndarray:
        """Arrays of shape (C,) in 1/mm (g unitless) -> image of shape (H, W, C)."""
        ...


def _as_channels(name: str, value, n: int) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.ndim == 0:
        v = np.full(n, float(v))
    if v.shape != (n,):
        raise InputError(f"{name}: expected {n} values (one per channel), got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise InputError(f"{name}: got {v.tolist()}: values must be finite")
    return v


def check_render_args(n_channels: int, kappa_a, kappa_s, g, brightness
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The one input check of ``ForwardModel.render``: scalars or arrays of shape (C,), finite,
    kappa_a and kappa_s >= 0 (1/mm), -1 < g < 1.  Returns the four as float arrays of shape (C,);
    raises InputError naming the offending argument."""
    ka, ks, gg, br = (_as_channels(name, v, n_channels) for name, v in
                      (("kappa_a", kappa_a), ("kappa_s", kappa_s), ("g", g),
                       ("brightness", brightness)))
    if np.any(ka < 0) or np.any(ks < 0):
        raise InputError(f"kappa_a {ka.tolist()} and kappa_s {ks.tolist()} must be >= 0 (1/mm)")
    if np.any(np.abs(gg) >= 1):
        raise InputError(f"g: got {gg.tolist()}: need -1 < g < 1")
    return ka, ks, gg, br

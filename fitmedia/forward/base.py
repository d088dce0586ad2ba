"""The interface every forward model implements."""

from __future__ import annotations

from typing import Protocol

import numpy as np


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

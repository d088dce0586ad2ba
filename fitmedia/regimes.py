"""The capture's regimes by optical depth: how much of the light the liquid takes away between
the light and the front wall.  Measured in the 100-round validation (docs/validation.md,
"Coverage by regime"): below :data:`INFORMATIVE_OPTICAL_DEPTH`'s lower end the light is barely
dimmed, the absorption is not resolved and kappa_t's interval follows the prior; above its
upper end the directly seen light is hidden and g's interval follows the prior."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Optical depth from the light's centre to the inside of the front wall (tank kappa_t x mm).
INFORMATIVE_OPTICAL_DEPTH = (0.1, 10.0)
REGIMES = ("thin", "informative", "dense")


def light_to_wall_mm(spec, index: int | None) -> float:
    """Distance (mm) from image ``index``'s light centre (None: the spec's light) to the
    inside of the front wall."""
    light = spec.light if index is None else spec.light_for(index)
    return float(spec.tank.half[2] - light.position[2])


def tank_optical_depths(spec, kappa_t: float, channel_index: int) -> tuple[float, ...]:
    """Per image of ``spec``: (``kappa_t`` x concentration + the water's absorption) x the
    light-to-wall distance, for the undiluted liquid's ``kappa_t`` (1/mm) in that channel."""
    return tuple(float((kappa_t * e.concentration + spec.water_kappa_a[channel_index])
                       * light_to_wall_mm(spec, i)) for i, e in enumerate(spec.images))


def concentration_for_optical_depth(spec, kappa_t: float, channel_index: int,
                                    optical_depth: float) -> float:
    """The inverse of :func:`tank_optical_depths` for the spec's own light: the concentration
    of a liquid with undiluted ``kappa_t`` (1/mm) that gives ``optical_depth``."""
    dist = light_to_wall_mm(spec, None)
    return (optical_depth / dist - spec.water_kappa_a[channel_index]) / kappa_t


def regime(optical_depths: Sequence[float] | None) -> str | None:
    """'thin' or 'dense' when every image is; 'informative' otherwise; None when unknown."""
    if not optical_depths or not np.all(np.isfinite(optical_depths)):
        return None
    lo, hi = INFORMATIVE_OPTICAL_DEPTH
    if max(optical_depths) < lo:
        return "thin"
    if min(optical_depths) > hi:
        return "dense"
    return "informative"

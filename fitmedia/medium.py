"""Optical properties of a medium per colour channel, the HG phase function,
and the bundled Narasimhan et al. (2006) table of undiluted liquids.

Units: coefficients in 1/mm (the published table is in 1/mm as well).
"""

from __future__ import annotations

import csv
import difflib
from dataclasses import dataclass
from importlib import resources

import numpy as np

from .errors import InputError
from .spec import CHANNELS


@dataclass(frozen=True)
class Medium:
    """κa, κs (1/mm) and g per channel; arrays of shape (C,)."""

    kappa_a: np.ndarray
    kappa_s: np.ndarray
    g: np.ndarray
    channels: tuple[str, ...] = CHANNELS
    name: str = ""

    def __post_init__(self):
        for f in ("kappa_a", "kappa_s", "g"):
            v = np.atleast_1d(np.asarray(getattr(self, f), dtype=float))
            if v.shape != (len(self.channels),):
                raise InputError(f"medium.{f}: expected {len(self.channels)} values "
                                 f"({', '.join(self.channels)}), got shape {v.shape}")
            if not np.all(np.isfinite(v)):
                raise InputError(f"medium.{f}: got {v.tolist()}: values must be finite")
            object.__setattr__(self, f, v)
        if np.any(self.kappa_a < 0) or np.any(self.kappa_s < 0):
            raise InputError(f"medium: kappa_a {self.kappa_a.tolist()} and kappa_s "
                             f"{self.kappa_s.tolist()} must be >= 0 (1/mm)")
        if np.any(np.abs(self.g) >= 1):
            raise InputError(f"medium.g: got {self.g.tolist()}: need -1 < g < 1")

    @property
    def kappa_t(self) -> np.ndarray:
        return self.kappa_a + self.kappa_s

    @property
    def albedo(self) -> np.ndarray:
        kt = self.kappa_t
        return np.divide(self.kappa_s, kt, out=np.zeros_like(kt), where=kt > 0)

    def scaled(self, concentration: float) -> "Medium":
        """The medium diluted to ``concentration`` (κa, κs scale; g does not)."""
        return Medium(self.kappa_a * concentration, self.kappa_s * concentration, self.g,
                      self.channels, self.name)

    def select(self, channels: tuple[str, ...]) -> "Medium":
        idx = [self.channels.index(c) for c in channels]
        return Medium(self.kappa_a[idx], self.kappa_s[idx], self.g[idx], tuple(channels), self.name)

    def as_dict(self) -> dict:
        return {q: dict(zip(self.channels, getattr(self, q).tolist()))
                for q in ("kappa_a", "kappa_s", "g", "kappa_t", "albedo")}


def hg_phase(cos_theta: np.ndarray, g: np.ndarray | float) -> np.ndarray:
    """Henyey–Greenstein phase function, normalised over the sphere (1/sr).

    ``cos_theta`` is the cosine between the directions of travel before and after.
    """
    return hg_phase_half_angle(0.5 * (1.0 - np.asarray(cos_theta, dtype=float)), g)


def hg_phase_half_angle(sin2_half: np.ndarray, g: np.ndarray | float) -> np.ndarray:
    """Henyey–Greenstein phase function of s = sin^2(theta / 2) (1/sr): the one place the
    formula is written (forward models and tests call this or :func:`hg_phase`).

    p = (1 - g^2) / (4 pi D^(3/2)), D = 1 + g^2 - 2 g cos(theta) = (1 - g)^2 + 4 g s, a form
    without cancellation near the forward peak (g -> 1, theta -> 0), where D -> (1 - g)^2.
    """
    g = np.asarray(g, dtype=float)
    denom = (1.0 - g) ** 2 + 4.0 * g * sin2_half
    return (1.0 - g * g) / (4.0 * np.pi) / (denom * np.sqrt(denom))


def reference_table() -> dict[str, Medium]:
    """The undiluted liquids of Narasimhan et al. 2006 (bundled CSV), by name."""
    text = resources.files("fitmedia.data").joinpath("narasimhan2006_undiluted.csv").read_text()
    out = {}
    for row in csv.DictReader(text.splitlines()):
        out[row["medium"]] = Medium(
            np.array([float(row[f"kappa_a_{c}"]) for c in CHANNELS]),
            np.array([float(row[f"kappa_s_{c}"]) for c in CHANNELS]),
            np.array([float(row[f"g_{c}"]) for c in CHANNELS]), CHANNELS, row["medium"])
    return out


def medium_by_name(name: str) -> Medium:
    table = reference_table()
    if name in table:
        return table[name]
    lower = {k.lower(): k for k in table}
    if name.lower() in lower:
        return table[lower[name.lower()]]
    hint = difflib.get_close_matches(name, list(table), n=3)
    raise InputError(f"--medium: unknown medium {name!r}"
                     + (f"; did you mean {', '.join(repr(h) for h in hint)}?" if hint else
                        f"; known: {', '.join(sorted(table))}"))

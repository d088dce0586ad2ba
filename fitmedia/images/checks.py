"""Sanity checks of loaded images that no real capture fails (thresholds here and in
docs/testing.md, "Bad-input corpus").

Each check raises :class:`~fitmedia.errors.ImageError` naming the file.  The thresholds
come from the noise model (variance = gain * value + read_var, CAPTURE_SPEC.md) and from
the floating-point range; a dilute capture (a faint glow over a background of read noise,
half of whose pixels are negative) passes every one of them.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import BlackImageError, ImageError
from .io import LoadedImage

#: After dividing by exposure_s the largest |value| must lie in this range, file units per
#: second: the likelihood squares residuals and divides by variances proportional to the
#: values, so values beyond 1e100 (squares 1e200, summed over 1e9 pixels) or below 1e-100
#: (variances near the float64 underflow at 1e-308) would overflow or divide by zero.
#: A 16-bit file at 1 microsecond gives 6.6e10; a float file of 1e-5 at 1e4 s gives 1e-9.
VALUE_RANGE = (1e-100, 1e100)
#: A pixel below -NEGATIVE_SIGMAS read-noise standard deviations is impossible for the noise
#: model (probability 2.9e-7 for normal read noise at 5 sigma) ...
NEGATIVE_SIGMAS = 5.0
#: ... and an image with more than this fraction of its usable pixels there is refused (a
#: negated or wrongly dark-subtracted image); 1 % is 3e4 times the normal tail's share ...
MAX_NEGATIVE_FRACTION = 0.01
#: ... as is one with more than this many such pixels (and this fraction, 350 times the
#: normal tail's share) when fewer of its pixels lie as far above 0: a photograph of the lit
#: tank has its glow and bulb far above the noise, a negated one has nothing there.
MIN_NEGATIVE_COUNT, MIN_NEGATIVE_SHARE = 10, 1e-4
#: A photograph of the lit tank has more than this fraction of its usable pixels above
#: LIT_SIGMAS read-noise sd (its own per-pixel read noise): pure normal noise puts 2.9e-7 of its
#: pixels there (7 of 24 megapixels), 1e-6 is 3.4 times that share.  No minimum count: a thin
#: or dark liquid can leave just the bulb's one or two pixels above the noise (Merlot 200 ml at
#: 24 x 18: 2 of 432 in R), and those are data.
MIN_LIT_SHARE, LIT_SIGMAS = 1e-6, 5.0


def check_values(img: LoadedImage, channels: Sequence[int], names: Sequence[str]) -> None:
    """The usable pixels of each channel are finite, not all equal (an all-zero or constant
    image has no glow to fit) and of a magnitude inside :data:`VALUE_RANGE` (an exposure_s
    of 1e-300 s gives 1e304)."""
    for ci, ch in zip(channels, names):
        v = img.data[..., ci][img.valid[..., ci]]
        if v.size == 0:
            continue  # load_entry already refuses an image with too few usable pixels
        if not np.all(np.isfinite(v)):
            raise ImageError(f"{img.source}: channel {ch} has {np.count_nonzero(~np.isfinite(v))} "
                             "non-finite values after dividing by exposure_s; check exposure_s")
        lo, hi = float(v.min()), float(v.max())
        if lo == hi:
            raise ImageError(f"{img.source}: channel {ch} is {lo:g} at every usable pixel: not a "
                             "photograph of the tank (an empty or blank image?)")
        top = max(abs(lo), abs(hi))
        if not VALUE_RANGE[0] <= top <= VALUE_RANGE[1]:
            raise ImageError(f"{img.source}: channel {ch}: largest |value| {top:.3g} per second "
                             f"after dividing by exposure_s, outside {VALUE_RANGE[0]:g} to "
                             f"{VALUE_RANGE[1]:g}; check exposure_s")


def check_negative(img: LoadedImage, channels: Sequence[int], names: Sequence[str],
                   read_var: Sequence[float], background_sd: float = 0.0) -> None:
    """Refuse a channel whose usable pixels more than :data:`NEGATIVE_SIGMAS` read-noise sd
    below 0 (the noise model's variance at value 0 is read_var; with read_var 0 no value may
    be negative) are more than :data:`MAX_NEGATIVE_FRACTION` of them, or more than
    :data:`MIN_NEGATIVE_COUNT` and :data:`MIN_NEGATIVE_SHARE` of them and more than those as
    far above 0.  With a background offset in the model (``background_sd``, its prior's sd)
    the limit moves down by :data:`NEGATIVE_SIGMAS` of those."""
    for ci, ch, rv in zip(channels, names, read_var):
        v = img.data[..., ci][img.valid[..., ci]]
        if v.size == 0:
            continue
        limit = -NEGATIVE_SIGMAS * (float(np.sqrt(max(rv, 0.0))) + background_sd)
        n_bad, n_high = int(np.count_nonzero(v < limit)), int(np.count_nonzero(v > -limit))
        mostly_negative = (n_bad > max(MIN_NEGATIVE_COUNT, MIN_NEGATIVE_SHARE * v.size)
                           and n_bad > n_high)
        if n_bad > MAX_NEGATIVE_FRACTION * v.size or mostly_negative:
            raise ImageError(
                f"{img.source}: channel {ch}: {n_bad} of {v.size} usable pixels are below "
                f"{limit:.3g}, {NEGATIVE_SIGMAS:g} read-noise sd below 0 ({n_high} as far above; "
                "docs/testing.md gives the limits): a negative image, or a dark frame brighter "
                "than the image (an offset in the whole image: set priors.background_sd)")


def _digest(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def check_distinct(named: Sequence[tuple[str, Sequence[Path], LoadedImage]]) -> None:
    """No two entries (``(field, paths, image)``: the medium images and the clear-water photo)
    share a file, a file's content or identical pixel values: the same photo given as two
    concentrations, or as the medium and the clear water, would be fitted as if the liquid
    changed nothing."""
    seen: dict[str, str] = {}
    for fld, paths, _ in named:
        for p in paths:
            key = _digest(Path(p))
            if key in seen and seen[key] != fld:
                raise ImageError(f"{p}: {fld} has the same file content as {seen[key]}; each "
                                 "concentration and the clear water need their own photo")
            seen.setdefault(key, fld)
    for k, (fld, _, img) in enumerate(named):
        for fld0, _, img0 in named[:k]:
            if img.data.shape == img0.data.shape and np.array_equal(img.data, img0.data):
                raise ImageError(f"{img.source}: {fld} has the same pixel values as {fld0} "
                                 f"({img0.source}); each concentration and the clear water need "
                                 "their own photo")


def check_lit(img: LoadedImage, channels: Sequence[int], names: Sequence[str],
              read_map: np.ndarray) -> None:
    """Refuse an image with no glow to fit: at most :data:`MIN_LIT_SHARE` of a channel's
    usable pixels above :data:`LIT_SIGMAS` sd of their own read noise (``read_map``,
    (H, W, 3), the image's units).  With saturated pixels that is a glow saturated in every
    frame (no unsaturated sample of it), refused per channel; without, a black image, refused
    only when every channel is black: one dark channel of a dense liquid (Regular Milk 199 ml
    at 64 x 48: no pixel of R above the noise) is data, a non-detection that the fit uses."""
    black = []
    for ci, ch in zip(channels, names):
        ok = img.valid[..., ci]
        v, rv = img.data[..., ci][ok], np.broadcast_to(read_map, img.data.shape)[..., ci][ok]
        n_lit = int(np.count_nonzero(v > LIT_SIGMAS * np.sqrt(np.maximum(rv, 0.0))))
        if v.size == 0 or n_lit > MIN_LIT_SHARE * v.size:
            continue
        if img.n_saturated:
            frames = "every frame" if len(img.exposures) > 1 else "the image"
            raise ImageError(f"{img.source}: channel {ch}: {n_lit} of {v.size} usable pixels are "
                             f"above {LIT_SIGMAS:g} read-noise sd: no unsaturated sample of the "
                             f"glow: its {img.n_saturated} saturated pixels are saturated in "
                             f"{frames} and the rest is dark; add a shorter exposure")
        black.append((ch, n_lit, v.size))
    if black and len(black) == len(names):
        ch, n_lit, n = black[0]
        raise BlackImageError(f"{img.source}: channel {ch}: {n_lit} of {n} usable pixels are "
                              f"above {LIT_SIGMAS:g} read-noise sd, and no channel has more: a "
                              "black image (lens cap, light off, exposure_s, or a liquid so dense "
                              "that no glow reaches the front wall: dilute it)")

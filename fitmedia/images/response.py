"""A camera's measured response curve: made from an exposure bracket with OpenCV's Debevec or
Robertson calibration, written as a CSV file, read back to decode 8- or 16-bit files whose
values carry a tone curve (docs/spec.md, "Measured response").

The file: one row per code value (256 for 8-bit files, 65536 for 16-bit), three columns R, G,
B: the relative linear exposure that code value records (any scale), ``#`` comment lines
allowed.  It is what ``cv2.createCalibrateDebevec().process`` / ``createCalibrateRobertson``
return (shape (256, 1, 3), channels in OpenCV's B, G, R order), flipped to R, G, B.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import ImageError, InputError

METHODS = ("debevec", "robertson")


def read_curve(path: str | Path, levels: int) -> np.ndarray:
    """The curve file as (levels, 3) float64, scaled so that its largest entry per channel is
    ``levels - 1`` (the file's full scale: decoded values stay in file units, like ``srgb``).

    Raises
    ------
    ImageError
        Unreadable, not ``levels`` rows of 3 finite values, negative, or not rising.
    """
    path = Path(path)
    try:
        curve = np.loadtxt(path, delimiter=",", comments="#", dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as exc:
        raise ImageError(f"{path}: not a readable response curve (CSV of R, G, B per code "
                         f"value: {' '.join(str(exc).split())})") from None
    bits = {256: "8-bit", 65536: "16-bit"}.get(levels, f"{levels}-level")
    if curve.shape != (levels, 3):
        raise ImageError(f"{path}: response curve has {curve.shape[0]} rows of "
                         f"{curve.shape[1] if curve.ndim > 1 else 1} values; a {bits} image "
                         f"needs {levels} rows of 3 (R, G, B), one per code value")
    if not np.all(np.isfinite(curve)) or np.any(curve < 0):
        raise ImageError(f"{path}: response curve has negative or non-finite values")
    top = curve.max(axis=0)
    if not np.all(top > curve[0]):
        raise ImageError(f"{path}: response curve does not rise in every channel")
    return curve / top * (levels - 1)


def decode(codes: np.ndarray, curve: np.ndarray) -> np.ndarray:
    """Integer code values (H, W, 3) through the curve (levels, 3), per channel."""
    idx = np.clip(codes.astype(np.int64), 0, curve.shape[0] - 1)
    return np.stack([curve[idx[..., c], c] for c in range(3)], axis=-1)


def curve_quantum(curve: np.ndarray) -> float:
    """The smallest positive step between neighbouring code values (a floor for the read
    variance, as the file's code step is for linear files)."""
    steps = np.diff(curve, axis=0)
    pos = steps[steps > 0]
    return float(pos.min()) if pos.size else 1.0


def _fill_unseen(curve: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
    """Robertson's curve is NaN at code values no frame holds: filled by linear interpolation
    between measured ones and, beyond them, the straight line through the last two (at least
    0).  Returns the curve and the range of codes measured in every channel."""
    out = curve.copy()
    codes = np.arange(curve.shape[0], dtype=float)
    lo, hi = 0, curve.shape[0] - 1
    for c in range(curve.shape[1]):
        ok = np.isfinite(curve[:, c]) & (curve[:, c] > 0)
        if np.count_nonzero(ok) < 2:
            raise InputError("calibrate_response: the bracket holds fewer than 2 distinct values "
                             f"in channel {'RGB'[c]}; photograph a scene with a range of tones")
        x, y = codes[ok], curve[ok, c]
        out[:, c] = np.interp(codes, x, y)
        left, right = codes < x[0], codes > x[-1]
        out[left, c] = y[0] + (codes[left] - x[0]) * (y[1] - y[0]) / (x[1] - x[0])
        out[right, c] = y[-1] + (codes[right] - x[-1]) * (y[-1] - y[-2]) / (x[-1] - x[-2])
        lo, hi = max(lo, int(x[0])), min(hi, int(x[-1]))
    return np.maximum(out, 0.0), (lo, hi)


def calibrate_response(paths: Sequence[str | Path], exposures: Sequence[float],
                       out: str | Path, *, method: str = "debevec", samples: int = 70,
                       smoothness: float = 10.0) -> np.ndarray:
    """Measure an 8-bit camera's response from an exposure bracket of one still scene and write
    the curve file ``out`` (CSV, 256 rows x R, G, B); returns the (256, 3) curve.

    ``method``: ``debevec`` (cv2.createCalibrateDebevec, ``samples`` pixel positions,
    ``smoothness`` lambda) or ``robertson`` (cv2.createCalibrateRobertson).  The curve's scale
    is arbitrary (Debevec's is 1 at mid-grey); fitmedia rescales it when reading.

    Raises
    ------
    InputError
        Fewer than 2 frames, an exposure per frame missing, an unknown method, or frames that
        are not 8-bit RGB images of one size.
    """
    import cv2

    if method not in METHODS:
        raise InputError(f"method: {method!r} is not one of {', '.join(METHODS)}")
    if len(paths) < 2 or len(exposures) != len(paths) or not all(t > 0 for t in exposures):
        raise InputError(f"calibrate_response: {len(paths)} frames with exposures {list(exposures)};"
                         " give 2 or more frames of one scene, one positive exposure each")
    frames = []
    for p in paths:  # OpenCV's own reader: B, G, R order, as its calibration wants
        buf = np.fromfile(p, dtype=np.uint8) if Path(p).is_file() else np.zeros(0, np.uint8)
        arr = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
        if arr is None or arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] < 3:
            raise InputError(f"{p}: not a readable 8-bit RGB image (OpenCV's response "
                             "calibration takes 8-bit frames)")
        if frames and arr.shape[:2] != frames[0].shape[:2]:
            raise InputError(f"{p}: frames of one bracket must be of one size")
        frames.append(np.ascontiguousarray(arr[..., :3]))
    times = np.asarray(exposures, np.float32)
    cal = (cv2.createCalibrateDebevec(samples=samples, lambda_=smoothness) if method == "debevec"
           else cv2.createCalibrateRobertson())
    curve = np.asarray(cal.process(frames, times), np.float64).reshape(256, 3)[:, ::-1]
    curve, seen = _fill_unseen(curve)
    head = (f"fitmedia response curve ({method}, {len(paths)} frames): linear value per code "
            f"value 0-255, columns R,G,B; codes {seen[0]}-{seen[1]} measured, others filled")
    from ..util import atomic_write

    atomic_write(out, lambda tmp: np.savetxt(tmp, curve, delimiter=",", header=head, fmt="%.8g"))
    return curve

"""Reading linear photographs and turning an image entry into one radiance map.

Supported files (CAPTURE_SPEC.md, "Image files"): 16-bit and float TIFF,
16- and 8-bit PNG, OpenEXR and camera RAW (decoded linearly by rawpy).  Every
bad file raises :class:`~fitmedia.errors.ImageError` whose one-line message
names the file and what is wrong; library exceptions never escape.

Units: a file's own values are "file units" (0..65535 for 16-bit files);
:func:`load_entry` divides by the exposure time, so its output is in file
units per second.
"""

from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import ImageError, InputError
from ..spec import ImageEntry
from ..util import atomic_write

TIFF_EXT = frozenset({".tif", ".tiff"})
PNG_EXT = frozenset({".png"})
EXR_EXT = frozenset({".exr"})
RAW_EXT = frozenset(".dng .cr2 .cr3 .crw .nef .nrw .arw .srf .sr2 .raf .orf .rw2 .pef .srw "
                    ".x3f .3fr .erf .kdc .mos .mrw .iiq .rwl .raw".split())
#: A pixel channel is saturated where its raw value is >= this fraction of the level.
SATURATION_FRACTION = 0.999
#: :func:`load_entry` refuses an entry with more than this fraction of unusable pixels.
MAX_UNUSABLE_FRACTION = 0.5
# Float images may hold negative values (read noise after a dark subtraction, or in
# a frame where the light is fully attenuated): they are kept, never clamped; the
# likelihood's variance model (gain * max(model, 0) + read_var) accounts for them.
_MAX_BYTES = 8 * 2**30  # a header claiming more than this is taken as corrupt
_LEVELS = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}
# What tifffile and its codecs raise on truncated or corrupt files (found by fuzzing).
_TIFF_ERRORS = (OSError, EOFError, ValueError, TypeError, IndexError, KeyError,
                OverflowError, struct.error, zlib.error, MemoryError)


def _why(exc: BaseException) -> str:
    """A library exception as one line: its type and message."""
    msg = exc.args[0] if exc.args else ""
    msg = msg.decode(errors="replace") if isinstance(msg, bytes) else str(msg)
    return f"{type(exc).__name__}: {' '.join(msg.split())}"


def _read_tiff(path: Path) -> np.ndarray:
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            if page.dtype is None:
                raise ImageError(f"{path}: TIFF pixel format not supported (or file corrupt)")
            nbytes = int(np.prod(page.shape)) * page.dtype.itemsize
            if nbytes > _MAX_BYTES:
                raise ImageError(f"{path}: header claims a {page.shape} image "
                                 f"({nbytes / 2**30:.0f} GiB); the file is corrupt")
            arr = page.asarray()
            if page.planarconfig == tifffile.PLANARCONFIG.SEPARATE and arr.ndim == 3:
                arr = np.moveaxis(arr, 0, -1)
    except ImageError:
        raise
    except _TIFF_ERRORS as exc:
        raise ImageError(f"{path}: not a readable TIFF file ({_why(exc)})") from None
    return arr


def _read_cv2(path: Path) -> np.ndarray:
    """PNG or EXR through OpenCV, converted from its BGR(A) order to RGB(A)."""
    os.environ["OPENCV_IO_ENABLE_OPENEXR"] = "1"  # read by OpenCV at its first EXR decode
    import cv2

    arr = None
    try:
        buf = np.fromfile(path, dtype=np.uint8)
        if buf.size:
            arr = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    except (OSError, cv2.error) as exc:
        raise ImageError(f"{path}: cannot be read ({_why(exc)})") from None
    if arr is None:
        kind = "PNG" if path.suffix.lower() in PNG_EXT else "OpenEXR"
        raise ImageError(f"{path}: not a readable {kind} file (empty, truncated or corrupt)")
    if path.suffix.lower() in PNG_EXT and buf.size > 25 and buf[25] in (0, 4):
        # grey or grey+alpha PNG: OpenCV expands grey+alpha to BGRA; undo that
        return arr if arr.ndim == 2 else arr[..., [0, 3]]
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        arr = np.concatenate([arr[..., 2::-1], arr[..., 3:]], axis=-1)
    return arr


@dataclass(frozen=True)
class Frame:
    """One file's pixels in file units, and what its saturation is judged on.

    Attributes
    ----------
    data : ndarray of shape (H, W, 3), float64
        Channels R, G, B in file units; for RAW, sensor DN above the file's black level
        (negative values kept).
    peak : ndarray of shape (H, W, 3)
        The stored values saturation is judged on: for RAW the largest raw sensor value
        (black included) among the photosites binned into the pixel; else the file's value.
    level : float or None
        The saturation level in ``peak`` units: the RAW file's white level, the integer
        type's maximum, None for floating point.
    samples : ndarray of shape (3,)
        Stored samples averaged into one pixel per channel (binned Bayer: 1, 2, 1).
    quantum : float
        Step of one stored sample in ``data`` units: 1 for integer files; for float files
        the type's spacing at the largest absolute value.
    encoded : bool
        An 8- or 16-bit TIFF or PNG: its values may carry a tone curve, so it is used
        only with a declared response (:func:`linearise`).
    """

    data: np.ndarray
    peak: np.ndarray
    level: float | None
    samples: np.ndarray
    quantum: float
    encoded: bool = False


def _bin_bayer(path: Path, img: np.ndarray, colors: np.ndarray, black: np.ndarray,
               desc: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bin each 2x2 Bayer quad into one RGB pixel (no interpolation).

    ``img`` holds raw sensor values, ``colors`` each site's colour index into ``desc``
    (e.g. 'RGBG') and ``black`` the black level per colour index.  Returns the mean
    signal above black per channel, the largest raw value per channel (for saturation)
    and the number of sites averaged per channel.
    """
    h, w = (img.shape[0] // 2) * 2, (img.shape[1] // 2) * 2
    pattern = colors[:2, :2]
    tiled = np.tile(pattern, (h // 2, w // 2))
    if h < 2 or w < 2 or not np.array_equal(colors[:h, :w], tiled):
        raise ImageError(f"{path}: the colour filter is not a 2x2 Bayer mosaic; fitmedia bins "
                         "2x2 quads and cannot read this sensor layout")
    data = np.zeros((h // 2, w // 2, 3))
    peak = np.zeros((h // 2, w // 2, 3))
    count = np.zeros(3)
    for i in (0, 1):
        for j in (0, 1):
            letter = desc[int(pattern[i, j])]
            if letter not in "RGB":
                raise ImageError(f"{path}: colour filter '{desc}' is not R, G, B; fitmedia "
                                 "reads RGB Bayer sensors only")
            ch = "RGB".index(letter)
            site = img[i:h:2, j:w:2]
            data[..., ch] += site - black[int(pattern[i, j])]
            peak[..., ch] = np.maximum(peak[..., ch], site)
            count[ch] += 1
    if not np.all(count > 0):
        raise ImageError(f"{path}: the 2x2 colour filter '{desc}' lacks one of R, G, B")
    return data / count, peak, count


class _CapturedStderr:
    """The process's file descriptor 2 redirected to a temporary file while inside (LibRaw's C
    code prints its complaints, e.g. "Unexpected end of file", there): ``text`` afterwards."""

    def __enter__(self):
        import sys
        import tempfile

        sys.stderr.flush()
        self._tmp = tempfile.TemporaryFile()
        self._saved = os.dup(2)
        os.dup2(self._tmp.fileno(), 2)
        self.text = ""
        return self

    def __exit__(self, *exc):
        os.dup2(self._saved, 2)
        os.close(self._saved)
        self._tmp.seek(0)
        self.text = " ".join(self._tmp.read().decode(errors="replace").split())
        self._tmp.close()
        return False


def _read_raw(path: Path) -> Frame:
    """A camera RAW file in sensor units, exactly (docs/spec.md, "Camera RAW").

    LibRaw only unpacks: no scaling, brightening, white balance or interpolation.  A
    Bayer file is binned per 2x2 quad; a LinearRaw file (three samples per pixel) is
    read as is.  The per-channel black levels are subtracted, negative values kept.
    """
    import rawpy

    said = _CapturedStderr()
    try:
        with said, rawpy.imread(str(path)) as raw:
            img = np.array(raw.raw_image_visible, dtype=np.float64)
            black = np.asarray(raw.black_level_per_channel, dtype=np.float64)
            white = float(raw.white_level)
            desc = raw.color_desc.decode(errors="replace")
            flat = raw.raw_type == rawpy.RawType.Flat
            colors = np.array(raw.raw_colors_visible) if flat else None
    except (rawpy.LibRawError, OSError, MemoryError, ValueError) as exc:
        libraw = f"; LibRaw: {said.text.replace(str(path) + ': ', '')}" if said.text else ""
        raise ImageError(f"{path}: not a readable camera RAW file ({_why(exc)}{libraw})") from None
    if flat:
        data, peak, count = _bin_bayer(path, img, colors, black, desc)
    else:
        if img.ndim != 3 or img.shape[2] < 3 or desc[:3] != "RGB":
            raise ImageError(f"{path}: a RAW file with samples '{desc}' of shape {img.shape}; "
                             "fitmedia reads RGB Bayer or three-sample LinearRaw files")
        peak = img[..., :3]
        data, count = peak - black[:3], np.ones(3)
    if not white > 0:
        raise ImageError(f"{path}: the RAW file gives no white level")
    return Frame(data, peak, white, count, 1.0)


def _read_any(path: str | Path) -> np.ndarray:
    """The file's pixels in their own dtype: (H, W) or (H, W, C), channels in RGB(A) order."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: file not found")
    ext = path.suffix.lower()
    if ext in TIFF_EXT:
        arr = _read_tiff(path)
    elif ext in PNG_EXT or ext in EXR_EXT:
        arr = _read_cv2(path)
    elif ext in RAW_EXT:
        raise ImageError(f"{path}: a camera RAW file cannot be used here (only as an image)")
    else:
        known = sorted(TIFF_EXT | PNG_EXT | EXR_EXT) + ["camera RAW (.dng, .cr2, .nef, .arw, ...)"]
        raise ImageError(f"{path}: unknown image type '{ext}'; expected one of {', '.join(known)}")
    if arr.ndim not in (2, 3) or min(arr.shape[:2]) < 1:
        raise ImageError(f"{path}: array of shape {arr.shape}; expected (height, width, channels)")
    if arr.dtype not in _LEVELS and arr.dtype.kind != "f":
        raise ImageError(f"{path}: pixel type {arr.dtype} is not supported; expected 8- or "
                         "16-bit unsigned integers or floating point")
    if arr.dtype.kind == "f":
        bad = ~np.isfinite(arr)
        if bad.any():
            i, j = np.argwhere(bad)[0][:2]
            raise ImageError(f"{path}: {np.count_nonzero(bad)} NaN or infinite values (first at "
                             f"row {i}, column {j}); a linear image must be finite")
    return arr


def read_frame(path: str | Path) -> Frame:
    """Read one image file as a :class:`Frame` (channels R, G, B in file units).

    TIFF, PNG and OpenEXR files: the stored values (an alpha channel is dropped);
    camera RAW: sensor DN above black, Bayer quads binned (:func:`_read_raw`).

    Raises
    ------
    ImageError
        Missing, unreadable or truncated file; unknown extension; not 3 or 4
        channels; NaN or infinite values.
    """
    path = Path(path)
    if path.suffix.lower() in RAW_EXT:
        if not path.is_file():
            raise ImageError(f"{path}: file not found")
        return _read_raw(path)
    arr = _read_any(path)
    nch = 1 if arr.ndim == 2 else arr.shape[2]
    if nch not in (3, 4):
        raise ImageError(f"{path}: has {nch} channel{'s' if nch > 1 else ''}; an RGB image "
                         "(3 channels, or 4 with alpha) is needed")
    level = _LEVELS.get(arr.dtype)
    rgb = arr[..., :3]
    if level is None:  # float: the type's spacing at the largest value (a floor, not a step)
        quantum = float(np.spacing(np.abs(rgb).max().astype(rgb.dtype)))
    else:
        quantum = 1.0
    return Frame(rgb.astype(np.float64), rgb, level, np.ones(3), quantum, encoded=level is not None)


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """The sRGB decoding curve (IEC 61966-2-1) of values in [0, 1]."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((np.maximum(v, 0.04045) + 0.055) / 1.055) ** 2.4)


#: :func:`looks_srgb`'s threshold: the fraction of lit values in the mid-tones (10-90 % of
#: full scale) above which an undeclared file is called sRGB-like.  A glow exp(-r / 6 px)
#: in a black 80x60 frame gives 0.13 linear and 0.39 sRGB-encoded (tests/test_images.py).
SRGB_MIDTONE_FRACTION = 0.3


def looks_srgb(frame: Frame) -> float | None:
    """The fraction of lit values (above 1/256 of full scale) in the mid-tones, 10 % to
    90 % of full scale, when it is over ``SRGB_MIDTONE_FRACTION`` (a tone curve lifts the
    dim glow into the mid-tones; a linear glow falls over decades, mostly below 10 %), else
    None.  A heuristic: it only words the refusal of an undeclared file."""
    v = frame.data / frame.level
    lit = v[v > 1.0 / 256]
    if lit.size < 16:
        return None
    frac = float(np.mean((lit > 0.1) & (lit < 0.9)))
    return frac if frac > SRGB_MIDTONE_FRACTION else None


def linearise(frame: Frame, response: str | None, path: Path,
              curve: Path | None = None) -> Frame:
    """A frame in linear units: 8- and 16-bit files through their declared ``response``.

    ``linear``: as stored.  ``srgb``: through :func:`srgb_to_linear`, still scaled to the
    file's range (0..255 or 0..65535) so that file units keep their meaning.  ``curve``: through
    the measured response in the file ``curve`` (:mod:`fitmedia.images.response`; one row per
    code value, scaled to the file's range).  Undeclared: refused.  Float and RAW files are
    linear; ``srgb`` or a curve on them is refused.

    Raises
    ------
    ImageError
        Naming the file and the fix (and the sRGB look of its histogram when it has it).
    """
    if not frame.encoded:
        if response in ("srgb", "curve"):
            what = "srgb" if response == "srgb" else "{curve: ...}"
            raise ImageError(f"{path}: 'response: {what}' is for 8- or 16-bit TIFF/PNG files; "
                             "float and RAW files are linear (remove it)")
        return frame
    if response == "linear":
        return frame
    if response == "curve" and curve is not None:
        from .response import curve_quantum, decode, read_curve

        table = read_curve(curve, int(frame.level) + 1)
        return replace(frame, data=decode(frame.peak, table), quantum=curve_quantum(table),
                       encoded=False)
    if response == "srgb":
        lin = srgb_to_linear(frame.data / frame.level) * frame.level
        return replace(frame, data=lin, quantum=frame.quantum / 12.92, encoded=False)
    bits = 8 if frame.level == 255.0 else 16
    frac = looks_srgb(frame)
    seen = "" if frac is None else (f"; it looks sRGB-encoded ({100 * frac:.0f}% of its "
                                    "non-black values lie between 10% and 90% of full scale)")
    raise ImageError(f"{path}: a {bits}-bit image may carry a tone curve{seen}; declare on its "
                     "image entry 'response: srgb' (sRGB-encoded, decoded by fitmedia) or "
                     "'response: linear' (it holds linear sensor values), or a measured curve "
                     "'response: {curve: FILE}' (docs/spec.md, \"Measured response\")")


def read_image(path: str | Path) -> tuple[np.ndarray, float | None]:
    """Read one linear RGB image file: :func:`read_frame`'s data and saturation level.

    Returns
    -------
    image : ndarray of shape (H, W, 3), float64
        Channels R, G, B in file units (RAW: sensor DN above black, 2x2 quads binned).
    level : float or None
        The saturation level: 65535 for 16-bit files, 255 for 8-bit, the white level
        of a RAW file (a raw sensor value, black included), None for floating point.
    """
    frame = read_frame(path)
    return frame.data, frame.level


def _read_flat(path: Path, entry: ImageEntry, shape: tuple[int, int],
               valid: np.ndarray) -> np.ndarray:
    """A flat-field image (the camera's relative response per pixel and channel, vignetting
    included) scaled to mean 1 over the ``valid`` pixels of each channel.

    Raises
    ------
    ImageError
        Unreadable, of the wrong size, or not positive at a usable pixel.
    """
    flat = linearise(_frame(path, shape, "flat field", entry.binning), entry.response, path,
                     entry.response_curve).data.copy()
    for ci in range(3):
        f = flat[..., ci][valid[..., ci]]
        if f.size and not np.all(f > 0):
            i, j = np.argwhere(valid[..., ci] & ~(flat[..., ci] > 0))[0]
            raise ImageError(f"{path}: flat field is {flat[i, j, ci]:.3g} at row {i}, column {j} "
                             f"({'RGB'[ci]}); it must be positive wherever the image is used")
        flat[..., ci] /= f.mean() if f.size else 1.0
    return np.where(flat > 0, flat, 1.0)


def _read_mask(path: str | Path, shape: tuple[int, int], binning: int = 1) -> np.ndarray:
    """(H, W) x ``binning`` bool, True where the mask file is non-zero in every channel (alpha
    included); the mask is of the images' size (before binning)."""
    arr = _read_any(path)
    err = _size_error(Path(path), "mask", arr.shape, shape, binning)
    if err is not None:
        raise err
    arr = arr[:shape[0] * binning, :shape[1] * binning]
    return arr != 0 if arr.ndim == 2 else np.all(arr != 0, axis=2)


def write_float_tiff(path: str | Path, image: np.ndarray) -> None:
    """Write a linear RGB image as a float32 TIFF, atomically.

    The file is written to a temporary name in the same folder and renamed onto
    ``path``, so a killed process leaves the old file or the new one.

    Parameters
    ----------
    path : str or Path
        Destination; its folder is created if missing.
    image : ndarray of shape (H, W, 3)
        Channels R, G, B, finite; any unit (stored as given).

    Raises
    ------
    ValueError
        ``image`` has the wrong shape or non-finite values.
    """
    import tifffile

    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"write_float_tiff: image of shape {img.shape}; expected (H, W, 3)")
    img = np.ascontiguousarray(img, dtype=np.float32)
    if not np.isfinite(img).all():
        raise ValueError(f"write_float_tiff: {path}: image has NaN or infinite values "
                         "(or values beyond the float32 range)")
    atomic_write(path, lambda tmp: tifffile.imwrite(tmp, img, photometric="rgb"))


@dataclass(frozen=True)
class LoadedImage:
    """One image entry, merged and exposure-normalised.

    Attributes
    ----------
    data : ndarray of shape (H, W, 3), float64
        Dark-subtracted signal in file units per second, channels R, G, B.
        Finite everywhere; where ``valid`` is False the value is a placeholder.
    valid : ndarray of shape (H, W, 3), bool
        False where the channel is saturated in every frame or the mask is zero.
    n_saturated : int
        Pixels with at least one requested channel saturated in every frame.
    n_masked : int
        Pixels where the mask is zero.
    source : str
        The file path(s), for messages.
    exposure : ndarray of shape (H, W, 3)
        Summed exposure (s) of the frames merged into each pixel (all frames where
        every one is saturated).
    reads : ndarray of shape (H, W, 3)
        Read-noise variances summed in each pixel, in units of one read: the frames merged
        plus their dark frames (K^2 for one dark shared by the K frames merged).
    samples : ndarray of shape (3,)
        Stored samples averaged per pixel and channel (binned Bayer: 1, 2, 1).
    quant_var : float
        Variance of the quantisation of one stored sample, file units squared: step^2 / 12
        (the float type's spacing at the largest value for float files).
    exposures : tuple of float
        The frames' exposure times, s.
    flat : ndarray of shape (H, W, 3) or None
        The flat field ``data`` was divided by (mean 1 over the usable pixels), if any.
    noise_scale : tuple of two ndarrays of shape (H, W, 3), or None
        Binned images only (:func:`bin_image`): the per-pixel factors of the camera's ``a``
        and floored ``b`` in the variance (they replace exposure, reads, samples and flat).
    unbinned : LoadedImage or None
        Binned images only: the image before binning (the noise is estimated on it).
    """

    data: np.ndarray
    valid: np.ndarray
    n_saturated: int
    n_masked: int
    source: str
    exposure: np.ndarray | None = None
    reads: np.ndarray | None = None
    samples: np.ndarray = field(default_factory=lambda: np.ones(3))
    quant_var: float = 0.0
    exposures: tuple[float, ...] = (1.0,)
    flat: np.ndarray | None = None
    noise_scale: tuple[np.ndarray, np.ndarray] | None = None
    unbinned: LoadedImage | None = None

    def variance_maps(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel noise model of ``data``: variance = gain_map * mean + read_map.

        Parameters
        ----------
        a, b : array_like of shape (3,) or scalar
            The camera's noise per stored sample of one frame, in file units (DN):
            variance = a * signal + b, per channel R, G, B.

        Returns
        -------
        gain_map, read_map : ndarray of shape (H, W, 3)
            With T the pixel's summed exposure over the frames merged into it, N its
            number of reads (frames plus subtracted darks) and n the samples binned
            into it: gain_map = a / (n T), read_map = N max(b, quant_var) / (n T^2), both
            divided by the flat field (``gain_map``) and its square (``read_map``) if any.
            ``read_map`` is positive: ``b`` is floored at the quantisation variance.  A binned
            image (``noise_scale``) gives a and the floored b times its factors.
        """
        a = np.broadcast_to(np.asarray(a, float), (3,))
        b = np.maximum(np.broadcast_to(np.asarray(b, float), (3,)), self.quant_var)
        if self.noise_scale is not None:
            return a * self.noise_scale[0], b * self.noise_scale[1]
        t = self.exposure if self.exposure is not None else np.full(self.data.shape,
                                                                    self.exposures[0])
        n = self.reads if self.reads is not None else np.ones(self.data.shape)
        f = 1.0 if self.flat is None else self.flat  # data = signal / flat: variance / flat^2
        return a / (self.samples * t * f), n * b / (self.samples * t * t * f * f)


def _block_mean(a: np.ndarray, n: int) -> np.ndarray:
    """Mean of each n x n block of the first two axes (their sizes multiples of n)."""
    h, w = a.shape[0] // n, a.shape[1] // n
    return a.reshape(h, n, w, n, *a.shape[2:]).mean(axis=(1, 3))


def bin_image(img: LoadedImage, n: int, saturated: np.ndarray, masked: np.ndarray
              ) -> LoadedImage:
    """``img`` binned n x n (docs/spec.md, "Binning"): each pixel and channel the mean of its
    block; valid only where every member is; ``saturated`` / ``masked`` ((H, W) bool, before
    binning) give the binned pixels' counts.  The variance of a mean of n^2 independent pixels
    is the sum of theirs over n^4: with the members' factors g_i (of a) and r_i (of the floored
    b) the binned pixel's are mean(g_i) / n^2 and mean(r_i) / n^2, exact for the read part and
    for the gain part where the members share g_i (one frame, no flat), else at the block's
    mean level."""
    gain1, read1 = img.variance_maps(np.ones(3), np.ones(3))  # per unit a and floored b
    if img.quant_var > 1.0:  # variance_maps floors b = 1 at quant_var: undo that
        read1 = read1 / img.quant_var
    scale = (_block_mean(gain1, n) / n ** 2, _block_mean(read1, n) / n ** 2)
    valid = _block_mean(img.valid.astype(float), n) == 1.0
    h, w = img.data.shape[0] // n, img.data.shape[1] // n
    blocks = (lambda m: m.reshape(h, n, w, n).any(axis=(1, 3)))
    return replace(img, data=_block_mean(img.data, n), valid=valid,
                   n_saturated=int(np.count_nonzero(blocks(saturated))),
                   n_masked=int(np.count_nonzero(blocks(masked))),
                   exposure=_block_mean(img.exposure, n), reads=_block_mean(img.reads, n),
                   flat=None, noise_scale=scale, unbinned=img)


def _size_error(path: Path, what: str, got: tuple[int, ...], shape: tuple[int, int],
                binning: int) -> ImageError | None:
    """Why an image of ``got`` pixels (height, width) cannot be ``shape`` (camera.size) after
    ``binning`` x ``binning`` binning (which drops up to binning - 1 last rows and columns);
    None when it can."""
    h, w = got[:2]
    if (h // binning, w // binning) == tuple(shape):
        return None
    raw = " (a RAW file's 2x2 Bayer quads binned)" if path.suffix.lower() in RAW_EXT else ""
    want = (f"expected {shape[1]}x{shape[0]} (camera.size)" if binning == 1 else
            f"expected {binning * shape[1]}x{binning * shape[0]} (camera.size {shape[1]}x"
            f"{shape[0]} times binning {binning}; up to {binning - 1} more rows and columns "
            "are dropped)")
    return ImageError(f"{path}: {what} is {w}x{h} pixels{raw} (width x height), {want}")


def _frame(path: Path, shape: tuple[int, int], what: str, binning: int = 1) -> Frame:
    """The file as a Frame of ``shape`` x ``binning`` pixels (rows and columns that binning
    drops cut off)."""
    frame = read_frame(path)
    err = _size_error(path, what, frame.data.shape, shape, binning)
    if err is not None:
        raise err
    h, w = shape[0] * binning, shape[1] * binning
    if frame.data.shape[:2] != (h, w):
        frame = replace(frame, data=frame.data[:h, :w], peak=frame.peak[:h, :w])
    return frame


def _saturated(frame: Frame, saturation: float | None) -> np.ndarray:
    """Where the frame is saturated: its stored (RAW: raw sensor) values at or above the
    spec's ``saturation``, else at or above ``SATURATION_FRACTION`` of the file's level."""
    if saturation is not None:
        return frame.peak >= saturation
    if frame.level is None:
        return np.zeros(frame.peak.shape, bool)
    return frame.peak >= SATURATION_FRACTION * frame.level


def load_entry(entry: ImageEntry, *, expected_shape: tuple[int, int],
               channels: tuple[int, ...] = (0, 1, 2)) -> LoadedImage:
    """Read an image entry (one photo or an exposure bracket) as one linear image.

    Each frame k gives ``s_k = raw_k - dark_k``.  A pixel channel is saturated
    in frame k where its stored value (RAW: the raw sensor value of any photosite
    binned into it, black included) is at or above ``entry.saturation`` if given,
    else at or above ``SATURATION_FRACTION`` of the file's level (65535, 255, the
    RAW white level; float files have none).  The result is the exposure-weighted mean of
    ``s_k / t_k`` over unsaturated frames, ``sum(s_k) / sum(t_k)``: longer
    exposures, with better SNR, count more.  Where every frame is saturated
    the value is the same sum over all frames, marked invalid.  The per-pixel
    noise model follows from the frames merged into each pixel
    (:meth:`LoadedImage.variance_maps`).

    Parameters
    ----------
    entry : fitmedia.spec.ImageEntry
        Paths, exposure times in seconds, optional dark frame(s) (one, or one
        per path), mask, saturation level and response.
    expected_shape : tuple of int
        (H, W) in pixels, i.e. ``(camera.height, camera.width)``.
    channels : tuple of int
        Indices (0 = R, 1 = G, 2 = B) of the channels that will be used; only
        they count towards ``n_saturated`` and the unusable fraction.

    Returns
    -------
    LoadedImage

    Raises
    ------
    ImageError
        A bad file, a frame or dark of the wrong size, a dark of another pixel
        type, an 8- or 16-bit file without ``response`` (:func:`linearise`), or more
        than ``MAX_UNUSABLE_FRACTION`` of the pixels saturated or masked in the
        requested channels.
    """
    chans = tuple(channels)
    if not chans or any(c not in (0, 1, 2) for c in chans):
        raise InputError(f"channels: got {channels!r}; expected indices among 0, 1, 2 (R, G, B)")
    paths, exps, darks = list(entry.paths), list(entry.exposures), list(entry.darks)
    source = " + ".join(str(p) for p in paths)
    if not paths or len(exps) != len(paths) or not all(t > 0 for t in exps):
        raise InputError(f"{source}: exposure_s: {exps} for {len(paths)} path(s); expected one "
                         "positive time per path")
    if len(darks) not in (0, 1, len(paths)):
        raise InputError(f"{source}: dark: {len(darks)} dark frames for {len(paths)} paths")
    if not isinstance(entry.binning, int) or entry.binning < 1:
        raise InputError(f"{source}: binning: {entry.binning!r}; expected an integer >= 1")
    camera = (int(expected_shape[0]), int(expected_shape[1]))
    shape = (camera[0] * entry.binning, camera[1] * entry.binning)  # the files' (cut) size
    data, exposure, reads, samples, quant_var = _merge(entry, camera)
    usable = exposure > 0
    exposure = np.where(usable, exposure, sum(exps))
    k = len(paths)
    reads = np.where(usable, reads, k + (k * k if len(darks) == 1 and k > 1 else k) * bool(darks))
    mask_ok = (np.ones(shape, bool) if entry.mask is None else
               _read_mask(entry.mask, camera, entry.binning))
    valid = usable & mask_ok[..., None]
    flat = None if entry.flat is None else _read_flat(entry.flat, entry, camera, valid)
    if flat is not None:
        data = data / flat
    saturated = ~usable[..., chans].all(axis=2)
    n_sat, n_masked = _check_usable(source, saturated, mask_ok)
    img = LoadedImage(data=data, valid=valid, n_saturated=n_sat, n_masked=n_masked,
                      source=source, exposure=exposure, reads=reads, samples=samples,
                      quant_var=quant_var, exposures=tuple(exps), flat=flat)
    return img if entry.binning == 1 else bin_image(img, entry.binning, saturated, ~mask_ok)


def _check_usable(source: str, saturated: np.ndarray, mask_ok: np.ndarray) -> tuple[int, int]:
    """The counts of saturated and masked pixels; refused when more than
    ``MAX_UNUSABLE_FRACTION`` of the pixels are either."""
    n_sat, n_masked = int(np.count_nonzero(saturated)), int(np.count_nonzero(~mask_ok))
    frac = np.count_nonzero(saturated | ~mask_ok) / saturated.size
    if frac > MAX_UNUSABLE_FRACTION:
        fs, fm = 100.0 * n_sat / saturated.size, 100.0 * n_masked / saturated.size
        what = (f"is saturated in {fs:.0f}% of pixels" if fs > 100 * MAX_UNUSABLE_FRACTION else
                f"is saturated or masked in {100 * frac:.0f}% of pixels ({fs:.0f}% saturated, "
                f"{fm:.0f}% masked)")
        raise ImageError(f"{source}: {what}; at most {100 * MAX_UNUSABLE_FRACTION:.0f}% may be "
                         "unusable (use a shorter exposure or an exposure bracket)")
    return n_sat, n_masked


def _merge(entry: ImageEntry, shape: tuple[int, int]
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """The frames of ``entry`` merged: ``sum(s_k) / sum(t_k)`` over unsaturated frames
    (all frames where none is), the unsaturated exposure sum (0 where none), the reads
    (frames + darks) merged, the samples per pixel and the largest quantisation variance.
    ``shape`` is camera.size; the files are ``entry.binning`` times that (cut)."""
    paths, exps, darks = list(entry.paths), list(entry.exposures), list(entry.darks)
    full = (shape[0] * entry.binning, shape[1] * entry.binning)
    num, den, nread, all_num = (np.zeros(full + (3,)) for _ in range(4))
    dark_cache: dict[Path, Frame] = {}
    samples, qvar = None, 0.0
    for k, (path, t) in enumerate(zip(paths, exps)):
        frame = linearise(_frame(path, shape, "image", entry.binning), entry.response, path,
                          entry.response_curve)
        signal = frame.data
        if darks:
            dpath = darks[k if len(darks) > 1 else 0]
            if dpath not in dark_cache:
                dark_cache[dpath] = linearise(_frame(dpath, shape, "dark frame", entry.binning),
                                              entry.response, dpath, entry.response_curve)
            dark = dark_cache[dpath]
            if dark.level != frame.level or not np.array_equal(dark.samples, frame.samples):
                raise ImageError(f"{dpath}: dark frame has saturation level {dark.level} (pixel "
                                 f"type) but the image {path} has {frame.level}; they must "
                                 "be of the same type")
            signal = frame.data - dark.data
            qvar = max(qvar, dark.quantum ** 2 / 12.0)
        if samples is not None and not np.array_equal(samples, frame.samples):
            raise ImageError(f"{path}: frames of one bracket must be of the same file type")
        samples, qvar = frame.samples, max(qvar, frame.quantum ** 2 / 12.0)
        ok = ~_saturated(frame, entry.saturation)
        num += np.where(ok, signal, 0.0)
        den += np.where(ok, t, 0.0)
        nread += ok
        all_num += signal
    usable = den > 0
    data = np.where(usable, num / np.where(usable, den, 1.0), all_num / sum(exps))
    # the darks' reads: one per frame merged, or one dark shared by the K frames merged,
    # whose noise enters their sum K times over: K^2 reads' worth of variance
    dark_reads = (nread ** 2 if len(darks) == 1 and len(paths) > 1 else nread) if darks else 0
    return data, den, nread + dark_reads, samples, qvar

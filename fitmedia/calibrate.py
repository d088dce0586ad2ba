"""``fitmedia calibrate``: the camera block of a capture spec from photographs of a ChArUco
board (issue 16; user documentation in ``docs/calibrate.md``).

All images go into OpenCV's ``calibrateCamera`` (intrinsics fx, fy, cx, cy and the
distortion k1, k2, p1, p2, k3 of OpenCV's model on normalised coordinates); the first
image, the *pose view*, shows the board flat against the front wall's outer face at the
placement given in the board file, and its board pose gives the camera's position and
orientation in the tank frame (CAPTURE_SPEC.md).

Conventions.  OpenCV puts pixel (row i, column j)'s centre at (j, i); fitmedia at
(j + 0.5, i + 0.5) (``fitmedia.geometry.camera_rays``), so fitmedia's cx = cx_OpenCV + 0.5
and cy = cy_OpenCV + 0.5; fx, fy and the distortion coefficients are the same.  OpenCV's
camera frame (x right, y down, z forward) maps to the spec's right, -true_up, forward.
The board frame is OpenCV's: origin at the outer corner of the square grid beside square
(0, 0), x along the rows of squares, y down the printed board, z into the board.
Lengths in mm.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .errors import ImageError, InputError

#: Fewest ChArUco corners a view needs to be used (solvePnP needs 4 non-collinear points;
#: a handful more keeps one view's pose from being decided by noise).
MIN_CORNERS = 8
#: Fewest usable views: Zhang's method needs 3 views in general position for fx, fy, cx, cy.
MIN_VIEWS = 3
#: A view counts as tilted when the board's normal is this far (degrees) from the optical
#: axis; at least MIN_TILTED such views are required (planar views at one tilt leave the
#: focal length and the board's distance degenerate).
TILT_DEG = 10.0
MIN_TILTED = 2
#: Relative standard deviation of fx or fy above which the result is refused / warned about.
REFUSE_REL_SD = 0.02
WARN_REL_SD = 0.002
#: RMS reprojection error (px) above which a warning is printed.
WARN_RMS_PX = 0.5

_BOARD_KEYS = {"squares_x", "squares_y", "square_length_mm", "marker_length_mm", "dictionary",
               "legacy_pattern", "placement"}
_PLACEMENT_KEYS = {"wall_z_mm", "origin_mm", "x_axis", "thickness_mm"}


@dataclass(frozen=True)
class Board:
    """A ChArUco board and where it lies on the front wall in the pose view (mm)."""

    squares_x: int
    squares_y: int
    square_length_mm: float
    marker_length_mm: float
    dictionary: str
    legacy_pattern: bool
    wall_z_mm: float
    origin_mm: tuple[float, float]
    x_axis: tuple[float, float]
    thickness_mm: float = 0.0


def _warn(msg: str) -> None:
    print(f"fitmedia: warning: {msg}", file=sys.stderr)


def _number(d: dict, key: str, where: str, *, positive: bool = False, default=None) -> float:
    if key not in d:
        if default is not None:
            return float(default)
        raise InputError(f"{where}: {key}: is required but missing")
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"{where}: {key}: got {v!r}: expected a finite number")
    if positive and not v > 0:
        raise InputError(f"{where}: {key}: got {v!r}: must be > 0")
    return float(v)


def _pair(d: dict, key: str, where: str, default=None) -> tuple[float, float]:
    v = d.get(key, default)
    if v is None:
        raise InputError(f"{where}: {key}: is required but missing")
    if (not isinstance(v, list) or len(v) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool)
                       and math.isfinite(x) for x in v)):
        raise InputError(f"{where}: {key}: got {v!r}: expected two finite numbers [x, y] (mm)")
    return float(v[0]), float(v[1])


def _check_keys(d: Any, allowed: set, where: str) -> None:
    if not isinstance(d, dict):
        raise InputError(f"{where}: expected a mapping of fields, got {type(d).__name__}")
    extra = sorted(set(map(str, d)) - allowed)
    if extra:
        raise InputError(f"{where}: {extra[0]}: unknown field; allowed: "
                         f"{', '.join(sorted(allowed))}")


def load_board(path: str | Path) -> Board:
    """Read and check a board file (docs/calibrate.md, "The board file").

    Raises
    ------
    InputError
        Missing or unreadable file, invalid YAML, a missing, unknown or invalid field
        (named in the one-line message).
    """
    import cv2

    from .spec import SpecLoader

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: board file not found")
    try:
        d = yaml.load(path.read_text(), Loader=SpecLoader)  # noqa: S506 (a SafeLoader)
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: not a valid YAML board file ({type(exc).__name__})") from None
    where = str(path)
    _check_keys(d, _BOARD_KEYS, where)
    sq = {}
    for key in ("squares_x", "squares_y"):
        v = d.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < 2:
            raise InputError(f"{where}: {key}: got {v!r}: expected a whole number >= 2")
        sq[key] = v
    square = _number(d, "square_length_mm", where, positive=True)
    marker = _number(d, "marker_length_mm", where, positive=True)
    if not marker < square:
        raise InputError(f"{where}: marker_length_mm: got {marker:g}: must be smaller than "
                         f"square_length_mm ({square:g})")
    name = d.get("dictionary")
    if not (isinstance(name, str) and name.startswith("DICT_") and hasattr(cv2.aruco, name)):
        names = [n for n in dir(cv2.aruco) if n.startswith("DICT_") and n.upper() == n]
        raise InputError(f"{where}: dictionary: got {name!r}: expected an OpenCV ArUco dictionary "
                         f"name such as DICT_5X5_100 (one of {', '.join(sorted(names))})")
    n_markers = sq["squares_x"] * sq["squares_y"] // 2
    size = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name)).bytesList.shape[0]
    if n_markers > size:
        raise InputError(f"{where}: dictionary: {name} holds {size} markers; a "
                         f"{sq['squares_x']}x{sq['squares_y']} board needs {n_markers}")
    legacy = d.get("legacy_pattern", False)
    if not isinstance(legacy, bool):
        raise InputError(f"{where}: legacy_pattern: got {legacy!r}: expected true or false")
    return Board(sq["squares_x"], sq["squares_y"], square, marker, name, legacy,
                 *_placement(d.get("placement"), f"{where}: placement"))


def _placement(p: Any, where: str) -> tuple:
    if p is None:
        raise InputError(f"{where}: is required but missing (where the board lies on the front "
                         "wall in the first image)")
    _check_keys(p, _PLACEMENT_KEYS, where)
    wall_z = _number(p, "wall_z_mm", where, positive=True)
    origin = _pair(p, "origin_mm", where)
    axis = _pair(p, "x_axis", where, default=[1, 0])
    if not math.hypot(*axis) > 0:
        raise InputError(f"{where}: x_axis: got {list(axis)}: must be a non-zero direction")
    n = math.hypot(*axis)
    thick = _number(p, "thickness_mm", where, default=0.0)
    if thick < 0:
        raise InputError(f"{where}: thickness_mm: got {thick:g}: must be >= 0")
    return wall_z, origin, (axis[0] / n, axis[1] / n), thick


def make_board(board: Board):
    """The ``cv2.aruco.CharucoBoard`` of a :class:`Board` (lengths in mm)."""
    import cv2

    dic = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    cb = cv2.aruco.CharucoBoard((board.squares_x, board.squares_y), board.square_length_mm,
                                board.marker_length_mm, dic)
    cb.setLegacyPattern(board.legacy_pattern)
    return cb


def write_board_png(board_path: str | Path, out: str | Path, *, dpi: float = 300.0) -> None:
    """Write the board of ``board_path`` as a PNG to print at ``dpi`` (1:1 scale, no margin).

    Check the printed squares with a ruler and put the measured length in the board file.
    """
    import cv2

    from .util import atomic_write

    board = load_board(board_path)
    px_mm = dpi / 25.4
    size = (round(board.squares_x * board.square_length_mm * px_mm),
            round(board.squares_y * board.square_length_mm * px_mm))
    img = make_board(board).generateImage(size, marginSize=0, borderBits=1)
    ok, buf = cv2.imencode(".png", img)
    atomic_write(out, lambda p: p.write_bytes(buf.tobytes()))


def board_to_tank(board: Board) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (3x3) and offset t (3,) with X_tank = R @ X_board + t in the pose view.

    The board lies printed side towards the camera on the plane z = wall_z + thickness;
    its x axis is ``x_axis`` in the wall's (x, y) plane, its z axis points into the
    tank (-z), so its y axis is z x x.
    """
    ex = np.array([board.x_axis[0], board.x_axis[1], 0.0])
    ez = np.array([0.0, 0.0, -1.0])
    ey = np.cross(ez, ex)
    t = np.array([board.origin_mm[0], board.origin_mm[1], board.wall_z_mm + board.thickness_mm])
    return np.column_stack([ex, ey, ez]), t


def camera_block(K: np.ndarray, dist: np.ndarray, rvec: np.ndarray, tvec: np.ndarray,
                 size: tuple[int, int], board: Board) -> dict:
    """The spec's ``camera`` block (fitmedia's pixel convention) from OpenCV's calibration.

    ``K``, ``dist``: OpenCV camera matrix and distortion (k1, k2, p1, p2, k3);
    ``rvec``, ``tvec``: the board's pose in the camera in the pose view (X_cam = R X_board
    + t); ``size``: (width, height) in pixels.  ``look_at`` is where the optical axis
    meets the board's plane; ``up`` is the camera's true up (so the roll is kept).
    """
    import cv2

    R = cv2.Rodrigues(np.asarray(rvec, float).reshape(3))[0]
    t = np.asarray(tvec, float).reshape(3)
    Rbt, tbt = board_to_tank(board)
    cam_to_tank = Rbt @ R.T  # columns: the camera's x (right), y (down), z (forward) in the tank
    position = Rbt @ (-R.T @ t) + tbt
    right, down, forward = cam_to_tank.T
    dist_axis = float(t[2]) if t[2] > 0 else float(np.linalg.norm(t))
    d = np.ravel(dist).tolist() + [0.0] * 5
    return {
        "size": [int(size[0]), int(size[1])],
        "fx": float(K[0, 0]), "fy": float(K[1, 1]),
        "cx": float(K[0, 2]) + 0.5, "cy": float(K[1, 2]) + 0.5,
        "position": position.tolist(),
        "look_at": (position + dist_axis * forward).tolist(),
        "up": (-down).tolist(),
        "distortion": dict(zip(("k1", "k2", "p1", "p2", "k3"), map(float, d[:5]))),
    }


def _to_grey8(arr: np.ndarray) -> np.ndarray:
    """An image as 8-bit grey for detection: channels averaged, 8-bit kept as is, other
    types scaled between the 0.5th and 99.5th percentiles."""
    a = arr.astype(np.float64)
    if a.ndim == 3:
        a = a[..., :3].mean(axis=2) if a.shape[2] >= 3 else a[..., 0]
    if arr.dtype == np.uint8:
        return np.clip(np.rint(a), 0, 255).astype(np.uint8)
    lo, hi = np.percentile(a, [0.5, 99.5])
    if not hi > lo:
        return np.zeros(a.shape, np.uint8)
    return np.clip(np.rint((a - lo) / (hi - lo) * 255.0), 0, 255).astype(np.uint8)


def read_grey(path: str | Path) -> np.ndarray:
    """Read a calibration photograph as 8-bit grey (H, W).

    Camera RAW is decoded as ``fitmedia fit`` decodes it (2x2 Bayer quads binned, so the
    size is the fit's); TIFF, PNG and OpenEXR through fitmedia's readers; JPEG by OpenCV.

    Raises
    ------
    ImageError
        Missing, unreadable or unsupported file (naming it).
    """
    import cv2

    from .images.io import RAW_EXT, _read_any, read_frame

    path = Path(path)
    ext = path.suffix.lower()
    if ext in RAW_EXT:
        if not path.is_file():
            raise ImageError(f"{path}: file not found")
        return _to_grey8(read_frame(path).data)
    if ext in (".jpg", ".jpeg"):
        if not path.is_file():
            raise ImageError(f"{path}: file not found")
        arr = cv2.imdecode(np.fromfile(path, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
        if arr is None:
            raise ImageError(f"{path}: not a readable JPEG file (empty, truncated or corrupt)")
        return arr
    return _to_grey8(_read_any(path))


def detect(cboard, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """ChArUco corners of one view: (object points (N, 3) mm, image points (N, 2) in
    OpenCV's pixel convention), or None when fewer than MIN_CORNERS are found or they lie
    on one line."""
    import cv2

    try:
        corners, ids, _, _ = cv2.aruco.CharucoDetector(cboard).detectBoard(grey)
    except cv2.error:  # an image OpenCV's detector cannot take (too small): no board in it
        return None
    if ids is None or len(ids) < MIN_CORNERS:
        return None
    if cv2.aruco.testCharucoCornersCollinear(cboard, ids):
        return None
    obj, img = cboard.matchImagePoints(corners, ids)
    return obj.reshape(-1, 3).astype(np.float32), img.reshape(-1, 2).astype(np.float32)


def _detect_all(paths: list[Path], cboard, board: Board):
    """Read and detect every image; the usable views, their paths and the image size.

    Raises
    ------
    InputError
        Images of different sizes; no board in any image; the pose view (first image)
        without a usable board.
    """
    found, size = [], None
    for p in paths:
        grey = read_grey(p)
        hw = (grey.shape[1], grey.shape[0])
        if size is None:
            size = hw
        elif hw != size:
            raise ImageError(f"{p}: {hw[0]}x{hw[1]} pixels, but {paths[0]} is {size[0]}x{size[1]}; "
                             "all calibration images must come from one camera setting")
        found.append(detect(cboard, grey))
    if all(v is None for v in found):
        raise InputError(f"{paths[0]}: no ChArUco board ({board.squares_x}x{board.squares_y} "
                         f"squares, {board.dictionary}) found in any image (or fewer than "
                         f"{MIN_CORNERS} corners in each)")
    if found[0] is None:
        raise InputError(f"{paths[0]}: the pose view (first image): the board was not found or "
                         f"has fewer than {MIN_CORNERS} corners (need the board flat on the "
                         "front wall, in focus and whole)")
    for p, v in zip(paths, found):
        if v is None:
            _warn(f"{p}: board not found or fewer than {MIN_CORNERS} corners; image skipped")
    keep = [k for k, v in enumerate(found) if v is not None]
    return [found[k] for k in keep], [paths[k] for k in keep], size


def _tilts_deg(rvecs) -> np.ndarray:
    """Angle (degrees) between each view's board normal and the optical axis."""
    import cv2

    out = []
    for rv in rvecs:
        n = cv2.Rodrigues(np.asarray(rv, float).reshape(3))[0][:, 2]
        out.append(math.degrees(math.acos(min(1.0, abs(float(n[2]))))))
    return np.array(out)


def _coverage(views, size: tuple[int, int], n: int = 4) -> float:
    """Fraction of an n x n grid of image cells holding a detected corner in some view."""
    hit = np.zeros((n, n), bool)
    for _, img in views:
        j = np.clip((img[:, 0] / size[0] * n).astype(int), 0, n - 1)
        i = np.clip((img[:, 1] / size[1] * n).astype(int), 0, n - 1)
        hit[i, j] = True
    return float(hit.mean())


@dataclass(frozen=True)
class Calibration:
    """OpenCV's calibration of the views (pixel convention: OpenCV's)."""

    K: np.ndarray
    dist: np.ndarray
    rvecs: list
    tvecs: list
    rms_px: float
    per_view_px: np.ndarray
    sd: np.ndarray  # standard deviations of fx, fy, cx, cy, k1, k2, p1, p2, k3
    tilts_deg: np.ndarray
    n_corners: int


def calibrate_views(views, size: tuple[int, int], names: list, *,
                    fix_k3: bool = False) -> Calibration:
    """``cv2.calibrateCameraExtended`` on the views (k3 held at 0 with ``fix_k3``), with
    the checks that its focal length is determined (module constants; docs/calibrate.md).

    Raises
    ------
    InputError
        Fewer than MIN_VIEWS usable views, fewer than MIN_TILTED tilted ones, or fx/fy with
        a relative standard deviation above REFUSE_REL_SD.
    """
    import cv2

    if len(views) < MIN_VIEWS:
        raise InputError(f"{names[0]}: the board was found (with >= {MIN_CORNERS} corners) in "
                         f"{len(views)} image(s); at least {MIN_VIEWS} are needed")
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    try:
        rms, K, dist, rvecs, tvecs, sd, _, per_view = cv2.calibrateCameraExtended(
            [o for o, _ in views], [i for _, i in views], size, None, None,
            flags=cv2.CALIB_FIX_K3 if fix_k3 else 0, criteria=crit)
    except cv2.error as exc:
        raise InputError(f"{names[0]}: OpenCV's calibration failed on these views "
                         f"({' '.join(str(exc).split())[-120:]})") from None
    tilts = _tilts_deg(rvecs)
    n_tilted = int(np.sum(tilts >= TILT_DEG))
    if n_tilted < MIN_TILTED:
        raise InputError(f"{names[0]}: {n_tilted} of {len(views)} views show the board tilted by "
                         f">= {TILT_DEG:g} deg (tilts {', '.join(f'{x:.0f}' for x in tilts)} deg); "
                         f"at least {MIN_TILTED} are needed to determine the focal length "
                         "(docs/calibrate.md)")
    sd = np.ravel(sd)
    rel = np.array([sd[0] / K[0, 0], sd[1] / K[1, 1]])
    if not np.all(np.isfinite(rel)) or rel.max() > REFUSE_REL_SD:
        raise InputError(f"{names[0]}: the focal length is not determined by these views "
                         f"(relative sd of fx, fy: {rel[0]:.2%}, {rel[1]:.2%}); add views with the "
                         "board tilted 20-45 deg in different directions (docs/calibrate.md)")
    return Calibration(K, np.ravel(dist)[:5], list(rvecs), list(tvecs), float(rms),
                       np.ravel(per_view), sd[:9], tilts, int(sum(len(o) for o, _ in views)))


def fold_reason(block: dict) -> str | None:
    """Why the block's distortion folds back over its image (the spec parser refuses such a
    camera: ``fitmedia.distortion.check_monotonic``), or None."""
    from .distortion import KEYS, check_monotonic

    coeffs = tuple(block["distortion"][k] for k in KEYS)
    return check_monotonic(coeffs, block["size"][0], block["size"][1], block["fx"], block["fy"],
                           block["cx"], block["cy"])


def _calibrate_unfolded(views, size: tuple[int, int], used: list, bd: Board):
    """The calibration and its camera block; refitted with k3 = 0 (warned) when the full
    model's distortion folds back inside the image, refused when that folds too."""
    cal = calibrate_views(views, size, used)
    block = camera_block(cal.K, cal.dist, cal.rvecs[0], cal.tvecs[0], size, bd)
    why = fold_reason(block)
    if why is None:
        return cal, block
    _warn(f"the fitted distortion is not one-to-one over the image ({why}); refitted with "
          "k3 = 0: add views with the board's corners near the image's edges and corners")
    cal = calibrate_views(views, size, used, fix_k3=True)
    block = camera_block(cal.K, cal.dist, cal.rvecs[0], cal.tvecs[0], size, bd)
    why = fold_reason(block)
    if why is not None:
        raise InputError(f"{used[0]}: the fitted lens distortion folds back inside the image "
                         f"even with k3 = 0 ({why}); add views with the board's corners near "
                         "the image's edges and corners (docs/calibrate.md)")
    return cal, block


def _fmt(x: float) -> str:
    """A number YAML reads back as a float (PyYAML wants a '.' and a signed exponent)."""
    s = repr(round(float(x), 6))
    return s if abs(x) >= 1e-3 and "e" not in s else f"{float(x):.6e}"


def _vec(v) -> str:
    return "[" + ", ".join(_fmt(x) for x in v) + "]"


def format_camera_yaml(block: dict, notes: list[str]) -> str:
    """The camera block as YAML text, with ``notes`` as leading comment lines."""
    dist = ", ".join(f"{k}: {_fmt(v)}" for k, v in block["distortion"].items())
    lines = [f"# {n}" for n in notes] + [
        "camera:",
        f"  size: [{block['size'][0]}, {block['size'][1]}]",
        *(f"  {k}: {_fmt(block[k])}" for k in ("fx", "fy", "cx", "cy")),
        *(f"  {k}: {_vec(block[k])}" for k in ("position", "look_at", "up")),
        f"  distortion: {{{dist}}}",
    ]
    return "\n".join(lines) + "\n"


def _notes(cal: Calibration, used: list, n_images: int, board_path: str) -> list[str]:
    sd = cal.sd
    return [
        f"fitmedia calibrate: {len(used)} of {n_images} images used; board {board_path}",
        f"pose view (board on the front wall): {used[0]}",
        f"rms_reprojection_error_px: {cal.rms_px:.4f}",
        f"pose_view_rms_px: {cal.per_view_px[0]:.4f}",
        f"corners: {cal.n_corners}; view tilts (deg): "
        + ", ".join(f"{x:.0f}" for x in cal.tilts_deg),
        f"sd (1 sigma, OpenCV's estimate): fx {sd[0]:.3g}, fy {sd[1]:.3g}, cx {sd[2]:.3g}, "
        f"cy {sd[3]:.3g} px",
        "pixel convention: fitmedia's (pixel centres at j + 0.5, i + 0.5); "
        "OpenCV's cx, cy are 0.5 smaller",
    ]


def run_calibrate(*, images: list, board: str | Path, out: str | Path) -> int:
    """``fitmedia calibrate IMAGES... --board BOARD --out OUT``; returns the exit code 0.

    Bad input raises :class:`~fitmedia.errors.InputError` (the CLI's exit code 2).
    """
    import cv2

    level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)  # a broken file: 1 line
    try:
        return _run(images, board, out)
    finally:
        cv2.utils.logging.setLogLevel(level)


def _run(images: list, board: str | Path, out: str | Path) -> int:
    from .util import atomic_write_text

    if Path(out).is_dir():
        raise InputError(f"{out}: --out is a folder; give the camera YAML file to write")
    bd = load_board(board)
    paths = [Path(p) for p in images]
    views, used, size = _detect_all(paths, make_board(bd), bd)
    cal, block = _calibrate_unfolded(views, size, used, bd)
    if not block["position"][2] > bd.wall_z_mm:
        raise InputError(f"{board}: placement: the camera comes out at z = "
                         f"{block['position'][2]:.1f} mm, not in front of the front wall "
                         f"(z > {bd.wall_z_mm:g}); check placement.x_axis and that the first "
                         "image shows the board flat on the wall, printed side to the camera")
    rel = cal.sd[:2] / np.array([cal.K[0, 0], cal.K[1, 1]])
    if rel.max() > WARN_REL_SD:
        _warn(f"focal length weakly determined (relative sd fx {rel[0]:.2%}, fy {rel[1]:.2%}); "
              "add views with the board tilted 20-45 deg")
    if _coverage(views, size) < 0.75:
        _warn("the board's corners cover less than 3/4 of the image (4x4 cells); the "
              "distortion is extrapolated near the edges: add views with the board there")
    if cal.rms_px > WARN_RMS_PX:
        _warn(f"RMS reprojection error {cal.rms_px:.2f} px > {WARN_RMS_PX} px: blurred or "
              "moved views, a board that is not flat, or a wrong board file")
    try:
        atomic_write_text(out, format_camera_yaml(block, _notes(cal, used, len(paths), str(board))))
    except OSError as exc:
        raise InputError(f"{out}: cannot be written ({exc.strerror or exc})") from None
    print(f"wrote {out}: fx {block['fx']:.2f}, fy {block['fy']:.2f} px, camera at "
          f"{_vec(np.round(block['position'], 1))} mm; RMS reprojection error "
          f"{cal.rms_px:.3f} px over {len(used)} views")
    return 0

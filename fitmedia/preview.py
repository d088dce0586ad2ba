"""``fitmedia preview``: the spec's geometry drawn over each image, to check it before a fit.

What is drawn comes from the forward models' own geometry (:mod:`fitmedia.geometry`): every
pixel is split into ``sub x sub`` samples, each sample's camera ray is traced through the
front wall into the water (:func:`~fitmedia.geometry.trace_to_water`, lens distortion
included when the camera has one) and labelled by what it meets: the black face of the tank
where it leaves the water (back, left, right, floor, top), the bulb, the spot's cone, or
nothing (the ray misses the front wall's inner face).  The outlines are the 0.5 level lines
of each label's share of a pixel's samples (:func:`skimage.measure.find_contours`), so they
are sub-pixel and refracted exactly as the models assume.  The front wall's outer face is
seen in air: its outline is labelled the same way from the camera's rays, unrefracted.

Only pixels near a change of label are split (a first pass labels pixel centres); a feature
that lies wholly between pixel centres away from any other change is not seen.
docs/preview.md says how to read the figure and what its alignment was measured to be.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import InputError
from .spec import CHANNELS, Camera, Light, Spec, load_spec

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

#: Label planes of :class:`Outlines` (the walls exclusive; bulb, beam and front overlap them)
NAMES = ("outside", "back", "left", "right", "floor", "top", "bulb", "beam", "front_wall")
WALLS = ("back", "left", "right", "floor", "top")
_BULB, _BEAM, _FRONT = 8, 16, 32  # bit flags added to the wall code 0-5
#: Rays traced at once (memory: about 1 kB per ray in trace_to_water's temporaries)
CHUNK_RAYS = 1 << 17
#: Display stretch (:func:`display_stretch`): linear, clipped at this percentile of the
#: usable pixels or this share of the brightest, whichever is higher, then this gamma
CLIP_PERCENTILE, MIN_TOP, GAMMA = 99.5, 0.01, 1 / 2.2


@dataclass(frozen=True)
class Outlines:
    """What each pixel of one image sees, by the spec's geometry.

    Attributes
    ----------
    counts : ndarray of shape (H, W, len(NAMES)), uint8
        Samples of each pixel (of ``sub * sub``) whose ray meets each of :data:`NAMES`.
    sub : int
        Samples per pixel side.
    contours : dict of str to list of ndarray of shape (N, 2)
        The 0.5 level lines of ``water`` (1 - outside), each wall, ``bulb``, ``beam`` and
        ``front_wall``, as image points (x, y) in pixels (CAPTURE_SPEC.md's image frame).
    light_xy : ndarray of shape (2,)
        Image point of the light's centre (bulb) or apex (spot), refracted.
    axis_xy : ndarray of shape (M, 2) or None
        A spot's axis from its apex to the tank's wall, as image points.
    """

    counts: np.ndarray
    sub: int
    contours: dict[str, list[np.ndarray]] = field(default_factory=dict)
    light_xy: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    axis_xy: np.ndarray | None = None

    def fraction(self, name: str) -> np.ndarray:
        """(H, W) share of each pixel's samples that meet ``name`` (``water``: not outside)."""
        if name == "water":
            return 1.0 - self.fraction("outside")
        return self.counts[..., NAMES.index(name)] / float(self.sub * self.sub)

    def blob(self, name: str) -> tuple[np.ndarray, float]:
        """Centroid (x, y) and equivalent radius sqrt(area / pi), in pixels, of ``name``."""
        f = self.fraction(name)
        area = float(f.sum())
        if area == 0:
            return np.full(2, np.nan), 0.0
        i, j = np.indices(f.shape)
        return (np.array([((j + 0.5) * f).sum(), ((i + 0.5) * f).sum()]) / area,
                float(np.sqrt(area / np.pi)))


def _geometry(spec: Spec, index: int | None) -> tuple[Camera, Light]:
    if index is None or not spec.images:
        return spec.camera, spec.light
    return spec.camera_for(index), spec.light_for(index)


def sample_codes(spec: Spec, camera: Camera, light: Light, x: np.ndarray, y: np.ndarray
                 ) -> np.ndarray:
    """Label code of the ray through each image point (x, y) (1-d arrays): the wall where it
    leaves the water (0 outside, 1-5 as :data:`WALLS`), plus ``_BULB`` where it meets the
    bulb first, ``_BEAM`` where its water segment crosses the spot's cone, ``_FRONT`` where
    the unrefracted ray meets the front wall's outer face within the tank's width and height.
    """
    from .forward.single import _cone_interval
    from .geometry import camera_rays, trace_to_water

    tank, half = spec.tank, spec.tank.half
    rays = trace_to_water(camera, tank, spec.medium_ior, x, y)
    water = rays.factor > 0
    end = rays.origin + rays.length[:, None] * rays.direction
    gap = np.stack([half[0] - np.abs(end[:, 0]), half[1] - np.abs(end[:, 1]), half[2] + end[:, 2]])
    axis = np.argmin(gap, axis=0)  # 0: a side wall, 1: floor or top, 2: back
    wall = np.where(axis == 2, 1, np.where(axis == 0, np.where(end[:, 0] < 0, 2, 3),
                                           np.where(end[:, 1] < 0, 4, 5)))
    code = np.where(water, wall, 0)
    u = rays.origin - light.position
    s0 = -np.einsum("ij,ij->i", u, rays.direction)
    if light.type == "bulb":
        h2 = np.einsum("ij,ij->i", u, u) - s0 * s0
        s_hit = s0 - np.sqrt(np.clip(light.radius**2 - h2, 0.0, None))
        code = code + _BULB * (water & (h2 < light.radius**2) & (s_hit > 0)
                               & (s_hit < rays.length))
    else:
        s_in, s_out = _cone_interval(u, rays.direction, light.direction, light.cutoff_deg)
        code = code + _BEAM * (water & (np.maximum(s_in, 0.0) < np.minimum(s_out, rays.length)))
    d = camera_rays(camera, x, y).reshape(-1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = (half[2] + tank.wall_thickness - camera.position[2]) / d[:, 2]
    q = camera.position + np.where(lam > 0, lam, np.nan)[:, None] * d
    front = (np.abs(q[:, 0]) < half[0]) & (np.abs(q[:, 1]) < half[1])
    return code + _FRONT * front


def _codes_chunked(spec: Spec, camera: Camera, light: Light, x: np.ndarray, y: np.ndarray
                   ) -> np.ndarray:
    x, y = np.ravel(x), np.ravel(y)
    out = np.empty(x.size, np.int16)
    for k in range(0, x.size, CHUNK_RAYS):
        out[k:k + CHUNK_RAYS] = sample_codes(spec, camera, light, x[k:k + CHUNK_RAYS],
                                             y[k:k + CHUNK_RAYS])
    return out


def _planes(code: np.ndarray) -> np.ndarray:
    """One-hot (..., len(NAMES)) uint8 of label codes."""
    wall = code & 7
    planes = [wall == k for k in range(6)]
    planes += [(code & flag) > 0 for flag in (_BULB, _BEAM, _FRONT)]
    return np.stack(planes, axis=-1).astype(np.uint8)


def label_counts(spec: Spec, camera: Camera, light: Light, *, sub: int = 4) -> np.ndarray:
    """(H, W, len(NAMES)) samples per label of every pixel: pixel centres first, then
    ``sub x sub`` samples in the pixels within two pixels of a change of label and around
    the light's image point."""
    from scipy import ndimage

    from .geometry import pixel_grid

    h, w = camera.height, camera.width
    x, y = pixel_grid(camera, sub=1)
    code = _codes_chunked(spec, camera, light, x[..., 0], y[..., 0]).reshape(h, w)
    counts = _planes(code) * np.uint8(sub * sub)
    edge = ndimage.maximum_filter(code, 3) != ndimage.minimum_filter(code, 3)
    refine = ndimage.binary_dilation(edge, iterations=1)
    cxy = image_points(spec, camera, light.position[None, :])[0]
    if np.all(np.isfinite(cxy)):
        dist = np.linalg.norm(light.position - camera.position)
        rad = 3.0 + 1.5 * max(camera.fx, camera.fy) * light.radius / dist
        ii, jj = np.indices((h, w))
        refine |= np.hypot(jj + 0.5 - cxy[0], ii + 0.5 - cxy[1]) < rad
    if sub > 1 and refine.any():
        xs, ys = pixel_grid(camera, sub=sub)
        sel = np.broadcast_to(refine[..., None], xs.shape)
        fine = _codes_chunked(spec, camera, light, xs[sel], ys[sel]).reshape(-1, sub * sub)
        counts[refine] = _planes(fine).sum(axis=1, dtype=np.uint8)
    return counts


def image_points(spec: Spec, camera: Camera, points: np.ndarray, *, iters: int = 30
                 ) -> np.ndarray:
    """Image points (N, 2) at which the camera sees points (N, 3) in the water, through the
    front wall: Gauss-Newton on the image point until the traced ray passes through the
    point (from its unrefracted pinhole projection; the Jacobian by finite differences of
    :func:`~fitmedia.geometry.trace_to_water`).  NaN where it does not converge to 1e-6 mm."""
    from .geometry import trace_to_water

    pts = np.asarray(points, float).reshape(-1, 3)
    f, r, u = camera.frame()
    d = pts - camera.position
    xy = np.stack([camera.cx + camera.fx * (d @ r) / (d @ f),
                   camera.cy - camera.fy * (d @ u) / (d @ f)], axis=1)

    def miss(p: np.ndarray) -> np.ndarray:  # the point's offset from the ray, x and y parts
        rays = trace_to_water(camera, spec.tank, spec.medium_ior, p[:, 0], p[:, 1])
        v = pts - rays.origin
        e = v - np.einsum("ij,ij->i", v, rays.direction)[:, None] * rays.direction
        return e[:, :2]

    step = 1e-3
    for _ in range(iters):
        e = miss(xy)
        jac = np.stack([(miss(xy + [step, 0]) - e) / step, (miss(xy + [0, step]) - e) / step],
                       axis=2)
        # J = [[a, c], [b, d2]]: rows e_x, e_y; columns d/dx, d/dy
        (a, b), (c, d2) = jac[:, :, 0].T, jac[:, :, 1].T
        with np.errstate(divide="ignore", invalid="ignore"):
            det = a * d2 - b * c
            dxy = np.stack([(c * e[:, 1] - d2 * e[:, 0]) / det,
                            (b * e[:, 0] - a * e[:, 1]) / det], axis=1)
        xy = xy + dxy
        if np.all(np.abs(dxy) < 1e-9):
            break
    ok = np.linalg.norm(miss(xy), axis=1) < 1e-6
    return np.where(ok[:, None], xy, np.nan)


def _contours(counts: np.ndarray, sub: int) -> dict[str, list[np.ndarray]]:
    from skimage.measure import find_contours

    out: dict[str, list[np.ndarray]] = {}
    tmp = Outlines(counts, sub)
    for name in ("water",) + WALLS + ("bulb", "beam", "front_wall"):
        f = tmp.fraction(name)
        if f.min() < 0.5 <= f.max():
            out[name] = [c[:, ::-1] + 0.5 for c in find_contours(f, 0.5)]  # (row, col) -> (x, y)
    return out


def _spot_axis(spec: Spec, camera: Camera, light: Light, n: int = 24) -> np.ndarray:
    """Image points of the spot's axis from the apex to where it leaves the tank."""
    half, c, a = spec.tank.half, light.position, light.direction
    with np.errstate(divide="ignore"):
        t = np.min(np.where(a != 0, (np.sign(a) * half - c) / a, np.inf))
    return image_points(spec, camera, c + np.linspace(0.0, t, n)[:, None] * a)


def outline_geometry(spec: Spec, index: int | None = 0, *, sub: int = 4) -> Outlines:
    """The labels and outlines of image ``index`` of ``spec`` (None: the spec's own camera
    and light, as in the clear-water photo); see :class:`Outlines`."""
    if not 1 <= sub <= 15:
        raise ValueError(f"sub: got {sub}; expected 1 to 15 samples per pixel side")
    camera, light = _geometry(spec, index)
    counts = label_counts(spec, camera, light, sub=sub)
    axis = _spot_axis(spec, camera, light) if light.type == "spot" else None
    return Outlines(counts, sub, _contours(counts, sub),
                    image_points(spec, camera, light.position[None, :])[0], axis)


# ---------------------------------------------------------------------------------------------
# the figure

#: (contour name, colour, line style, width, legend text)
STYLES = (
    ("walls", "gold", "-", 0.8, "tank's inner edges, through wall and water"),
    ("water", "cyan", "-", 1.3, "front wall's inner edge = the fit's footprint"),
    ("front_wall", "lime", (0, (3, 3)), 1.0, "front wall's outer face (in air)"),
    ("bulb", "red", "-", 1.2, "bulb's outline"),
    ("beam", "magenta", (0, (3, 2)), 1.2, "spot's cone (rays crossing it)"),
)


def display_stretch(data: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) in [0, 1] for display: linear, divided by the :data:`CLIP_PERCENTILE`
    percentile of the usable pixels' values (all channels) or :data:`MIN_TOP` of the
    brightest pixel (saturated ones included), whichever is higher, clipped, raised to
    :data:`GAMMA`.  (The floor keeps a photo whose light covers under 0.5 % of the pixels,
    the clear-water bulb, from being stretched up to its noise.)"""
    every = data[np.isfinite(data)]
    vals = data[valid] if valid is not None and valid.any() else data.ravel()
    vals = vals[np.isfinite(vals)]
    top = (max(float(np.percentile(vals, CLIP_PERCENTILE)), MIN_TOP * float(every.max()))
           if vals.size else 0.0)
    if not top > 0:
        return np.zeros(data.shape)
    return np.clip(np.nan_to_num(data / top), 0.0, 1.0) ** GAMMA


def draw_panel(ax: Axes, image: np.ndarray | None, outlines: Outlines, camera: Camera,
               light: Light, title: str, unused: np.ndarray | None = None) -> None:
    """One image with its outlines on ``ax`` (image coordinates: x right, y down, pixel
    edges at integers); ``image`` None draws the outlines on black; ``unused`` (H, W) bool
    marks the pixels the fit cannot use (saturated or masked), tinted blue."""
    w, h = camera.width, camera.height
    shown = np.zeros((h, w, 3)) if image is None else image
    ax.imshow(shown, extent=(0, w, h, 0), interpolation="nearest")
    if unused is not None and unused.any():
        tint = np.zeros((h, w, 4))
        tint[unused] = (0.25, 0.45, 1.0, 0.7)
        ax.imshow(tint, extent=(0, w, h, 0), interpolation="nearest")
        ax.fill([], [], color=tint[unused][0], label="saturated or masked (not fitted)")
    for name, colour, ls, lw, label in STYLES:
        names = WALLS if name == "walls" else (name,)
        lines = [c for n in names for c in outlines.contours.get(n, [])]
        for k, c in enumerate(lines):
            ax.plot(c[:, 0], c[:, 1], color=colour, ls=ls, lw=lw, label=label if k == 0 else None)
    x, y = outlines.light_xy
    what = "bulb's centre" if light.type == "bulb" else "spot's apex"
    ax.plot([x], [y], "+", color="red" if light.type == "bulb" else "magenta", ms=6, mew=1.0,
            label=what)
    if outlines.axis_xy is not None:
        a = outlines.axis_xy[np.all(np.isfinite(outlines.axis_xy), axis=1)]
        if len(a) > 1:
            ax.plot(a[:, 0], a[:, 1], color="magenta", lw=1.2, label="spot's axis")
            ax.annotate("", xy=a[-1], xytext=a[-2],
                        arrowprops={"arrowstyle": "-|>", "color": "magenta", "lw": 1.2})
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_title(title, fontsize=8)
    ax.tick_params(labelsize=7)


def _panels(spec: Spec) -> list[tuple[str, int | None, object]]:
    """(title, image index for the geometry, image entry or None) of each panel."""
    if not spec.images:
        return [("geometry only (the spec lists no images)", None, None)]
    out: list[tuple[str, int | None, object]] = []
    for i, entry in enumerate(spec.images):
        names = ", ".join(p.name for p in entry.paths)
        out.append((f"images[{i}]: {names} (concentration {entry.concentration:g})", i, entry))
    if spec.clear_water is not None:
        names = ", ".join(p.name for p in spec.clear_water.paths)
        out.append((f"calibration.clear_water: {names}", None, spec.clear_water))
    return out


def preview_figure(spec: Spec, *, sub: int = 4) -> tuple[Figure, list[str]]:
    """The preview of ``spec``: one panel per image (and the clear-water photo), each
    image loaded as the fit loads it (:func:`fitmedia.images.load_entry`) and stretched
    for display (:func:`display_stretch`); and a line per panel saying where the light is.

    Raises :class:`~fitmedia.errors.InputError` (a missing, unreadable or wrongly sized
    image) from the loader."""
    from .images import load_entry
    from .report.plots import new_figure

    panels = _panels(spec)
    ncol = min(len(panels), 2)
    nrow = -(-len(panels) // ncol)
    aspect = spec.camera.height / spec.camera.width
    fig = new_figure(5.2 * ncol, 5.2 * aspect * nrow + 1.1)
    axes = fig.subplots(nrow, ncol, squeeze=False).ravel()
    chans = tuple(CHANNELS.index(c) for c in spec.channels)
    lines = []
    for ax, (title, index, entry) in zip(axes, panels):
        camera, light = _geometry(spec, index)
        image = unused = None
        if entry is not None:
            with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
                loaded = load_entry(entry, expected_shape=(camera.height, camera.width),
                                    channels=chans)
            image = display_stretch(loaded.data, loaded.valid)
            unused = ~loaded.valid[..., list(chans)].all(axis=2)
        outlines = outline_geometry(spec, index, sub=sub)
        draw_panel(ax, image, outlines, camera, light, title, unused)
        lines.append(_summary(title, outlines, light))
    for ax in axes[len(panels):]:
        ax.set_axis_off()
    entries: dict = {}
    for ax in axes[:len(panels)]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            entries.setdefault(label, handle)
    fig.legend(list(entries.values()), list(entries), loc="outside lower center", ncol=ncol,
               fontsize=7, frameon=False)
    return fig, lines


def _summary(title: str, outlines: Outlines, light: Light) -> str:
    x, y = outlines.light_xy
    where = f"{title.split(':')[0]}: {'bulb centre' if light.type == 'bulb' else 'spot apex'} " \
            f"at x = {x:.1f}, y = {y:.1f} px"
    if light.type == "bulb":
        where += f", radius {outlines.blob('bulb')[1]:.1f} px"
    water = outlines.fraction("water")
    return where + f"; water seen in {100 * water.mean():.0f} % of the image"


def _check_out(out: str | Path) -> Path:
    path = Path(out)
    if path.is_dir():
        raise InputError(f"--out: {path} is a folder; give the PNG file to write")
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"--out: {parent} is a file, not a folder")
            break
    return path


def run_preview(*, spec: str | Path, out: str | Path, sub: int = 4) -> int:
    """``fitmedia preview SPEC --out PNG``: write the preview (:func:`preview_figure`)
    atomically as PNG and print a line per panel.  Returns the exit code (0)."""
    from .util import atomic_write

    path = _check_out(out)
    parsed = load_spec(spec, require_images=False)
    if parsed.images:
        parsed = load_spec(spec)  # checks that every file named exists
    fig, lines = preview_figure(parsed, sub=sub)
    try:
        atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))
    except OSError as exc:
        raise InputError(f"--out: cannot write {path}: {exc.strerror or exc}") from None
    for line in lines:
        print(line)
    print(f"wrote {path}")
    return 0


# ---------------------------------------------------------------------------------------------
# the report's section


def _report_spec(results: dict) -> tuple[Spec | None, str]:
    """The fitted spec, loaded from the path results.json records, or None and why not."""
    from .inference.identity import _sha256_json

    recorded = results.get("spec")
    if not recorded:
        return None, "results.json records no spec path"
    path = Path(str(recorded))
    if not path.is_file():
        return None, (f"the spec {path} is not found from {Path.cwd()} (results.json records "
                      "the path given to fit; run fitmedia report from the folder fit ran in)")
    try:
        spec = load_spec(path)
    except InputError as exc:
        return None, str(exc)
    stored = (results.get("run_identity") or {}).get("spec_sha256")
    if stored is not None and stored != _sha256_json(spec.raw):
        return None, f"the spec {path} has changed since the fit"
    return spec, ""


def report_section(results: dict) -> str:
    """The report's "Geometry preview" section: the preview of the fitted spec as an embedded
    PNG, or one line saying why it is not drawn (the spec or an image not reachable from
    here, or changed since the fit)."""
    import html

    from .report.plots import figure_to_data_uri

    head = "<h2>Geometry preview</h2>\n"
    spec, why = _report_spec(results)
    if spec is not None:
        try:
            fig, _ = preview_figure(spec)
        except InputError as exc:
            spec, why = None, str(exc)
    if spec is None:
        return head + f'<p class="muted">Not drawn: {html.escape(why)}.</p>\n'
    return head + ("<p>The spec's tank, front wall and light drawn over each image from the "
                   "geometry the forward model uses (as <code>fitmedia preview</code>; "
                   "docs/preview.md): the outlines must sit on the tank and the bulb in the "
                   "photographs.</p>\n"
                   f'<img alt="geometry preview" src="{figure_to_data_uri(fig)}">\n')

"""fitmedia preview (issue 16): the spec's geometry drawn over each image.

The outlines are checked against the image the forward model renders (edge detection on
the rendered bulb and glow, not a second drawing) and against Snell's law solved by hand
for points in the water; the command against its exit codes and its PNG.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from fitmedia.cli import main
from fitmedia.forward.single import SingleScattering
from fitmedia.preview import outline_geometry
from fitmedia.spec import parse_spec

from conftest import geometry_dict


def _polyline_distance(points: np.ndarray, lines: list[np.ndarray]) -> np.ndarray:
    """Distance (px) from each point (N, 2) to the nearest segment of the polylines."""
    best = np.full(len(points), np.inf)
    for line in lines:
        a, b = line[:-1], line[1:]
        ab = b - a
        t = np.clip(np.einsum("nkj,kj->nk", points[:, None, :] - a[None], ab)
                    / np.maximum(np.einsum("kj,kj->k", ab, ab), 1e-30), 0.0, 1.0)
        near = a[None] + t[..., None] * ab[None]
        best = np.minimum(best, np.linalg.norm(points[:, None, :] - near, axis=2).min(axis=1))
    return best


def _polygon_blob(line: np.ndarray) -> tuple[np.ndarray, float]:
    """Centroid (x, y) and equivalent radius of a closed polyline (shoelace formula)."""
    x, y = line[:, 0], line[:, 1]
    cross = x[:-1] * y[1:] - x[1:] * y[:-1]
    area = 0.5 * cross.sum()
    cx = ((x[:-1] + x[1:]) * cross).sum() / (6 * area)
    cy = ((y[:-1] + y[1:]) * cross).sum() / (6 * area)
    return np.array([cx, cy]), float(np.sqrt(abs(area) / np.pi))


def _bulb_spec(dx: float = 0.0):
    d = geometry_dict(width=96, height=72,
                      light={"type": "bulb", "position": [40 + dx, 10, 30], "radius": 15})
    return parse_spec(d, require_images=False)


@pytest.fixture(scope="module")
def rendered():
    """A dilute medium's single-scattering image (G, 4 x 4 samples per pixel everywhere, so
    that the window's edge pixels hold their covered share) of a bright 15 mm bulb."""
    spec = _bulb_spec()
    model = SingleScattering(spec, None, channels=("G",), supersample=4)
    img = model.render([5e-4], [2e-4], [0.5], [1.0])[..., 0]
    return spec, img


def test_bulb_outline_on_the_rendered_bulb(rendered):
    """The drawn bulb outline against the bulb in the forward model's image: the disk above
    half the bulb's radiance (pixels >= 0.5 x the brightest), its centroid and equivalent
    radius sqrt(n / pi), within 1 px of the centroid and equivalent radius of the drawn
    contour.  Negative control: the same spec with the bulb 8 mm to the right is > 1 px off."""
    spec, img = rendered
    disk = img >= 0.5 * img.max()
    i, j = np.nonzero(disk)
    seen_c, seen_r = np.array([j.mean() + 0.5, i.mean() + 0.5]), np.sqrt(disk.sum() / np.pi)
    drawn = outline_geometry(spec, None).contours["bulb"]
    assert len(drawn) == 1
    drawn_c, drawn_r = _polygon_blob(drawn[0])
    off, dr = np.linalg.norm(drawn_c - seen_c), drawn_r - seen_r
    print(f"bulb: rendered centre {seen_c.round(2)} radius {seen_r:.2f} px; drawn "
          f"{drawn_c.round(2)} radius {drawn_r:.2f} px; offset {off:.3f} px, radius {dr:+.3f} px")
    assert off < 1.0 and abs(dr) < 1.0
    wrong_c, _ = _polygon_blob(outline_geometry(_bulb_spec(dx=8.0), None).contours["bulb"][0])
    assert np.linalg.norm(wrong_c - seen_c) > 1.0


@pytest.mark.mitsuba
def test_bulb_outline_on_the_mitsuba_bulb():
    """The drawn bulb outline against the bulb in clear water rendered by Mitsuba 3 (its own
    ray tracing through the two dielectric faces of the wall: independent of
    fitmedia.geometry), 64 spp: the disk above half the brightest pixel within 1 px (centre
    and equivalent radius), and the bulb's area-weighted centre and radius (each pixel
    weighted by its share of the brightest, clipped to 1) within 0.2 px (measured 0.05 px).
    About 8 s on the shared 2-core machine, most of it Mitsuba's import and JIT."""
    from fitmedia.forward.mitsuba import MitsubaModel

    spec = _bulb_spec()
    img = MitsubaModel(spec, None, spp=64, max_depth=3, channels=("G",)).render(0, 0, 0, 1.0)
    img = img[..., 0]
    drawn_c, drawn_r = _polygon_blob(outline_geometry(spec, None).contours["bulb"][0])
    disk = img >= 0.5 * img.max()
    i, j = np.nonzero(disk)
    assert np.linalg.norm([j.mean() + 0.5 - drawn_c[0], i.mean() + 0.5 - drawn_c[1]]) < 1.0
    assert abs(np.sqrt(disk.sum() / np.pi) - drawn_r) < 1.0
    w = np.clip(img / img.max(), 0.0, 1.0)
    ii, jj = np.indices(img.shape)
    seen_c = np.array([((jj + 0.5) * w).sum(), ((ii + 0.5) * w).sum()]) / w.sum()
    seen_r = np.sqrt(w.sum() / np.pi)
    print(f"Mitsuba bulb: centre {seen_c.round(3)} radius {seen_r:.3f} px; drawn "
          f"{drawn_c.round(3)} radius {drawn_r:.3f} px")
    assert np.linalg.norm(seen_c - drawn_c) < 0.2 and abs(seen_r - drawn_r) < 0.2


def _edge_points(img: np.ndarray) -> np.ndarray:
    """Sub-pixel points (x, y) of the glow's outer boundary along rows and columns.  The glow
    does not step there but fades to zero: a ray entering the water next to the front
    wall's inner edge leaves it through the side wall (or floor, top) after a path that
    shrinks to zero at the edge.  The boundary is where the ramp of the two fully lit
    pixels next to the first (last) lit one, extrapolated linearly, reaches zero.  Lines
    within 3 px of a corner are skipped."""
    pts = []
    for arr, transpose in ((img, False), (img.T, True)):
        lit_lines = np.nonzero(arr[:, arr.shape[1] // 2] > 0)[0]  # lines lit at mid-image
        for k in lit_lines[3:-3]:
            line = arr[k]
            lit = np.nonzero(line > 0)[0]
            a, b = lit[0] + 1, lit[-1] - 1  # the first and last fully lit pixels
            left = a + 0.5 - line[a] / (line[a + 1] - line[a])
            right = b + 0.5 + line[b] / (line[b - 1] - line[b])
            for p in (left, right):
                pts.append((k + 0.5, p) if transpose else (p, k + 0.5))
    return np.array(pts)


def test_water_outline_on_the_rendered_glow(rendered):
    """The drawn front-wall inner edge (the fit's footprint) against the glow's boundary in
    the forward model's image, found along every row and column (sub-pixel, where the glow's
    ramp reaches zero: _edge_points): every boundary point within 1 px of the drawn outline.
    Negative control: the outline of a tank 10 mm wider than the rendered one is > 1 px off
    (measured 1.26 px; 4 mm wider: 0.59 px)."""
    spec, img = rendered
    pts = _edge_points(img)
    dist = _polyline_distance(pts, outline_geometry(spec, None).contours["water"])
    print(f"glow boundary: {len(pts)} points, distance to the drawn outline max "
          f"{dist.max():.3f} px, mean {dist.mean():.3f} px")
    assert len(pts) > 200
    assert dist.max() < 1.0
    d = geometry_dict(width=96, height=72,
                      light={"type": "bulb", "position": [40, 10, 30], "radius": 15})
    d["tank"]["inner_size"] = [310, 250, 300]
    wider = outline_geometry(parse_spec(d, require_images=False), None).contours["water"]
    assert _polyline_distance(pts, wider).max() > 1.0


def _snell_image_point(spec, p: np.ndarray) -> np.ndarray:
    """Image point of a point p in the water, by hand: the ray from the camera stays in the
    vertical plane through the camera and p (the wall's faces are planes z = const); its
    angle theta to -z in air solves a tan(theta) + t tan(theta_glass) + w tan(theta_water)
    = the lateral distance (Snell: sin(theta) = n_glass sin(theta_glass) = n_water
    sin(theta_water)), a, t, w the depths of air, glass and water crossed.  The air ray's
    direction is then projected with the pinhole of CAPTURE_SPEC.md."""
    cam, tank = spec.camera, spec.tank
    half_z, t = tank.half[2], tank.wall_thickness
    lat = p[:2] - cam.position[:2]
    rho = np.linalg.norm(lat)
    a, w = cam.position[2] - half_z - t, half_z - p[2]

    def gap(theta):
        s = np.sin(theta)
        return (a * np.tan(theta) + t * np.tan(np.arcsin(s / tank.wall_ior))
                + w * np.tan(np.arcsin(s / spec.medium_ior)) - rho)

    theta = brentq(gap, 0.0, 0.5 * np.pi - 1e-9, xtol=1e-14)
    return _pinhole(cam, np.append(np.sin(theta) * lat / rho, -np.cos(theta)))


def _pinhole(cam, d: np.ndarray) -> np.ndarray:
    """Image point (x, y) of the air ray direction d, by CAPTURE_SPEC.md's pinhole."""
    f = cam.look_at - cam.position
    f /= np.linalg.norm(f)
    r = np.cross(f, cam.up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    return np.array([cam.cx + cam.fx * (d @ r) / (d @ f), cam.cy - cam.fy * (d @ u) / (d @ f)])


def test_back_edges_and_light_against_snell():
    """The drawn back wall's edges and the light's image point against Snell's law solved by
    hand (_snell_image_point) for a camera off the tank's axis, looking down and sideways:
    points along the four back edges within 0.25 px of the drawn back-wall outline (4 x 4
    samples per pixel; see the comment at the assert), the bulb's and a spot's
    image point within 1e-3 px.  Negative control: the same points projected without
    refraction are each > 1 px off (1.6-4.6 px)."""
    d = geometry_dict(width=120, height=90)
    d["camera"].update(position=[60, 40, 800], look_at=[20, 0, 0])
    spec = parse_spec(d, require_images=False)
    hx, hy, hz = spec.tank.half
    s = np.linspace(-0.9, 0.9, 7)
    const = np.full(7, 1.0)
    edge = np.concatenate([np.stack([s * hx, y * const, -hz * const], 1) for y in (-hy, hy)]
                          + [np.stack([x * const, s * hy, -hz * const], 1) for x in (-hx, hx)])
    ref = np.array([_snell_image_point(spec, p) for p in edge])
    outlines = outline_geometry(spec, 0)
    dist = _polyline_distance(ref, outlines.contours["back"])
    plain = np.array([_pinhole(spec.camera, p - spec.camera.position) for p in edge])
    print(f"back edges: max {dist.max():.3f} px from the drawn outline; unrefracted points "
          f"{_polyline_distance(plain, outlines.contours['back']).min():.1f}+ px")
    # 0.25 px: the outline's resolution, not its geometry: the 0.5 level of each pixel's
    # share of 4 x 4 samples, interpolated linearly between pixel centres, lies up to ~0.2 px
    # from a slanted edge (measured max 0.24 / 0.20 / 0.14 / 0.10 px at 2 / 4 / 8 / 15
    # samples per side; mean 0.08 px at 4)
    assert dist.max() < 0.25
    assert _polyline_distance(plain, outlines.contours["back"]).min() > 1.0
    bulb_ref = _snell_image_point(spec, spec.light.position)
    assert np.linalg.norm(outlines.light_xy - bulb_ref) < 1e-3
    d["light"] = {"type": "spot", "position": [-30, 20, -40], "direction": [0.3, -1, 0.2],
                  "cutoff_deg": 10}
    spot = parse_spec(d, require_images=False)
    spot_lines = outline_geometry(spot, 0)
    spot_ref = _snell_image_point(spot, spot.light.position)
    assert np.linalg.norm(spot_lines.light_xy - spot_ref) < 1e-3
    assert np.allclose(spot_lines.axis_xy[0], spot_lines.light_xy)
    assert "beam" in spot_lines.contours and "bulb" not in spot_lines.contours


@pytest.fixture
def capture(tmp_path, rendered):
    """The rendered image as a one-image capture (float TIFFs: the image and, as its clear
    water photo, the same), spec beside it."""
    import yaml

    from fitmedia.images import write_float_tiff

    spec, img = rendered
    (tmp_path / "images").mkdir()
    write_float_tiff(tmp_path / "images" / "a.tiff", np.repeat(img[..., None], 3, axis=2))
    d = geometry_dict(width=96, height=72,
                      light={"type": "bulb", "position": [40, 10, 30], "radius": 15})
    d["images"] = [{"path": "images/a.tiff", "exposure_s": 1.0}]
    d["calibration"] = {"clear_water": {"path": "images/a.tiff", "exposure_s": 1.0}}
    (tmp_path / "capture.yaml").write_text(yaml.safe_dump(d))
    return tmp_path / "capture.yaml"


def test_preview_command_writes_the_png(capture, tmp_path, capsys):
    """`fitmedia preview` exits 0 and writes a PNG with two panels' worth of pixels (the image
    and the clear-water photo), and says where the bulb is (the drawn outline's centre)."""
    import matplotlib.image

    out = tmp_path / "p" / "preview.png"
    assert main(["preview", str(capture), "--out", str(out)]) == 0
    png = matplotlib.image.imread(out)
    assert png.ndim == 3 and png.shape[1] > 2 * 96 and png.std() > 0.05
    text = capsys.readouterr().out
    assert "images[0]: bulb centre at x = 56.6, y = 33.9 px" in text and f"wrote {out}" in text
    assert [p.name for p in out.parent.iterdir()] == ["preview.png"]  # no temporary file left


@pytest.mark.parametrize("case, words", [
    ("missing image", "images[0].path: file not found"),
    ("wrong size", "expected 80x60 (camera.size)"),
    ("out is a folder", "is a folder; give the PNG file to write"),
])
def test_preview_bad_input_exit_2(capture, tmp_path, capsys, case, words):
    """Bad input: one line on stderr naming the field or file, exit code 2, no PNG."""
    import yaml

    out = tmp_path / "o" / "preview.png"
    if case == "missing image":
        (capture.parent / "images" / "a.tiff").unlink()
    elif case == "wrong size":
        d = yaml.safe_load(capture.read_text())
        d["camera"].update(size=[80, 60], cx=40, cy=30)
        capture.write_text(yaml.safe_dump(d))
    else:
        out.mkdir(parents=True)
    assert main(["preview", str(capture), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not out.is_file()


def test_report_section_says_why_not(capture, tmp_path):
    """The report's preview section: one line when the spec is not found or has changed since
    the fit (its run identity's hash), the figure otherwise."""
    from fitmedia.inference.identity import _sha256_json
    from fitmedia.preview import report_section
    from fitmedia.spec import load_spec

    text = report_section({"spec": str(tmp_path / "gone.yaml")})
    assert "Not drawn: the spec" in text and "is not found from" in text and "<img" not in text
    stale = {"spec": str(capture), "run_identity": {"spec_sha256": "0" * 64}}
    assert "has changed since the fit" in report_section(stale)
    fresh = {"spec": str(capture),
             "run_identity": {"spec_sha256": _sha256_json(load_spec(capture).raw)}}
    assert 'alt="geometry preview"' in report_section(fresh)

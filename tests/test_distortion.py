"""Lens distortion (``camera.distortion``, OpenCV's Brown-Conrady k1, k2, p1, p2, k3): the
camera's rays against OpenCV's own projection, every model rendering through it, a fit
that needs it, and the spec's refusals (docs/spec.md, "Lens distortion")."""

from __future__ import annotations

import copy
import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest
import yaml

from fitmedia.errors import SpecError
from fitmedia.geometry import camera_rays, pixel_grid, project, trace_to_water
from fitmedia.spec import parse_spec
from conftest import geometry_dict

cv2 = pytest.importorskip("cv2")

#: the capture of the fit test: a 70 deg wide-angle camera 244 mm in front of the wall,
#: k1 = -0.25, k2 = 0.08 (barrel, 10 % at the corners), the bulb off-axis
WIDE = {"fx": 45.0, "fy": 45.0, "position": [0, 0, 400]}
BARREL = {"k1": -0.25, "k2": 0.08}


def wide_dict(width=64, height=48, distortion=BARREL, light_at=(100.0, 60.0, 30.0)) -> dict:
    d = geometry_dict(width, height)
    d["camera"].update(WIDE, fx=45.0 * width / 64, fy=45.0 * width / 64)
    d["light"]["position"] = list(light_at)
    if distortion is not None:
        d["camera"]["distortion"] = dict(distortion)
    return d


def opencv_pose(cam):
    """OpenCV's rvec, tvec, K, distCoeffs of a fitmedia camera: camera axes x = right,
    y = -true_up (down), z = forward; the same cx, cy (both models put x = cx + fx x_n)."""
    f, r, u = cam.frame()
    rot = np.stack([r, -u, f])
    rvec, _ = cv2.Rodrigues(rot)
    k = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1.0]])
    return rvec, -rot @ cam.position, k, np.array(cam.distortion or (0.0,) * 5)


def cv2_project(cam, pts: np.ndarray) -> np.ndarray:
    rvec, tvec, k, dist = opencv_pose(cam)
    out, _ = cv2.projectPoints(np.asarray(pts, float).reshape(-1, 1, 3), rvec, tvec, k, dist)
    return out.reshape(-1, 2)


# ------------------------------------------------------------------- the rays
def test_rays_and_projection_agree_with_opencv_project_points():
    """Reference: cv2.projectPoints.  A camera with a tilted pose, fx != fy, an off-centre
    principal point and all five coefficients; 3D points drawn at random (seeded) whose
    OpenCV projections fall in the image.  (a) geometry.project gives OpenCV's pixel to
    1e-9 px; (b) the ray camera_rays casts through OpenCV's pixel, followed to the point's
    depth and projected again by OpenCV, lands on the same pixel to 1e-6 px (the undistortion's
    Newton iteration; a y sign slip, swapped p1/p2 or OpenCV's approximate undistortPoints
    would miss by 1e-3 px or more).  Also the principal point's ray is the forward axis."""
    d = geometry_dict(64, 48)
    d["camera"].update(fx=50.0, fy=47.0, cx=29.3, cy=26.1, position=[40.0, -25.0, 600.0],
                       look_at=[10.0, 5.0, 0.0], up=[0.1, 1.0, 0.05],
                       distortion={"k1": -0.21, "k2": 0.06, "p1": 0.004, "p2": -0.003, "k3": -0.01})
    cam = parse_spec(d, require_images=False).camera
    rng = np.random.default_rng(20261201)
    f, r, u = cam.frame()
    n = 4000
    depth = rng.uniform(200.0, 900.0, n)
    pts = cam.position + depth[:, None] * (f + rng.uniform(-0.8, 0.8, (n, 1)) * r
                                           + rng.uniform(-0.6, 0.6, (n, 1)) * u)
    px = cv2_project(cam, pts)
    inside = (px[:, 0] > 0) & (px[:, 0] < cam.width) & (px[:, 1] > 0) & (px[:, 1] < cam.height)
    pts, px = pts[inside], px[inside]
    assert len(px) > 500
    x, y, ahead = project(cam, pts)
    assert ahead.all()
    assert np.max(np.hypot(x - px[:, 0], y - px[:, 1])) < 1e-9
    rays = camera_rays(cam, px[:, 0], px[:, 1])
    t = np.einsum("ij,j->i", pts - cam.position, f) / (rays @ f)
    back = cv2_project(cam, cam.position + t[:, None] * rays)
    miss = np.max(np.hypot(*(back - px).T))
    print(f"\nround trip through camera_rays: {len(px)} points, largest miss {miss:.2e} px")
    assert miss < 1e-6
    np.testing.assert_allclose(camera_rays(cam, np.array(cam.cx), np.array(cam.cy)), f,
                               atol=1e-15)


def test_binned_camera_casts_the_same_rays():
    """Reference: the full camera's own rays.  The multiple-scattering term traces a camera
    with b x b pixels merged (forward.multiple._binned_camera: fx, cx scaled by 1/b, the same
    distortion); its ray through (x/b, y/b) must be the camera's through (x, y), since the
    distortion acts on normalised coordinates."""
    from fitmedia.forward.multiple import _binned_camera

    cam = parse_spec(wide_dict(), require_images=False).camera
    low = _binned_camera(cam, 4)
    x, y = pixel_grid(cam, sub=2)
    np.testing.assert_allclose(camera_rays(low, x / 4, y / 4), camera_rays(cam, x, y), atol=1e-12)


def _bulb_image(spec):
    """Clear water, no refraction: order 0 of SingleScattering is the bulb alone."""
    from fitmedia.forward.single import SingleScattering

    return SingleScattering(spec, None, channels=("G",), supersample=4).render(
        0.0, 0.0, 0.0, 1.0)[..., 0]


def centroid(img: np.ndarray) -> np.ndarray:
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]] + 0.5
    return np.array([(img * xx).sum(), (img * yy).sum()]) / img.sum()


def no_refraction(d: dict) -> dict:
    d = copy.deepcopy(d)
    d["tank"]["front_wall"]["ior"] = 1.0
    d["medium"]["ior"] = 1.0
    return d


def test_single_scattering_sees_the_bulb_where_opencv_projects_it():
    """Reference: cv2.projectPoints of the bulb's centre.  With all indices 1 (straight rays)
    the centroid of the bulb's image rendered by SingleScattering through the distortion lies
    on OpenCV's projection (within 0.05 px; the bulb spans ~2 px and the distortion varies
    little over it), 1 px or more from the undistorted pinhole's projection."""
    d = no_refraction(wide_dict(light_at=(120.0, 95.0, 100.0)))
    d["light"]["radius"] = 10.0
    spec = parse_spec(d, require_images=False)
    got = centroid(_bulb_image(spec))
    want = cv2_project(spec.camera, spec.light.position)[0]
    pin = cv2_project(dataclasses.replace(spec.camera, distortion=None), spec.light.position)[0]
    print(f"\nbulb centroid {got.round(3)}, OpenCV {want.round(3)}, pinhole {pin.round(3)} px")
    assert np.hypot(*(got - want)) < 0.05
    assert np.hypot(*(pin - want)) > 1.0


def test_unseen_bulb_is_placed_through_the_distortion():
    """Reference: cv2.projectPoints.  The camera of test_bad_inputs turned 56 degrees away
    (80 x 60): the message names the bulb's pixel through the distortion, (-76, 28) as OpenCV
    puts it (the bare pinhole: (-97, 28)); with k1 = -0.5 the bulb's direction (normalised
    radius 0.91) lies beyond the map's fold (0.82), where the polynomial would put it back
    towards the image, and the message says so instead of naming a pixel."""
    from fitmedia.inference.fit import why_bulb_unseen

    d = geometry_dict()
    d["camera"].update(look_at=[900, 0, 0], distortion=BARREL)
    spec = parse_spec(d, require_images=False)
    x, y = cv2_project(spec.camera, spec.light.position)[0]
    assert f"near pixel ({x:.0f}, {y:.0f})" in why_bulb_unseen(spec) and round(x) == -76
    d["camera"]["distortion"] = {"k1": -0.5}
    assert "beyond the fold of camera.distortion" in why_bulb_unseen(
        parse_spec(d, require_images=False))


# ------------------------------------------------------------ Mitsuba's resampling
def _glow_mask(spec, ref, h_min):
    x, y = pixel_grid(spec.camera)
    r = trace_to_water(spec.camera, spec.tank, spec.medium_ior, x[..., 0], y[..., 0])
    u = spec.light.position - r.origin
    s0 = np.einsum("...i,...i->...", u, r.direction)
    h = np.linalg.norm(u - s0[..., None] * r.direction, axis=-1)
    return (h > h_min) & (r.factor > 0) & (ref > 1e-3 * ref.max())


def test_mitsuba_resampler_area_sample_error():
    """Reference: SingleScattering rendered through the distortion directly (8 x 8 samples
    per pixel).  The Mitsuba model's path with distortion, without Mitsuba: the same model
    rendered on forward.mitsuba.pinhole_cover's distortion-free camera (3x the resolution) and
    area-sampled by forward.mitsuba.resampler to the distorted pixels.  Over the glow beyond 3
    bulb radii (64 x 48, dilute milk, g = 0.9, a steep glow), measured on this machine: mean
    relative error +0.32 %, largest 1.5 % (at 2x: +0.61 % and 2.6 %; bilinear point samples
    at 2x: +1.2 % and 3.6 %): the pinhole pixels' box averages smooth the steep glow.  Bounds
    0.5 % and 2.5 %.  Control: without distortion the area sample is the exact 3 x 3 pixel
    mean (to the pinhole render's own 0.05 %)."""
    from fitmedia.forward.mitsuba import pinhole_cover, resampler
    from fitmedia.forward.single import SingleScattering

    for dist, mean_tol, max_tol in ((BARREL, 5e-3, 2.5e-2), (None, 5e-4, 1e-3)):
        spec = parse_spec(wide_dict(distortion=dist, light_at=(60.0, 30.0, 30.0)),
                          require_images=False)
        cover = pinhole_cover(spec.camera)
        pin_spec = dataclasses.replace(spec, camera=cover)
        args = (3e-4, 1.07e-2, 0.9, 1.0)
        pin = SingleScattering(pin_spec, None, channels=("G",), supersample=2).render(*args)
        got = (resampler(spec.camera, cover) @ pin[..., 0].ravel()).reshape(spec.camera.height,
                                                                         spec.camera.width)
        ref = SingleScattering(spec, None, channels=("G",), supersample=8).render(*args)[..., 0]
        glow = _glow_mask(spec, ref, 3 * 6.0)
        rel = (got[glow] - ref[glow]) / ref[glow]
        print(f"\ndistortion {dist}: pinhole {cover.width} x {cover.height}, {glow.sum()} glow "
              f"pixels, mean {100 * rel.mean():+.3f} %, largest {100 * np.abs(rel).max():.3f} %")
        assert abs(rel.mean()) < mean_tol and np.abs(rel).max() < max_tol


@pytest.mark.mitsuba
def test_mitsuba_renders_through_the_distortion():
    """Reference: SingleScattering with the same distortion.  Mitsuba (32 x 24, single-
    scattering depth; the bulb far off-axis): (a) clear water: the bulb's centroid matches
    the analytic model's within 0.1 px (measured 0.006 px; the distortion moves it 0.84 px:
    a flipped or mirrored resampling would miss); (b) dilute milk, g = 0.5: the glow beyond
    3 bulb radii agrees in sum within 3 Monte Carlo standard errors (1024 spp, 8 batches; the
    error printed and required below 1 %) plus 0.5 % for the resampling (the test above)."""
    from fitmedia.forward.mitsuba import MitsubaModel, single_scattering_depth
    from fitmedia.forward.single import SingleScattering

    d = wide_dict(32, 24, light_at=(120.0, 95.0, 100.0))
    d["light"]["radius"] = 10.0
    spec = parse_spec(d, require_images=False)
    depth = single_scattering_depth(spec)
    m = MitsubaModel(spec, None, spp=64, max_depth=depth - 1, channels=("G",), seed=3)
    bulb_m = m.render(0.0, 0.0, 0.0, 1.0)[..., 0]
    bulb_a = SingleScattering(spec, None, channels=("G",), supersample=4).render(
        0.0, 0.0, 0.0, 1.0)[..., 0]
    pin = dataclasses.replace(spec, camera=dataclasses.replace(spec.camera, distortion=None))
    moved = np.hypot(*(centroid(_bulb_image(pin)) - centroid(bulb_a)))
    print(f"\nbulb centroid Mitsuba {centroid(bulb_m).round(3)}, analytic "
          f"{centroid(bulb_a).round(3)} px (moved {moved:.2f} px by the distortion)")
    assert np.hypot(*(centroid(bulb_m) - centroid(bulb_a))) < 0.1 and moved > 0.5
    args = (1e-5, 0.01, 0.5, 1.0)
    m = MitsubaModel(spec, None, spp=1024, max_depth=depth, channels=("G",), seed=4)
    img, err = (a[..., 0] for a in m.render_with_error(*args, batches=8))
    ref = SingleScattering(spec, None, channels=("G",), supersample=8).render(*args)[..., 0]
    glow = _glow_mask(spec, ref, 3 * 10.0)
    rel = img[glow].sum() / ref[glow].sum() - 1
    rel_err = math.sqrt(np.sum(err[glow] ** 2)) / ref[glow].sum()
    print(f"glow ({glow.sum()} px): Mitsuba / analytic - 1 = {100 * rel:+.2f} % "
          f"+- {100 * rel_err:.2f} % (MC)")
    assert rel_err < 0.01 and abs(rel) < 3 * rel_err + 0.005


# -------------------------------------------------------------- a fit that needs it
def _fit_g(spec):
    from fitmedia.inference.fit import FitOptions, prepare, run_channels

    # global_evals 100 (default 400) to keep CI time: the same MAPs as 400 at seed 12345
    opts = FitOptions(mcmc=False, seed=1, workers=1, progress=False, global_evals=100)
    f = run_channels(prepare(spec), opts, None)["G"]
    u, cov = f["x_map"], f["laplace_cov"]
    albedo, g = f["map"]["albedo"], f["map"]["g"]
    j = np.zeros(len(u))
    j[0], j[1] = 1.0, 1.0 - albedo
    return f["map"]["kappa_s"], g, math.sqrt(j @ cov @ j), math.sqrt(cov[2, 2]) * (1 - g * g)


def test_fit_needs_the_distortion(tmp_path, seed):
    """Reference: the synthesised truth.  A capture (Lowfat Milk 16 ml in 23 l, 48 x 36, the
    wide-angle WIDE camera with k1 = -0.25, k2 = 0.08, bulb off-axis) rendered by
    ``synthesize`` through the distortion, fitted (MAP, channel G) with the spec as written
    and with ``camera.distortion`` deleted.  With it, kappa_s and g are within 4 of the fit's
    own Laplace sd of the truth (as the quick round trip of test_roundtrip.py); without it
    the fit misses by more than 4 sd.  Measured: seed 12345 with z -0.72 (kappa_s 14.88,
    truth 15.44 1/mm), +0.26 (g 0.9030, truth 0.902); without -60.8 (kappa_s 5.85), -13.6
    (g 0.862); seed 1 with -2.00, -0.65, without -61.0, -14.1.  (The bulb is unresolved: its
    image, which calibrates its brightness, falls on other pixels without the distortion.)"""
    from fitmedia.medium import medium_by_name
    from fitmedia.spec import load_spec
    from fitmedia.synth import synthesize

    milk = medium_by_name("Lowfat Milk")
    path = synthesize(parse_spec(wide_dict(48, 36), require_images=False), tmp_path / "cap", milk,
                      [16], seed=seed)
    raw = copy.deepcopy(load_spec(path).raw)
    raw["channels"] = ["G"]
    z = {}
    for name in ("with", "without"):
        if name == "without":
            del raw["camera"]["distortion"]
        ks, g, sd_ks, sd_g = _fit_g(parse_spec(raw, source=str(path), base=path.parent))
        z[name] = (math.log(ks / milk.kappa_s[1]) / sd_ks, (g - milk.g[1]) / sd_g)
        print(f"\n{name} camera.distortion: kappa_s {ks:.3f} (truth {milk.kappa_s[1]:.3f}, "
              f"z {z[name][0]:+.2f}), g {g:.4f} (truth {milk.g[1]:.4f}, z {z[name][1]:+.2f})")
    assert max(map(abs, z["with"])) < 4.0, z
    assert max(map(abs, z["without"])) > 4.0, z


# ------------------------------------------------------------------ spec checks
@pytest.mark.parametrize("patch, field, words", [
    ({"k4": 0.1}, "camera.distortion", "unknown field 'k4'"),
    ({"k1": float("nan")}, "camera.distortion.k1", "finite"),
    ({"k1": "0.1"}, "camera.distortion.k1", "'0.1'"),
    ({"k1": -0.9}, "camera.distortion", "folds back"),
    ({"k1": 0.3, "k2": -0.5}, "camera.distortion", "folds back"),
    ({"p1": 1e300}, "camera.distortion", "folds back"),
])
def test_bad_distortion_is_refused_naming_the_field(patch, field, words):
    """Reference: the spec contract (docs/spec.md, "Lens distortion"): unknown keys, non-finite
    or non-numeric values and a map that folds back inside the 64 x 48 image (k1 = -0.9 at
    fx 45: the distorted radius peaks at r = 0.61, inside the corner's 0.89) are SpecErrors
    naming the field."""
    d = wide_dict(distortion=patch)
    with pytest.raises(SpecError) as e:
        parse_spec(d, source="s.yaml", require_images=False)
    assert e.value.field == field and words in e.value.message, str(e.value)


def test_distortion_parsing_overrides_and_identity():
    """Reference: the documented defaults.  Absent keys are 0, all zero is no distortion;
    an image's camera override inherits the spec's distortion, replaces it as a whole when it
    gives one (and is checked under its own name); the run identity's spec hash changes with
    it."""
    from fitmedia.inference.identity import _sha256_json

    spec = parse_spec(wide_dict(distortion={"p2": 0.001}), require_images=False)
    assert spec.camera.distortion == (0.0, 0.0, 0.0, 0.001, 0.0)
    assert parse_spec(wide_dict(distortion={"k1": 0}), require_images=False).camera.distortion \
        is None
    d = wide_dict()
    d["images"] = [{"path": "a.tiff", "exposure_s": 1, "camera": {"position": [0, 0, 420]}},
                   {"path": "b.tiff", "exposure_s": 1, "camera": {"distortion": {"k1": -0.1}}}]
    spec = parse_spec(d, require_images=False)
    assert spec.camera_for(0).distortion == (-0.25, 0.08, 0.0, 0.0, 0.0)
    assert spec.camera_for(1).distortion == (-0.1, 0.0, 0.0, 0.0, 0.0)
    d["images"][1]["camera"]["distortion"] = {"k1": -0.9}
    with pytest.raises(SpecError, match=r"images\[1\]\.camera\.distortion: got k1 -0\.9"):
        parse_spec(d, require_images=False)
    other = wide_dict(distortion={"k1": -0.25, "k2": 0.081})
    assert _sha256_json(parse_spec(other, require_images=False).raw) != \
        _sha256_json(parse_spec(wide_dict(), require_images=False).raw)


def test_cli_refuses_bad_distortion_with_exit_2(tmp_path):
    """Reference: the CLI contract (bad input: one line, exit 2, no traceback)."""
    spec = tmp_path / "geo.yaml"
    spec.write_text(yaml.safe_dump(wide_dict(distortion={"k1": -0.2, "kk2": 0.1})))
    p = subprocess.run([sys.executable, "-m", "fitmedia.cli", "synth", str(spec), "--medium",
                        "Lowfat Milk", "--ml", "16", "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "camera.distortion" in lines[0] and "kk2" in lines[0], p.stderr
    assert "Traceback" not in p.stderr and not (tmp_path / "out").exists()

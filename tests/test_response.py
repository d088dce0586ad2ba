"""A measured camera response (issue 16): `response: {curve: FILE}` decodes 8- and 16-bit
files through a curve file, made by fitmedia.images.response.calibrate_response from a bracket
with OpenCV's Debevec (or Robertson) calibration."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile
import yaml

from conftest import geometry_dict
from fitmedia.errors import ImageError
from fitmedia.images import load_entry
from fitmedia.images.response import calibrate_response, read_curve
from fitmedia.spec import ImageEntry

H, W = 24, 32
TIMES = (1 / 64, 1 / 16, 1 / 4, 1.0)
NOISE = 0.01  # relative sd of the scene's light in each frame


def camera(x: np.ndarray) -> np.ndarray:
    """The known non-linear camera, 0..1: a shoulder 1.25 x / (1 + x) (full scale at x = 4),
    then gamma 1/2.2."""
    v = np.clip(x, 0, None)
    return np.minimum(1.25 * v / (1 + v), 1.0) ** (1 / 2.2)


def inverse(code: np.ndarray, full: float) -> np.ndarray:
    """The exposure x a code value (0..full) records: camera's inverse (4 at full scale)."""
    y = (np.asarray(code, float) / full) ** 2.2
    return y / (1.25 - y)


def _scene() -> np.ndarray:
    """A smooth scene over three decades of radiance, channels at 1, 0.8, 0.6."""
    yy, xx = np.mgrid[0:H, 0:W]
    return np.exp(-3.0 + 4.9 * xx / (W - 1) + 2.1 * yy / (H - 1))[..., None] * [1.0, 0.8, 0.6]


def test_a_debevec_curve_decodes_relative_radiance(tmp_path):
    """Synthetic round trip: a seeded 4-frame 8-bit bracket (1/64 to 1 s) of a smooth scene
    through a known non-linear camera; the curve calibrated from it decodes the 1/4 s frame
    (through load_entry and `response: {curve: ...}`) to the true relative radiance.  The
    scale is free per channel (Debevec fixes mid-grey at 1; the fit's clear-water calibration
    absorbs it), so the decoded / true ratio is divided by its median per channel.  Tolerance
    per pixel, codes 20-235: half the true curve's quantisation step at that code (8 bits: up
    to 5.5 % at code 20) + 4 sd of the frame's 1 % light noise + 3 % for the curve's shape
    (measured 0.4-0.7 % rms, up to 2.8 % over codes 20-235 at this seed)."""
    rng = np.random.default_rng(16)
    scene = _scene()
    paths = []
    for k, t in enumerate(TIMES):
        x = scene * t * (1 + NOISE * rng.standard_normal(scene.shape))
        paths.append(tmp_path / f"f{k}.tiff")
        tifffile.imwrite(paths[-1], np.round(255 * camera(x)).astype(np.uint8), photometric="rgb")
    curve = calibrate_response(paths, TIMES, tmp_path / "curve.csv")
    assert curve.shape == (256, 3)
    img = load_entry(ImageEntry(paths=(paths[2],), exposures=(TIMES[2],), response="curve",
                                response_curve=tmp_path / "curve.csv"), expected_shape=(H, W))
    codes = tifffile.imread(paths[2]).astype(float)
    use = (codes >= 20) & (codes <= 235)
    assert np.all(img.valid[codes < 255]) and not np.any(img.valid[codes == 255])
    ratio = img.data / scene
    ratio /= np.array([np.median(ratio[..., c][use[..., c]]) for c in range(3)])
    half_step = 0.5 * (inverse(codes + 1, 255) / inverse(codes, 255) - 1)
    tol = half_step + 4 * NOISE + 0.03
    assert np.all(np.abs(ratio - 1)[use] < tol[use]), np.max((np.abs(ratio - 1) - tol)[use])


def test_a_curve_that_does_not_fit_the_file_is_refused(tmp_path):
    """A 256-row curve for a 16-bit file, a curve on a float file, a curve with NaN, a curve
    of 2 columns: ImageError naming the file and what it needs."""
    from fitmedia.images import write_float_tiff

    good = np.linspace(0, 1, 256)[:, None] ** 2.2 * np.ones(3)
    np.savetxt(tmp_path / "c8.csv", good, delimiter=",")
    tifffile.imwrite(tmp_path / "a16.tiff", np.full((H, W, 3), 900, np.uint16), photometric="rgb")
    write_float_tiff(tmp_path / "f.tiff", np.ones((H, W, 3)))

    def load(name, curve):
        return load_entry(ImageEntry(paths=(tmp_path / name,), exposures=(1.0,), response="curve",
                                     response_curve=tmp_path / curve), expected_shape=(H, W))
    with pytest.raises(ImageError, match="c8.csv: response curve has 256 rows .* a 16-bit "
                                         "image needs 65536 rows"):
        load("a16.tiff", "c8.csv")
    with pytest.raises(ImageError, match="f.tiff: 'response: {curve: ...}' is for 8- or 16-bit"):
        load("f.tiff", "c8.csv")
    bad = good.copy()
    bad[7, 1] = np.nan
    np.savetxt(tmp_path / "nan.csv", bad, delimiter=",")
    np.savetxt(tmp_path / "two.csv", good[:, :2], delimiter=",")
    tifffile.imwrite(tmp_path / "a8.tiff", np.full((H, W, 3), 90, np.uint8), photometric="rgb")
    with pytest.raises(ImageError, match="nan.csv: response curve has negative or non-finite"):
        load("a8.tiff", "nan.csv")
    with pytest.raises(ImageError, match="two.csv: response curve has 256 rows of 2 values"):
        load("a8.tiff", "two.csv")
    assert read_curve(tmp_path / "c8.csv", 256).max() == 255.0


def test_a_capture_through_a_curve_fits_like_the_linear_one(tmp_path):
    """Second model: one noisy linear capture (32x24, G, Lowfat Milk) written (a) as float
    TIFFs and (b) as 16-bit TIFFs through the known non-linear camera, with a 65536-row curve
    file of the camera's inverse at an arbitrary scale (x 3.7: a measured curve's scale is
    arbitrary), the clear-water photo through the same curve.  The noise block of (b) is (a)'s
    in the decoded units; negative values are clipped in both (an encoded file has none).
    Both MAPs (polished from the truth) agree to 0.1 Laplace sd in log
    kappa_t, log kappa_s and atanh g (16-bit quantisation of the curve is the only
    difference), and (b) is within 3 sd of the truth: the curve's scale does not bias kappa."""
    from fitmedia.images import write_float_tiff
    from test_camera_formats import A, B, K_FLOAT, fit_at_truth, render_truth

    geo = geometry_dict(width=32, height=24)
    lit, clear, truth, c = render_truth(geo, ("G",))
    rng = np.random.default_rng(5)
    top = 1.2 * K_FLOAT * float(max(lit.max(), clear.max()))  # x = 4 (full scale): 1.2x the bulb
    codes = np.arange(65536)
    np.savetxt(tmp_path / "curve.csv", 3.7 * inverse(codes, 65535)[:, None] * np.ones(3),
               delimiter=",", fmt="%.12g")
    r = float(65535 / inverse(65535, 65535) * 4 / top)  # decoded units per linear unit
    specs = {}
    for kind in ("float", "curve"):
        d = dict(geo, name=kind, channels=["G"], images=[{"path": f"m_{kind}.tiff",
                                                           "exposure_s": 1.0, "concentration": c}],
                 calibration={"clear_water": {"path": f"w_{kind}.tiff", "exposure_s": 1.0}},
                 noise={"gain": A * (r if kind == "curve" else 1.0),
                        "read_var": B * (r * r if kind == "curve" else 1.0)})
        if kind == "curve":
            for e in (d["images"][0], d["calibration"]["clear_water"]):
                e["response"] = {"curve": "curve.csv"}
        specs[kind] = tmp_path / f"{kind}.yaml"
        specs[kind].write_text(yaml.safe_dump(d))
    for tag, img in (("m", lit), ("w", clear)):
        mean = K_FLOAT * np.repeat(img, 3, axis=2)
        x = A * rng.poisson(mean / A) + rng.normal(0, np.sqrt(B), mean.shape)
        x = np.clip(x, 0, None)  # an encoded file holds no negative value: the same data in both
        write_float_tiff(tmp_path / f"{tag}_float.tiff", x)
        enc = np.round(65535 * camera(x * 4 / top)).astype(np.uint16)
        tifffile.imwrite(tmp_path / f"{tag}_curve.tiff", enc, photometric="rgb")
    lin = fit_at_truth(specs["float"], truth, K_FLOAT)["G"]
    cur = fit_at_truth(specs["curve"], truth, K_FLOAT * r)["G"]
    assert np.all(np.abs(cur["est"] - lin["est"]) < 0.1 * lin["sd"]), (cur["map"], lin["map"])
    assert np.all(np.abs((cur["est"] - cur["ref"]) / cur["sd"]) < 3), (cur["map"], truth)


def test_the_spec_names_the_curve_file_relative_to_itself(tmp_path):
    """The spec's `response: {curve: FILE}` (docs/spec.md): the path relative to the spec's
    folder; a mistyped key named with the closest one; a missing file named by its field."""
    from fitmedia.errors import SpecError
    from fitmedia.spec import load_spec

    tifffile.imwrite(tmp_path / "a.tiff", np.full((H, W, 3), 90, np.uint8), photometric="rgb")
    (tmp_path / "c.csv").write_text("0,0,0\n")

    def spec(response):
        d = dict(geometry_dict(width=W, height=H),
                 images=[{"path": "a.tiff", "exposure_s": 1.0, "response": response}])
        (tmp_path / "s.yaml").write_text(yaml.safe_dump(d))
        return load_spec(tmp_path / "s.yaml")
    entry = spec({"curve": "c.csv"}).images[0]
    assert entry.response == "curve" and entry.response_curve == tmp_path / "c.csv"
    with pytest.raises(SpecError, match=r"images\[0\].response: unknown field 'curv' \(did you "
                                        "mean 'curve'"):
        spec({"curv": "c.csv"})
    with pytest.raises(SpecError, match=r"images\[0\].response.curve: file not found"):
        spec({"curve": "nope.csv"})

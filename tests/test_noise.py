"""The noise model from the camera to the likelihood: the read-variance floor, per-pixel
variances of brackets, darks and binning, and noise estimation per image."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from fitmedia.images import load_entry
from fitmedia.inference.likelihood import ChannelProblem, Observation
from fitmedia.inference.params import ChannelParams, ParameterSpace
from fitmedia.spec import ImageEntry


class FixedModel:
    """A forward model that renders one fixed image times the brightness (for tests of the
    likelihood alone)."""

    channels = ("G",)

    def __init__(self, image: np.ndarray):
        self.image = np.asarray(image, float)
        self.shape = self.image.shape
        self.support = np.ones(self.shape, bool)

    def render(self, kappa_a, kappa_s, g, brightness):
        return (self.image * np.asarray(brightness, float).reshape(-1)[0])[..., None]


def _u(space: ParameterSpace) -> np.ndarray:
    return space.to_vector(ChannelParams(1.0, 0.5, 0.5))


def test_zero_read_variance_is_floored():
    """An estimated read variance of exactly 0 with zero-valued pixels where the model is 0:
    the log-likelihood is finite with no warning (warnings are errors here), and each
    zero pixel's variance is the floor: the float spacing at the data's largest value,
    squared, over 12 (independent: computed here from numpy's spacing)."""
    image = np.zeros((6, 8))
    image[2:4, 3:5] = 1.0
    data = image.copy()
    data[2, 3] = 1.01
    obs = [Observation(FixedModel(image), data, np.ones_like(data, bool), 1.0)]
    space = ParameterSpace()
    problem = ChannelProblem(obs, space, 1.0, (1e-4, 0.0))
    u = _u(space)
    assert np.isfinite(problem.log_likelihood(u))
    floor = np.spacing(1.01) ** 2 / 12
    chi2, n = problem.chi2(u)
    assert n == 48 and chi2 == pytest.approx(0.01 ** 2 / (1e-4 + floor))
    assert problem.variance(0, np.zeros(1))[0] == pytest.approx(floor)


def test_quantisation_floor_of_integer_files(tmp_path):
    """A 16-bit file with read variance 0: the read map is the quantisation variance 1/12
    DN^2 in image units, doubled by a subtracted dark, over the exposure squared."""
    raw = np.full((4, 5, 3), 1000, np.uint16)
    tifffile.imwrite(tmp_path / "a.tif", raw, photometric="rgb")
    tifffile.imwrite(tmp_path / "d.tif", np.full((4, 5, 3), 100, np.uint16), photometric="rgb")
    entry = ImageEntry(paths=(tmp_path / "a.tif",), exposures=(0.5,),
                       darks=(tmp_path / "d.tif",), response="linear")
    img = load_entry(entry, expected_shape=(4, 5))
    gain, read = img.variance_maps(2.0, 0.0)
    np.testing.assert_allclose(read, 2 * (1 / 12) / 0.5 ** 2)
    np.testing.assert_allclose(gain, 2.0 / 0.5)


@pytest.fixture(scope="module")
def tank_image() -> np.ndarray:
    """A noise-free synthetic tank image (single scattering, 240x180, a diluted milk-like
    medium at 100 ml in 23 l), rendered once for the noise-estimation tests."""
    from conftest import make_spec

    from fitmedia.forward.single import SingleScattering

    spec = make_spec(width=240, height=180)
    c = 100.0 / 23000.0
    return SingleScattering(spec, None, channels=("R", "G", "B")).render(
        c * np.array([0.05, 0.08, 0.12]), c * np.array([1.2, 1.5, 1.9]), np.full(3, 0.8),
        np.ones(3))


@pytest.mark.parametrize("case, gain, read_var", [
    ("photon-limited", 1e-6, 9e-12),   # read noise 3 e-; the glow (1e-5..4e-4) is shot noise
    ("read-limited", 1e-7, 1e-9),      # read noise 316 e-: shot noise matters at the bulb only
])
def test_noise_estimate_recovers_or_refuses(tmp_path, tank_image, seed, case, gain, read_var):
    """Per-image estimation on a synthetic tank image with fitmedia.synth's Poisson-Gaussian
    noise of known gain and read variance: every channel's estimate is within 10 % of the
    truth, or the estimate is refused (exit-2 InputError asking for a noise block or a
    dark frame).  The photon-limited case must be recovered (so the test can fail)."""
    from fitmedia.errors import InputError
    from fitmedia.images import write_float_tiff
    from fitmedia.images.noise import estimate_sensor_noise
    from fitmedia.synth import CameraNoise

    t = 0.5  # the file holds the noisy values; the estimate is per stored value (file units)
    noisy = CameraNoise(gain, read_var).apply(tank_image, np.random.default_rng(seed))
    write_float_tiff(tmp_path / "a.tiff", noisy)
    entry = ImageEntry(paths=(tmp_path / "a.tiff",), exposures=(t,))
    img = load_entry(entry, expected_shape=noisy.shape[:2])
    try:
        est = estimate_sensor_noise(img, entry, (0, 1, 2), "images[0]")
    except InputError as exc:
        assert case != "photon-limited", str(exc)
        assert "give a `noise` block" in str(exc) and "images[0]" in str(exc)
        return
    np.testing.assert_allclose(est.a, gain, rtol=0.10)
    np.testing.assert_allclose(est.b, read_var, rtol=0.10)
    assert est.source == "estimated from this image"


def _radiance(h: int = 60, w: int = 80) -> np.ndarray:
    """A glow around a bright disc (a bulb), DN per second per channel: from ~30 DN/s at the
    corners to 4e6 DN/s in the disc, so the long frames saturate and the short ones read
    little above their read noise."""
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot(yy - h / 2, xx - w / 2)
    glow = 3e5 * np.exp(-r / 6.0) + 30.0
    return np.where(r < 4, 4e6, glow)[..., None] * np.array([1.0, 0.6, 0.3])


def test_bracket_with_dark_chi2_at_truth(tmp_path, rng):
    """A 3-frame 16-bit bracket (1, 0.1, 0.01 s) with one shared dark frame, simulated here
    with Poisson-Gaussian noise (a = 2 DN per electron, read variance 25 DN^2, pedestal
    500 DN, clipped at 65535): chi2 per pixel at the true radiance through the likelihood
    is 1 within 4 sigma (sqrt(2 / n)) with the per-pixel variances, while one noise level
    for every pixel (the longest frame's, as before) gives chi2 > 10 per pixel on the pixels
    known only from the shortest frame."""
    a, b, pedestal, exposures = 2.0, 25.0, 500.0, (1.0, 0.1, 0.01)
    radiance = _radiance()
    shape = radiance.shape[:2]
    dark = pedestal + rng.normal(0.0, np.sqrt(b), radiance.shape)
    paths = []
    for k, t in enumerate(exposures):
        electrons = rng.poisson(radiance * t / a)
        raw = pedestal + a * electrons + rng.normal(0.0, np.sqrt(b), radiance.shape)
        paths.append(tmp_path / f"f{k}.tif")
        tifffile.imwrite(paths[-1], np.clip(np.round(raw), 0, 65535).astype(np.uint16),
                         photometric="rgb")
    tifffile.imwrite(tmp_path / "dark.tif", np.round(dark).astype(np.uint16), photometric="rgb")
    entry = ImageEntry(paths=tuple(paths), exposures=exposures, darks=(tmp_path / "dark.tif",),
                       response="linear")
    img = load_entry(entry, expected_shape=shape)
    assert img.n_saturated == 0 and img.valid.all()
    assert 0.01 < np.mean(img.exposure < 1.0) < 0.5  # the long frame saturates near the disc
    assert np.mean(img.exposure < 0.1) > 0.005        # and the middle one in the disc
    gain_map, read_map = img.variance_maps(a, b)
    space = ParameterSpace()
    for ci in range(3):
        obs = [Observation(FixedModel(radiance[..., ci]), img.data[..., ci], img.valid[..., ci],
                           1.0, gain_map[..., ci], read_map[..., ci])]
        chi2, n = ChannelProblem(obs, space, 1.0, (np.nan, np.nan)).chi2(_u(space))
        assert abs(chi2 / n - 1.0) < 4 * np.sqrt(2.0 / n), (ci, chi2 / n)
        short = img.exposure[..., ci] < 0.05  # known from the 0.01 s frame only
        flat = ChannelProblem([Observation(FixedModel(radiance[..., ci]), img.data[..., ci],
                                           short, 1.0)], space, 1.0, (a / 1.0, b))
        chi2_flat, n_short = flat.chi2(_u(space))
        assert n_short > 10 and chi2_flat / n_short > 10, (ci, chi2_flat / n_short)


def test_noise_from_a_dark_frame(tmp_path, tank_image, rng):
    """With a dark frame the read variance is the dark frame's own noise variance and only
    the gain is fitted: both within 10 % of the values the frames were simulated with
    (photon-limited case, float files, the dark subtracted)."""
    from fitmedia.images import write_float_tiff
    from fitmedia.images.noise import estimate_sensor_noise
    from fitmedia.synth import CameraNoise

    gain, read_var = 1e-6, 9e-12
    write_float_tiff(tmp_path / "a.tiff", CameraNoise(gain, read_var).apply(tank_image, rng))
    write_float_tiff(tmp_path / "d.tiff", rng.normal(0.0, np.sqrt(read_var), tank_image.shape))
    entry = ImageEntry(paths=(tmp_path / "a.tiff",), exposures=(2.0,),
                       darks=(tmp_path / "d.tiff",))
    img = load_entry(entry, expected_shape=tank_image.shape[:2])
    est = estimate_sensor_noise(img, entry, (0, 1, 2), "images[0]")
    np.testing.assert_allclose(est.a, gain, rtol=0.10)
    np.testing.assert_allclose(est.b, read_var, rtol=0.10)
    assert est.source == "estimated from this image and its dark frame d.tiff"
    gain_map, read_map = img.variance_maps(est.a, est.b)
    # image and dark: two reads, over t^2 = 4
    np.testing.assert_allclose(read_map, np.broadcast_to(2 * est.b / 4.0, read_map.shape))


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory):
    """A small synthetic capture (60 x 45, float TIFFs) made by `fitmedia synth`."""
    import yaml
    from conftest import geometry_dict

    from fitmedia.cli import main

    d = tmp_path_factory.mktemp("cap")
    (d / "geom.yaml").write_text(yaml.safe_dump(geometry_dict(width=60, height=45)))
    assert main(["synth", str(d / "geom.yaml"), "--medium", "Espresso", "--ml", "8", "--out",
                 str(d / "c"), "--seed", "3"]) == 0
    return d / "c"


def _fit_exit(capture, tmp_path, capsys, mutate) -> tuple[int, str]:
    import yaml

    from fitmedia.cli import main

    data = yaml.safe_load((capture / "capture.yaml").read_text())
    for entry in data["images"] + [data["calibration"]["clear_water"]]:
        entry["path"] = str(capture / entry["path"])
    mutate(data)
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump(data))
    code = main(["fit", str(tmp_path / "spec.yaml"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    return code, err


def test_cli_refuses_undeclared_16bit_tiff(small_capture, tmp_path, capsys):
    """The capture's image as a 16-bit TIFF without `response`: exit 2, one line naming the
    file and the fix; nothing written."""
    from fitmedia.images import read_image

    img, _ = read_image(small_capture / "images" / "medium_00_8ml.tiff")
    tifffile.imwrite(tmp_path / "m16.tif", np.clip(img / img.max() * 60000, 0, 65535)
                     .astype(np.uint16), photometric="rgb")
    code, err = _fit_exit(small_capture, tmp_path, capsys,
                          lambda d: d["images"][0].update(path=str(tmp_path / "m16.tif")))
    assert code == 2 and "m16.tif" in err and "'response: srgb'" in err
    assert "'response: linear'" in err and not (tmp_path / "out").exists()


def test_cli_refuses_a_bracket_noise_block_without_exposure(small_capture, tmp_path, capsys):
    """A bracket of different exposures with a `noise` block but no noise.exposure_s: exit 2
    naming noise.exposure_s (the block's exposure is ambiguous)."""
    def mutate(d):
        p = d["images"][0]["path"]
        d["images"][0].update(path=[p, p], exposure_s=[1.0, 0.5])
    code, err = _fit_exit(small_capture, tmp_path, capsys, mutate)
    assert code == 2 and "noise.exposure_s" in err and "images[0]" in err


def test_noise_estimate_of_a_bracket(tmp_path, tank_image, rng):
    """A 2-frame float bracket (1 and 0.1 s, clipped at 65000 with `saturation: 65000`)
    simulated here with 2 DN per electron and 25 DN^2 read variance: the per-frame camera
    noise (a, b) comes back within 10 % in every channel, estimated on the pixels merged from
    both frames (sum of exposures 1.1 s, two reads)."""
    from fitmedia.images import write_float_tiff
    from fitmedia.images.noise import estimate_sensor_noise

    a, b, scale = 2.0, 25.0, 4e6  # DN per electron, DN^2, DN per second per image unit
    paths = []
    for k, t in enumerate((1.0, 0.1)):
        frame = a * rng.poisson(scale * t * tank_image / a) + rng.normal(0, np.sqrt(b),
                                                                         tank_image.shape)
        paths.append(tmp_path / f"b{k}.tiff")
        write_float_tiff(paths[-1], np.minimum(frame, 65000.0))
    entry = ImageEntry(paths=tuple(paths), exposures=(1.0, 0.1), saturation=65000.0)
    img = load_entry(entry, expected_shape=tank_image.shape[:2])
    assert np.any(img.exposure < 1.0)  # the bulb is known from the short frame only
    est = estimate_sensor_noise(img, entry, (0, 1, 2), "images[0]")
    np.testing.assert_allclose(est.a, a, rtol=0.10)
    np.testing.assert_allclose(est.b, b, rtol=0.10)


def test_flat_field(tmp_path, rng):
    """A frame vignetted by v = 1 - 0.3 (r / r_max)^2 with Poisson-Gaussian noise, and the flat
    field 7 v (any scale) as a float TIFF: the loaded image is the unvignetted radiance
    (mean ratio 1 within 1 %, where without the flat the corners read 0.72x the centre), and chi2 per
    pixel at the truth with the flat-divided variances is 1 within 4 sigma.  A flat of the
    wrong size or with a zero at a used pixel: ImageError naming the flat file."""
    from fitmedia.errors import ImageError
    from fitmedia.images import write_float_tiff

    h, w, a, b = 60, 80, 2.0, 25.0
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((yy - h / 2) ** 2 + (xx - w / 2) ** 2) / ((h / 2) ** 2 + (w / 2) ** 2)
    vignet = (1 - 0.3 * r2)[..., None] * np.ones(3)
    radiance = np.full((h, w, 3), 5000.0) * np.array([1.0, 0.8, 0.5])
    frame = a * rng.poisson(vignet * radiance / a) + rng.normal(0, np.sqrt(b), radiance.shape)
    write_float_tiff(tmp_path / "a.tiff", frame)
    write_float_tiff(tmp_path / "flat.tiff", 7 * vignet)
    entry = ImageEntry(paths=(tmp_path / "a.tiff",), exposures=(1.0,), flat=tmp_path / "flat.tiff")
    img = load_entry(entry, expected_shape=(h, w))
    scale = vignet.mean() / img.flat.mean()  # the flat is scaled to mean 1
    np.testing.assert_allclose(np.mean(img.data / (radiance * scale), axis=(0, 1)), 1, rtol=0.01)
    plain = load_entry(ImageEntry(paths=entry.paths, exposures=(1.0,)), expected_shape=(h, w))
    centre = plain.data[h // 2 - 2:h // 2 + 3, w // 2 - 2:w // 2 + 3].mean()
    assert plain.data[:5, :5].mean() / centre == pytest.approx(0.72, abs=0.03)  # vignetted
    gain_map, read_map = img.variance_maps(a, b)
    chi2 = np.sum((img.data - radiance * scale) ** 2 / (gain_map * radiance * scale + read_map))
    assert abs(chi2 / img.data.size - 1) < 4 * np.sqrt(2 / img.data.size)
    write_float_tiff(tmp_path / "small.tiff", vignet[:-1])
    with pytest.raises(ImageError, match=r"small\.tiff: flat field is 80x59"):
        load_entry(ImageEntry(paths=entry.paths, exposures=(1.0,), flat=tmp_path / "small.tiff"),
                   expected_shape=(h, w))
    bad = vignet.copy()
    bad[3, 4, 1] = 0.0
    write_float_tiff(tmp_path / "bad.tiff", bad)
    with pytest.raises(ImageError, match=r"bad\.tiff: flat field is 0 at row 3, column 4 \(G\)"):
        load_entry(ImageEntry(paths=entry.paths, exposures=(1.0,), flat=tmp_path / "bad.tiff"),
                   expected_shape=(h, w))

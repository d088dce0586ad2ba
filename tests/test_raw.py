"""Camera RAW read exactly: small DNGs written by tifffile with known sensor values.

Each test compares fitmedia's values with the sensor values written into the file
(independent of LibRaw's own processing): signal = raw - black per photosite, each
2x2 Bayer quad binned (G the mean of its two sites), saturation judged on the raw
values against the file's white level.  LibRaw (through rawpy) reads these Bayer
(CFA) and LinearRaw DNGs; it refuses images under 22 pixels a side, hence 24x32.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile

from fitmedia.errors import ImageError
from fitmedia.images import load_entry, read_frame
from fitmedia.spec import ImageEntry

H, W = 24, 32          # sensor sites; binned image 12 x 16
WHITE = 16383          # a 14-bit sensor
BLACK = (200, 210, 220, 230)  # per site of the 2x2 pattern (R, G1 / G2, B), all different
RGGB = (0, 1, 1, 2)    # CFAPattern: 0 = R, 1 = G, 2 = B


def _dng_tags(black, white, cfa: bool) -> list[tuple]:
    tags = [(50706, "B", 4, (1, 4, 0, 0), True),            # DNGVersion
            (50707, "B", 4, (1, 1, 0, 0), True),            # DNGBackwardVersion
            (50708, "s", 0, "fitmedia test camera", True),  # UniqueCameraModel
            (50721, "i", 18, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),
            (50778, "H", 1, 21, True)]                      # CalibrationIlluminant1: D65
    if cfa:
        tags += [(33421, "H", 2, (2, 2), True),             # CFARepeatPatternDim
                 (33422, "B", 4, RGGB, True),               # CFAPattern
                 (50710, "B", 3, (0, 1, 2), True),          # CFAPlaneColor
                 (50711, "H", 1, 1, True),                  # CFALayout: rectangular
                 (50713, "H", 2, (2, 2), True)]             # BlackLevelRepeatDim
    tags += [(50714, "H", len(black), tuple(black), True),  # BlackLevel
             (50717, "H", len(white), tuple(white), True)]  # WhiteLevel
    return tags


def write_bayer_dng(path: Path, sensor: np.ndarray, black=BLACK, white=WHITE) -> Path:
    """A Bayer (CFA, RGGB) DNG holding exactly ``sensor`` (uint16 raw values)."""
    tifffile.imwrite(path, sensor.astype(np.uint16), photometric=32803, subfiletype=0,
                     extratags=_dng_tags(black, (white,), cfa=True))
    return path


def _sensor(rng: np.random.Generator) -> np.ndarray:
    """Raw values (black included) with a bright site at 80 % and 99 % of white, sites
    below their black level, and one saturated site (a G2 site)."""
    s = rng.integers(150, 3000, size=(H, W)).astype(np.int64)
    s[4, 6] = int(0.80 * WHITE)    # R site of quad (2, 3)
    s[6, 9] = int(0.99 * WHITE)    # G1 site of quad (3, 4)
    s[9, 10] = WHITE               # G2 site of quad (4, 5): saturated
    s[0, 0], s[1, 1], s[3, 2] = 150, 190, 5   # below black (R, B, G2)
    return s


def _expected(sensor: np.ndarray) -> np.ndarray:
    """Binned signal computed here from the written values: (R, mean of G1 and G2, B)."""
    sig = sensor.astype(float) - np.tile(np.reshape(BLACK, (2, 2)), (H // 2, W // 2))
    return np.stack([sig[0::2, 0::2], 0.5 * (sig[0::2, 1::2] + sig[1::2, 0::2]),
                     sig[1::2, 1::2]], axis=-1)


def _entry(path: Path, **kw) -> ImageEntry:
    return ImageEntry(paths=(path,), exposures=(1.0,), **kw)


def test_bayer_values_are_sensor_minus_black(tmp_path, rng):
    """Values equal the written sensor values minus the per-site black, binned per quad,
    negatives kept, to 1e-9 DN; only the quad channel holding the saturated site is
    invalid; the sites at 80 % and 99 % of white are valid and read as written."""
    sensor = _sensor(rng)
    frame = read_frame(write_bayer_dng(tmp_path / "a.dng", sensor))
    exp = _expected(sensor)
    assert frame.level == WHITE
    np.testing.assert_array_equal(frame.samples, [1, 2, 1])
    np.testing.assert_allclose(frame.data, exp, rtol=0, atol=1e-9)
    assert frame.data[0, 0, 0] == 150 - 200 and frame.data[0, 0, 2] == 190 - 230
    out = load_entry(_entry(tmp_path / "a.dng"), expected_shape=(H // 2, W // 2))
    want_bad = np.zeros((H // 2, W // 2, 3), bool)
    want_bad[4, 5, 1] = True
    np.testing.assert_array_equal(~out.valid, want_bad)
    assert out.n_saturated == 1
    assert out.data[2, 3, 0] == int(0.80 * WHITE) - 200
    assert out.data[3, 4, 1] == pytest.approx(0.5 * (int(0.99 * WHITE) - 210 + sensor[7, 8] - 220))


def test_values_do_not_depend_on_the_image_maximum(tmp_path, rng):
    """The same sensor values with the brightest site at 50 %, 80 %, 99 % of white or
    saturated: every other pixel reads identically (no content-dependent scaling)."""
    sensor = _sensor(rng)
    sensor[6, 9], sensor[9, 10] = 1000, 1000
    reads = []
    for k, frac in enumerate((0.5, 0.8, 0.99, 1.0)):
        s = sensor.copy()
        s[4, 6] = int(frac * WHITE)
        reads.append(read_frame(write_bayer_dng(tmp_path / f"m{k}.dng", s)).data)
    others = np.ones((H // 2, W // 2, 3), bool)
    others[2, 3, 0] = False
    for r in reads:
        np.testing.assert_array_equal(r[others], reads[0][others])
        np.testing.assert_allclose(r, _expected(sensor) * others + r * ~others, atol=1e-9)


def test_spec_saturation_is_a_sensor_value(tmp_path, rng):
    """`saturation: 4000` on a 14-bit RAW masks exactly the quads with a raw site >= 4000
    (sensor units, black included), not every pixel."""
    sensor = _sensor(rng)
    path = write_bayer_dng(tmp_path / "a.dng", sensor)
    out = load_entry(_entry(path, saturation=4000), expected_shape=(H // 2, W // 2))
    peak = np.stack([sensor[0::2, 0::2], np.maximum(sensor[0::2, 1::2], sensor[1::2, 0::2]),
                     sensor[1::2, 1::2]], axis=-1)
    np.testing.assert_array_equal(~out.valid, peak >= 4000)
    assert 0 < np.count_nonzero(~out.valid) < 5


def test_dark_subtraction_keeps_negative_values(tmp_path, rng):
    """RAW image minus RAW dark: sensor - sensor_dark exactly, negative values kept."""
    sensor = _sensor(rng)
    dark = rng.integers(180, 260, size=(H, W))
    a = write_bayer_dng(tmp_path / "a.dng", sensor)
    d = write_bayer_dng(tmp_path / "d.dng", dark)
    out = load_entry(_entry(a, darks=(d,)), expected_shape=(H // 2, W // 2))
    want = _expected(sensor) - _expected(dark)
    ok = out.valid
    np.testing.assert_allclose(out.data[ok], want[ok], atol=1e-9)
    assert np.any(out.data[ok] < 0)


def test_linear_raw_dng(tmp_path, rng):
    """A LinearRaw DNG (three samples per pixel): raw minus the per-sample black, and
    the saturated sample masked."""
    img = rng.integers(100, 4000, size=(H, W, 3)).astype(np.uint16)
    img[5, 7, 2] = WHITE
    black = (200, 210, 220)
    tifffile.imwrite(tmp_path / "l.dng", img, photometric=34892, subfiletype=0,
                     planarconfig="contig", extratags=_dng_tags(black, (WHITE,) * 3, cfa=False))
    frame = read_frame(tmp_path / "l.dng")
    np.testing.assert_allclose(frame.data, img - np.array(black, float), atol=1e-9)
    np.testing.assert_array_equal(frame.samples, [1, 1, 1])
    out = load_entry(_entry(tmp_path / "l.dng"), expected_shape=(H, W))
    assert out.n_saturated == 1 and not out.valid[5, 7, 2]


def test_raw_of_wrong_size_says_binned(tmp_path, rng):
    path = write_bayer_dng(tmp_path / "a.dng", _sensor(rng))
    with pytest.raises(ImageError, match=r"a\.dng: image is 16x12 pixels \(a RAW file's 2x2"):
        load_entry(_entry(path), expected_shape=(H, W))


def test_binned_bayer_chi2_at_truth(tmp_path, rng):
    """Photosites simulated with Poisson-Gaussian noise (2 DN per electron, read variance
    16 DN^2, black 512 DN) from a known radiance, written as a Bayer DNG: through fitmedia's
    binning and per-pixel variances (G the mean of two sites: half the variance) chi2 per
    pixel at the true radiance is 1 within 4 sigma in R, G and B; treating G like a single
    site (its variance doubled) moves G's chi2 to about 0.5."""
    from fitmedia.inference.likelihood import ChannelProblem, Observation
    from fitmedia.inference.params import ChannelParams, ParameterSpace

    a, b, black, h, w = 2.0, 16.0, 512, 60, 80
    yy, xx = np.mgrid[0:h, 0:w]
    radiance = (8000.0 * np.exp(-np.hypot(yy - h / 2, xx - w / 2) / 10.0) + 20.0)[..., None] \
        * np.array([1.0, 0.7, 0.4])  # DN per second per site, exposure 1 s
    site = np.empty((2 * h, 2 * w))
    for (i, j), ch in zip(((0, 0), (0, 1), (1, 0), (1, 1)), (0, 1, 1, 2)):
        mean = radiance[..., ch]
        site[i::2, j::2] = black + a * rng.poisson(mean / a) + rng.normal(0, np.sqrt(b), mean.shape)
    path = write_bayer_dng(tmp_path / "c.dng", np.clip(np.round(site), 0, WHITE),
                           black=(black,) * 4)
    img = load_entry(_entry(path), expected_shape=(h, w))
    gain_map, read_map = img.variance_maps(a, b)
    space = ParameterSpace()
    u = space.to_vector(ChannelParams(1.0, 0.5, 0.5))

    class Fixed:
        def __init__(self, image):
            self.image, self.shape, self.support = image, image.shape, np.ones(image.shape, bool)

        def render(self, *args):
            return self.image[..., None]

    for ci in range(3):
        obs = [Observation(Fixed(radiance[..., ci]), img.data[..., ci], img.valid[..., ci], 1.0,
                           gain_map[..., ci], read_map[..., ci])]
        chi2, n = ChannelProblem(obs, space, 1.0, (np.nan, np.nan)).chi2(u)
        assert n == h * w and abs(chi2 / n - 1) < 4 * np.sqrt(2 / n), (ci, chi2 / n)
    single = [Observation(Fixed(radiance[..., 1]), img.data[..., 1], img.valid[..., 1], 1.0,
                          2 * gain_map[..., 1], 2 * read_map[..., 1])]
    chi2, n = ChannelProblem(single, space, 1.0, (np.nan, np.nan)).chi2(u)
    assert abs(chi2 / n - 0.5) < 4 * np.sqrt(2 / n) / 2

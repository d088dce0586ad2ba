"""Tests of fitmedia.images: file formats, exposure handling, saturation, masks, noise."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import tifffile

from fitmedia.errors import ImageError, InputError
from fitmedia.images import estimate_noise, load_entry, read_image, write_float_tiff
from fitmedia.spec import ImageEntry

SEED = int(os.environ.get("FITMEDIA_TEST_SEED", "20240611"))
H, W = 12, 16


def _cv2():
    os.environ["OPENCV_IO_ENABLE_OPENEXR"] = "1"
    import cv2

    return cv2


def _rgb16(rng: np.random.Generator) -> np.ndarray:
    """(H, W, 3) uint16 with clearly different R, G, B levels."""
    base = rng.integers(0, 1000, size=(H, W, 3))
    return (base + np.array([1000, 20000, 40000])).astype(np.uint16)


def _tiff(path: Path, arr: np.ndarray) -> Path:
    tifffile.imwrite(path, arr, photometric="rgb" if arr.ndim == 3 else "minisblack")
    return path


def _entry(paths, exposures, **kw) -> ImageEntry:
    """An image entry; 8- and 16-bit files declared linear unless ``response`` is given."""
    kw.setdefault("response", "linear")
    return ImageEntry(paths=tuple(Path(p) for p in paths), exposures=tuple(exposures), **kw)


# ---------------------------------------------------------------- formats


def test_float_tiff_round_trip(tmp_path):
    img = np.random.default_rng(SEED).random((H, W, 3)).astype(np.float32) * 3.0
    path = tmp_path / "out" / "img.tiff"
    write_float_tiff(path, img)
    back, level = read_image(path)
    assert level is None
    assert back.dtype == np.float64 and back.shape == (H, W, 3)
    np.testing.assert_array_equal(back, img)
    assert sorted(p.name for p in path.parent.iterdir()) == ["img.tiff"]  # no temp file left


def test_uint16_tiff(tmp_path):
    img = _rgb16(np.random.default_rng(SEED))
    back, level = read_image(_tiff(tmp_path / "a.tif", img))
    assert level == 65535
    np.testing.assert_array_equal(back, img)


def test_uint16_png_channel_order(tmp_path):
    cv2 = _cv2()
    img = _rgb16(np.random.default_rng(SEED))
    assert cv2.imwrite(str(tmp_path / "a.png"), img[..., ::-1])  # OpenCV writes BGR
    back, level = read_image(tmp_path / "a.png")
    assert level == 65535
    np.testing.assert_array_equal(back, img)


def test_uint8_png_read_by_other_library(tmp_path):
    import imageio.v3 as iio

    img = np.zeros((H, W, 3), np.uint8) + np.array([10, 100, 200], np.uint8)
    iio.imwrite(tmp_path / "a.png", img)  # Pillow writes RGB: checks order independently of cv2
    back, level = read_image(tmp_path / "a.png")
    assert level == 255
    np.testing.assert_array_equal(back, img)
    out = load_entry(_entry([tmp_path / "a.png"], [1.0]), expected_shape=(H, W))
    np.testing.assert_array_equal(out.data, img)


def _glow(rng: np.random.Generator, h: int = 60, w: int = 80) -> np.ndarray:
    """A linear glow in a black tank, values in [0, 1]: exp(-r / 6 px) plus a little noise."""
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot(yy - h / 2, xx - w / 2)
    img = np.exp(-r / 6.0)[..., None] * np.array([0.9, 0.6, 0.3])
    return np.clip(img + rng.normal(0.0, 1e-4, img.shape), 0.0, 1.0)


def _srgb_encode(v: np.ndarray) -> np.ndarray:
    """The sRGB encoding curve, written here independently of fitmedia's decoder."""
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)


@pytest.mark.parametrize("bits", [8, 16])
def test_undeclared_integer_file_is_refused_and_srgb_named(tmp_path, rng, bits):
    """An 8- or 16-bit file without `response` is refused naming the file and the fix;
    the sRGB-encoded one is named as such (histogram), the linear one is not."""
    dtype, top = (np.uint8, 255) if bits == 8 else (np.uint16, 65535)
    lin = _glow(rng)
    enc = _tiff(tmp_path / "enc.tif", np.round(_srgb_encode(lin) * top).astype(dtype))
    raw = _tiff(tmp_path / "lin.tif", np.round(lin * top).astype(dtype))
    shape = lin.shape[:2]
    with pytest.raises(ImageError, match=rf"enc\.tif: a {bits}-bit image .*looks sRGB-encoded"
                                         r".*'response: srgb'.*'response: linear'"):
        load_entry(_entry([enc], [1.0], response=None), expected_shape=shape)
    with pytest.raises(ImageError, match=r"lin\.tif: .*may carry a tone curve; declare") as exc:
        load_entry(_entry([raw], [1.0], response=None), expected_shape=shape)
    assert "sRGB" not in str(exc.value).split("declare")[0]


def test_srgb_response_decodes_to_linear(tmp_path, rng):
    """`response: srgb` on a 16-bit sRGB-encoded file gives back the linear values the file
    was encoded from (to the 16-bit quantisation), like the linear file does."""
    lin = _glow(rng)
    enc = _tiff(tmp_path / "enc.tif", np.round(_srgb_encode(lin) * 65535).astype(np.uint16))
    out = load_entry(_entry([enc], [2.0], response="srgb"), expected_shape=lin.shape[:2])
    step = np.gradient(lin, axis=1)  # slack: one 16-bit code step of the encoded value
    np.testing.assert_allclose(out.data, lin * 65535 / 2.0, rtol=2e-3, atol=0.5)
    assert np.abs(step).max() > 0  # the glow is not flat


def test_float_file_with_srgb_is_refused(tmp_path):
    write_float_tiff(tmp_path / "f.tiff", np.ones((H, W, 3), np.float32))
    with pytest.raises(ImageError, match=r"f\.tiff: 'response: srgb' is for 8- or 16-bit"):
        load_entry(_entry([tmp_path / "f.tiff"], [1.0], response="srgb"), expected_shape=(H, W))
    load_entry(_entry([tmp_path / "f.tiff"], [1.0], response=None), expected_shape=(H, W))


def test_exr_channel_order(tmp_path):
    cv2 = _cv2()
    img = np.zeros((H, W, 3), np.float32) + np.array([0.25, 1.5, 7.0], np.float32)
    img[3, 4] = [2.0, 0.0, 0.125]
    assert cv2.imwrite(str(tmp_path / "a.exr"), img[..., ::-1])
    back, level = read_image(tmp_path / "a.exr")
    assert level is None
    np.testing.assert_array_equal(back, img)


def test_rgba_drops_alpha_and_grey_is_refused(tmp_path):
    img = _rgb16(np.random.default_rng(SEED))
    rgba = np.concatenate([img, np.full((H, W, 1), 7, np.uint16)], axis=2)
    tifffile.imwrite(tmp_path / "rgba.tif", rgba, photometric="rgb", extrasamples=["unassalpha"])
    back, _ = read_image(tmp_path / "rgba.tif")
    np.testing.assert_array_equal(back, img)
    with pytest.raises(ImageError, match=r"grey\.tif: has 1 channel"):
        read_image(_tiff(tmp_path / "grey.tif", img[..., 0]))


@pytest.mark.parametrize("name, content", [
    ("trunc.tif", "truncate"),
    ("garbage.tif", b"this is not an image " * 20),
    ("garbage.png", b"\x89PNG\r\n\x1a\n" + b"\x00" * 100),
    ("trunc.png", "truncate"),
    ("garbage.exr", b"v/1\x01" + b"\x07" * 200),
    ("garbage.dng", b"II*\x00" + b"\x13" * 500),
    ("empty.png", b""),
    ("photo.jpg", b"\xff\xd8\xff"),
])
def test_unreadable_file_raises_image_error(tmp_path, name, content):
    path = tmp_path / name
    if content == "truncate":
        full = tmp_path / ("full" + path.suffix)
        arr = _rgb16(np.random.default_rng(SEED))
        if path.suffix == ".png":
            _cv2().imwrite(str(full), arr)
        else:
            _tiff(full, arr)
        content = full.read_bytes()[: full.stat().st_size // 2]
    path.write_bytes(content)
    with pytest.raises(ImageError, match=name.replace(".", r"\.")):
        read_image(path)


def test_missing_file(tmp_path):
    with pytest.raises(ImageError, match=r"nope\.tif: file not found"):
        read_image(tmp_path / "nope.tif")


@pytest.mark.parametrize("bad, match", [(np.nan, "NaN or infinite"), (np.inf, "NaN or infinite")])
def test_bad_float_values_raise(tmp_path, bad, match):
    img = np.ones((H, W, 3), np.float32)
    img[2, 3, 1] = bad
    with pytest.raises(ImageError, match=rf"bad\.tif: .*{match}"):
        read_image(_tiff(tmp_path / "bad.tif", img))


def test_negative_float_values_are_kept(tmp_path):
    """Read noise around zero (dark-subtracted, or the light fully attenuated) is negative
    half the time; such values are data, kept and never clamped."""
    img = np.full((H, W, 3), 1e-4, np.float32)
    img[2, 3, 1] = -0.5
    back, _ = read_image(_tiff(tmp_path / "ok.tif", img))
    assert back[2, 3, 1] == pytest.approx(-0.5)


# ---------------------------------------------------------------- load_entry


def test_exposure_normalisation_and_dark(tmp_path):
    rng = np.random.default_rng(SEED)
    raw = _rgb16(rng)
    dark = rng.integers(50, 150, size=(H, W, 3)).astype(np.uint16)
    entry = _entry([_tiff(tmp_path / "a.tif", raw)], [0.25], darks=(_tiff(tmp_path / "d.tif", dark),))
    out = load_entry(entry, expected_shape=(H, W))
    np.testing.assert_allclose(out.data, (raw.astype(float) - dark) / 0.25)
    assert out.valid.all() and out.n_saturated == 0 and out.n_masked == 0
    assert "a.tif" in out.source


def test_dark_of_wrong_size_raises(tmp_path):
    raw = _rgb16(np.random.default_rng(SEED))
    entry = _entry([_tiff(tmp_path / "a.tif", raw)], [1.0],
                   darks=(_tiff(tmp_path / "d.tif", raw[:-1]),))
    with pytest.raises(ImageError, match=r"d\.tif: dark frame is 16x11"):
        load_entry(entry, expected_shape=(H, W))


def test_bracket_merge_recovers_radiance(tmp_path):
    """Noise-free bracket of a known radiance L (file units per second) whose
    long exposure saturates on the bright half: every pixel must come back as L
    to within the quantisation of the frames that were not saturated."""
    exposures = [1.0, 0.1, 0.01]
    radiance = np.linspace(1e3, 4e5, H * W * 3).reshape(H, W, 3)
    paths, unsat_time = [], np.zeros_like(radiance)
    for k, t in enumerate(exposures):
        raw = np.minimum(np.round(radiance * t), 65535).astype(np.uint16)
        unsat_time += np.where(raw < 0.999 * 65535, t, 0.0)
        paths.append(_tiff(tmp_path / f"b{k}.tif", raw))
    assert (unsat_time < 1.0).mean() > 0.5  # the long frame is mostly saturated
    out = load_entry(_entry(paths, exposures), expected_shape=(H, W))
    assert out.valid.all() and out.n_saturated == 0
    err = np.abs(out.data - radiance)
    assert np.all(err <= 0.5 * len(exposures) / unsat_time + 1e-9)


def test_bracket_weights_by_exposure(tmp_path):
    # 1000 counts in 1 s and 110 counts in 0.1 s: exposure-weighted mean is 1110/1.1
    a = _tiff(tmp_path / "a.tif", np.full((H, W, 3), 1000, np.uint16))
    b = _tiff(tmp_path / "b.tif", np.full((H, W, 3), 110, np.uint16))
    out = load_entry(_entry([a, b], [1.0, 0.1]), expected_shape=(H, W))
    np.testing.assert_allclose(out.data, 1110 / 1.1)


def test_saturation_marking(tmp_path):
    raw = np.full((H, W, 3), 30000, np.uint16)
    raw[0, 0, 0] = 65535
    raw[1, 1, 2] = 65500  # >= 0.999 * 65535
    raw[2, 2, :] = 65000  # below: valid
    path = _tiff(tmp_path / "s.tif", raw)
    out = load_entry(_entry([path], [1.0]), expected_shape=(H, W))
    assert out.n_saturated == 2
    assert not out.valid[0, 0, 0] and out.valid[0, 0, 1:].all()
    assert not out.valid[1, 1, 2] and out.valid[2, 2].all()
    assert np.count_nonzero(~out.valid) == 2
    only_g = load_entry(_entry([path], [1.0]), expected_shape=(H, W), channels=(1,))
    assert only_g.n_saturated == 0 and not only_g.valid[0, 0, 0]
    # a 12-bit camera in a 16-bit file: the spec's level replaces the dtype's
    raw12 = np.full((H, W, 3), 2000, np.uint16)
    raw12[5, 6, 1] = 4095
    out12 = load_entry(_entry([_tiff(tmp_path / "s12.tif", raw12)], [1.0], saturation=4095),
                       expected_shape=(H, W))
    assert out12.n_saturated == 1 and not out12.valid[5, 6, 1]


def test_mask(tmp_path):
    cv2 = _cv2()
    mask = np.full((H, W), 255, np.uint8)
    mask[:3, :5] = 0
    cv2.imwrite(str(tmp_path / "m.png"), mask)
    raw = _tiff(tmp_path / "a.tif", _rgb16(np.random.default_rng(SEED)))
    out = load_entry(_entry([raw], [1.0], mask=tmp_path / "m.png"), expected_shape=(H, W))
    assert out.n_masked == 15 and out.n_saturated == 0
    np.testing.assert_array_equal(out.valid, np.broadcast_to((mask > 0)[..., None], (H, W, 3)))
    cv2.imwrite(str(tmp_path / "m2.png"), mask[:-2])
    with pytest.raises(ImageError, match=r"m2\.png: mask is 16x10"):
        load_entry(_entry([raw], [1.0], mask=tmp_path / "m2.png"), expected_shape=(H, W))


def test_mostly_saturated_raises(tmp_path):
    raw = np.full((H, W, 3), 20000, np.uint16)
    raw[: H // 2 + 1, :, 1] = 65535  # 58 % of pixels, green only
    path = _tiff(tmp_path / "sat.tif", raw)
    with pytest.raises(ImageError, match=r"sat\.tif: is saturated in 58% of pixels"):
        load_entry(_entry([path], [1.0]), expected_shape=(H, W))
    out = load_entry(_entry([path], [1.0]), expected_shape=(H, W), channels=(0, 2))
    assert out.n_saturated == 0  # green is not used


def test_wrong_size_names_file(tmp_path):
    path = _tiff(tmp_path / "small.tif", _rgb16(np.random.default_rng(SEED)))
    with pytest.raises(ImageError, match=r"small\.tif: image is 16x12 .* expected 20x12"):
        load_entry(_entry([path], [1.0]), expected_shape=(H, 20))


# ---------------------------------------------------------------- noise


def test_estimate_noise_recovers_known_model():
    """Synthetic round trip: a smooth gradient image with Poisson-Gaussian noise
    of known gain and read_var (seeded rng) must give both back within 10 %."""
    rng = np.random.default_rng(SEED)
    gain, read_var = 2e-3, 4e-4
    yy, xx = np.mgrid[0:160:1.0, 0:240:1.0]
    signal = 0.05 + 0.95 * xx / 240 + 0.1 * (yy / 160) ** 2
    signal = signal[..., None] * np.array([1.0, 0.7, 0.4])
    noisy = gain * rng.poisson(signal / gain) + rng.normal(0.0, np.sqrt(read_var), signal.shape)
    valid = np.ones(noisy.shape, bool)
    valid[:20, :20] = False
    noisy[:20, :20] = 1e6  # invalid pixels must not matter
    g, r = estimate_noise(noisy, valid, rng=rng)
    assert g == pytest.approx(gain, rel=0.10)
    assert r == pytest.approx(read_var, rel=0.10)


def test_estimate_noise_needs_enough_pixels():
    data = np.ones((30, 30, 3))
    valid = np.zeros(data.shape, bool)
    valid[:10, :10] = True  # 8 * 8 * 3 = 192 interior samples
    with pytest.raises(InputError, match="only 192 usable"):
        estimate_noise(data, valid)

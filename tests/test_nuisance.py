"""Priors from the spec, the background offset and the clear water's own absorption."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile
import yaml

from fitmedia.inference.fit import FitOptions
from fitmedia.inference.likelihood import ChannelProblem, Observation
from fitmedia.inference.params import ChannelParams, ParameterSpace
from fitmedia.forward.single import SingleScattering
from fitmedia.medium import medium_by_name
from fitmedia.pipeline import fit
from fitmedia.synth import synthesize
from conftest import make_spec


@pytest.fixture(scope="module")
def milk_capture(tmp_path_factory):
    d = tmp_path_factory.mktemp("milk")
    return synthesize(make_spec(width=48, height=36), d, medium_by_name("Lowfat Milk"), [16],
                      seed=11)


def _with(spec_path, tmp_path, mutate):
    data = yaml.safe_load(spec_path.read_text())
    mutate(data)
    for e in data["images"] + [data["calibration"]["clear_water"]]:
        e["path"] = str(spec_path.parent / e["path"])
    p = tmp_path / "spec.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


def test_spec_priors_bound_the_fit(milk_capture, tmp_path):
    """A prior range for g that excludes the truth (0.93) keeps the MAP inside it; the bounds
    used are reported in results.json."""
    spec = _with(milk_capture, tmp_path, lambda d: d.update(priors={"g": [0.0, 0.5]}))
    res = fit(spec, tmp_path / "o", FitOptions(mcmc=False, workers=1), report=False)
    for ch in "RGB":
        assert 0.0 <= res["parameters"]["g"][ch]["map"] <= 0.5 + 1e-9
    assert res["priors"]["bounds"]["atanh_g"][1] == pytest.approx(np.arctanh(0.5))
    assert res["priors"]["spec_overrides"] == {"g": [0.0, 0.5]}


def test_background_offset_is_recovered(milk_capture, tmp_path):
    """Synthetic: a constant offset added to the photo is found by the background nuisance
    parameter (MAP within 20 %), and the fit with it has chi2/pixel ~1 while the fit without it
    does not (negative control)."""
    offset = 2e-4  # ~6 read-noise sigmas
    img_path = milk_capture.parent / "images" / "medium_00_16ml.tiff"
    img = tifffile.imread(img_path) + np.float32(offset)
    shifted = tmp_path / "shifted.tiff"
    tifffile.imwrite(shifted, img, photometric="rgb")
    spec = _with(milk_capture, tmp_path, lambda d: (d["images"][0].update(path=str(shifted)),
                                                    d.update(priors={"background_sd": 5e-4})))
    res = fit(spec, tmp_path / "bg", FitOptions(mcmc=False, workers=1, background=True),
              report=False)
    plain = fit(_with(milk_capture, tmp_path, lambda d: d["images"][0].update(path=str(shifted))),
                tmp_path / "plain", FitOptions(mcmc=False, workers=1), report=False)
    for ch in "RGB":
        d = res["diagnostics"]["channels"][ch]
        assert d["chi2_per_pixel"] < 1.1
        assert plain["diagnostics"]["channels"][ch]["chi2_per_pixel"] > 1.3
    import numpy as np_
    s = np_.load(tmp_path / "bg" / "samples.npz")
    names = list(s["names"])
    for ch in "RGB":
        bg = s[f"{ch}/map_unconstrained"][names.index("background")]
        assert bg == pytest.approx(offset, rel=0.2)


def test_water_absorption_adds_to_kappa_a_at_every_concentration():
    """The clear water's own absorption enters as kappa_a = c kappa_a_liquid + kappa_a_water."""
    spec = make_spec(width=32, height=24)
    model = SingleScattering(spec, None, channels=("G",))
    data = np.zeros(spec.camera.height * spec.camera.width).reshape(24, 32)
    obs = [Observation(model, data, np.ones_like(data, bool), 0.01)]
    space = ParameterSpace()
    u = space.to_vector(ChannelParams(2.0, 0.9, 0.8))
    with_water = ChannelProblem(obs, space, 1.0, (1e-5, 1e-9), water_kappa_a=3e-3).render(u)[0]
    direct = model.render(0.01 * 0.2 + 3e-3, 0.01 * 1.8, 0.8, 1.0)[..., 0]
    np.testing.assert_allclose(with_water, direct, rtol=1e-12)

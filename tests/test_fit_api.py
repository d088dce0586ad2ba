"""The fitter's seam (issue 14): ``fitmedia.fit(capture, model=..., options=...)`` takes any
ForwardModel and returns one FitResult, which results.json is written from and read back into.

The stub forward model is a test double with a known analytic image, so the fit's answer
is checked against the parameters the test drew the image from (a synthetic round trip
through a model that shares no code with fitmedia's physics)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import yaml

import fitmedia
from fitmedia.errors import InputError
from fitmedia.images.io import write_float_tiff
from fitmedia.inference.result import FitOptions, FitResult
from fitmedia.spec import load_spec
from conftest import geometry_dict

W, H = 32, 24
PATH_MM = 100.0  # the stub's light path: optical depth kappa_t * PATH_MM
CONCENTRATION = 1e-3
TRUTH = {"kappa_t": 8.0, "albedo": 0.85, "g": 0.6}  # undiluted, 1/mm; one channel (G)
BRIGHTNESS = 1.0
NOISE = (1e-4, 1e-6)  # gain, read variance


class StubBlob:
    """A ForwardModel test double: a 3 px bump at (8, 12) that the medium attenuates by
    exp(-kappa_t L) (the directly seen light) and a Gaussian glow at (20, 12) of amplitude
    brightness kappa_s L exp(-kappa_t L) and width 1.5 + 4 (1 - g) px: kappa_t, kappa_s and g
    each change the image their own way, so all three are recoverable."""

    name = "stub-blob"

    def __init__(self, spec, image_index, channels=("G",)):
        self.channels = tuple(channels)
        self.shape = (H, W)
        self.support = np.ones(self.shape, bool)
        yy, xx = np.mgrid[0:H, 0:W]
        self._r2_bump = (xx - 8.0) ** 2 + (yy - 12.0) ** 2
        self._r2_glow = (xx - 20.0) ** 2 + (yy - 12.0) ** 2

    def render(self, kappa_a, kappa_s, g, brightness):
        ka, ks, gg, b = (np.broadcast_to(np.asarray(v, float), (len(self.channels),))
                         for v in (kappa_a, kappa_s, g, brightness))
        att = np.exp(-(ka + ks) * PATH_MM)
        width = 1.5 + 4.0 * (1.0 - gg)
        bump = np.exp(-self._r2_bump[..., None] / (2 * 1.5 ** 2))
        glow = np.exp(-self._r2_glow[..., None] / (2 * width ** 2))
        return b * att * (bump + ks * PATH_MM * glow)


def _capture(tmp_path, rng) -> str:
    """A one-image capture (channel G only) whose image is the stub's at TRUTH plus the noise
    model's noise; the spec's brightness is given, so no clear-water calibration is needed."""
    geo = geometry_dict(width=W, height=H)
    geo["light"]["radiance"] = [BRIGHTNESS] * 3
    geo.update(channels=["G"], noise={"gain": NOISE[0], "read_var": NOISE[1]},
               images=[{"path": "image.tiff", "exposure_s": 1.0,
                        "concentration": CONCENTRATION}])
    spec_path = tmp_path / "capture.yaml"
    spec_path.write_text(yaml.safe_dump(geo))
    spec = load_spec(spec_path, require_images=False)  # the image is written below
    kt = TRUTH["kappa_t"] * CONCENTRATION
    ks = kt * TRUTH["albedo"]
    wka = spec.water_kappa_a[1]
    mean = StubBlob(spec, 0).render(kt - ks + wka, ks, TRUTH["g"], BRIGHTNESS)[..., 0]
    noisy = mean + rng.normal(0.0, np.sqrt(NOISE[0] * mean + NOISE[1]))
    write_float_tiff(tmp_path / "image.tiff", np.repeat(noisy[..., None], 3, axis=2))
    return str(spec_path)


def test_fit_recovers_a_stub_forward_models_parameters(tmp_path, seed):
    """The seam: ``fitmedia.fit(capture, model=StubBlob)`` fits the stub (not fitmedia's own
    physics) and recovers the parameters the image was drawn from, within 4 posterior sd
    (the sampler's own spread: the reference is the truth of this synthetic round trip).
    The result's results.json is FitResult.to_json(), and reads back equal."""
    rng = np.random.default_rng(seed)
    spec = _capture(tmp_path, rng)
    opts = FitOptions(seed=seed % 2**31, max_steps=1500, n_tau=20, workers=1, progress=False,
                      global_evals=100)
    res = fitmedia.fit(spec, model=StubBlob, options=opts, out=tmp_path / "fit", report=False)
    assert isinstance(res, FitResult)
    assert res.model == res.model_used == "stub-blob"
    assert res.run_identity["model"] == "stub-blob"
    assert res.channels == ("G",) and res.statistic == "median"
    for q, truth in TRUTH.items():
        s = res.samples[f"G/{q}"]
        z = (np.median(s) - truth) / np.std(s)
        assert abs(z) < 4, (q, truth, res.value(q, "G"), np.std(s))
        lo, hi = res.interval(q, "G")
        assert lo < res.value(q, "G") < hi
    # the fit judged the stub's images: chi2/pixel near 1 for the model the data came from
    assert 0.8 < res.diagnostics["channels"]["G"]["chi2_per_pixel"] < 1.25
    assert res.ok
    written = json.loads((tmp_path / "fit" / "results.json").read_text())
    assert written == res.to_json()
    assert list(written) == list(res.to_json())
    back = FitResult.from_json(tmp_path / "fit", samples=True)
    assert back == res
    assert np.array_equal(back.samples["G/kappa_s"], res.samples["G/kappa_s"])


def test_fit_takes_a_model_instance_and_writes_nothing_without_out(tmp_path, seed):
    """A ForwardModel instance (a capture of one image) is fitted as it is: MAP only, no
    folder written; its MAP agrees with the factory's to the optimiser's precision (the
    same posterior; reference: the same fit through the other door)."""
    spec = _capture(tmp_path, np.random.default_rng(seed))
    opts = FitOptions(mcmc=False, seed=1, workers=1, progress=False, global_evals=100)
    by_instance = fitmedia.fit(spec, model=StubBlob(None, 0, ("R", "G", "B")), options=opts)
    by_factory = fitmedia.fit(load_spec(spec), model=StubBlob, options=opts)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture.yaml", "image.tiff"]
    assert by_instance.statistic == "map" and by_instance.interval("g", "G") is None
    for q in TRUTH:
        assert by_instance.value(q, "G") == pytest.approx(by_factory.value(q, "G"), rel=1e-3)


def test_fit_refuses_what_is_not_a_model(tmp_path, seed):
    """Bad ``model`` / option combinations are InputErrors naming the field, before any work."""
    spec = _capture(tmp_path, np.random.default_rng(seed))
    with pytest.raises(InputError, match="model"):
        fitmedia.fit(spec, model=42)
    with pytest.raises(InputError, match="options.model"):
        fitmedia.fit(spec, model=StubBlob, options=FitOptions(model="full"))
    with pytest.raises(InputError, match="model: 'mitsuba'"):
        fitmedia.fit(spec, model="mitsuba", options=FitOptions(mcmc=False))
    with pytest.raises(InputError, match="options.resume"):
        fitmedia.fit(spec, options=FitOptions(resume=True))


def test_fit_options_are_frozen_and_keyword_only():
    """FitOptions cannot be changed in place or built positionally (a positional call silently
    meant another field when fields were added); the CLI's defaults are FitOptions'."""
    from fitmedia.cli import build_parser

    with pytest.raises(dataclasses.FrozenInstanceError):
        FitOptions().seed = 3
    with pytest.raises(TypeError):
        FitOptions("single")  # type: ignore[misc]
    a = build_parser().parse_args(["fit", "spec.yaml", "--out", "o"])
    d = FitOptions()
    assert (a.seed, a.n_tau, a.max_steps, a.workers, a.model) == \
        (d.seed, d.n_tau, d.max_steps, d.workers, d.model)
    v = build_parser().parse_args(["validate", "--rounds", "1", "--media", "Espresso",
                                   "--out", "o"])
    assert (v.n_tau, v.max_steps) == (d.n_tau, d.max_steps)


def test_fit_result_reads_an_older_results_json_and_keeps_unknown_keys(tmp_path):
    """from_json on a hand-written minimal results.json (CAPTURE_SPEC.md's example, plus a key
    this version does not know): the values read back, missing entries take defaults, and
    to_json writes the unknown key back (reference: the dict written by hand)."""
    doc = {"fitmedia_spec": 1, "model": "single", "units": {"length": "mm", "kappa": "1/mm"},
           "channels": ["R", "G", "B"],
           "parameters": {q: {c: {"map": 0.5, "median": 0.4, "q05": 0.1, "q16": 0.2,
                                  "q84": 0.6, "q95": 0.8} for c in "RGB"}
                          for q in ("kappa_a", "kappa_s", "g", "kappa_t", "albedo")},
           "diagnostics": {"converged": True}, "from_the_future": [1, 2]}
    (tmp_path / "results.json").write_text(json.dumps(doc))
    r = FitResult.from_json(tmp_path / "results.json")
    assert r.value("g", "B") == 0.4 and r.value("g", "B", "map") == 0.5
    assert r.interval("kappa_s", "R") == (0.1, 0.8) and r.interval("kappa_s", "R", 0.68) == (0.2, 0.6)
    assert r.converged is True and r.ok and r["channels"] == ["R", "G", "B"]
    assert r.to_json()["from_the_future"] == [1, 2]
    for k, v in doc.items():
        assert r.to_json()[k] == v
    (tmp_path / "bad.json").write_text("[1]")
    with pytest.raises(InputError, match="bad.json"):
        FitResult.from_json(tmp_path / "bad.json")
    with pytest.raises(InputError, match="not found"):
        FitResult.from_json(tmp_path / "nothing")

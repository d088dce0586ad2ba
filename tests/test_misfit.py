"""The misfit guard (fitmedia.trust, docs/results.md "trust"): chi2/pixel at the MAP against
what the noise model allows; fires on a full-transport milk capture fitted with single
scattering, silent on a single-scattering one; `fitmedia fit` exits 1 when it fires."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import norm

from fitmedia import trust
from fitmedia.cli import main

from conftest import geometry_dict

DATA = Path(__file__).resolve().parent / "data" / "misfit"


def test_chi2_limit_against_wilson_hilferty():
    """The noise-only part of the limit against the Wilson-Hilferty approximation of the chi2
    quantile (independent of scipy's chi2.isf; accurate to ~1e-3 relative for N >= 100)."""
    z = norm.isf(trust.CHI2_TAIL)
    for n in (100, 480, 1080, 30000):
        wh = (1 - 2 / (9 * n) + z * np.sqrt(2 / (9 * n))) ** 3
        assert trust.chi2_limit(n) - trust.MODEL_ERROR_ALLOWANCE == pytest.approx(wh, rel=2e-3)


def test_guard_silent_on_noise_fires_on_misfit(rng):
    """Simulated standardised residuals: 20000 noise-only chi2/pixel draws of N = 480 pixels
    never reach the limit (their largest is ~1.3, the limit 1.44); residuals whose
    variance is 1.7 times the noise model's (a model error) exceed it."""
    n = 480
    noise_only = rng.chisquare(n, size=20000) / n
    assert noise_only.max() < trust.chi2_limit(n)
    assert trust.misfit(float(noise_only.max()), n)["ok"] is True
    assert trust.misfit(float(np.mean((1.7 ** 0.5 * rng.standard_normal(n)) ** 2)), n)["ok"] \
        is False
    assert trust.misfit(float("nan"), n)["ok"] is None


def _results(chi2_images: list[float], n: int = 500) -> tuple[dict, list[dict]]:
    images = [{"channels": {"G": {"chi2_per_pixel_map": c, "n_pixels_used": n}}}
              for c in chi2_images]
    chans = {"G": {"chi2_per_pixel": float(np.mean(chi2_images)), "n_pixels": n * len(images),
                   "optical_depth_regime": "informative", "kappa_s_g_separable": True}}
    return chans, images


def test_series_with_one_bad_image():
    """A dilution series whose images pass together but one fails on its own (chi2/pixel 1.2
    times its limit in image 2 of 4): the channel fails, the reason names image 2, and the
    channel's optical_depth_regime is no longer 'informative'."""
    from fitmedia.inference.results import assess

    chans, images = _results([1.0, 1.0, 1.2 * trust.chi2_limit(500), 1.0])
    assert trust.misfit(chans["G"]["chi2_per_pixel"], 2000)["ok"] is True  # the total passes
    verdict = assess({"kappa_s_reduced": {"G": {"map": 1.0}}}, chans, images, "single")
    assert verdict["ok"] is False
    assert "(worst: image 2)" in verdict["reasons"][0] and "channel G" in verdict["reasons"][0]
    assert chans["G"]["optical_depth_regime"] is None
    chans, images = _results([1.0, 1.02])
    verdict = assess({"kappa_s_reduced": {"G": {"map": 1.0}}}, chans, images, "single")
    assert verdict["ok"] is True and verdict["reasons"] == []
    assert chans["G"]["optical_depth_regime"] == "informative"
    chans, images = _results([9.0])
    verdict = assess({"kappa_s_reduced": {"G": {"map": 1.0}}}, chans, images, "single",
                     robust=True)
    assert verdict["ok"] is False and "with --robust, outliers" in verdict["reasons"][0]


def test_unconverged_sampler_is_a_reason():
    """A channel whose sampler stopped at its step cap (``converged`` false) makes the verdict
    not ok, with a reason naming the channel, the sampler's own reason and how to continue;
    a converged channel, or a MAP-only fit (no ``converged`` key), gives none.  The same on
    real chains cut short: tests/test_resume.py and tests/test_faults.py."""
    from fitmedia.inference.results import assess

    params = {"kappa_s_reduced": {"G": {"map": 1.0}}}
    chans, images = _results([1.0])
    chans["G"].update(converged=False, reason="step cap 300 reached at 2.1 tau")
    verdict = assess(params, chans, images, "single")
    assert verdict["ok"] is False and len(verdict["reasons"]) == 1
    assert "sampler of channel G did not converge (step cap 300 reached at 2.1 tau)" in \
        verdict["reasons"][0] and "--resume --max-steps" in verdict["reasons"][0]
    assert verdict["reason_kinds"] == ["sampler"]
    # with a misfit as well: one kind per reason, in the reasons' order, plain strings in JSON
    chans["G"]["chi2_per_pixel"] = 40.0
    both = assess(params, chans, images, "single")
    assert both["reason_kinds"] == ["misfit", "sampler"], both["reason_kinds"]
    assert "does not describe the images" in both["reasons"][0]
    assert json.loads(json.dumps(both))["reasons"] == both["reasons"]
    chans["G"]["chi2_per_pixel"] = 1.0
    chans["G"]["converged"] = True
    assert assess(params, chans, images, "single")["ok"] is True
    del chans["G"]["converged"]
    assert assess(params, chans, images, "single")["ok"] is True


def test_fit_exits_1_when_the_guard_fires(monkeypatch, tmp_path, capsys):
    """`fitmedia fit` prints the reason and exits 1 when results' trust is not ok, 0 when it
    is (the fit itself replaced by a stub returning a results dict)."""
    import fitmedia.pipeline

    chans, images = _results([40.0])
    from fitmedia.inference.results import assess

    res = {"channels": ["G"], "diagnostics": {"channels": chans},
           "parameters": {q: {"G": {"map": 0.5}} for q in
                          ("kappa_a", "kappa_s", "g", "kappa_t", "albedo", "kappa_s_reduced")}}
    res["trust"] = assess(res["parameters"], chans, images, "single")
    monkeypatch.setattr(fitmedia.pipeline, "fit", lambda *a, **k: res)
    code = main(["fit", "x.yaml", "--out", str(tmp_path), "--no-mcmc", "--no-report"])
    err = capsys.readouterr().err
    assert code == 1
    assert "does not describe the images: chi2/pixel 40" in err and "Traceback" not in err
    res["trust"] = assess(res["parameters"], *_results([1.0]), "single")
    assert main(["fit", "x.yaml", "--out", str(tmp_path), "--no-mcmc", "--no-report"]) == 0


@pytest.mark.slow
@pytest.mark.parametrize("capture, fires", [("milk_full", True), ("milk_mitsuba_ss", False)])
def test_guard_on_full_transport_capture(capture, fires, tmp_path, capsys):
    """Lowfat Milk 16 ml in 23 l, 32 x 24 px, channel G, made by Mitsuba 3 at 1024 spp
    (tests/data/misfit/README.md): with all orders of scattering (multiple scattering ~60 % of
    the glow, docs/multiple_scattering.md) the single-scattering fit's chi2/pixel is far above
    the limit and `fitmedia fit` exits 1; the same scene rendered by Mitsuba with scattering
    orders 0 and 1 only, the same spp (so the same kind of Monte Carlo noise), passes: the
    guard fires because multiple scattering is missing from the model, not because of the
    render's noise."""
    spec = tmp_path / capture
    shutil.copytree(DATA / capture, spec)
    code = main(["fit", str(spec / "capture.yaml"), "--out", str(tmp_path / "fit"), "--no-mcmc",
                 "--quiet", "--workers", "1", "--model", "single"])
    out = capsys.readouterr()
    res = json.loads((tmp_path / "fit" / "results.json").read_text())
    page = (tmp_path / "fit" / "report.html").read_text()
    # the report names the folder the fit ends in, not the staging folder it was written in
    assert f"<code>{tmp_path / 'fit'}</code>" in page and ".partial" not in page
    assert code == (1 if fires else 0), out.err
    assert res["trust"]["ok"] is (not fires)
    check = res["trust"]["misfit"]["G"]
    ms = res["diagnostics"]["channels"]["G"]["multiple_scattering"]
    assert 0.4 < ms["share"][0] < 0.8  # ~60 % of milk's glow (docs/multiple_scattering.md)
    if fires:
        assert check["chi2_per_pixel"] > 3 * check["limit"]
        assert "does not describe the images" in out.err
        assert res["diagnostics"]["channels"]["G"]["optical_depth_regime"] is None
        assert any("a likely cause of the misfit" in n for n in res["trust"]["notes"])
    else:
        assert check["chi2_per_pixel"] < check["limit"]
        # the single-scattering check: at 480 px the guard could see the term (trust.py)
        assert ms["chi2_excess_if_present"] > trust.MS_DETECT_FACTOR * (check["limit"] - 1)
        assert any("the misfit guard can see it here" in n for n in res["trust"]["notes"])


def _ms_chans(share: float, excess: float, chi2: float = 1.0, sd: float | None = 0.01) -> dict:
    return {"G": {"chi2_per_pixel": chi2, "n_pixels": 480, "model_used": "single",
                  "multiple_scattering": {"share": [share], "chi2_excess_if_present": excess,
                                          "kappa_s_log_sd": sd}}}


def test_single_scattering_check_rule():
    """trust.single_scattering_checks on made-up diagnostics, against its stated rule (480
    pixels: the guard's room above 1 is 0.44; kappa_s known to 1 %): a share above AUTO_SHARE
    with a predicted rise below MS_DETECT_FACTOR times the room is a reason, and so it is
    without a stated uncertainty; with the bias bound (MS_BIAS_PER_SHARE x share) inside a
    wider sd, a note; with the rise above the margin, a note; with the misfit guard fired, a
    note naming the cause; on a capture that declares a single-scattering render, a note; a
    share at or below AUTO_SHARE, a --model full channel or a fit
    without the check, nothing."""
    from fitmedia.inference.full import AUTO_SHARE

    def run(chans):
        checks, _ = trust.misfit_checks(chans, [], "single")
        return trust.single_scattering_checks(chans, checks)

    room = trust.chi2_limit(480) - 1
    blind = 0.9 * trust.MS_DETECT_FACTOR * room
    reasons, notes = run(_ms_chans(0.3, blind))
    assert len(reasons) == 1 and not notes
    assert "30 % of the glow in channel G" in reasons[0] and "cannot show" in reasons[0]
    assert "up to about 24 %" in reasons[0] and "(1 %)" in reasons[0]
    assert len(run(_ms_chans(0.3, blind, sd=None))[0]) == 1
    reasons, notes = run(_ms_chans(0.3, blind, sd=1.01 * trust.MS_BIAS_PER_SHARE * 0.3))
    assert not reasons and "within kappa_s's uncertainty" in notes[0]
    reasons, notes = run(_ms_chans(0.3, 1.1 * trust.MS_DETECT_FACTOR * room))
    assert not reasons and "can see it here" in notes[0]
    reasons, notes = run(_ms_chans(0.3, 0.0, chi2=10.0))
    assert not reasons and "a likely cause of the misfit" in notes[0]
    declared = _ms_chans(0.3, blind)
    declared["G"]["multiple_scattering"]["capture_declared_single_scattering_render"] = True
    reasons, notes = run(declared)
    assert not reasons and "declares a single-scattering render" in notes[0]
    for chans in (_ms_chans(AUTO_SHARE, 0.0), _ms_chans(0.3, None)):
        assert run(chans) == ([], [])
    full = _ms_chans(0.3, 0.0)
    full["G"]["model_used"] = "full"
    assert run(full) == ([], [])


@pytest.mark.slow
def test_single_scattering_check_where_the_guard_is_blind(tmp_path, capsys):
    """Espresso 8 ml in 23 l (the 2006 dilution) at 16 x 12 px, channel G, rendered with all
    orders of scattering (``synth --model hybrid``: the analytic orders 0-1 plus fitmedia's
    multiple-scattering term, 1024 paths): the term is ~25 % of the glow, but at 192 pixels
    chi2/pixel at the single-scattering MAP stays within the misfit guard's limit, so the
    guard alone passes a fit whose values are biased by the missing light.  The single-
    scattering check finds the guard blind there (the term would raise chi2/pixel by much
    less than the guard's room) and ``fitmedia fit --model single`` exits 1 with that reason.
    Control: the 480-pixel milk capture above, where the guard can see the term, exits 0."""
    geo = tmp_path / "geo.yaml"
    geo.write_text(json.dumps({**geometry_dict(16, 12), "channels": ["G"]}))
    assert main(["synth", str(geo), "--medium", "Espresso", "--ml", "8", "--model", "hybrid",
                 "--spp", "1024", "--seed", "303", "--out", str(tmp_path / "cap")]) == 0
    import yaml  # synth declares what rendered the images (docs/spec.md: synthetic)

    assert yaml.safe_load((tmp_path / "cap" / "capture.yaml").read_text())["synthetic"] == \
        {"model": "hybrid"}
    code = main(["fit", str(tmp_path / "cap" / "capture.yaml"), "--out", str(tmp_path / "fit"),
                 "--no-mcmc", "--quiet", "--no-report", "--workers", "1", "--model", "single"])
    err = capsys.readouterr().err
    res = json.loads((tmp_path / "fit" / "results.json").read_text())
    assert res["trust"]["misfit"]["G"]["ok"] is True  # the guard alone would pass it
    ms = res["diagnostics"]["channels"]["G"]["multiple_scattering"]
    assert 0.1 < ms["share"][0] < 0.5
    assert code == 1, err
    assert "these images cannot show whether it is there" in err and "Traceback" not in err


def test_fit_many_exit_code_carries_the_verdict(monkeypatch, tmp_path, capsys):
    """`fitmedia fit-many`: 1 when some capture's guard fired (its reason on stderr), 0 when
    none did, 2 when one failed (fit_many itself replaced by a stub returning records)."""
    import fitmedia.batch

    bad = {"ok": False, "reasons": ["the model (single) does not describe the images: x"]}
    recs = [{"name": "a", "out": "o/a", "status": "done", "trust": {"ok": True, "reasons": []}},
            {"name": "b", "out": "o/b", "status": "done", "trust": bad}]
    monkeypatch.setattr(fitmedia.batch, "fit_many", lambda *a, **k: recs)
    argv = ["fit-many", "a.yaml", "b.yaml", "--out", str(tmp_path), "--no-report"]
    assert main(argv) == 1
    assert "b: the model (single) does not describe the images" in capsys.readouterr().err
    recs[1]["trust"] = {"ok": True, "reasons": []}
    assert main(argv) == 0
    recs.append({"name": "c", "out": "o/c", "status": "failed", "error": "spec: bad"})
    assert main(argv) == 2


def test_thin_and_dense_channels_get_a_note():
    """A channel too thin (or too dense) in every image gets a plain-words note in
    results.json's trust, which `fitmedia fit` prints, naming its optical depths and what
    follows the prior there; an informative one gets none; the verdict (exit code) is not
    changed by it."""
    from fitmedia.inference.results import assess

    for regime, depth, words in (("thin", 0.062, "too dilute"), ("dense", 14.0, "too dense")):
        chans, images = _results([1.0])
        chans["G"]["optical_depth_regime"] = regime
        images[0]["channels"]["G"]["optical_depth_light_to_wall"] = depth
        verdict = assess({"kappa_s_reduced": {"G": {"map": 1.0}}}, chans, images, "single")
        assert verdict["ok"] is True and verdict["reasons"] == []
        (note,) = verdict["notes"]
        assert words in note and "channel G" in note and f"{depth:.2g}" in note
    chans, images = _results([1.0])
    assert assess({"kappa_s_reduced": {"G": {"map": 1.0}}}, chans, images, "single")["notes"] == []

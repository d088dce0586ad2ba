"""The HTML report: built from a real (tiny) fit output, it shows the table values in 1/mm
and 1/m, a corner plot per channel, the data/model/residual images and the sampler
diagnostics; a MAP-only fit still gives a report; missing files raise InputError."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.special import expit

from conftest import geometry_dict
from fitmedia.errors import InputError
from fitmedia.inference.fit import FitOptions
from fitmedia.medium import Medium
from fitmedia.pipeline import fit
from fitmedia.report import write_report
from fitmedia.report.html import format_estimate
from fitmedia.spec import parse_spec
from fitmedia.synth import synthesize

IMG_TAG = re.compile(r"<img [^>]*src=\"data:image/png;base64,")


@pytest.fixture(scope="module")
def fit_outputs(tmp_path_factory) -> dict[str, Path]:
    """A tiny synthetic capture fitted twice: with the sampler and MAP only (no report)."""
    root = tmp_path_factory.mktemp("report")
    seed = 7
    spec = parse_spec(geometry_dict(width=40, height=30), require_images=False)
    medium = Medium([2e-3, 4e-3, 8e-3], [1.0, 1.2, 1.5], [0.8, 0.8, 0.8])
    spec_path = synthesize(spec, root / "synth", medium, [200.0], seed=seed, medium_name="test")
    opts = dict(max_steps=60, n_tau=5, global_evals=100, workers=1, progress=False, seed=seed)
    fit(spec_path, root / "mcmc", FitOptions(**opts), report=False)
    fit(spec_path, root / "map", FitOptions(mcmc=False, **opts), report=False)
    return {"mcmc": root / "mcmc", "map": root / "map"}


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.h5", "report.html"))
    return dst


def _cells(text: str, ch: str, quantity: str, unit: str) -> list[str]:
    """The cells of the estimates table's row of one channel, quantity and unit."""
    m = re.search(rf'<tr[^>]*data-channel="{ch}" data-quantity="{quantity}" '
                  rf'data-unit="{re.escape(unit)}">(.*?)</tr>', text, re.S)
    assert m, f"no table row for {ch} {quantity} {unit}"
    return re.findall(r'<td class="num">(.*?)</td>', m.group(1))


def test_report_with_samples(fit_outputs, tmp_path):
    out = _copy(fit_outputs["mcmc"], tmp_path / "fit")
    results = json.loads((out / "results.json").read_text())
    path = write_report(out)
    assert path == out / "report.html" and path.is_file()
    text = path.read_text(encoding="ascii")
    assert text.startswith("<!DOCTYPE html>") and text.rstrip().endswith("</html>")
    # self-contained: no external assets
    assert not re.search(r'(src|href)="(?!data:)', text)

    # the median kappa_s of channel G, as formatted in the table, in 1/mm and in 1/m
    ks = results["parameters"]["kappa_s"]["G"]
    per_mm = format_estimate(ks)
    per_m = format_estimate(ks, 1000.0)
    assert float(per_mm["estimate"]) == pytest.approx(ks["median"], rel=1e-2)
    assert float(per_m["estimate"]) == pytest.approx(1000 * ks["median"], rel=1e-2)
    row_mm = _cells(text, "G", "kappa_s", "1/mm")
    row_m = _cells(text, "G", "kappa_s", "1/m")
    assert row_mm[0] == per_mm["estimate"] and row_m[0] == per_m["estimate"]
    assert row_mm[1] == per_mm["q68"] and row_mm[2] == per_mm["q90"]
    lo, hi = (float(x) for x in row_m[1].split("&ndash;"))
    assert lo == pytest.approx(1000 * ks["q16"], rel=1e-2)
    assert hi == pytest.approx(1000 * ks["q84"], rel=1e-2)
    assert "undiluted liquid (concentration 1)" in text

    # a corner plot per channel and one data/model/residual figure per image
    n_images = len(results["images"])
    # and the geometry preview (fitmedia.preview.report_section: the spec is reachable here)
    assert len(IMG_TAG.findall(text)) == len(results["channels"]) + n_images + 1
    assert 'alt="geometry preview"' in text
    for ch in results["channels"]:
        assert f'alt="corner plot channel {ch}"' in text

    # header and diagnostics
    diag = results["diagnostics"]
    assert results["name"] in text and results["spec"] in text
    assert "Sampler diagnostics" in text
    assert ("yes" if diag["converged"] else '<span class="bad">NO</span>') in text
    for info in diag["channels"].values():
        for name in info["autocorr_time"]:
            assert f"<code>{name}</code>" in text
        assert f">{info['n_samples']}<" in text
        assert f">{info['burn_in']}<" in text


def test_report_flags_and_notes(fit_outputs, tmp_path):
    out = _copy(fit_outputs["map"], tmp_path / "fit")  # MAP only: quicker, same flags
    results = json.loads((out / "results.json").read_text())
    results["notes"] = ["image 0: 12 pixels saturated <and masked>"]
    results["diagnostics"]["channels"]["B"]["g_constrained"] = False
    results["diagnostics"]["channels"]["B"]["kappa_s_consistent_with_zero"] = True
    results["diagnostics"]["channels"]["R"]["kappa_a_upper_limit_only"] = True
    results["diagnostics"]["channels"]["R"]["optical_depth_regime"] = "thin"
    results["diagnostics"]["channels"]["G"]["optical_depth_regime"] = "dense"
    results["diagnostics"]["channels"]["G"]["g_modes"] = [{"g_map": 0.56, "weight": 0.855},
                                                          {"g_map": -0.67, "weight": 0.145}]
    results["diagnostics"]["channels"]["B"]["g_modes"] = [{"g_map": 0.56, "weight": 0.997},
                                                          {"g_map": -0.66, "weight": 0.003}]
    (out / "results.json").write_text(json.dumps(results))
    text = write_report(out).read_text(encoding="ascii")
    assert "too dilute: optical depth light-to-wall below 0.1" in text
    assert "too dense: optical depth light-to-wall above 10" in text
    assert "image 0: 12 pixels saturated &lt;and masked&gt;" in text
    assert "g unconstrained: the medium hardly scatters in this channel" in text
    assert "consistent with zero" in text
    assert "read its q95 as an upper limit" in text
    assert ("g &asymp; 0.56 with probability 0.855, g &asymp; -0.67 with probability 0.145; "
            "the 99 % intervals reach into both") in text
    assert "probability 0.003; the smaller holds &lt; 0.5 %, outside the 99 % intervals" in text
    # no channel said "not separately measured": no row greyed
    assert 'class="alone' not in text and "(not separately measured)" not in text


def test_report_greys_what_is_not_separately_measured(fit_outputs, tmp_path):
    """Where kappa_s and g are not separately measured (results.json kappa_s_g_separable
    false), the estimates table greys kappa_a, kappa_s, g and the albedo of that channel
    (each moves with g along the similarity ridge) and says so, and leaves kappa_t and
    kappa_s' as they are; the other channels are untouched."""
    import re

    out = _copy(fit_outputs["map"], tmp_path / "fit")
    results = json.loads((out / "results.json").read_text())
    results["diagnostics"]["channels"]["G"]["kappa_s_g_separable"] = False
    (out / "results.json").write_text(json.dumps(results))
    text = write_report(out).read_text(encoding="ascii")
    grey = re.findall(r'<tr class="(?:permetre )?alone" data-channel="(\w)" data-quantity="(\w+)"',
                      text)
    assert {c for c, _ in grey} == {"G"}
    assert {q for _, q in grey} == {"kappa_a", "kappa_s", "g", "albedo"}
    assert len(grey) == 6  # kappa_a and kappa_s in 1/mm and 1/m, g and albedo unitless
    assert text.count("(not separately measured)") == 6
    assert "read &kappa;<sub>t</sub> and &kappa;<sub>s</sub>&prime;" in text


def test_kappa_a_upper_limit_flag_follows_its_definition(fit_outputs):
    """results.json's kappa_a_upper_limit_only is true exactly when kappa_a's 90 % interval
    spans more than a decade (q95 > 10 q05), per channel (docs/results.md)."""
    results = json.loads((fit_outputs["mcmc"] / "results.json").read_text())
    for ch, info in results["diagnostics"]["channels"].items():
        ka = results["parameters"]["kappa_a"][ch]
        assert info["kappa_a_upper_limit_only"] is (ka["q95"] > 10 * ka["q05"])


def test_optical_depth_in_results(fit_outputs):
    """results.json's optical depth light-to-wall per image and channel, against a hand
    computation from the fitted kappa_t: concentration x kappa_t x (150 - 30) mm for the
    canonical tank (300 mm deep, bulb at z = 30 mm, no water absorption), and its regime."""
    from fitmedia.regimes import regime

    for kind in ("mcmc", "map"):
        results = json.loads((fit_outputs[kind] / "results.json").read_text())
        for ch, info in results["diagnostics"]["channels"].items():
            kt = results["parameters"]["kappa_t"][ch]
            kt = kt.get("median", kt["map"])
            taus = [im["channels"][ch]["optical_depth_light_to_wall"] for im in results["images"]]
            expect = [im["concentration"] * kt * 120.0 for im in results["images"]]
            assert taus == pytest.approx(expect, rel=1e-9)
            assert info["optical_depth_regime"] == regime(taus)


def test_report_map_only(fit_outputs, tmp_path):
    out = _copy(fit_outputs["map"], tmp_path / "fit")
    results = json.loads((out / "results.json").read_text())
    assert "converged" not in results["diagnostics"]
    text = write_report(out).read_text(encoding="ascii")
    ks = results["parameters"]["kappa_s"]["G"]
    assert _cells(text, "G", "kappa_s", "1/mm") == [format_estimate(ks)["estimate"]]
    per_m = float(_cells(text, "G", "kappa_s", "1/m")[0])
    assert per_m == pytest.approx(1000 * ks["map"], rel=1e-3)
    assert "no corner plots" in text
    # image figures only (the geometry preview, when the spec is reachable from here, aside)
    assert len([t for t in IMG_TAG.findall(text) if "geometry preview" not in t]) == \
        len(results["images"])
    assert "No sampler ran" in text


@pytest.mark.parametrize("missing", ["results.json", "samples.npz", "fit_images.npz"])
def test_report_missing_file(fit_outputs, tmp_path, missing):
    out = _copy(fit_outputs["map"], tmp_path / "fit")
    (out / missing).unlink()
    with pytest.raises(InputError, match=re.escape(missing)) as err:
        write_report(out)
    assert "file not found" in str(err.value) and "not a readable" not in str(err.value)
    assert not (out / "report.html").exists()


@pytest.mark.parametrize("broken", ["results.json", "fit_images.npz"])
def test_report_broken_file(fit_outputs, tmp_path, broken):
    out = _copy(fit_outputs["map"], tmp_path / "fit")
    (out / broken).write_text("{not json")
    with pytest.raises(InputError, match=re.escape(broken) + ": not a readable"):
        write_report(out)


def test_format_estimate():
    # interval-limited decimals, two significant digits of the 68 % width
    e = {"map": 15.4518, "median": 15.44213, "q05": 15.356, "q16": 15.3972, "q84": 15.4824,
         "q95": 15.5034}
    assert format_estimate(e)["estimate"] == "15.442"
    assert format_estimate(e, 1000.0)["estimate"] == "15442"
    # an interval over decades: three significant digits each
    e = {"map": 4.1e-6, "median": 4.02e-4, "q05": 7.31e-6, "q16": 1.74e-5, "q84": 7.38e-3,
         "q95": 0.0219}
    assert format_estimate(e)["q68"] == "1.74e-05 &ndash; 0.00738"
    # an albedo close to 1 shows the digits of 1 - albedo; MAP only has no interval
    assert format_estimate({"map": 0.99999969})["estimate"] == "0.99999969"
    assert format_estimate({"map": np.float64(13.16)})["q90"] == "&mdash;"


def _uniform_half_percentile(x: np.ndarray, albedo: np.ndarray, lo: float, hi: float,
                             pct: float) -> float:
    """The ``pct`` percentile of samples ``x`` under the albedo prior's uniform half alone,
    recomputed here from the stated mixture (docs/inference.md: 0.5 flat in logit albedo on
    [lo, hi] + 0.5 uniform in albedo): weight a (1 - a) / (a(hi) - a(lo)) over the mixture's
    density, and the weighted empirical CDF with numpy's (linear) positions."""
    unif = albedo * (1 - albedo) / (expit(hi) - expit(lo))
    w = unif / (0.5 / (hi - lo) + 0.5 * unif)
    i = np.argsort(x)
    below = np.concatenate([[0.0], np.cumsum(w[i])[:-1]])
    return float(np.interp(pct / 100, below / below[-1], x[i]))


def test_kappa_s_reduced_in_results_and_report(fit_outputs, tmp_path):
    """results.json's kappa_s' against kappa_s (1 - g) recomputed from samples.npz: its median
    exactly, its 90 % interval the envelope of the samples' own and of the samples reweighted
    to the albedo prior's uniform half (recomputed here from the stated prior); the same for
    kappa_t and kappa_a; and the report's row of it; MAP only: the Laplace interval, which
    brackets the MAP, shown beside it."""
    results = json.loads((fit_outputs["mcmc"] / "results.json").read_text())
    s = np.load(fit_outputs["mcmc"] / "samples.npz")
    lo, hi = results["priors"]["bounds"]["logit_albedo"]
    for ch in results["channels"]:
        a = s[f"{ch}/albedo"]
        for q, x in (("kappa_s_reduced", s[f"{ch}/kappa_s"] * (1 - s[f"{ch}/g"])),
                     ("kappa_t", s[f"{ch}/kappa_t"]), ("kappa_a", s[f"{ch}/kappa_a"])):
            e = results["parameters"][q][ch]
            assert e["median"] == pytest.approx(np.median(x), rel=1e-12)
            assert e["q05"] == pytest.approx(min(np.percentile(x, 5), _uniform_half_percentile(
                x, a, lo, hi, 5)), rel=1e-9)
            assert e["q95"] == pytest.approx(max(np.percentile(x, 95), _uniform_half_percentile(
                x, a, lo, hi, 95)), rel=1e-9)
        assert results["parameters"]["kappa_s_reduced"][ch]["source"] == "samples"
    out = _copy(fit_outputs["mcmc"], tmp_path / "mcmc")
    text = write_report(out).read_text(encoding="ascii")
    red = results["parameters"]["kappa_s_reduced"]["G"]
    assert _cells(text, "G", "kappa_s_reduced", "1/mm")[0] == format_estimate(red)["estimate"]
    out = _copy(fit_outputs["map"], tmp_path / "map")
    red = json.loads((out / "results.json").read_text())["parameters"]["kappa_s_reduced"]["G"]
    assert red["source"] == "laplace" and red["q05"] < red["map"] < red["q95"]
    cell = _cells(write_report(out).read_text(encoding="ascii"), "G", "kappa_s_reduced", "1/mm")[0]
    assert cell.startswith(format_estimate(red)["estimate"]) and "Laplace" in cell


def test_report_trust_box(fit_outputs, tmp_path):
    """The trust verdict at the top of the report: a passed check says so with the model's
    name; a failed one (results.json trust.ok false) gives the red box with every reason,
    before the estimates, and the channel's flag names the limit."""
    out = _copy(fit_outputs["map"], tmp_path / "fit")
    results = json.loads((out / "results.json").read_text())
    assert results["trust"]["ok"] is True and results["trust"]["model"] == "single"
    text = write_report(out).read_text(encoding="ascii")
    assert "Misfit check passed" in text and "Do not use these values" not in text
    reason = "the model (single) does not describe the images: chi2/pixel 39 in channel G <x>"
    results["trust"].update(ok=False, reasons=[reason])
    results["trust"]["misfit"]["G"].update(ok=False, limit=1.25)
    results["diagnostics"]["channels"]["G"]["chi2_per_pixel"] = 39.0
    (out / "results.json").write_text(json.dumps(results))
    text = write_report(out).read_text(encoding="ascii")
    assert text.index('class="untrusted"') < text.index("<h2>Estimates</h2>")
    assert "Do not use these values" in text and "Misfit check passed" not in text
    assert "chi2/pixel 39 in channel G &lt;x&gt;" in text
    assert "&chi;&sup2;/pixel = 39, above the 1.25 that the noise model allows" in text


def test_report_shows_the_multiple_scattering_part(fit_outputs, tmp_path):
    """With ms_0 in fit_images.npz (a model with a multiple-scattering term) the image figure
    has five panels per channel (data, model, its single- and multiple-scattering parts,
    residual) and the text says so; without it three."""
    from fitmedia.report.plots import image_figure

    out = _copy(fit_outputs["map"], tmp_path / "fit")
    z = dict(np.load(out / "fit_images.npz"))
    ms = 0.4 * z["model_0"]
    noise = {c: {"gain": 2e-5, "read_var": 1e-9} for c in "RGB"}
    for extra, n in ((None, 3), (ms, 5)):
        fig, _ = image_figure(z["data_0"], z["model_0"], z["valid_0"], ["R", "G", "B"], noise,
                              "t", ms=extra)
        titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
        assert len(titles) == 3 * n
        assert any("multiple scattering" in t for t in titles) is (extra is not None)
    np.savez(out / "fit_images.npz", **z, ms_0=ms)
    text = write_report(out).read_text(encoding="ascii")
    assert "single- and multiple-scattering parts beside it" in text
    # one image figure (the geometry preview, found from here, is the other <img>)
    assert len([t for t in IMG_TAG.findall(text) if "geometry preview" not in t]) == 1


def test_report_multiple_scattering_table_and_full_model_causes(fit_outputs, tmp_path):
    """A full-transport result (results.json diagnostics.channels.G.multiple_scattering, as
    inference/results.py writes it) gets its own table with the share and its error, the
    refreshes, the seed shift, the restart's log posterior and a misfit's scan in words, not a
    raw dict; an untrusted full-model result
    names the term's Monte Carlo error as a cause and does not tell the user to switch to
    the model that was already used."""
    out = _copy(fit_outputs["map"], tmp_path / "fit")
    results = json.loads((out / "results.json").read_text())
    results["model_used"] = "full"
    results["diagnostics"]["channels"]["G"].update(model_used="full", multiple_scattering={
        "share": [0.6123], "share_se": [0.0123], "share_at_single_scattering_map": [0.55],
        "refreshes": 3, "converged": True, "moves_sd": [2.0, 0.4, 0.05], "seed_shift_sd": 3.25,
        "term_sd": {"log_kappa_t": 0.0166, "logit_albedo": 0.82, "atanh_g": 0.0114},
        "restart_shift_sd": 7.31, "restart_values": {"kappa_t": 14.72, "g": 0.887},
        "restart_delta_log_posterior": -3.125, "misfit_scan": {
            "rows": [], "chi2_per_pixel_before": 2.834, "chi2_per_pixel_after": 1.043,
            "delta_log_posterior": 5000.0, "used": True},
        "final_paths": 4096, "final_move": {"kappa_t": 0.0126, "g": 0.0069}, "final_move_sd": 0.81})
    results["trust"].update(ok=False, reasons=["the multiple-scattering term's own Monte Carlo "
                                               "error moves the values of channel G by 3.2 sd"])
    (out / "results.json").write_text(json.dumps(results))
    text = write_report(out).read_text(encoding="ascii")
    ms = text[text.index("<h2>Multiple scattering</h2>"):]
    ms = ms[:ms.index("</table>")]
    assert "0.612 &plusmn; 0.012" in ms and "3.25" in ms and "Refreshes settled" in ms
    assert "0.017, 0.011" in ms and "7.31" in ms and "14.72, 0.887" in ms  # jackknife, restart
    assert "4096" in ms and "+1.3 %, +0.007" in ms  # the last refreshes: paths, move
    assert "-3.12" in ms and "2.83, 1.04 (kept)" in ms  # the restart's log posterior, the scan
    assert "{" not in ms and "{'share'" not in text  # no raw dict anywhere
    box = text[text.index('class="untrusted"'):text.index("<h2>Estimates</h2>")]
    assert "Monte Carlo error" in box and "--model full" not in box


def test_residual_panel_uses_the_fits_own_variance(fit_outputs, tmp_path):
    """The residual panel's chi2/pixel, from fit_images.npz's var_0 (the likelihood's variance
    per pixel), equals results.json's chi2_per_pixel (computed by the fit's likelihood, a
    separate code path) per channel; a fit written before var_ existed falls back to the
    scalar noise model and the caption says which sigma is used."""
    from fitmedia.report.plots import image_figure

    out = _copy(fit_outputs["map"], tmp_path / "fit")
    results = json.loads((out / "results.json").read_text())
    z = dict(np.load(out / "fit_images.npz"))
    assert z["var_0"].shape == z["data_0"].shape
    assert np.all(np.isnan(z["var_0"]) == ~z["valid_0"].astype(bool))
    noise = results["noise"]["per_channel"]
    _, chi2 = image_figure(z["data_0"], z["model_0"], z["valid_0"].astype(bool),
                           ["R", "G", "B"], noise, "t", var=z["var_0"])
    for ch in "RGB":
        assert chi2[ch] == pytest.approx(
            results["diagnostics"]["channels"][ch]["chi2_per_pixel"], rel=1e-9)
    assert "the fit's own variance of each pixel" in write_report(out).read_text(encoding="ascii")
    del z["var_0"]
    np.savez(out / "fit_images.npz", **z)
    assert "&sigma;&sup2; = gain&middot;model + read_var" in \
        write_report(out).read_text(encoding="ascii")


def test_trust_causes_left_out_for_an_unconverged_sampler_only():
    """The red box's "common causes" paragraph (misfit causes) is left out when every reason
    is that of a sampler that did not converge (trust.sampler_reasons of the same
    diagnostics), and kept when any other reason is there."""
    from fitmedia.report.html import _trust_causes
    from fitmedia.trust import sampler_reasons

    chans = {"G": {"converged": False, "reason": "step cap 200 reached"}}
    res = {"model": "single", "diagnostics": {"channels": chans},
           "trust": {"reasons": sampler_reasons(chans)}}
    assert _trust_causes(res) == ""
    res["trust"]["reasons"].append("the model (single) does not describe the images")
    assert "Common causes" in _trust_causes(res)
    # since 2026-12-03 results.json names each reason's kind: the report reads those
    res["trust"]["reasons"] = ["any words"]
    res["trust"]["reason_kinds"] = ["sampler"]
    assert _trust_causes(res) == ""
    res["trust"]["reasons"].append("more words")
    res["trust"]["reason_kinds"].append("misfit")
    assert "Common causes" in _trust_causes(res)

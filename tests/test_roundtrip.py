"""Synthetic round trips (synth -> fit) over media of the Narasimhan 2006 table."""

from __future__ import annotations

import pytest

from fitmedia.inference.fit import FitOptions
from fitmedia.medium import medium_by_name
from fitmedia.validate import coverage_table, grid_verdict, round_trip
from conftest import make_spec

# Regular Milk at 60 ml (its 2006 dilution), not 240 ml as until 2026-12-02: the 240 ml
# single-scattering capture at 64 x 48 is black in every channel, which `fit` now refuses
# (errors.BlackImageError; its scores were prior against a fixed truth, not a calibration test)
GRID = [("Lowfat Milk", 8), ("Regular Milk", 60), ("Espresso", 16),
        ("White Grapefruit Juice", 160), ("Head & Shoulders Shampoo", 40)]


def grid_scores(seed: int, out_dir) -> list:
    """The grid's round trips (64 x 48 px; medium k synthesised and fitted with seed + k), one
    folder each in ``out_dir``; their scores (also run by docs/studies/grid_seeds.py)."""
    geometry = make_spec(width=64, height=48)
    scores = []
    for k, (name, ml) in enumerate(GRID):
        scores += round_trip(geometry, medium_by_name(name), [ml], out_dir / f"r{k}",
                             seed=seed + k,
                             options=FitOptions(seed=seed + k, progress=False, workers=2))
    # the grid's 45 values and their documented pass rates are kappa_s, kappa_t and g;
    # kappa_s' (scored since 2026-12-02) is a function of two of them
    return [s for s in scores if s.quantity in ("kappa_s", "kappa_t", "g")]


# ~610 s wall on 2 cores, a third of CI's 30-minute budget: run by `make test-calibration`, not
# by `make test` (docs/testing.md, "Test costs"); its last result is in the stop's closing note
@pytest.mark.slow
@pytest.mark.calibration
def test_round_trip_grid_recovers_truth_within_99_percent(tmp_path, seed):
    """Synthetic round trip: one capture of each medium and dilution of ``GRID`` (8-160 ml in
    23 l; 45 values: 5 media x 3 channels x kappa_s, kappa_t, g), fitted with the sampler,
    every truth inside its 99 % interval in the grid's simultaneous sense
    (:func:`fitmedia.validate.grid_verdict`): no normal score beyond the Bonferroni limit
    (|z| <= 3.69), and at most 3 values outside their own central 99 % interval (the 99 %
    quantile of Binomial(45, 0.01)).  A calibrated method passes with probability 0.989.

    Why not "each value inside its own 99 % interval", the issue's first wording: a calibrated
    method does that with probability 0.99^45 = 0.64.  This test's seed (12345) failed it for
    one value (Head & Shoulders 40 ml R g, truth at posterior quantile 0.0012, z +3.04) through
    stops 5-10, after every cause but chance had been ruled out (docs/validation.md, "The
    round-trip grid").  Against the analytic pass rates (tests/test_grid_verdict.py) the
    criterion fails intervals 0.7x too narrow in 55 % and 0.6x in 90 % of grids; the
    100-round coverage runs of docs/validation.md are the strong check of calibration.

    The data are rendered with 2x2 samples per pixel and fitted with the pixel-centre model
    plus its footprint correction, so the fit is not an inverse crime.  Reduced image size
    (64 x 48) keeps CI time down; the sampler still runs to 50 tau."""
    scores = grid_scores(seed, tmp_path)
    verdict = grid_verdict(scores)
    print("\n" + coverage_table(scores) + "\n" + verdict.describe())
    assert verdict.passed, verdict.describe()


#: largest |MAP - truth| in Laplace standard deviations that the quick round trip accepts
#: (6 values per seed: a calibrated normal error exceeds 4 sd with probability 4e-4)
QUICK_Z = 4.0


def test_round_trip_dilute_milk_quick(tmp_path, seed):
    """Synthetic round trip at small size (60 x 45 px, MAP only): the MAP of kappa_s and g of
    dilute milk is within QUICK_Z of the fit's own Laplace standard deviations of the truth (the
    reference: the synthesised truth).  The old fixed tolerances (kappa_s 3 %, g 0.01) were
    fitted to the default seed.  log kappa_s = log kappa_t + log albedo, so its Laplace sd is
    that of (1, 1 - albedo, 0) . u; milk's unresolved albedo (a plateau in logit albedo, sd up
    to ~200) hardly enters through 1 - albedo.  Measured |z| at seeds 12345 and 1-5: see
    docs/testing.md ("Round-trip tolerances")."""
    import math

    import numpy as np

    from fitmedia.inference.fit import prepare, run_channels
    from fitmedia.spec import load_spec
    from fitmedia.synth import synthesize

    milk = medium_by_name("Lowfat Milk")
    spec = load_spec(synthesize(make_spec(width=60, height=45), tmp_path / "cap", milk, [16],
                                seed=seed))
    fits = run_channels(prepare(spec), FitOptions(mcmc=False, seed=seed, workers=1,
                                                  progress=False), None)
    for k, ch in enumerate("RGB"):
        f = fits[ch]
        u, cov = f["x_map"], f["laplace_cov"]
        assert cov is not None, ch  # the MAP is inside the bounds: the Hessian is definite
        albedo, g = f["map"]["albedo"], f["map"]["g"]
        j = np.zeros(len(u))
        j[0], j[1] = 1.0, 1.0 - albedo
        sd_log_ks = math.sqrt(j @ cov @ j)
        sd_g = math.sqrt(cov[2, 2]) * (1.0 - g * g)  # d tanh(u) / du
        z_ks = math.log(f["map"]["kappa_s"] / milk.kappa_s[k]) / sd_log_ks
        z_g = (g - milk.g[k]) / sd_g
        assert abs(z_ks) < QUICK_Z and abs(z_g) < QUICK_Z, (ch, z_ks, z_g, sd_log_ks, sd_g)
        assert sd_log_ks < 0.1 and sd_g < 0.02, (ch, sd_log_ks, sd_g)  # and they are tight


def test_second_g_mode_is_reported(tmp_path):
    """A thin dilution (White Grapefruit Juice 9 ml in 23 l, 64 x 48 px; round 38 of the
    coverage run in docs/validation.md, seed 1174215102) where forward (truth g = 0.55) and
    backward scattering (g ~ -0.6) fit the data almost equally well: in R and G the best
    candidate of the other sign is reported as ``other_g_mode`` within 5 log-posterior units of
    the MAP (with the sampler both modes are then sampled, see the next test).
    Negative controls: Lowfat Milk 16 ml has its other-sign candidate > 100 units below; a
    dense capture whose posterior hardly depends on g reports no second mode."""
    from fitmedia.spec import load_spec
    from fitmedia.synth import synthesize
    from fitmedia.pipeline import fit
    from conftest import ROOT

    geo = load_spec(ROOT / "capture_specs" / "bulb_64x48.yaml", require_images=False)
    opts = FitOptions(mcmc=False, seed=1, workers=1, progress=False)
    wgj = synthesize(geo, tmp_path / "wgj", medium_by_name("White Grapefruit Juice"), [9],
                     seed=1174215102)
    res = fit(wgj, tmp_path / "fit_wgj", opts, report=False)
    for ch in "RG":
        other = res["diagnostics"]["channels"][ch]["other_g_mode"]
        assert other["g"] * res["parameters"]["g"][ch]["map"] < 0  # the other sign
        assert other["delta_log_posterior"] > -5.0, (ch, other)
    milk = synthesize(geo, tmp_path / "milk", medium_by_name("Lowfat Milk"), [16], seed=1)
    chans = fit(milk, tmp_path / "fit_milk", opts, report=False)["diagnostics"]["channels"]
    assert all(c["other_g_mode"]["delta_log_posterior"] < -100 for c in chans.values())
    # dense Regular Milk (199.1 ml; round 21 of the 8-240 ml run, docs/validation.md): g hardly
    # matters and the other sign's candidate slid to g ~ 1e-7 at 0 units below the MAP, which
    # was reported as a second mode.  It is the MAP's own region, not a mode.
    dense = synthesize(geo, tmp_path / "dense", medium_by_name("Regular Milk"), [199.1],
                       seed=1756264304)
    # this single-scattering capture is black in every channel, which `fit` refuses before
    # fitting (images.checks.check_lit); the fitter's handling of a posterior flat in g is
    # what is guarded here, so the check is bypassed for the second call
    from fitmedia.errors import BlackImageError
    from fitmedia.images import checks
    with pytest.raises(BlackImageError):
        fit(dense, tmp_path / "fit_dense_refused", opts, report=False)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(checks, "check_lit", lambda *a, **k: None)
        chans = fit(dense, tmp_path / "fit_dense", opts, report=False)["diagnostics"]["channels"]
    assert all(c["other_g_mode"] is None for c in chans.values()), chans


@pytest.mark.slow
def test_both_g_modes_are_sampled_and_mixed_by_mass(tmp_path):
    """The same White Grapefruit Juice 9 ml capture with the sampler: where the other mode of
    g is within ``OTHER_MODE_DELTA`` of the MAP, both modes get a chain, and the posterior
    samples are the two chains mixed by the modes' masses (the masses' estimator is checked
    against an analytic two-mode posterior in test_sampler.py).  Checked here: the wiring.
    Each reported mode's share of the samples equals its weight, the weights sum to 1, the
    samples' g has both signs in those shares, the second chain is written as
    posterior_<ch>_mode2.nc, and the report renders.  Channels R and B only (spec
    ``channels``): G's chain is 10x longer (autocorrelation time 233 steps) and adds nothing
    here; B's other mode is 5.1 units below, R's 1.6."""
    import numpy as np

    from fitmedia.inference.fit import OTHER_MODE_DELTA
    from fitmedia.pipeline import fit
    from fitmedia.spec import load_spec
    from fitmedia.synth import synthesize
    from conftest import ROOT

    geo = load_spec(ROOT / "capture_specs" / "bulb_64x48.yaml", require_images=False)
    wgj = synthesize(geo, tmp_path / "wgj", medium_by_name("White Grapefruit Juice"), [9],
                     seed=1174215102)
    wgj.write_text(wgj.read_text() + "channels: [R, B]\n")
    out = tmp_path / "fit"
    res = fit(wgj, out, FitOptions(seed=1, workers=2, progress=False), report=True)
    samples = np.load(out / "samples.npz")
    n_two = 0
    for ch, info in res["diagnostics"]["channels"].items():
        other = info["other_g_mode"]
        close = other is not None and other["delta_log_posterior"] > -OTHER_MODE_DELTA
        assert ("g_modes" in info) == close, (ch, other)
        if not close:
            continue
        n_two += 1
        modes = info["g_modes"]
        assert len(modes) == 2 and abs(sum(m["weight"] for m in modes) - 1) < 1e-12
        assert np.sign(modes[0]["g_map"]) != np.sign(modes[1]["g_map"])
        assert other["sampled"] and other["weight"] == modes[1]["weight"]
        g = samples[f"{ch}/g"]
        assert sum(m["n_samples_used"] for m in modes) == len(g) == info["n_samples"]
        share = np.mean(np.sign(g) == np.sign(modes[1]["g_map"]))
        assert abs(share - modes[1]["weight"]) <= 1.0 / len(g) + 1e-12, (ch, share, modes)
        assert (out / f"posterior_{ch}_mode2.nc").exists()
        assert info["converged"], info["reason"]  # both chains, and weights known to 0.01
    assert n_two == 2
    assert (out / "report.html").exists()

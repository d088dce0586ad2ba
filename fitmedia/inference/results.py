"""results.json (CAPTURE_SPEC.md) and the files beside it: the fit's :class:`FitResult`
(inference/result.py) built from the per-channel fits, posterior samples, data/model images
for the report."""

from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..version import __version__
from ..regimes import regime, tank_optical_depths
from ..spec import CHANNELS
from ..trust import (log_kappa_s_sd, misfit_checks, not_separable_note, reason_kinds,
                     reduced_from_laplace, reduced_from_samples, regime_notes, sampler_reasons,
                     separable, single_scattering_checks, transport_reasons)
from ..util import save_npz, write_json
from .fit import FitOptions, Prepared, prior_g_interval_width
from .params import ALBEDO_UNIFORM_WEIGHT
from .result import QUANTITIES, FitResult
from .summary import kish_ess, summarise, weighted_percentiles


def build_results(prep: Prepared, fits: dict[str, dict], options: FitOptions, *,
                  model: str | None = None) -> FitResult:
    """The :class:`FitResult` of a fit from its per-channel ``fits`` (``fit_channel``'s dicts);
    ``model``: the name of a forward model given to the fitter (else ``options.model``)."""
    spec = prep.spec
    params: dict = {q: {} for q in QUANTITIES}
    chans, taus, samples = {}, {}, {}
    for ch in spec.channels:
        f = fits[ch]
        phys = f["space"].physical_samples(f["samples"]) if "samples" in f else {}
        samples.update({f"{ch}/{q}": v for q, v in phys.items()})
        weights = albedo_weights(f)
        for q in QUANTITIES:
            params[q][ch] = summarise(phys.get(q), f["map"][q], weights)
        # optical depth light-to-wall per image, from the posterior median (else MAP) kappa_t
        kt = params["kappa_t"][ch].get("median", params["kappa_t"][ch]["map"])
        taus[ch] = tank_optical_depths(spec, float(kt), CHANNELS.index(ch))
        chans[ch] = _channel_info(prep, ch, f, phys, params, taus[ch], weights)
    images = _image_records(prep, fits, taus)
    name = model or options.model
    used = [chans[c].get("model_used", name) for c in spec.channels]
    model_used = "full" if "full" in used else ("single" if model is None else name)
    first = fits[spec.channels[0]]
    return FitResult(
        channels=tuple(spec.channels), parameters=params,
        diagnostics=_diagnostics(chans, spec.channels, options.mcmc),
        trust=assess(params, chans, images, model_used, robust=options.robust),
        model=name, model_used=model_used, fitmedia_version=__version__,
        date=datetime.now(timezone.utc).isoformat(timespec="seconds"),
        options={k: getattr(options, k) for k in ("robust", "n_walkers", "n_tau", "max_steps",
                                                  "global_evals", "mcmc")},
        priors=_priors(spec, first["names"], first["space"]), spec=str(spec.source),
        name=spec.name, seed=options.seed,
        calibration={"brightness_source": prep.brightness_source,
                     "brightness": {c: chans[c]["brightness"] for c in spec.channels}},
        noise={"source": prep.noise_source,
               "per_channel": {c: {"gain": g, "read_var": r} for c, (g, r) in prep.noise.items()},
               "per_image": prep.noise_per_image},  # source and values per entry (issue 16)
        images=images, notes=prep.notes, samples=samples or None)


def albedo_weights(f: dict) -> np.ndarray | None:
    """One channel's fit ``f``: the importance weights of its posterior samples under the
    albedo prior's uniform half (:meth:`ParameterSpace.uniform_albedo_weights`); None without
    samples."""
    if "samples" not in f or not len(f["samples"]):
        return None
    return f["space"].uniform_albedo_weights(np.asarray(f["samples"])[:, 1])


def _envelope_info(phys: dict, weights: np.ndarray) -> dict:
    """``diagnostics.channels.<ch>.albedo_prior_envelope``: the effective sample size of the
    reweighted samples and, per quantity, the 90 % interval under the uniform half alone."""
    ess = kish_ess(weights)
    uniform = {q: [float(v) for v in weighted_percentiles(phys[q], weights, (5, 95))]
               for q in QUANTITIES if q in phys}
    return {"uniform_albedo_ess": ess, "uniform_albedo_90": uniform}


def _channel_info(prep: Prepared, ch: str, f: dict, phys: dict, params: dict,
                  taus: tuple[float, ...], weights: np.ndarray | None) -> dict:
    """results.json's ``diagnostics.channels.<ch>``; adds ``kappa_s_reduced`` to ``params``.
    ``weights``: the samples' :func:`albedo_weights`."""
    chi2, n = f["chi2"]
    info = {"map_log_posterior": f["map_logp"], "n_evals_map": f["n_evals"],
            "chi2_per_pixel": chi2 / max(n, 1), "n_pixels": n,
            "brightness_calibrated": prep.brightness[ch],
            "brightness_calibration_rel_sd": prep.brightness_rel_sd.get(ch),
            "brightness": f["map"].get("brightness", prep.brightness[ch]),
            "other_g_mode": f.get("other_g_mode"), "optical_depth_regime": regime(taus)}
    if f.get("map_from_samples"):  # the MAP search had stopped short (fit.map_from_samples)
        info["map_from_samples"] = f["map_from_samples"]
    if "samples" in f:
        info.update(_sampler_info(f, phys, {q: params[q][ch] for q in QUANTITIES}))
        info["albedo_prior_envelope"] = _envelope_info(phys, weights)
    if "model_used" in f:  # --model full / auto (inference/full.py)
        info["model_used"] = f["model_used"]
        info["multiple_scattering"] = {
            "share": f.get("ms_share"), "share_se": f.get("ms_share_se"),
            "share_at_single_scattering_map": f.get("ms_share_single_map"),
            **({"auto_reason": f["auto_reason"]} if "auto_reason" in f else {}),
            **({"spot_scan": f["ms_scan"]} if "ms_scan" in f else {}),
            **({"spot_scan_gain": f["ms_scan_gain"], "spot_scan_best": f["ms_scan_best"],
                "spot_scan_verdict": f["ms_scan_verdict"]} if "ms_scan_gain" in f else {}),
            **({"chi2_excess_if_present": f["ms_chi2_excess"],
                "capture_declared_single_scattering_render": f["ms_declared_single_render"],
                "kappa_s_log_sd": log_kappa_s_sd(phys.get("kappa_s"), f["x_map"],
                                                 f.get("laplace_cov"), f["names"])}
               if "ms_chi2_excess" in f else {}),
            **({"refreshes": f["full_refreshes"], "converged": f["full_converged"],
                "moves_sd": f["full_moves_sd"], "moves_term_units": f.get("full_moves_term"),
                "midpoints": f.get("full_midpoints"),
                "extrapolated": f.get("full_extrapolated"),
                "seed_shift_sd": f["ms_seed_shift_sd"],
                "seed_shift_jackknife_sd": f.get("ms_seed_shift_jackknife_sd"),
                "term_sd": _term_sd(f),
                "offset_sd": _term_sd(f, "ms_offset_cov"),
                "restart_shift_sd": f.get("ms_restart_shift_sd"),
                "restart_values": f.get("ms_restart_values"),
                "restart_adopted": f.get("ms_restart_adopted"),
                "restart_delta_log_posterior": f.get("ms_restart_delta"),
                "restart_delta_seeds": f.get("ms_restart_delta_seeds"),
                "misfit_scan": f.get("ms_misfit_scan"),
                "final_paths": f.get("ms_final_paths"), "final_move": f.get("ms_final_move"),
                "final_move_sd": f.get("ms_final_move_sd"),
                "other_g_mode": f.get("other_g_mode")}
               if f["model_used"] == "full" else {})}
    params.setdefault("kappa_s_reduced", {})[ch], ratio = _reduced(f, phys, weights)
    info.update(kappa_s_reduced_width_ratio=ratio, kappa_s_g_separable=separable(
        ratio, info.get("kappa_s_consistent_with_zero")))
    return info


def _term_sd(f: dict, key: str = "ms_term_cov") -> dict | None:
    """The sd of the values' error from the multiple-scattering term's own Monte Carlo
    realisation (its jackknife, inference/full.py), per coordinate of the sampler (log
    kappa_t, logit albedo, atanh g, ...); None where it could not be measured.  With ``key``
    ``ms_offset_cov``: that of the offset that may remain after the last refreshes
    (inference/full.py: offset_budget)."""
    cov = f.get(key)
    if cov is None:
        return None
    return {n: float(np.sqrt(max(v, 0.0))) for n, v in zip(f["names"], np.diag(cov))}


def _sampler_info(f: dict, phys: dict, p: dict) -> dict:
    """One channel's sampler diagnostics (``p``: its parameter summaries by quantity)."""
    u, space = f["samples"], f["space"]
    near = (u < space.lower + 0.02 * (space.upper - space.lower)) | \
           (u > space.upper - 0.02 * (space.upper - space.lower))
    info: dict = {"at_prior_bound": [n for n, frac in zip(space.names, near.mean(0))
                                     if frac > 0.05]}
    if "brightness" in phys:
        info["brightness_posterior"] = summarise(phys["brightness"], f["map"]["brightness"])
    g90 = p["g"]["q95"] - p["g"]["q05"]
    ks, ka = p["kappa_s"], p["kappa_a"]
    # kappa_a resolved: its 90 % interval spans less than a decade; else its shape is
    # the prior's tail and only q95 (an upper limit) is a measurement
    info["kappa_a_upper_limit_only"] = bool(not ka["q05"] > 0.1 * ka["q95"])
    names = f["names"]
    info.update(converged=bool(f["converged"]), reason=f["reason"], n_steps=f["n_steps"],
                autocorr_time=dict(zip(names, np.asarray(f["tau"]).tolist())),
                acceptance_fraction=f["acceptance"], burn_in=f["burn"], thin=f["thin"],
                ess_bulk=None if f["ess"] is None else dict(zip(names, f["ess"].tolist())),
                rhat=None if f["rhat"] is None else dict(zip(names, f["rhat"].tolist())),
                n_samples=len(u), image_table_logl_error=f.get("table_err"),
                term_table_logl_error=f.get("term_table_err"),
                g_constrained=bool(g90 < 0.5 * prior_g_interval_width(space)),
                kappa_s_consistent_with_zero=bool(ks["q05"] < 1e-3 * ks["q95"]))
    if "modes" in f:
        info["g_modes"] = f["modes"]
    return info


def _diagnostics(chans: dict[str, dict], channels, mcmc: bool) -> dict:
    """results.json's ``diagnostics``: the chains' overall convergence, then ``channels``."""
    diag: dict = {}
    if mcmc:
        diag.update(converged=all(chans[c]["converged"] for c in channels),
                    n_steps=int(max(chans[c]["n_steps"] for c in channels)),
                    autocorr_time_max=float(max(max(chans[c]["autocorr_time"].values())
                                                for c in channels)),
                    acceptance_fraction=float(np.mean([chans[c]["acceptance_fraction"]
                                                       for c in channels])))
        if all(chans[c]["rhat"] for c in channels):
            diag.update(rhat_max=max(max(chans[c]["rhat"].values()) for c in channels),
                        ess_bulk_min=min(min(chans[c]["ess_bulk"].values()) for c in channels))
    diag["channels"] = chans
    return diag


def _image_records(prep: Prepared, fits: dict[str, dict], taus: dict) -> list[dict]:
    """results.json's ``images``: per image its files, concentration, excluded pixels and
    per channel the pixels used, chi2/pixel at the MAP and the optical depth."""
    spec, images = prep.spec, []
    for i, (entry, im) in enumerate(zip(spec.images, prep.images)):
        per = {}
        for ch in spec.channels:
            c2, n = fits[ch]["chi2_images"][i]
            per[ch] = {"n_pixels_used": n, "chi2_per_pixel_map": c2 / max(n, 1),
                       "optical_depth_light_to_wall": taus[ch][i]}
            if fits[ch].get("ms_share") is not None:
                per[ch]["multiple_scattering_share"] = fits[ch]["ms_share"][i]
        images.append({"path": [str(p) for p in entry.paths], "concentration": entry.concentration,
                       "n_saturated": im.n_saturated, "n_masked": im.n_masked, "channels": per})
    return images


def _priors(spec, names: list[str], space) -> dict:
    """results.json's ``priors``: the priors in words and the bounds of the sampler's
    coordinates (the spec's ``priors`` where it sets them)."""
    return {"kappa_t": "log-uniform",
            "albedo": (f"mixture: {1 - ALBEDO_UNIFORM_WEIGHT:g} flat in logit albedo "
                       f"(log-uniform kappa_a, kappa_s) + {ALBEDO_UNIFORM_WEIGHT:g} "
                       "uniform in albedo, on the bounds"),
            "g": "uniform", "spec_overrides": spec.priors,
            "bounds": {n: [lo, hi] for n, lo, hi in zip(names, space.lower.tolist(),
                                                         space.upper.tolist())
                       if n != "log_brightness"}}


def _reduced(f: dict, phys: dict, weights: np.ndarray | None) -> tuple[dict, float | None]:
    """kappa_s' = kappa_s (1 - g) of one channel's fit ``f`` (physical samples ``phys``, their
    :func:`albedo_weights`): from the samples, else from the Laplace covariance; and the width
    ratio (fitmedia.trust)."""
    if "kappa_s" in phys:
        return reduced_from_samples(phys["kappa_s"], phys["g"], f["map"]["kappa_s"], f["map"]["g"],
                                    weights)
    return reduced_from_laplace(f["x_map"], f.get("laplace_cov"), f["names"], f["map"]["kappa_s"],
                                f["map"]["g"])


def assess(params: dict, chans: dict[str, dict], images: list[dict], model: str, *,
           robust: bool = False) -> dict:
    """results.json's ``trust`` (docs/results.md): the misfit guard on every channel and image,
    and the channels whose kappa_s and g are not separately measured.  A channel that fails
    the guard gets ``optical_depth_regime`` None: its kappa_t, hence its optical depth, is
    biased by an unknown amount."""
    checks, reasons = misfit_checks(chans, images, model, robust=robust)
    reasons += transport_reasons(chans) + sampler_reasons(chans)
    ms_reasons, ms_notes = single_scattering_checks(chans, checks)
    reasons += ms_reasons
    for ch, c in checks.items():
        if c["ok"] is False:
            chans[ch]["optical_depth_regime"] = None
    notes = [not_separable_note(ch, params["kappa_s_reduced"][ch]) for ch, info in chans.items()
             if info.get("kappa_s_g_separable") is False] + ms_notes + regime_notes(chans, images)
    return {"ok": not reasons, "model": model, "reasons": [str(r) for r in reasons],
            "reason_kinds": reason_kinds(reasons), "notes": notes, "misfit": checks}


def write_outputs(out_dir: Path, prep: Prepared, fits: dict[str, dict], result: FitResult
                  ) -> None:
    """results.json (``result.to_json()``), samples.npz (posterior, physical and
    unconstrained), fit_images.npz."""
    out_dir = Path(out_dir)
    spec = prep.spec
    samples = {}
    for ch, f in fits.items():
        if "samples" in f:
            phys = f["space"].physical_samples(f["samples"])
            for q, v in phys.items():
                samples[f"{ch}/{q}"] = v
            samples[f"{ch}/unconstrained"] = f["samples"]
            samples[f"{ch}/uniform_albedo_weight"] = albedo_weights(f)
            samples[f"{ch}/log_prob"] = f["log_prob"]
        samples[f"{ch}/map_unconstrained"] = f["x_map"]
    samples["names"] = np.array(fits[spec.channels[0]]["names"])
    save_npz(out_dir / "samples.npz", samples)
    for ch, f in fits.items():
        if "chain" in f:
            write_inference_data(out_dir / f"posterior_{ch}.nc", f)
        if "chain_mode2" in f:  # the other mode of g's chain (docs/inference.md)
            write_inference_data(out_dir / f"posterior_{ch}_mode2.nc",
                                 dict(f, chain=f["chain_mode2"]))
    imgs = {}
    idx = [CHANNELS.index(c) for c in spec.channels]
    for i, im in enumerate(prep.images):
        imgs[f"data_{i}"] = im.data[..., idx]
        # the pixels the fit used (the image's valid pixels that see the water) where the fit
        # says which, else the image's valid pixels
        imgs[f"valid_{i}"] = np.stack([fits[c]["valid_images"][i] if "valid_images" in fits[c]
                                       else im.valid[..., CHANNELS.index(c)]
                                       for c in spec.channels], -1)
        imgs[f"model_{i}"] = np.stack([fits[c]["model_images"][i] for c in spec.channels], -1)
        if all("var_images" in fits[c] for c in spec.channels):  # the likelihood's variance
            imgs[f"var_{i}"] = np.stack([fits[c]["var_images"][i] for c in spec.channels], -1)
        if all("ms_images" in fits[c] for c in spec.channels):  # the multiple-scattering part
            imgs[f"ms_{i}"] = np.stack([fits[c]["ms_images"][i] for c in spec.channels], -1)
    imgs["channels"] = np.array(spec.channels)
    save_npz(out_dir / "fit_images.npz", imgs)
    write_json(out_dir / "results.json", result.to_json())


def write_inference_data(path: Path, fit: dict) -> None:
    """The chain of one channel (after burn-in, walkers as chains) as ArviZ InferenceData in
    NetCDF: the unconstrained parameters and the physical quantities (1/mm)."""
    from ..util import atomic_write
    from .sample import to_inference_data

    chain = fit["chain"]
    extra = {q: v for q, v in fit["space"].physical_samples(chain).items()}
    idata = to_inference_data(chain, list(fit["names"]), extra=extra)
    atomic_write(path, lambda tmp: idata.to_netcdf(str(tmp), engine="h5netcdf"))

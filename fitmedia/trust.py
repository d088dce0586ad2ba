"""Can a fit's numbers be trusted?  Two checks on every fit (docs/results.md, "trust"):

* the **misfit guard**: chi2/pixel at the MAP against what the noise model allows for that
  many pixels.  A model that does not describe the images (single scattering where multiple
  scattering is most of the glow, a wrong geometry) gives values biased by an amount the
  intervals do not show; ``fitmedia fit`` then says so and exits 1.
* **kappa_s and g separable?**  In a dense medium the images constrain only kappa_t and the
  reduced scattering coefficient kappa_s' = kappa_s (1 - g) (the similarity relation), so a
  kappa_s and a g reported on their own are one arbitrary point of a ridge.  kappa_s' is
  always reported with its interval; where it is known much better than kappa_s, the verdict
  says that kappa_s and g are not separately measured.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from .inference.full import RESTART_DELTA as FULL_RESTART_DELTA
from .inference.sample import OTHER_MODE_DELTA
from .inference.summary import summarise

#: Tail probability of the noise-only chi2 distribution that the guard tolerates.
CHI2_TAIL = 1e-6
#: Allowance for model error in chi2/pixel, added to the noise-only limit.  Chosen from
#: measurements (docs/results.md, "trust"; docs/studies/misfit_study.py).
MODEL_ERROR_ALLOWANCE = 0.1
#: kappa_s and g count as not separately measured when the 90 % interval of log kappa_s' is
#: narrower than this fraction of the 90 % interval of log kappa_s (docs/results.md).
SEPARABLE_WIDTH_RATIO = 0.5
Z90 = 1.6448536269514722  # the standard normal's 95 % quantile
Z68 = 0.9944578832097532  # its 84 % quantile


class Reason(str):
    """One of ``trust.reasons``: its plain words, and ``kind``, which check gave it (results.json's
    ``trust.reason_kinds``, docs/results.md): ``misfit``, ``unsettled``, ``other_g``,
    ``restart``, ``final_move``, ``seed_shift``, ``sampler``, ``spot_scan`` or
    ``single_scattering``."""

    kind: str

    def __new__(cls, text: str, kind: str):
        self = super().__new__(cls, text)
        self.kind = kind
        return self


def _add(reasons: list, kind: str, text: str) -> None:
    reasons.append(Reason(text, kind))


def reason_kinds(reasons: Sequence[str]) -> list[str]:
    """The ``kind`` of each reason (``other`` for a plain string)."""
    return [getattr(r, "kind", "other") for r in reasons]


def chi2_limit(n_pixels: int) -> float:
    """The largest chi2/pixel at the MAP that the guard accepts for ``n_pixels`` pixels: the
    upper ``CHI2_TAIL`` quantile of chi2 with ``n_pixels`` degrees of freedom, divided by
    ``n_pixels``, plus ``MODEL_ERROR_ALLOWANCE``."""
    from scipy.stats import chi2

    n = max(int(n_pixels), 1)
    return float(chi2.isf(CHI2_TAIL, n) / n) + MODEL_ERROR_ALLOWANCE


def misfit(chi2_per_pixel: float | None, n_pixels: int) -> dict:
    """The guard's verdict on one chi2/pixel: ``chi2_per_pixel``, ``n_pixels``, ``limit``,
    ``ok`` (None where chi2 is unknown: no pixels or not finite)."""
    limit = chi2_limit(n_pixels)
    known = chi2_per_pixel is not None and n_pixels > 0 and math.isfinite(chi2_per_pixel)
    return {"chi2_per_pixel": chi2_per_pixel if known else None, "n_pixels": int(n_pixels),
            "limit": limit, "ok": bool(chi2_per_pixel <= limit) if known else None}


def misfit_reason(ch: str, check: dict, model: str, where: str = "", robust: bool = False
                  ) -> str:
    """The plain-words reason of a failed :func:`misfit` check (``robust``: the fit used the
    Student-t likelihood, whose outliers still count in chi2)."""
    return (f"the model ({model}) does not describe the images{where}: chi2/pixel "
            f"{check['chi2_per_pixel']:.3g} at the best fit in channel {ch}, where the noise "
            f"model allows at most {check['limit']:.3g} ({check['n_pixels']} pixels); the values "
            f"of channel {ch} are biased by an unknown amount and their intervals do not show it"
            + ("; with --robust, outliers (dust, bubbles) count in chi2 too: if the residual "
               "image shows only a few of them, the rest of the fit may be fine" if robust
               else ""))


def misfit_checks(chans: dict[str, dict], images: Sequence[dict], model: str, *,
                  robust: bool = False) -> tuple[dict[str, dict], list[str]]:
    """The guard on every channel (all images together) and, for a series, on every image.

    Parameters
    ----------
    chans : dict
        results.json's ``diagnostics.channels``: ``chi2_per_pixel``, ``n_pixels``.
    images : list of dict
        results.json's ``images``: ``channels.<ch>.chi2_per_pixel_map``, ``n_pixels_used``.
    model : str
        The forward model's name, for the reasons.
    robust : bool
        The fit used the Student-t likelihood (the reasons say that outliers count).

    Returns
    -------
    checks : dict
        Per channel: :func:`misfit` of all its pixels, with ``images`` (:func:`misfit` per
        image) for a series; ``ok`` is False when the channel or any of its images fails.
    reasons : list of str
        One line per failed channel (naming the worst image of a series).
    """
    checks, reasons = {}, []
    for ch, info in chans.items():
        c = misfit(info.get("chi2_per_pixel"), int(info.get("n_pixels") or 0))
        per = [misfit(im["channels"][ch]["chi2_per_pixel_map"], im["channels"][ch]["n_pixels_used"])
               for im in images if ch in im.get("channels", {})] if len(images) > 1 else []
        bad = [i for i, p in enumerate(per) if p["ok"] is False]
        if per:
            c["images"] = per
        if bad:
            worst = max(bad, key=lambda i: per[i]["chi2_per_pixel"] / per[i]["limit"])
            c["ok"] = False
            _add(reasons, "misfit", misfit_reason(ch, per[worst], model, f" (worst: image {worst})",
                                         robust))
        elif c["ok"] is False:
            _add(reasons, "misfit", misfit_reason(ch, c, model, robust=robust))
        checks[ch] = c
    return checks, reasons


#: a full-transport MAP that moves by more than this many posterior sd when the multiple-
#: scattering term is traced with other random numbers has intervals too narrow to trust
#: (results without the term's jackknife error, ``term_sd``, in their intervals)
SEED_SHIFT_SD = 1.0
#: with the jackknife error in the intervals, ``seed_shift_sd`` is the move in units of the sd
#: the term's error stated in the intervals gives it (its jackknife and, since 2026-12-07, the
#: last refreshes' offset budget, each scaled to the loop's paths: inference/full.py
#: ``seed_shift_units``); beyond this many, the intervals understate the term's error: a
#: 3-sigma event for one coordinate, ~0.5 % for the larger of two
SEED_SHIFT_Z = 3.0
#: a second full-transport fit started beyond the MAP (inference/full.py: restart_shift) that
#: ends more than this many sd (Laplace plus the term's jackknife) away: two fixed points
RESTART_SD = 3.0
#: ... unless it settled where the log posterior (the local model rebuilt there) is more than
#: this many units below the MAP's: a fixed point of the loop that the images decide against
#: (``restart_delta_log_posterior``, the part of the difference beyond the term's noise over
#: seeds; inference/full.py: ``RESTART_DELTA``, the bound for a second mode, and
#: ``delta_beyond_noise``)
RESTART_DELTA = FULL_RESTART_DELTA
#: the last refreshes, at 8 times the paths (inference/full.py: more_paths), move the values
#: from the loop's fixed point by most of the offset the term's own noise gave it; a share of
#: that move may remain (inference/full.py: ``OFFSET_SHARE``), and is in the intervals as a
#: budget along the move (``offset_budget``; until 2026-12-06 a move beyond 1.5 sd was a
#: reason instead, which every 100 x 75 and 200 x 150 milk fit gave).  That share rests on
#: moves of up to 4.6 % in kappa_t and 0.011 in g (docs/inference.md, "The offset left after
#: the last refreshes"): a move beyond about twice those is outside what it was measured on,
#: and says the loop's fixed point was not near the answer, a reason
FINAL_MOVE_KAPPA_T = 0.10
FINAL_MOVE_G = 0.025
#: with the full model, an optimum with g of the other sign within this many log-posterior
#: units leaves the sign of g undetermined: the bound for sampling both modes.  With the
#: sampler both are sampled and mixed by their masses (``sampled`` true: no reason); without
#: it (``--no-mcmc``) the values of one mode are not the answer, a reason
OTHER_G_DELTA = OTHER_MODE_DELTA


def transport_reasons(chans: dict[str, dict]) -> list[str]:
    """Plain-words reasons from the full-transport fit of each channel (results.json's
    ``diagnostics.channels.<ch>.multiple_scattering``, inference/full.py): the refreshes of the
    multiple-scattering term did not settle, or another realisation of the term moves the
    values by more than ``SEED_SHIFT_SD`` posterior sd."""
    reasons = []
    for ch, info in chans.items():
        ms = info.get("multiple_scattering") or {}
        if ms.get("converged") is False:
            _add(reasons, "unsettled", 
                f"the full-transport fit of channel {ch} did not settle: after "
                f"{ms['refreshes']} refreshes of the multiple-scattering term the best fit still "
                f"moved by {ms['moves_sd'][-1]:.2g} posterior sd, more than the term's own "
                f"Monte Carlo error explains; the values of channel {ch} are uncertain by more "
                "than their intervals show")
        other = ms.get("other_g_mode") or {}
        if other.get("delta_log_posterior") is not None and not other.get("sampled") \
                and not other["delta_log_posterior"] < -OTHER_G_DELTA:
            _add(reasons, "other_g", 
                f"with the full-transport model, g of the other sign in channel {ch} (g "
                f"{other['g']:.3g}, kappa_t {other['kappa_t']:.4g}) fits within "
                f"{-other['delta_log_posterior']:.2g} log-posterior units of the values given: "
                f"the sign of g in channel {ch} is not determined by the images")
        _restart_reason(reasons, ch, ms)
        move = ms.get("final_move") or {}
        if move and not (abs(move.get("kappa_t", np.nan)) <= FINAL_MOVE_KAPPA_T
                         and abs(move.get("g", np.nan)) <= FINAL_MOVE_G):
            _add(reasons, "final_move", 
                f"tracing the multiple-scattering term with {ms.get('final_paths')} paths per "
                f"sample pixel moved the values of channel {ch} by kappa_t "
                f"{100 * move.get('kappa_t', float('nan')):+.1f} % and g "
                f"{move.get('g', float('nan')):+.3f} ({ms.get('final_move_sd', float('nan')):.2g} sd), "
                f"beyond {100 * FINAL_MOVE_KAPPA_T:.0f} % or {FINAL_MOVE_G:.3g}: the fit at fewer "
                "paths was far from the answer, and how much of the offset its noise gave the "
                "values remains is not known; their intervals may not include it")
        shift = ms.get("seed_shift_sd")
        if shift is None:
            continue
        if ms.get("term_sd") is None and not shift <= SEED_SHIFT_SD:
            _add(reasons, "seed_shift", 
                f"the multiple-scattering term's own Monte Carlo error moves the values of channel "
                f"{ch} by {shift:.2g} posterior sd (the term traced again with other random "
                "numbers); their intervals do not include that error")
        elif ms.get("term_sd") is not None and not shift <= SEED_SHIFT_Z:
            _add(reasons, "seed_shift", 
                f"the multiple-scattering term traced again with other random numbers moved the "
                f"values of channel {ch} by {shift:.2g} times the sd that the term's error stated in "
                "the intervals (its Monte Carlo error and the last refreshes' offset budget) gives "
                "such a move; the intervals understate that error")
    return reasons


def _restart_reason(reasons: list, ch: str, ms: dict) -> None:
    """transport_reasons' restart check: a second fit that ended more than ``RESTART_SD`` sd
    away, unless it settled more than ``RESTART_DELTA`` log-posterior units below the MAP."""
    restart = ms.get("restart_shift_sd")
    worse = ms.get("restart_delta_log_posterior")
    if restart is None or restart <= RESTART_SD or (worse is not None and worse < -RESTART_DELTA):
        return
    second = ms.get("restart_values") or {}
    _add(reasons, "restart",
         f"a second full-transport fit of channel {ch}, started further along the "
         f"direction in which multiple scattering moves the values, ended {restart:.2g} sd "
         f"away (kappa_t {second.get('kappa_t', float('nan')):.4g}, g "
         f"{second.get('g', float('nan')):.3g}"
         + ("" if worse is None else f"; its log posterior {worse:+.3g} units from the "
            f"values' beyond the term's own noise, within {RESTART_DELTA:.3g}")
         + "): the images do not decide between the two, "
         f"and the values of channel {ch} are not determined to within their intervals")


def sampler_reasons(chans: dict[str, dict]) -> list[str]:
    """Plain-words reasons for channels whose posterior sampler did not converge (results.json's
    ``diagnostics.channels.<ch>.converged`` false, with its ``reason``): the intervals of such a
    chain are not known to be a posterior's (docs/inference.md, "Posterior": 50 tau, R-hat,
    bulk ESS).  Until 2026-12-03 ``fitmedia fit`` only warned and exited 0."""
    reasons = []
    for ch, info in chans.items():
        if info.get("converged") is False:
            why = info.get("reason")
            _add(reasons, "sampler", 
                f"the posterior sampler of channel {ch} did not converge"
                + (f" ({why})" if why else "")
                + f": the intervals of channel {ch} are not reliable; continue the chain with "
                "fitmedia fit ... --resume --max-steps N (N above the steps it ran)")
    return reasons


#: a single-scattering fit whose multiple-scattering share at its MAP is above the share at
#: which ``--model auto`` switches to full transport (inference/full.py: AUTO_SHARE) is asked
#: whether the misfit guard could see that term (inference/full.py: ms_detectability): it
#: could where the predicted rise of chi2/pixel is at least this many times the guard's room
#: above 1 (its limit minus 1).  The prediction is rough either way (docs/results.md, "trust":
#: 3.5 predicted where a full-transport render of the same scene rose by 10; 3.0 and 4.2
#: predicted at a MAP already biased by the term, where the rise was ~0.05 and ~0.35), so the
#: rule only finds where the guard is blind, with a margin of 3
MS_DETECT_FACTOR = 3.0
#: the single-scattering fit's bias of kappa_s per unit multiple-scattering share, at most:
#: measured 0.2-0.8 at shares 0.21-0.66 (issue 15's Mitsuba renders at 100 x 75 px, 2006
#: dilutions; docs/inference.md, "--model auto").  Where the guard is blind, a bias bound
#: (this times the share) above the sd of log kappa_s (the stated uncertainty) is a reason
MS_BIAS_PER_SHARE = 0.8


def _spot_scan_reason(ch: str, ms: dict) -> str:
    """The reason a spot's single-scattering values of channel ``ch`` are not determined, from
    the full model's scan (results.json's ``multiple_scattering.spot_scan_*``)."""
    best, gain = ms.get("spot_scan_best") or {}, ms.get("spot_scan_gain")
    how = (f"better than the single-scattering values, by {gain:.3g} log-posterior units"
           if ms.get("spot_scan_verdict") == "better" else
           f"about as well as the single-scattering values ({gain:+.3g} log-posterior units)")
    return (f"full transport at kappa_t {best.get('kappa_t', float('nan')):.4g}, g "
            f"{best.get('g', float('nan')):.3g} describes the images of channel {ch} {how}: the "
            "single-scattering fit of a spot can take multiple scattering for a thinner medium, "
            f"and its values of channel {ch} are not determined; fit with --model auto or full")


def single_scattering_checks(chans: dict[str, dict], checks: dict[str, dict]
                             ) -> tuple[list[str], list[str]]:
    """Reasons and notes on what the single-scattering model leaves out, per channel fitted
    with it (results.json's ``diagnostics.channels.<ch>.multiple_scattering`` with
    ``chi2_excess_if_present`` and ``kappa_s_log_sd``; ``checks``: :func:`misfit_checks`'
    verdicts).  A spot's scan verdict is a reason.  Then, where the share is above AUTO_SHARE:

    * the misfit guard fired: a note naming multiple scattering as a likely cause;
    * the capture declares a single-scattering render (``synthetic.model: single``, as
      ``fitmedia synth`` writes): a note, as it holds no multiple scattering;
    * the guard could see the term (its predicted rise of chi2/pixel at least
      ``MS_DETECT_FACTOR`` times the guard's room): a note with the share and the rise;
    * the guard is blind to it, but the bias it would cause (``MS_BIAS_PER_SHARE`` times the
      share, relative) is within the sd of log kappa_s: a note;
    * else a reason: the guard's silence says nothing here, and in a photograph the term is
      there and biases kappa_s by more than its stated uncertainty (``fitmedia fit`` exits 1).
    """
    from .inference.full import AUTO_SHARE

    reasons, notes = [], []
    for ch, info in chans.items():
        ms = info.get("multiple_scattering") or {}
        if info.get("model_used") == "single" and ms.get("spot_scan_verdict") is not None:
            _add(reasons, "spot_scan", _spot_scan_reason(ch, ms))  # a spot's scan: not determined
            continue
        excess, share = ms.get("chi2_excess_if_present"), ms.get("share") or []
        if info.get("model_used") != "single" or excess is None or not share \
                or not max(share) > AUTO_SHARE:
            continue
        top = max(share)
        pct = f"{100 * top:.0f} %" if top >= 0.1 else f"{100 * top:.1f} %"
        what = (f"multiple scattering, which the single-scattering model leaves out, would be "
                f"{pct} of the glow in channel {ch} at the fitted values")
        check = checks.get(ch) or {}
        room = check.get("limit", float("nan")) - 1.0
        bias, sd = MS_BIAS_PER_SHARE * top, ms.get("kappa_s_log_sd")
        blind = (f"these images cannot show whether it is there (it would raise chi2/pixel by "
                 f"about {excess:.2g}, where the guard allows {room:.2g})")
        if check.get("ok") is False:
            notes.append(f"{what}: a likely cause of the misfit; fit with --model full")
        elif ms.get("capture_declared_single_scattering_render"):
            notes.append(f"{what}; the capture declares a single-scattering render (spec: "
                         "synthetic.model: single), which holds none: a photograph would, and "
                         "its single-scattering values would be biased")
        elif excess >= MS_DETECT_FACTOR * room:
            notes.append(f"{what}; the misfit guard can see it here (images holding it would "
                         f"raise chi2/pixel by about {excess:.2g} at these values, where the guard "
                         f"allows {room:.2g})")
        elif sd is not None and bias <= sd:
            notes.append(f"{what}, and {blind}; the bias it would cause (up to {100 * bias:.2g} % "
                         f"in kappa_s) is within kappa_s's uncertainty ({100 * sd:.2g} %)")
        else:
            _add(reasons, "single_scattering", 
                f"{what}, and {blind}: in a photograph it is there, and then kappa_s of channel "
                f"{ch} is biased by up to about {100 * bias:.2g} % (measured: {MS_BIAS_PER_SHARE:g} "
                "times the share at most), more than its stated uncertainty"
                + (f" ({100 * sd:.2g} %)" if sd is not None else " (none without the sampler's "
                   "or the Laplace covariance)")
                + "; fit with --model full, or use more pixels")
    return reasons, notes


# ---------------------------------------------------------------------------------------------
# kappa_s' = kappa_s (1 - g)


def _log_width90(x: np.ndarray) -> float | None:
    """log(q95 / q05) of positive samples ``x``; None where q05 is not positive."""
    q05, q95 = np.percentile(x, [5, 95])
    return float(np.log(q95 / q05)) if q05 > 0 else None


def reduced_from_samples(kappa_s: np.ndarray, g: np.ndarray, map_kappa_s: float, map_g: float,
                         weights: np.ndarray | None = None) -> tuple[dict, float | None]:
    """kappa_s' = kappa_s (1 - g) from posterior samples: its summary (``map``, ``median``,
    ``mean``, ``std``, ``q05`` ... ``q95``, the intervals the envelope with ``weights`` as in
    ``inference.summary.summarise``; ``source: "samples"``) and the ratio of the 90 %
    interval widths of log kappa_s' and log kappa_s (None where kappa_s reaches 0)."""
    red = np.asarray(kappa_s) * (1.0 - np.asarray(g))
    out = {**summarise(red, map_kappa_s * (1.0 - map_g), weights), "source": "samples"}
    w_s, w_r = _log_width90(np.asarray(kappa_s)), _log_width90(red)
    ratio = w_r / w_s if w_s and w_r is not None else None
    return out, ratio


def reduced_from_laplace(x_map: np.ndarray, cov: np.ndarray | None, names: Sequence[str],
                         map_kappa_s: float, map_g: float) -> tuple[dict, float | None]:
    """kappa_s' from the MAP and the Laplace covariance of (log kappa_t, logit albedo,
    atanh g, ...): log kappa_s' is linearised, its quantiles those of a normal in the log
    (``source: "laplace"``); the width ratio as in :func:`reduced_from_samples`."""
    red = float(map_kappa_s * (1.0 - map_g))
    out: dict = {"map": red, "source": "laplace"}
    if cov is None or not np.all(np.isfinite(cov)):
        return out, None
    u = np.asarray(x_map, float)
    i_g = list(names).index("atanh_g")
    g = np.tanh(u[i_g])
    j_s = _log_kappa_s_gradient(u, names)
    j_r = j_s.copy()
    j_r[i_g] = -(1.0 + g)                   # d log(1 - tanh u) / du = -(1 + g)
    var_s, var_r = float(j_s @ cov @ j_s), float(j_r @ cov @ j_r)
    if not (var_s > 0 and var_r > 0):
        return out, None
    sd = math.sqrt(var_r)
    out.update({k: red * math.exp(z * sd) for k, z in
                (("q05", -Z90), ("q16", -Z68), ("q84", Z68), ("q95", Z90))}, sd_log=sd)
    return out, sd / math.sqrt(var_s)


def _log_kappa_s_gradient(u: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """d log kappa_s / d u in the sampler's coordinates (log kappa_t, logit albedo, ...)."""
    i_t, i_a = (list(names).index(n) for n in ("log_kappa_t", "logit_albedo"))
    j = np.zeros(len(u))
    j[i_t], j[i_a] = 1.0, 1.0 - 1.0 / (1.0 + np.exp(-u[i_a]))
    return j


def log_kappa_s_sd(kappa_s: np.ndarray | None, x_map: np.ndarray, cov: np.ndarray | None,
                   names: Sequence[str]) -> float | None:
    """The sd of log kappa_s: from the posterior samples ``kappa_s`` (their 90 % interval's
    width in the log over 2 x 1.645, robust to a tail at 0), else from the Laplace covariance
    linearised at the MAP; None where neither gives one."""
    if kappa_s is not None and len(kappa_s):
        lo, hi = np.quantile(kappa_s, [0.05, 0.95])
        return float(np.log(hi / lo) / (2 * Z90)) if lo > 0 else None
    if cov is None or not np.all(np.isfinite(cov)):
        return None
    j = _log_kappa_s_gradient(np.asarray(x_map, float), names)
    var = float(j @ cov @ j)
    return math.sqrt(var) if var > 0 else None


def separable(width_ratio: float | None, kappa_s_consistent_with_zero: bool | None
              ) -> bool | None:
    """Are kappa_s and g separately measured?  False when log kappa_s' is known more than
    1 / ``SEPARABLE_WIDTH_RATIO`` times better than log kappa_s; None when that cannot be
    told (no interval, or kappa_s consistent with zero)."""
    if width_ratio is None or kappa_s_consistent_with_zero:
        return None
    return bool(width_ratio >= SEPARABLE_WIDTH_RATIO)


def not_separable_note(ch: str, reduced: dict) -> str:
    """The plain-words note for a channel whose kappa_s and g are not separately measured."""
    lo, hi = reduced.get("q05"), reduced.get("q95")
    value = reduced.get("median", reduced["map"])
    interval = f" (90 % interval {lo:.4g} - {hi:.4g})" if lo is not None else ""
    return (f"channel {ch}: kappa_s and g are not separately measured (the images constrain "
            f"kappa_s' = kappa_s (1 - g) much better than kappa_s and g: in a dense medium "
            f"because of the similarity relation, in a thin one or at few pixels for want of "
            f"information on g); read "
            f"kappa_s' = {value:.4g} 1/mm{interval}, not kappa_s and g on their own")


def regime_notes(chans: dict[str, dict], images: list[dict]) -> list[str]:
    """Plain-words notes for the channels too thin or too dense in every image
    (``optical_depth_regime``, fitmedia/regimes.py), which until 2026-12-06 only the report's
    channel flags named: there the 100-round validation found kappa_t's (thin) or g's (dense)
    intervals driven by the prior (docs/validation.md, "Coverage by regime")."""
    from .regimes import INFORMATIVE_OPTICAL_DEPTH

    lo, hi = INFORMATIVE_OPTICAL_DEPTH
    notes = []
    for ch, info in chans.items():
        if info.get("optical_depth_regime") not in ("thin", "dense"):
            continue
        taus = [((im.get("channels") or {}).get(ch) or {}).get("optical_depth_light_to_wall")
                for im in images]
        depths = ", ".join("?" if t is None else f"{t:.2g}" for t in taus)
        if info.get("optical_depth_regime") == "thin":
            notes.append(f"channel {ch} is too dilute: its optical depth from the light to the "
                         f"front wall is {depths}, below {lo:g} in every image, and the "
                         "intervals of kappa_t and kappa_a there follow the prior more than the "
                         "images (read kappa_a as an upper limit); add liquid to measure them")
        elif info.get("optical_depth_regime") == "dense":
            notes.append(f"channel {ch} is too dense: its optical depth from the light to the "
                         f"front wall is {depths}, above {hi:g} in every image; the light is "
                         "hidden and g's interval follows the prior more than the images; "
                         "dilute to measure g")
    return notes


# ---------------------------------------------------------------------------------------------
# what `fitmedia fit` prints


def _value(entry: dict, key: str, digits: str = ".4g") -> str:
    """``entry[key]``, with the 90 % interval where the entry has one (a sampler ran)."""
    text = format(entry[key], digits)
    if "q05" in entry and "q95" in entry and entry.get("source") != "laplace":
        text += f" [{entry['q05']:{digits}}, {entry['q95']:{digits}}]"
    return text


def value_line(results: dict, ch: str) -> str:
    """One channel's line of ``fitmedia fit``'s output: kappa_a, kappa_s, g (with their 90 %
    intervals in brackets when a sampler ran), or kappa_t and kappa_s' where kappa_s and g are
    not separately measured (kappa_a = kappa_t - kappa_s is not either: where g is free, the
    split of kappa_t into kappa_a and kappa_s moves with it)."""
    p = results["parameters"]
    key = "median" if "median" in p["kappa_s"][ch] else "map"
    what = ("(1/mm, undiluted, median [90 % interval])" if key == "median" else
            "(1/mm, undiluted, map; no intervals without the sampler)")
    info = results.get("diagnostics", {}).get("channels", {}).get(ch, {})
    red = p.get("kappa_s_reduced", {}).get(ch)
    if red is not None and info.get("kappa_s_g_separable") is False:
        value = red.get(key, red["map"])
        interval = f" (90 %: {red['q05']:.4g} - {red['q95']:.4g})" if "q05" in red else ""
        return (f"  {ch}: kappa_t={_value(p['kappa_t'][ch], key)} kappa_s'=kappa_s(1-g)="
                f"{value:.4g}{interval}; kappa_s, g and kappa_a = kappa_t - kappa_s not "
                f"separately measured {what}")
    ka = p["kappa_a"][ch]
    if info.get("kappa_a_upper_limit_only") is True and "q95" in ka:  # not resolved: a limit
        ka_text = (f"kappa_a<{ka['q95']:.4g} (95 % upper limit; "
                   f"kappa_t={_value(p['kappa_t'][ch], key)})")
    else:
        ka_text = f"kappa_a={_value(ka, key)}"
    return (f"  {ch}: {ka_text} kappa_s={_value(p['kappa_s'][ch], key)} "
            f"g={_value(p['g'][ch], key, '.3f')} {what}")


def model_lines(results: dict) -> list[str]:
    """``--model auto``: per channel, the model it used and why (results.json's
    ``diagnostics.channels.<ch>.multiple_scattering.auto_reason``); else nothing."""
    if results.get("model") != "auto":
        return []
    chans = results.get("diagnostics", {}).get("channels", {})
    lines = []
    for ch in results.get("channels", []):
        info = chans.get(ch, {})
        reason = (info.get("multiple_scattering") or {}).get("auto_reason")
        if reason:
            used = {"full": "full transport", "single": "single scattering"}.get(
                info.get("model_used"), str(info.get("model_used")))
            lines.append(f"model auto, channel {ch}: {used}, as {reason}")
    return lines


def print_values(results: dict) -> None:
    """Print every channel's :func:`value_line`."""
    for ch in results["channels"]:
        print(value_line(results, ch))


def print_verdict(results: dict) -> int:
    """Print results.json's ``trust`` reasons and notes; the exit code of ``fitmedia fit``:
    1 when the misfit guard fired (the values are doubtful), else 0."""
    import sys

    trust = results.get("trust") or {}
    for note in trust.get("notes", []):
        print(f"note: {note}")
    if trust.get("ok", True):
        return 0
    for reason in trust.get("reasons", []):
        print(f"fitmedia: doubtful result: {reason}", file=sys.stderr)
    print("fitmedia: doubtful result: the values above cannot be trusted; results.json (trust) "
          "and the report say why (exit code 1)", file=sys.stderr)
    return 1

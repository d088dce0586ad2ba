"""Synthetic round trips: synthesise a capture with known truth, fit it, and
score the posterior against the truth (standardised error, where the truth falls
in the posterior, coverage of credible intervals)."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .inference.fit import FitOptions
from .inference.summary import weighted_cdf
from .medium import Medium
from .regimes import INFORMATIVE_OPTICAL_DEPTH, REGIMES, regime, tank_optical_depths
from .spec import Spec
from .util import atomic_write, atomic_write_text, write_json

SCORED = ("kappa_s", "kappa_t", "g", "kappa_s_reduced")
#: what the scored quantities are, from a channel's posterior samples (kappa_s' = kappa_s (1 - g):
#: the reduced scattering coefficient, the one a dense medium constrains)
_FROM_SAMPLES = {"kappa_s_reduced": lambda get: get("kappa_s") * (1.0 - get("g"))}
#: Central credible intervals whose coverage is reported.
LEVELS = (0.68, 0.90, 0.99)
#: Pass criteria: the 90 % intervals cover the truth in this fraction of the scores ...
COVERAGE_90_RANGE = (0.85, 0.95)
#: ... and the mean standardised bias z (:attr:`Score.z`, Phi^-1(1 - PIT)) is smaller than this.
MAX_ABS_MEAN_Z = 0.2
#: z's PIT is kept this far from 0 and 1 (a truth outside every posterior sample)
PIT_CLIP = 1e-4


@dataclass
class Score:
    medium: str
    ml: tuple[float, ...]
    channel: str
    quantity: str
    truth: float
    median: float
    std: float
    pit: float  # fraction of posterior samples below the truth
    #: per image: the tank's kappa_t (truth, this channel) x the light-to-front-wall distance
    optical_depth: tuple[float, ...] | None = None
    #: (median - truth) / sd in the sampler's coordinate (log kappa, atanh g), where the
    #: posterior is close to normal; None where undefined (see :func:`normal_score`)
    z_normal: float | None = None
    #: results.json's ``trust.ok`` of the fit (False: ``fitmedia fit`` exited 1 and said the
    #: values cannot be trusted); None for scores recorded before it was kept
    trusted: bool | None = None
    #: the truth's quantile as results.json's intervals see it (:func:`envelope_pit`; they are
    #: an envelope over the albedo prior's halves since 2026-12-06); None: ``pit``'s
    pit_envelope: float | None = None

    @classmethod
    def from_record(cls, d: dict) -> Score:
        """A score from its round.json record (JSON lists back to tuples)."""
        tau = d.get("optical_depth")
        return cls(**{**d, "ml": tuple(d["ml"]),
                      "optical_depth": None if tau is None else tuple(tau)})

    @property
    def regime(self) -> str | None:
        """'thin', 'informative' or 'dense' (:func:`fitmedia.regimes.regime`)."""
        return regime(self.optical_depth)

    @property
    def z(self) -> float:
        """The truth's position in the posterior as a normal score: Phi^-1(1 - PIT), with the
        PIT kept inside [1e-4, 1 - 1e-4] (|z| <= 3.72).  For a normal posterior this is
        (median - truth) / sd; unlike that ratio it does not shrink when a second mode of g,
        however light, inflates the posterior's sd (docs/validation.md)."""
        from scipy.stats import norm

        return float(norm.isf(min(max(self.pit, PIT_CLIP), 1.0 - PIT_CLIP)))

    def inside(self, level: float) -> bool:
        """Is the truth inside the central ``level`` interval that results.json gives?"""
        tail = 0.5 * (1 - level)
        pit = self.pit if self.pit_envelope is None else self.pit_envelope
        return tail <= pit <= 1 - tail

    def describe(self) -> str:
        return (f"{self.medium} {'+'.join(f'{m:g}' for m in self.ml)} ml {self.channel} "
                f"{self.quantity}: truth {self.truth:.5g}, median {self.median:.5g} +- "
                f"{self.std:.3g} (z = {self.z:+.2f}, truth at posterior quantile {self.pit:.4f})")


def round_trip(geometry: Spec, medium: Medium, ml: list[float], out_dir: str | Path, *,
               seed: int = 0, options: FitOptions | None = None, tank_ml: float = 23000.0,
               name: str = "", synth_model: str = "single", synth_spp: int = 256
               ) -> list[Score]:
    """Synthesise ``medium`` at ``ml`` (ml in ``tank_ml``) with ``geometry`` (rendered by
    ``synth_model`` at ``synth_spp``, as ``fitmedia synth``), fit it, score it."""
    from .pipeline import fit
    from .synth import synthesize

    out = Path(out_dir)
    spec_path = synthesize(geometry, out / "capture", medium, list(ml), tank_ml=tank_ml, seed=seed,
                           medium_name=name or medium.name, model=synth_model, spp=synth_spp)
    opts = options or FitOptions(seed=seed, progress=False)
    fit(spec_path, out / "fit", opts, report=False)
    return score_fit(out / "fit", medium, ml, name=name or medium.name, spec=spec_path)


def optical_depths(spec: Spec, truth: Medium, channel: str) -> tuple[float, ...]:
    """Per image of ``spec``: the tank's extinction in ``channel`` (``truth`` at the image's
    concentration plus the clear water's absorption) times the distance from the light's
    centre to the inside of the front wall, mm."""
    from .spec import CHANNELS

    ci = CHANNELS.index(channel)
    return tank_optical_depths(spec, float(truth.kappa_t[ci]), ci)


def score_fit(fit_dir: str | Path, truth: Medium, ml: list[float], *, name: str,
              spec: Spec | str | Path | None = None) -> list[Score]:
    """Score a finished fit (``fit_dir`` with results.json and samples.npz) against ``truth``;
    with the capture's ``spec`` (or its path) each score also carries the optical depths."""
    from .inference.result import FitResult
    from .spec import load_spec

    fit_dir = Path(fit_dir)
    result = FitResult.from_json(fit_dir)
    trusted = bool((json.loads((fit_dir / "results.json").read_text()).get("trust") or {})
                   .get("ok", True))
    if spec is not None and not isinstance(spec, Spec):
        spec = load_spec(spec)
    values = truth.as_dict()
    scores = []
    with np.load(fit_dir / "samples.npz") as samples:
        for ch in result.channels:
            tau = optical_depths(spec, truth, ch) if spec is not None else None
            key = f"{ch}/uniform_albedo_weight"  # absent in fits made before 2026-12-06
            w = samples[key] if key in samples.files else None
            for q in SCORED:
                if q in _FROM_SAMPLES:
                    s = _FROM_SAMPLES[q](lambda n: samples[f"{ch}/{n}"])
                    t = float(_FROM_SAMPLES[q](lambda n: np.asarray(values[n][ch])))
                else:
                    s, t = samples[f"{ch}/{q}"], values[q][ch]
                scores.append(Score(name, tuple(ml), ch, q, t, float(np.median(s)),
                                    float(np.std(s)), float(np.mean(s < t)), tau,
                                    normal_score(s, t, q), trusted, envelope_pit(s, t, w)))
    return scores


def envelope_pit(samples: np.ndarray, truth: float, weights: np.ndarray | None = None) -> float:
    """The truth's posterior quantile (the fraction of ``samples`` below it) as results.json's
    intervals see it.  With ``weights`` (the albedo prior's uniform half) those intervals are
    the envelope of the samples' own and the reweighted samples' (``inference.summary``), so
    of the two quantiles (the reweighted one by ``weighted_cdf``) the one nearer 0.5, and 0.5
    where they lie on either side of it.  ``Score.inside`` reads it: true exactly where the
    envelope holds the truth."""
    s = np.asarray(samples, float)
    own = float(np.mean(s < truth))
    if weights is None:
        return own
    other = weighted_cdf(s, weights, truth)
    if (own - 0.5) * (other - 0.5) <= 0.0:
        return 0.5
    return own if abs(own - 0.5) < abs(other - 0.5) else other


def normal_score(samples: np.ndarray, truth: float, quantity: str) -> float | None:
    """The truth's distance from the posterior median in posterior standard deviations, in the
    coordinate the sampler moves in (log kappa for ``kappa_*``, atanh g for ``g``), where the
    posteriors are close to normal.  Unlike the PIT it resolves the far tails: a few thousand
    thinned draws cannot tell a quantile of 1e-4 from 1e-3.  None where the transform or the
    ratio is undefined (a zero kappa, |g| = 1, every sample equal: a spread at most
    :data:`DEGENERATE_SPREAD` of the samples' scale, so that the last bit of a sum, which
    differs between CPUs, cannot turn equal samples into a score of 1e15)."""
    f = np.arctanh if quantity == "g" else np.log
    x = np.asarray(samples, float)
    with np.errstate(all="ignore"):
        h, t = f(x), f(float(truth))
    # degeneracy judged on the samples themselves: rounding is relative to their scale (kappa
    # = 1 +- 1e-16 has log kappa ~ 1e-16, whose spread is not small next to its own scale)
    if not (h.size and np.all(np.isfinite(h)) and np.isfinite(t)) or is_degenerate(x):
        return None
    return float((np.median(h) - t) / np.std(h))


#: A spread of samples at most this fraction of their scale (largest |value|) is rounding
#: error, not a spread: np.std of 10 equal values is 0 or 1e-16 depending on the CPU's sums.
#: 1e-9 is ~1e7 ulps, far above the error of any sum here and far below a posterior's sd.
DEGENERATE_SPREAD = 1e-9


def is_degenerate(samples: np.ndarray) -> bool:
    """Are the (finite) ``samples`` all equal up to rounding, i.e. is their standard deviation
    at most :data:`DEGENERATE_SPREAD` times their largest absolute value (or exactly 0)?"""
    a = np.asarray(samples, float)
    return bool(np.std(a) <= DEGENERATE_SPREAD * float(np.max(np.abs(a), initial=0.0)))


#: Family-wise level of a round-trip grid (issue 2's test): a calibrated method puts every
#: value of the grid inside its simultaneous interval with at least this probability.
GRID_FAMILY_LEVEL = 0.99


@dataclass
class GridVerdict:
    """Is a grid of round-trip scores consistent with calibrated posteriors?  See
    :func:`grid_verdict`."""

    n: int
    z_limit: float  # |z_normal| beyond this: outside the simultaneous (Bonferroni) interval
    max_misses_99: int  # most values allowed outside their own 99 % interval
    outside: list[Score]
    misses_99: list[Score]
    worst: Score

    @property
    def passed(self) -> bool:
        return not self.outside and len(self.misses_99) <= self.max_misses_99

    def describe(self) -> str:
        lines = [f"worst: {self.worst.describe()}, normal score {_z_used(self.worst):+.2f}",
                 f"{len(self.outside)} of {self.n} values outside their simultaneous "
                 f"{GRID_FAMILY_LEVEL:.0%} intervals (|normal score| > {self.z_limit:.2f})",
                 f"{len(self.misses_99)} of {self.n} outside their own 99 % intervals "
                 f"(at most {self.max_misses_99} allowed)"]
        lines += [f"  outside: {s.describe()}" for s in self.outside]
        lines += [f"  99 % miss: {s.describe()}" for s in self.misses_99]
        return "\n".join(lines)


def _z_used(s: Score) -> float:
    """The score's normal score, or its PIT's where that is undefined (clipped at 3.72)."""
    return s.z if s.z_normal is None else s.z_normal


def grid_verdict(scores: Sequence[Score], family_level: float = GRID_FAMILY_LEVEL
                 ) -> GridVerdict:
    """Two conditions that a grid of n values from calibrated posteriors meets with probability
    >= ``family_level`` (about; exactly for independent normal values, tests/test_grid_verdict):

    1. every truth lies inside its simultaneous interval: |normal score| <= z_limit =
       Phi^-1(1 - (1 - family_level) / (2 n)) (Bonferroni; 3.69 for n = 45), judged by
       :func:`normal_score` (the PIT's z where that is undefined; NaN counts as outside);
    2. at most k values lie outside their own central 99 % interval (sample PIT), k the
       ``family_level`` quantile of Binomial(n, 0.01) (3 for n = 45).

    Asking for every value inside its own 99 % interval instead fails a calibrated method
    with probability 1 - 0.99^n (0.36 for n = 45): a test that fails a third of the time for
    correct code (docs/validation.md, "The round-trip grid").
    """
    from scipy.stats import binom, norm

    n = len(scores)
    if n == 0:
        raise ValueError("grid_verdict: no scores")
    z_limit = float(norm.isf((1.0 - family_level) / (2 * n)))
    outside = [s for s in scores if not abs(_z_used(s)) <= z_limit]
    misses = [s for s in scores if not s.inside(0.99)]
    worst = max(scores, key=lambda s: abs(_z_used(s)) if np.isfinite(_z_used(s)) else np.inf)
    return GridVerdict(n, z_limit, int(binom.ppf(family_level, n, 0.01)), outside, misses, worst)


def coverage_table(scores: list[Score], levels=LEVELS) -> str:
    """Per quantity: fraction of truths inside each central credible interval, mean z."""
    return _table({q: _block([s for s in scores if s.quantity == q], levels)
                   for q in SCORED if any(s.quantity == q for s in scores)}, levels)


def _table(blocks: dict[str, dict], levels: Sequence[float]) -> str:
    """The text table of per-quantity blocks (see :func:`_block`); z means over finite z."""
    lines = [f"{'quantity':15s} {'n':>4s} " + " ".join(f"{int(100 * lv):>5d}%" for lv in levels)
             + "   mean z  mean|z|"]
    for q, b in blocks.items():
        mz, maz = (np.nan if b[k] is None else b[k] for k in ("mean_z", "mean_abs_z"))
        lines.append(f"{q:15s} {b['n']:4d} " + " ".join(f"{c:6.2f}" for c in b["coverage"].values())
                     + f"   {mz:+6.2f}  {maz:6.2f}")
    return "\n".join(lines)


@dataclass
class ValidationResult:
    """What :func:`validate` found: ``rounds`` (one record per round: ``index``, ``medium``,
    ``ml``, ``seed``, ``dir``, ``status`` ``"done"``, ``"done earlier"``, ``"failed"`` or ``"skipped"`` (a
    black capture, nothing to score) with ``error``), ``scores`` (per round, channel and quantity), ``coverage`` (coverage.json, see
    :func:`coverage_summary`), ``table`` (coverage.txt) and the ``files`` written."""

    rounds: list[dict]
    scores: list[Score]
    coverage: dict
    table: str
    files: list[Path] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        """True when every quantity meets the coverage and bias criteria."""
        return bool(self.coverage["passed"])


def _block(sel: list[Score], levels: Sequence[float]) -> dict:
    z = np.array([s.z for s in sel], float)
    fin = np.isfinite(z)
    cov = {f"{round(100 * lv)}": float(np.mean([s.inside(lv) for s in sel])) for lv in levels}
    return {"n": len(sel), "coverage": cov,
            "coverage_90_standard_error": float(np.sqrt(0.9 * 0.1 / len(sel))),
            "mean_z": float(np.mean(z[fin])) if fin.any() else None,
            "mean_abs_z": float(np.mean(np.abs(z[fin]))) if fin.any() else None,
            "n_infinite_z": int(np.sum(~fin))}


def coverage_summary(scores: list[Score], levels: Sequence[float] = LEVELS) -> dict:
    """Coverage of the central credible intervals and standardised bias with the criteria.

    Returns
    -------
    dict
        ``quantities.<q>`` and ``media.<medium>.<q>``, each with ``n`` (rounds x channels),
        ``coverage`` (fraction of truths inside the central 68/90/99 % interval),
        ``coverage_90_standard_error`` (binomial), ``mean_z``, ``mean_abs_z`` (z = Phi^-1(1 -
        PIT), :attr:`Score.z`), ``n_infinite_z`` (0 since z became PIT-based; kept for
        readers of older files); ``regimes.<regime>.<q>``; ``trusted.<q>``: the same over the
        scores of fits that exited 0 (``Score.trusted`` not False), with
        ``n_untrusted_scores``; ``criteria.<q>`` (``coverage_90_ok``, ``bias_ok``,
        ``passed``), judged on all scores; ``passed``.
    """
    quantities = {q: _block([s for s in scores if s.quantity == q], levels)
                  for q in SCORED if any(s.quantity == q for s in scores)}
    media = {m: {q: _block([s for s in scores if s.medium == m and s.quantity == q], levels)
                 for q in quantities}
             for m in dict.fromkeys(s.medium for s in scores)}
    regimes = {r: {q: _block([s for s in scores if s.regime == r and s.quantity == q], levels)
                   for q in quantities if any(s.regime == r and s.quantity == q for s in scores)}
               for r in REGIMES if any(s.regime == r for s in scores)}
    kept = [s for s in scores if s.trusted is not False]
    trusted = {q: _block([s for s in kept if s.quantity == q], levels)
               for q in quantities if any(s.quantity == q for s in kept)}
    criteria = {}
    for q, b in quantities.items():
        c90, mz = b["coverage"]["90"], b["mean_z"]
        cov_ok = COVERAGE_90_RANGE[0] <= c90 <= COVERAGE_90_RANGE[1]
        bias_ok = mz is not None and abs(mz) < MAX_ABS_MEAN_Z
        criteria[q] = {"coverage_90_ok": cov_ok, "bias_ok": bias_ok, "passed": cov_ok and bias_ok}
    return {"levels": list(levels), "quantities": quantities, "media": media,
            "regimes": regimes, "trusted": trusted,
            "n_untrusted_scores": sum(s.trusted is False for s in scores),
            "regime_definition": {
                "optical_depth": "tank kappa_t x distance from the light to the front wall",
                "thin": f"every image below {INFORMATIVE_OPTICAL_DEPTH[0]:g}",
                "dense": f"every image above {INFORMATIVE_OPTICAL_DEPTH[1]:g}",
                "informative": "otherwise"},
            "criteria": criteria, "criteria_definition": {
                "coverage_90_range": list(COVERAGE_90_RANGE), "max_abs_mean_z": MAX_ABS_MEAN_Z},
            "passed": bool(criteria) and all(c["passed"] for c in criteria.values())}


def write_coverage(out: Path, rounds: list[dict], scores: list[Score]) -> ValidationResult:
    """Write coverage.json, coverage.txt and coverage.png into ``out`` (atomically)."""
    summary = coverage_summary(scores)
    failed = [r for r in rounds if r["status"] == "failed"]
    skipped = [r for r in rounds if r["status"] == "skipped"]
    lines = [f"{len(rounds)} rounds, {len(failed)} failed, {len(skipped)} skipped (a black "
             "capture: no glow above the noise, nothing to score); n counts rounds x channels",
             "",
             _table(summary["quantities"], LEVELS) if scores else "(no scores)"]
    for m, blocks in summary["media"].items():
        lines += ["", f"{m}:", _table(blocks, LEVELS)]
    lo, hi = INFORMATIVE_OPTICAL_DEPTH
    what = {"thin": f"optical depth light-to-wall < {lo:g}", "dense": f"> {hi:g}",
            "informative": f"{lo:g}-{hi:g}"}
    for r, blocks in summary["regimes"].items():
        lines += ["", f"regime {r} ({what[r]}):", _table(blocks, LEVELS)]
    if summary["n_untrusted_scores"]:
        lines += ["", f"only the fits that exited 0 (trust.ok; {summary['n_untrusted_scores']} of "
                  f"{len(scores)} scores are from fits that said their values cannot be "
                  "trusted, exit 1):",
                  _table(summary["trusted"], LEVELS) if summary["trusted"] else "(none)"]
    lines += ["", (f"criteria: 90 % intervals cover in {COVERAGE_90_RANGE[0]:.0%}-"
                   f"{COVERAGE_90_RANGE[1]:.0%} of the scores and |mean z| < {MAX_ABS_MEAN_Z}")]
    for q, c in summary["criteria"].items():
        lines.append(f"  {q:15s} {'pass' if c['passed'] else 'FAIL'}"
                     + ("" if c["coverage_90_ok"] else "  (90 % coverage out of range)")
                     + ("" if c["bias_ok"] else "  (|mean z| too large)"))
    lines += [f"  round {r['index']} ({r['medium']}): {r['error']}" for r in failed + skipped]
    table = "\n".join(lines) + "\n"
    summary["rounds"] = [{k: v for k, v in r.items() if k != "scores"} for r in rounds]
    files = [out / "coverage.json", out / "coverage.txt", out / "coverage.png"]
    write_json(files[0], summary)
    atomic_write_text(files[1], table)
    atomic_write(files[2], lambda p: _coverage_figure(rounds).savefig(p, format="png"))
    return ValidationResult(rounds, scores, summary, table, files)


def _coverage_figure(rounds: list[dict]):
    """Top: histogram of the truth's posterior quantile (PIT; uniform if calibrated) per
    quantity, with the ±2σ Poisson band.  Bottom: z per round, coloured by channel; open
    markers for fits that said their values cannot be trusted (exit 1)."""
    from matplotlib.ticker import MaxNLocator

    from .report.plots import new_figure

    fig = new_figure(3.2 * len(SCORED), 6.0)
    axes = fig.subplots(2, len(SCORED), squeeze=False)
    for k, q in enumerate(SCORED):
        sel = [(r["index"], Score.from_record(s)) for r in rounds for s in r.get("scores", [])
               if s["quantity"] == q]
        top, bottom, per_bin = axes[0, k], axes[1, k], len(sel) / 10
        top.hist([s.pit for _, s in sel], bins=10, range=(0, 1), color="0.6", edgecolor="k")
        top.axhline(per_bin, color="k", ls="--", lw=0.8)
        top.axhspan(max(per_bin - 2 * np.sqrt(per_bin), 0), per_bin + 2 * np.sqrt(per_bin),
                    color="k", alpha=0.1)
        top.set_title(f"{q} (n = {len(sel)}):\ntruth's posterior quantile", fontsize=9)
        top.set(xlabel="PIT (unitless)", ylabel="scores per bin", ylim=(0, None))
        for ch, colour in {"R": "tab:red", "G": "tab:green", "B": "tab:blue"}.items():
            for ok, face, tag in ((True, colour, ""), (False, "none", " (exit 1)")):
                pts = [(i, s.z) for i, s in sel if s.channel == ch and (s.trusted is not False) == ok]
                if pts or ok:
                    x, z = zip(*pts) if pts else ((), ())
                    bottom.plot(x, np.clip(z, -10, 10), "o", ms=3, color=colour, mfc=face,
                                label=ch + tag)
        for y in (-2, -1, 0, 1, 2):
            bottom.axhline(y, color="0.5", ls="-" if y == 0 else ":", lw=0.8)
        bottom.set(xlabel="round", ylabel="z = (median - truth) / std (clipped ±10)")
        bottom.xaxis.set_major_locator(MaxNLocator(integer=True))
        bottom.legend(fontsize=7)
    return fig

"""Synthetic round trips: synthesise a capture with known truth, fit it, and
score the posterior against the truth (standardised error, where the truth falls
in the posterior, coverage of credible intervals)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .inference.fit import FitOptions
from .medium import Medium
from .regimes import INFORMATIVE_OPTICAL_DEPTH, REGIMES, regime, tank_optical_depths
from .spec import Spec
from .util import atomic_write, atomic_write_text, write_json

SCORED = ("kappa_s", "kappa_t", "g")
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
        """Is the truth inside the central ``level`` credible interval?"""
        tail = 0.5 * (1 - level)
        return tail <= self.pit <= 1 - tail

    def describe(self) -> str:
        return (f"{self.medium} {'+'.join(f'{m:g}' for m in self.ml)} ml {self.channel} "
                f"{self.quantity}: truth {self.truth:.5g}, median {self.median:.5g} +- "
                f"{self.std:.3g} (z = {self.z:+.2f}, truth at posterior quantile {self.pit:.4f})")


def round_trip(geometry: Spec, medium: Medium, ml: list[float], out_dir: str | Path, *,
               seed: int = 0, options: FitOptions | None = None, tank_ml: float = 23000.0,
               name: str = "") -> list[Score]:
    """Synthesise ``medium`` at ``ml`` (ml in ``tank_ml``) with ``geometry``, fit it, score it."""
    from .pipeline import fit
    from .synth import synthesize

    out = Path(out_dir)
    spec_path = synthesize(geometry, out / "capture", medium, list(ml), tank_ml=tank_ml, seed=seed,
                           medium_name=name or medium.name)
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
    import json

    from .spec import load_spec

    fit_dir = Path(fit_dir)
    channels = json.loads((fit_dir / "results.json").read_text())["channels"]
    if spec is not None and not isinstance(spec, Spec):
        spec = load_spec(spec)
    values = truth.as_dict()
    scores = []
    with np.load(fit_dir / "samples.npz") as samples:
        for ch in channels:
            tau = optical_depths(spec, truth, ch) if spec is not None else None
            for q in SCORED:
                s, t = samples[f"{ch}/{q}"], values[q][ch]
                scores.append(Score(name, tuple(ml), ch, q, t, float(np.median(s)),
                                    float(np.std(s)), float(np.mean(s < t)), tau))
    return scores


def coverage_table(scores: list[Score], levels=LEVELS) -> str:
    """Per quantity: fraction of truths inside each central credible interval, mean z."""
    return _table({q: _block([s for s in scores if s.quantity == q], levels)
                   for q in SCORED if any(s.quantity == q for s in scores)}, levels)


def _table(blocks: dict[str, dict], levels: Sequence[float]) -> str:
    """The text table of per-quantity blocks (see :func:`_block`); z means over finite z."""
    lines = [f"{'quantity':10s} {'n':>4s} " + " ".join(f"{int(100 * lv):>5d}%" for lv in levels)
             + "   mean z  mean|z|"]
    for q, b in blocks.items():
        mz, maz = (np.nan if b[k] is None else b[k] for k in ("mean_z", "mean_abs_z"))
        lines.append(f"{q:10s} {b['n']:4d} " + " ".join(f"{c:6.2f}" for c in b["coverage"].values())
                     + f"   {mz:+6.2f}  {maz:6.2f}")
    return "\n".join(lines)


@dataclass
class ValidationResult:
    """What :func:`validate` found: ``rounds`` (one record per round: ``index``, ``medium``,
    ``ml``, ``seed``, ``dir``, ``status`` ``"done"``, ``"done earlier"`` or ``"failed"`` with
    ``error``), ``scores`` (per round, channel and quantity), ``coverage`` (coverage.json, see
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
        readers of older files); ``criteria.<q>``
        (``coverage_90_ok``, ``bias_ok``, ``passed``); ``passed``.
    """
    quantities = {q: _block([s for s in scores if s.quantity == q], levels)
                  for q in SCORED if any(s.quantity == q for s in scores)}
    media = {m: {q: _block([s for s in scores if s.medium == m and s.quantity == q], levels)
                 for q in quantities}
             for m in dict.fromkeys(s.medium for s in scores)}
    regimes = {r: {q: _block([s for s in scores if s.regime == r and s.quantity == q], levels)
                   for q in quantities if any(s.regime == r and s.quantity == q for s in scores)}
               for r in REGIMES if any(s.regime == r for s in scores)}
    criteria = {}
    for q, b in quantities.items():
        c90, mz = b["coverage"]["90"], b["mean_z"]
        cov_ok = COVERAGE_90_RANGE[0] <= c90 <= COVERAGE_90_RANGE[1]
        bias_ok = mz is not None and abs(mz) < MAX_ABS_MEAN_Z
        criteria[q] = {"coverage_90_ok": cov_ok, "bias_ok": bias_ok, "passed": cov_ok and bias_ok}
    return {"levels": list(levels), "quantities": quantities, "media": media,
            "regimes": regimes, "regime_definition": {
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
    lines = [f"{len(rounds)} rounds, {len(failed)} failed; n counts rounds x channels", "",
             _table(summary["quantities"], LEVELS) if scores else "(no scores)"]
    for m, blocks in summary["media"].items():
        lines += ["", f"{m}:", _table(blocks, LEVELS)]
    lo, hi = INFORMATIVE_OPTICAL_DEPTH
    what = {"thin": f"optical depth light-to-wall < {lo:g}", "dense": f"> {hi:g}",
            "informative": f"{lo:g}-{hi:g}"}
    for r, blocks in summary["regimes"].items():
        lines += ["", f"regime {r} ({what[r]}):", _table(blocks, LEVELS)]
    lines += ["", (f"criteria: 90 % intervals cover in {COVERAGE_90_RANGE[0]:.0%}-"
                   f"{COVERAGE_90_RANGE[1]:.0%} of the scores and |mean z| < {MAX_ABS_MEAN_Z}")]
    for q, c in summary["criteria"].items():
        lines.append(f"  {q:10s} {'pass' if c['passed'] else 'FAIL'}"
                     + ("" if c["coverage_90_ok"] else "  (90 % coverage out of range)")
                     + ("" if c["bias_ok"] else "  (|mean z| too large)"))
    lines += [f"  round {r['index']} ({r['medium']}): {r['error']}" for r in failed]
    table = "\n".join(lines) + "\n"
    summary["rounds"] = [{k: v for k, v in r.items() if k != "scores"} for r in rounds]
    files = [out / "coverage.json", out / "coverage.txt", out / "coverage.png"]
    write_json(files[0], summary)
    atomic_write_text(files[1], table)
    atomic_write(files[2], lambda p: _coverage_figure(rounds).savefig(p, format="png"))
    return ValidationResult(rounds, scores, summary, table, files)


def _coverage_figure(rounds: list[dict]):
    """Top: histogram of the truth's posterior quantile (PIT; uniform if calibrated) per
    quantity, with the ±2σ Poisson band.  Bottom: z per round, coloured by channel."""
    from matplotlib.ticker import MaxNLocator

    from .report.plots import new_figure

    fig = new_figure(11.0, 6.0)
    axes = fig.subplots(2, len(SCORED), squeeze=False)
    for k, q in enumerate(SCORED):
        sel = [(r["index"], Score.from_record(s)) for r in rounds for s in r.get("scores", [])
               if s["quantity"] == q]
        top, bottom, per_bin = axes[0, k], axes[1, k], len(sel) / 10
        top.hist([s.pit for _, s in sel], bins=10, range=(0, 1), color="0.6", edgecolor="k")
        top.axhline(per_bin, color="k", ls="--", lw=0.8)
        top.axhspan(max(per_bin - 2 * np.sqrt(per_bin), 0), per_bin + 2 * np.sqrt(per_bin),
                    color="k", alpha=0.1)
        top.set_title(f"{q}: truth's posterior quantile (n = {len(sel)})", fontsize=9)
        top.set(xlabel="PIT (unitless)", ylabel="scores per bin", ylim=(0, None))
        for ch, colour in {"R": "tab:red", "G": "tab:green", "B": "tab:blue"}.items():
            x, z = [i for i, s in sel if s.channel == ch], [s.z for _, s in sel if s.channel == ch]
            bottom.plot(x, np.clip(z, -10, 10), "o", ms=3, color=colour, label=ch)
        for y in (-2, -1, 0, 1, 2):
            bottom.axhline(y, color="0.5", ls="-" if y == 0 else ":", lw=0.8)
        bottom.set(xlabel="round", ylabel="z = (median - truth) / std (clipped ±10)")
        bottom.xaxis.set_major_locator(MaxNLocator(integer=True))
        bottom.legend(fontsize=7)
    return fig

"""Synthetic round trips: synthesise a capture with known truth, fit it, and
score the posterior against the truth (standardised error, where the truth falls
in the posterior, coverage of credible intervals)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .inference.fit import FitOptions
from .medium import Medium
from .spec import Spec

SCORED = ("kappa_s", "kappa_t", "g")


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

    @property
    def z(self) -> float:
        return (self.median - self.truth) / self.std if self.std > 0 else np.inf

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
    return score_fit(out / "fit", medium, ml, name=name or medium.name)


def score_fit(fit_dir: str | Path, truth: Medium, ml: list[float], *, name: str) -> list[Score]:
    """Score a finished fit (``fit_dir`` with results.json and samples.npz) against ``truth``."""
    import json

    fit_dir = Path(fit_dir)
    channels = json.loads((fit_dir / "results.json").read_text())["channels"]
    values = truth.as_dict()
    scores = []
    with np.load(fit_dir / "samples.npz") as samples:
        for ch in channels:
            for q in SCORED:
                s, t = samples[f"{ch}/{q}"], values[q][ch]
                scores.append(Score(name, tuple(ml), ch, q, t, float(np.median(s)),
                                    float(np.std(s)), float(np.mean(s < t))))
    return scores


def coverage_table(scores: list[Score], levels=(0.68, 0.9, 0.99)) -> str:
    """Per quantity: fraction of truths inside each central credible interval, mean z."""
    lines = [f"{'quantity':10s} {'n':>4s} " + " ".join(f"{int(100 * lv):>5d}%" for lv in levels)
             + "   mean z  mean|z|"]
    for q in SCORED:
        sel = [s for s in scores if s.quantity == q]
        if not sel:
            continue
        z = np.array([s.z for s in sel])
        cov = [np.mean([s.inside(lv) for s in sel]) for lv in levels]
        lines.append(f"{q:10s} {len(sel):4d} " + " ".join(f"{c:6.2f}" for c in cov)
                     + f"   {np.mean(z):+6.2f}  {np.mean(np.abs(z)):6.2f}")
    return "\n".join(lines)

"""Coverage of a finished ``fitmedia validate`` run's intervals: the posterior's own (the
albedo mixture prior) against results.json's since 2026-12-06, the envelope of those and the
intervals under the prior's uniform-in-albedo half alone (docs/inference.md, "The intervals:
an envelope over the albedo prior's halves").

For a run made before the envelope (its samples.npz without ``<ch>/uniform_albedo_weight``) the
weights are computed here from the samples' albedo and the fit's prior bounds, as the fit now
does (``ParameterSpace.uniform_albedo_weights``).  Prints, per quantity, the 68 % and 90 %
coverage both ways, over all rounds and over the rounds that exited 0, with the channels whose
kappa_a was unresolved (``kappa_a_upper_limit_only``) apart, and how much wider the envelope's
90 % intervals are (median and largest ratio).

Run: python docs/studies/albedo_envelope.py VALIDATE_OUT    (seconds)
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy.special import expit

from fitmedia.inference.params import ParameterSpace
from fitmedia.inference.summary import summarise
from fitmedia.validate import envelope_pit

QUANTITIES = ("kappa_t", "kappa_s", "g", "kappa_s_reduced")


def channel_rows(d: Path, rec: dict) -> list[dict]:
    """One finished round's scores, both ways, per channel and quantity."""
    res = json.loads((d / "fit" / "results.json").read_text())
    truth = json.loads((d / "capture" / "truth.json").read_text())["undiluted"]
    lo, hi = res["priors"]["bounds"]["logit_albedo"]
    space = ParameterSpace(priors={"albedo": [float(expit(lo)), float(expit(hi))]})
    rows = []
    with np.load(d / "fit" / "samples.npz") as s:
        for ch in res["channels"]:
            info = res["diagnostics"]["channels"][ch]
            w = space.uniform_albedo_weights(s[f"{ch}/unconstrained"][:, 1])
            for q in QUANTITIES:
                if q == "kappa_s_reduced":
                    x = s[f"{ch}/kappa_s"] * (1 - s[f"{ch}/g"])
                    t = truth["kappa_s"][ch] * (1 - truth["g"][ch])
                else:
                    x, t = s[f"{ch}/{q}"], truth[q][ch]
                own, env = summarise(x, 0.0), summarise(x, 0.0, w)
                rows.append({"q": q, "trusted": bool(rec["trust"]["ok"]),
                             "unresolved": bool(info.get("kappa_a_upper_limit_only")),
                             "pit": float(np.mean(x < t)), "pit_env": envelope_pit(x, t, w),
                             "widen": (env["q95"] - env["q05"]) / (own["q95"] - own["q05"])})
    return rows


def coverage(rows: list[dict], key: str, level: float) -> str:
    tail = 0.5 * (1 - level)
    return f"{np.mean([tail <= r[key] <= 1 - tail for r in rows]):.2f}" if rows else "-"


def main() -> None:
    rows = []
    for rj in sorted(Path(sys.argv[1]).glob("round_*/round.json")):
        rec = json.loads(rj.read_text())
        if rec.get("status") == "done":
            rows += channel_rows(rj.parent, rec)
    print("| quantity | rounds | n | 68 % own / envelope | 90 % own / envelope | 90 %, kappa_a "
          "unresolved (n) | 90 % width, envelope / own: median, largest |")
    print("|---|---|---|---|---|---|---|")
    for q in QUANTITIES:
        for label, sel in (("all", [r for r in rows if r["q"] == q]),
                           ("exit 0", [r for r in rows if r["q"] == q and r["trusted"]])):
            un = [r for r in sel if r["unresolved"]]
            widen = [r["widen"] for r in sel]
            print(f"| {q} | {label} | {len(sel)} | {coverage(sel, 'pit', .68)} / "
                  f"{coverage(sel, 'pit_env', .68)} | {coverage(sel, 'pit', .9)} / "
                  f"{coverage(sel, 'pit_env', .9)} | {coverage(un, 'pit', .9)} / "
                  f"{coverage(un, 'pit_env', .9)} ({len(un)}) | "
                  f"{np.median(widen):.3f}, {np.max(widen):.2f} |")


if __name__ == "__main__":
    main()

"""The table rows and the running coverage of a coverage run's kept round records
(docs/studies/coverage_rounds.py's KEEP; docs/validation.md, "A coverage run at 100 x 75
pixels").

Per round: the liquid and ml, the fit's exit code (0 when results.json's trust was ok) and
why not, the errors of the posterior median of kappa_t and kappa_s' against the truth (%)
and kappa_t's z (:attr:`fitmedia.validate.Score.z`), as markdown rows.  Then, over every
kept round: per quantity, how many channels' 90 % intervals (results.json's, the envelope's)
held the truth, the mean and sd of z, and every value beyond its 95 % interval.

Run: python docs/studies/coverage_rows.py docs/studies/coverage100
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from fitmedia.validate import SCORED, Score


def row(rec: dict) -> str:
    sc = {(s.channel, s.quantity): s for s in map(Score.from_record, rec["scores"])}
    chans = [c for c in "RGB" if (c, "kappa_t") in sc]
    trust = rec.get("trust") or {}
    code = "0" if trust.get("ok") else f"1 ({', '.join(trust.get('reason_kinds') or []) or '?'})"

    def err(q: str) -> str:
        return " / ".join(f"{100 * (sc[c, q].median / sc[c, q].truth - 1):+.2f}" for c in chans) + " %"

    z = " / ".join(f"{sc[c, 'kappa_t'].z:+.1f}" for c in chans)
    ml = "+".join(f"{m:g}" for m in rec["ml"])
    return f"| {rec['index']} | {rec['medium']} {ml} | {code} | {err('kappa_t')} | {z} | {err('kappa_s_reduced')} |"


def main(keep: Path) -> None:
    recs = sorted((json.loads(p.read_text()) for p in keep.glob("round_*.json")),
                  key=lambda r: r["index"])
    print("| round | liquid, ml | exit | kappa_t error R / G / B | z of kappa_t R / G / B "
          "| kappa_s' error R / G / B |\n|---|---|---|---|---|---|")
    for rec in recs:
        print(row(rec))
    scores = [Score.from_record(s) for r in recs for s in r["scores"]]
    print(f"\n{len(recs)} rounds: {[r['index'] for r in recs]}")
    for q in SCORED:
        sel = [s for s in scores if s.quantity == q]
        z = np.array([s.z for s in sel])
        print(f"{q}: 90 % intervals held {sum(s.inside(0.90) for s in sel)} of {len(sel)}; "
              f"mean z {z.mean():+.2f}, sd z {z.std(ddof=1) if len(z) > 1 else float('nan'):.2f}")
        for s in sel:
            if not s.inside(0.95):
                print(f"   beyond 95 %: {s.describe()}")


if __name__ == "__main__":
    main(Path(sys.argv[1]))

"""Issue 2's round-trip grid at several seeds: how often does the whole grid pass, and how many
of its values miss their 99 % intervals?

Two criteria are counted: the test's (``fitmedia.validate.grid_verdict``: every value inside
its simultaneous 99 % interval, at most 3 outside their own 99 % intervals; a calibrated method
passes 98.9 % of grids) and the older "every value inside its own 99 % interval" (0.99^45 =
0.64).

Runs the grid of ``tests/test_roundtrip.py::test_round_trip_grid_recovers_truth_within
_99_percent`` through that file's ``grid_scores`` (same media, 64 x 48 geometry and options;
medium k at seed + k) at each seed given, appends one JSON line per seed to --out (a rerun
skips the seeds already there), then summarises: grids passed against the count a calibrated
method would give (Binomial(n, p_all), p_all = 0.99^45 for independent values), and the misses
over all values against Binomial(45 n, 0.01).

  python docs/studies/grid_seeds.py --seeds 100 200 300 400 500 600 700 800 --out rows.jsonl

The seeds should be fixed before the run (docs/validation.md lists the ones used); seeds
that differ by less than len(GRID) share synthetic-capture seeds between media.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from scipy.stats import binom

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from test_roundtrip import grid_scores  # noqa: E402

from fitmedia.validate import grid_verdict  # noqa: E402

LEVEL = 0.99


def run_seed(seed: int) -> dict:
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        scores = grid_scores(seed, Path(tmp))
    worst = max(scores, key=lambda s: abs(s.pit - 0.5))
    verdict = grid_verdict(scores)
    return {"seed": seed, "n_values": len(scores), "wall_s": round(time.perf_counter() - t0, 1),
            "misses": [s.describe() for s in scores if not s.inside(LEVEL)],
            "worst": worst.describe(), "pits": [s.pit for s in scores],
            "z_normal": [s.z_normal for s in scores], "verdict_passed": verdict.passed,
            "verdict": verdict.describe()}


def summarise(rows: list[dict]) -> None:
    n = len(rows)
    if not n:
        return
    m = rows[0]["n_values"]
    passed = sum(not r["misses"] for r in rows)
    misses = sum(len(r["misses"]) for r in rows)
    p_all = LEVEL ** m
    p_misses = binom.sf(misses - 1, n * m, 1 - LEVEL)
    print(f"{n} grids of {m} values: {passed} passed (expected {n * p_all:.1f} for independent "
          f"values, P(<= {passed}) = {binom.cdf(passed, n, p_all):.3f}); "
          f"{misses} of {n * m} values outside their {LEVEL:.0%} intervals (expected "
          f"{n * m * (1 - LEVEL):.1f}, P(>= {misses}) = {p_misses:.3f})")
    judged = [r for r in rows if "verdict_passed" in r]
    if judged:
        v_pass = sum(r["verdict_passed"] for r in judged)
        print(f"the test's criterion (grid_verdict): {v_pass} of {len(judged)} grids passed "
              f"(expected {0.989 * len(judged):.1f}, P(<= {v_pass}) = "
              f"{binom.cdf(v_pass, len(judged), 0.989):.3f})")
    for r in rows:
        print(f"  seed {r['seed']}: every value inside its own interval: "
              f"{'yes' if not r['misses'] else 'no'} ({r['wall_s']} s); "
              f"worst: {r['worst']}")
        if "verdict" in r:
            print("    grid_verdict: " + ("passes" if r["verdict_passed"] else "FAILS") + "; "
                  + r["verdict"].replace("\n", "\n    "))
        for miss in r["misses"]:
            print(f"    miss: {miss}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--out", default="grid_seeds.jsonl")
    a = ap.parse_args(argv)
    out = Path(a.out)
    rows = [json.loads(line) for line in out.read_text().splitlines()] if out.exists() else []
    done = {r["seed"] for r in rows}
    for s in a.seeds:
        if s in done:
            continue
        row = run_seed(s)
        rows.append(row)
        with open(out, "a") as f:  # one line per seed: a killed run loses at most the seed
            f.write(json.dumps(row) + "\n")
        print(f"seed {s}: grid_verdict {'passes' if row['verdict_passed'] else 'FAILS'}; "
              f"{len(row['misses'])} of {row['n_values']} outside their own "
              f"{LEVEL:.0%} intervals ({row['wall_s']} s)", flush=True)
    summarise([r for r in rows if r["seed"] in set(a.seeds)])


if __name__ == "__main__":
    main()

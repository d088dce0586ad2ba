"""The MAP pipeline on many fresh synthetic captures: is its Laplace interval calibrated?

Each capture is synthesised with its own seed (noise and clear-water photo redrawn), then each
channel goes through ``fit_channel`` with the sampler off: the global search, the local searches
on both signs of g, the polish and the Laplace covariance, with the capture's own calibration.
z = (MAP - truth) / Laplace sd in the sampler's coordinates (log kappa_t, logit albedo, atanh g,
log brightness).  Also counts the channels whose other-sign optimum of g is within 5 and 2
log-posterior units of the MAP, and MAPs in the backward mode.

  python docs/studies/map_pipeline_study.py "Head & Shoulders Shampoo" 40 --captures 300 \
      --start 10000 --out rows.jsonl          (docs/validation.md, "The lead settled")

Rows are appended to --out as they finish (two processes on two ranges of --start share a file).
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from fitmedia.inference.fit import FitOptions, channel_args, fit_channel, prepare
from fitmedia.medium import medium_by_name
from fitmedia.spec import CHANNELS, load_spec
from fitmedia.synth import synthesize

ROOT = Path(__file__).resolve().parents[2]


def run(a) -> None:
    med = medium_by_name(a.medium)
    geo = load_spec(a.spec, require_images=False)
    with open(a.out, "a") as out:
        for s in range(a.start, a.start + a.captures):
            with tempfile.TemporaryDirectory() as tmp:
                spec = load_spec(synthesize(geo, tmp, med, [a.ml], seed=s))
                prep = prepare(spec)
            for ch in a.channels:
                r = fit_channel(*channel_args(prep, ch, FitOptions(mcmc=False, progress=False,
                                                                   seed=s), None))
                cov = r["laplace_cov"]
                out.write(json.dumps({
                    "seed": s, "ch": ch, "x_map": r["x_map"].tolist(),
                    "sd": None if cov is None else np.sqrt(np.diag(cov)).tolist(),
                    "map": r["map"], "other": r["other_g_mode"]}) + "\n")
                out.flush()


def summarise(a) -> None:
    med = medium_by_name(a.medium)
    rows = [json.loads(line) for line in open(a.out)]
    for ch in a.channels:
        rs = [r for r in rows if r["ch"] == ch and r["sd"]]
        x, sd = np.array([r["x_map"] for r in rs]), np.array([r["sd"] for r in rs])
        ci = CHANNELS.index(ch)
        kt = med.kappa_t[ci]
        alb = med.kappa_s[ci] / kt
        # the sampler's kappa_t is the undiluted liquid's, as in results.json
        truth = np.array([np.log(kt), np.log(alb / (1 - alb)), np.arctanh(med.g[ci]), 0.0])
        z = (x - truth) / sd
        d = np.array([r["other"]["delta_log_posterior"] if r["other"] else -np.inf
                      for r in rows if r["ch"] == ch])
        print(f"{ch}: {len(rs)} captures; z mean / sd: " + ", ".join(
            f"{n} {z[:, j].mean():+.2f} / {z[:, j].std():.2f}" for j, n in enumerate(
                ("log_kappa_t", "logit_albedo", "atanh_g", "log_brightness"))))
        print(f"   atanh g: spread of the MAP {np.std(x[:, 2] - truth[2]):.4f}, mean Laplace sd "
              f"{sd[:, 2].mean():.4f}; outside 99 %: {int(np.sum(abs(z[:, 2]) > 2.576))}; "
              f"other mode within 5: {int(np.sum(d > -5))}, within 2: {int(np.sum(d > -2))}; "
              f"backward MAPs: {int(np.sum(x[:, 2] < 0))}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("medium")
    ap.add_argument("ml", type=float)
    ap.add_argument("--captures", type=int, default=100)
    ap.add_argument("--start", type=int, default=10000, help="first capture's synth seed")
    ap.add_argument("--channels", default="RGB")
    ap.add_argument("--spec", default=str(ROOT / "capture_specs" / "bulb_64x48.yaml"))
    ap.add_argument("--out", default="map_pipeline_rows.jsonl")
    ap.add_argument("--summary-only", action="store_true")
    a = ap.parse_args(argv)
    if not a.summary_only:
        run(a)
    summarise(a)


if __name__ == "__main__":
    main()

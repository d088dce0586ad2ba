"""The same synthetic capture written as a float TIFF, a 3-frame 16-bit bracket with a dark
frame, and Bayer DNGs, each fitted (the fit's own MAP search, no MCMC) with Laplace standard
deviations: issue 16, docs/spec.md "Camera formats compared".

Per format and channel it prints the MAP, the Laplace sd of log kappa_t, log kappa_s and
atanh g, the z-scores against the truth and between formats, chi2/pixel at the MAP and at the
TRUE parameters (true brightness: the per-pixel variance is right when it is ~1 within
sqrt(2 / n)).  The writers and the posterior are those of tests/test_camera_formats.py.

Run: PYTHONPATH=. python docs/studies/camera_formats.py [SEED] [OUT_DIR]
     (64x48, three channels; about 2 CPU-minutes per format)
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from conftest import geometry_dict  # noqa: E402
from test_camera_formats import (channel_problem, laplace_sd, render_truth,  # noqa: E402
                                 truth_vector, write_formats)

from fitmedia.inference.fit import FitOptions, prepare, run_channels  # noqa: E402
from fitmedia.spec import load_spec  # noqa: E402

SEED = int(sys.argv[1]) if len(sys.argv) > 1 else 7
OUT = Path(sys.argv[2] if len(sys.argv) > 2 else "camera_formats_out")
W, H = 64, 48


def main() -> None:
    geo = geometry_dict(width=W, height=H)
    lit, clear, truth, c = render_truth(geo, ("R", "G", "B"))
    formats = write_formats(OUT, geo, lit, clear, c, np.random.default_rng(SEED))
    print("truth", json.dumps(truth))
    rows = {}
    for name, (path, k) in formats.items():
        t0 = time.process_time()
        prep = prepare(load_spec(path))
        fits = run_channels(prep, FitOptions(mcmc=False, workers=1, progress=False), None)
        rows[name] = {}
        for ch, t in truth.items():
            f = fits[ch]
            problem, space = channel_problem(prep, ch)
            chi2_t, n = problem.chi2(truth_vector(space, t, k))
            problem.adapt(f["x_map"])  # the fit's quadrature at its MAP
            est, sd = laplace_sd(problem, space, f["x_map"], f["laplace_cov"])
            ref = np.log([t["kappa_t"], t["kappa_s"]]).tolist() + [np.arctanh(t["g"])]
            rows[name][ch] = {
                "kappa_t": float(np.exp(est[0])), "kappa_s": float(np.exp(est[1])),
                "g": float(np.tanh(est[2])), "sd": sd.round(4).tolist(), "est": est,
                "z_truth": ((est - ref) / sd).round(2).tolist(),
                "chi2_map": round(f["chi2"][0] / f["chi2"][1], 3),
                "chi2_truth": round(chi2_t / n, 3), "n": n,
                "chi2_truth_sd": round(float(np.sqrt(2.0 / n)), 3)}
        print(name, f"{time.process_time() - t0:.0f} s CPU", flush=True)
        for ch, r in rows[name].items():
            print(f"  {ch}: kappa_t {r['kappa_t']:.3f} kappa_s {r['kappa_s']:.3f} g {r['g']:.4f}"
                  f"  sd(log kt, log ks, atanh g) {r['sd']}  z vs truth {r['z_truth']}"
                  f"  chi2/px MAP {r['chi2_map']} truth {r['chi2_truth']} (n {r['n']}, "
                  f"sd {r['chi2_truth_sd']})", flush=True)
    names = list(rows)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            z = {ch: ((rows[a][ch]["est"] - rows[b][ch]["est"])
                      / np.hypot(rows[a][ch]["sd"], rows[b][ch]["sd"])).round(2).tolist()
                 for ch in truth}
            print(f"z {a} - {b} (log kt, log ks, atanh g):", json.dumps(z))


if __name__ == "__main__":
    main()

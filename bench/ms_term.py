"""Cost and error of the multiple-scattering term (fitmedia.forward.multiple).

For the canonical 200 x 150 bulb capture (capture_specs/bulb.yaml) and each medium, the
analytic single-scattering render of the three channels is timed (median of repeats, warm),
then the term's render (traced at 50 x 38, bin 4) at a few path counts.  Printed per path
count: wall and CPU time (this process), their ratios to the analytic render measured in
the same run (on a shared machine the CPU-time ratio is the steadier one), and the
term's Monte Carlo error two ways, both from 16 independent batches: the relative standard
error of the term summed over the glow (pixels off the bulb whose analytic order 1 is above
1e-3 of its brightest), and the median over the glow of each pixel's relative standard error.
numpy runs single-threaded (OMP_NUM_THREADS=1), as in bench/forward_single.py.

Usage:  python bench/ms_term.py [n_paths ...]     (default 16 64)
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from fitmedia.forward.multiple import MultipleScattering  # noqa: E402
from fitmedia.forward.single import SingleScattering  # noqa: E402
from fitmedia.medium import medium_by_name  # noqa: E402
from fitmedia.spec import load_spec  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CASES = [("Lowfat Milk", 16), ("Espresso", 8)]


def main(paths: list[int]) -> None:
    spec = load_spec(ROOT / "capture_specs" / "bulb.yaml", require_images=False)
    ss = SingleScattering(spec, None)
    for name, ml in CASES:
        m = medium_by_name(name).scaled(ml / 23000)
        args = (m.kappa_a, m.kappa_s, m.g, np.ones(3))
        ss.render(*args)
        t, c = [], []
        for _ in range(7):
            t0, c0 = time.perf_counter(), time.process_time()
            single = ss.render(*args)
            t.append(time.perf_counter() - t0)
            c.append(time.process_time() - c0)
        t_ss, c_ss = float(np.median(t)), float(np.median(c))
        bulb = ss.render(m.kappa_t, np.zeros(3), m.g, np.ones(3)) > 0
        print(f"{name} {ml} ml in 23 l, 200 x 150 x 3: analytic single scattering {t_ss * 1e3:.1f} ms "
              f"wall, {c_ss * 1e3:.1f} ms CPU")
        for n in paths:
            ms = MultipleScattering(spec, None, n_paths=n, batches=16)
            t0, c0 = time.perf_counter(), time.process_time()
            per = []  # (16, H, W) per channel: batch images, for the glow-sum error
            for k in range(3):
                kt, a, g = float(m.kappa_t[k]), float(m.albedo[k]), float(m.g[k])
                orders = ms.orders(kt, g, rr_albedo=a)
                pw = a ** np.arange(orders.shape[1])
                pw[0] = 0.0
                per.append(np.stack([ms.upsample(r).reshape(ms.shape)
                                     for r in np.tensordot(orders, pw, axes=([1], [0]))]))
            dt, dc = time.perf_counter() - t0, time.process_time() - c0
            rows = []
            for k, ch in enumerate("RGB"):
                s = single[..., k]
                glow = ~bulb[..., k] & (s > 1e-3 * s[~bulb[..., k]].max())
                b = per[k][:, glow]
                sums = b.sum(1)
                mean, se = b.mean(0), b.std(0, ddof=1) / 4
                share = sums.mean() / (sums.mean() + s[glow].sum())
                err_sum = sums.std(ddof=1) / 4 / sums.mean()
                rows.append(f"{ch}: share {share:.3f}, glow-sum error {err_sum:.2%}, "
                            f"median pixel error {np.median(se[mean > 0] / mean[mean > 0]):.0%}")
            paths_total = n * ms.low_shape[0] * ms.low_shape[1] * 3
            print(f"  {n:4d} paths per 4x4 px ({paths_total / 1e6:.2f} M paths): {dt:6.1f} s wall = "
                  f"{dt / t_ss:5.0f} x analytic, {dc:6.1f} s CPU = {dc / c_ss:5.0f} x; "
                  + "; ".join(rows), flush=True)


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [16, 64])

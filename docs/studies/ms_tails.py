"""How the multiple-scattering term's error falls with its paths, and why: the paths'
contributions per pixel are heavy-tailed (docs/multiple_scattering.md, "Heavy tails per
pixel").

Scene: the canonical tank and bulb at 16 x 12 px (tests/conftest.py's geometry), Lowfat Milk
16 ml in 23 l, channel G, one sample pixel per camera pixel (bin 1).

1. Per-path contributions (one batch per path, 2048 paths, orders up to 120) at four pixels
   ranked by their mean: the share of the largest path and of the largest ten in the
   pixel's sum, and a Hill estimate of the tail index from the 50 largest (below 2: infinite
   variance; below 1: the sum is made by its largest terms).
2. Across seeds (4 independent renders per path count): the median over the pixels of the
   relative sd between the renders, at 256, 1024, 4096 and 16384 paths per pixel (for a
   finite-variance estimator it halves for every 4x the paths), and the four renders of the
   median pixel (a heavy tail makes a typical render too low there at few paths).

Run: python docs/studies/ms_tails.py   (about 2 CPU-minutes)
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from conftest import make_spec  # noqa: E402

from fitmedia.forward.multiple import MultipleScattering  # noqa: E402
from fitmedia.medium import medium_by_name  # noqa: E402


def main() -> None:
    spec = make_spec(width=16, height=12)
    med = medium_by_name("Lowfat Milk").scaled(16 / 23000)
    k = 1  # G
    kt = med.kappa_a[k] + med.kappa_s[k]
    a, g = med.kappa_s[k] / kt, med.g[k]
    n = 2048
    ms = MultipleScattering(spec, None, channels=("G",), bin=1, n_paths=n, batches=n)
    acc, _ = ms.tracer.trace(kt, g, n, 3, n, 120, a)
    pw = a ** np.arange(acc.shape[1])
    pw[0] = 0.0
    per = np.tensordot(acc, pw, axes=([1], [0]))  # (paths, pixels)
    mean = per.mean(0)
    lit = np.flatnonzero(mean > 0)
    ranked = lit[np.argsort(mean[lit])]
    print(f"1. per-path contributions, {n} paths per pixel")
    for q in (0.25, 0.5, 0.75, 0.99):
        p = ranked[int(q * (len(ranked) - 1))]
        x = np.sort(per[:, p])[::-1]
        hill = 1.0 / np.mean(np.log(x[:50] / x[50])) if x[50] > 0 else float("nan")
        print(f"   pixel {p} (quantile {q:.2f} of the means, mean {mean[p]:.3g}): largest path "
              f"{x[0] / x.sum():.2f} of the sum, largest 10 {x[:10].sum() / x.sum():.2f}, "
              f"tail index {hill:.2f}")
    dim = ranked[int(0.5 * (len(ranked) - 1))]  # the median pixel
    print("2. across 4 seeds")
    for paths in (256, 1024, 4096, 16384):
        m = MultipleScattering(spec, None, channels=("G",), bin=1, n_paths=paths, batches=16)
        imgs = np.array([m.combine(m.orders(kt, g, seed=s, rr_albedo=a), a)[0]
                         for s in range(5, 9)])
        mu = imgs.mean(0)
        ok = mu > 0
        rel = np.median(imgs.std(0, ddof=1)[ok] / mu[ok])
        print(f"   {paths:6d} paths: median relative sd between seeds {rel:.3f}; the median "
              f"pixel ({dim}): its 4 renders {np.round(imgs[:, dim] * 1e5, 2).tolist()} x 1e-5")


if __name__ == "__main__":
    main()

"""Is the multiple-scattering term's expectation independent of the number of paths?
(docs/inference.md, "Full transport", the g offset at the truth.)

For a one-image, one-channel capture with truth.json (the tank's medium at its image), the
term (all orders, and order 2 alone) is traced at 256 paths per pixel with N seeds and at
16384 paths with 2 other seeds, and their sums over the glow (pixels above 5 % of the
brightest) compared: a ratio of 1 within its standard error (over the N seeds) says the
estimator has no path-count bias there.  Also per region: the brightest tenth of the glow
and the next 40 %.

Run: python docs/studies/ms_term_expectation.py CAPTURE_DIR [N_SEEDS]   (~3 CPU-min at 32 x 24)
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from fitmedia.forward.multiple import MultipleScattering
from fitmedia.spec import load_spec


def term(spec, ch, kt, g, a, n_paths, seed):
    """(all orders, order 2) per traced pixel, mean over the batches, unit bulb."""
    ms = MultipleScattering(spec, 0, channels=(ch,), bin=1, n_paths=n_paths)
    o = ms.orders(kt, g, seed=seed, rr_albedo=a)
    pw = a ** np.arange(o.shape[1])
    pw[0] = 0.0
    return (np.tensordot(o, pw, axes=([1], [0])).mean(0),
            np.tensordot(o[:, :3], pw[:3], axes=([1], [0])).mean(0))


def main():
    cap = Path(sys.argv[1])
    n = int(sys.argv[2]) if len(sys.argv) > 2 else 32
    spec = load_spec(cap / "capture.yaml")
    ch = spec.channels[0]
    tank = json.loads((cap / "truth.json").read_text())["images"][0]["tank"]
    args = (spec, ch, tank["kappa_t"][ch], tank["g"][ch], tank["albedo"][ch])
    ref = [term(*args, 16384, 9000 + s) for s in range(2)]
    low = [term(*args, 256, 100 + s) for s in range(n)]
    for k, name in ((0, "all orders"), (1, "order 2")):
        r = np.mean([x[k] for x in ref], axis=0)
        lo = np.array([x[k] for x in low])
        glow = r > 0.05 * r.max()
        sums = lo[:, glow].sum(axis=1) / r[glow].sum()
        print(f"{name}: 256-path mean / 16384-path {sums.mean():.4f} +- "
              f"{sums.std(ddof=1) / np.sqrt(n):.4f} ({n} seeds; per seed sd {sums.std(ddof=1):.4f})")
    r = np.mean([x[0] for x in ref], axis=0)
    lo = np.array([x[0] for x in low])
    order = np.argsort(-r)
    for name, sel in (("brightest 10 %", order[: len(order) // 10]),
                      ("next 40 %", order[len(order) // 10: len(order) // 2])):
        s = lo[:, sel].sum(axis=1) / r[sel].sum()
        print(f"{name} of the pixels: {s.mean():.4f} +- {s.std(ddof=1) / np.sqrt(n):.4f}")


if __name__ == "__main__":
    main()

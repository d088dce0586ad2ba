"""Speed and accuracy of the analytic single-scattering model.

Prints, for one 200 x 150 x 3 image of the canonical bulb capture (diluted milk):
the wall time per render on one core (median of repeats, numpy single-threaded),
and its error against the same model with 16x as many quadrature nodes per ray
(128 + 128), as max and mean relative difference over pixels with signal, plus the
ratio to the target (20 ms, 0.1 %).  The frozen-node render (what a fit uses after
the MAP) is timed too, as a ratio against the adaptive render measured in this run.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from fitmedia.forward.single import SingleScattering  # noqa: E402
from fitmedia.medium import medium_by_name  # noqa: E402
from fitmedia.spec import load_spec  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def timed(fn, repeats=15):
    fn()
    t = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        t.append(time.perf_counter() - t0)
    return float(np.median(t))


def main() -> None:
    spec = load_spec(ROOT / "capture_specs" / "bulb.yaml", require_images=False)
    for name, ml in [("Lowfat Milk", 16), ("Regular Milk", 240), ("Espresso", 8)]:
        m = medium_by_name(name).scaled(ml / 23000)
        args = (m.kappa_a, m.kappa_s, m.g, np.ones(3))
        model = SingleScattering(spec)
        fine = SingleScattering(spec, nodes=128, nodes_upper=128)
        t = timed(lambda: model.render(*args))
        img, ref = model.render(*args), fine.render(*args)
        sig = ref > 1e-3 * ref.max(axis=(0, 1))
        rel = np.abs(img - ref)[sig] / ref[sig]
        model.freeze_nodes(m.kappa_t, m.g)
        tf = timed(lambda: model.render(*args))
        print(f"{name} {ml} ml, 200x150x3: render {1e3 * t:.1f} ms (target 20 ms: ratio {t / 0.020:.2f}); "
              f"vs 16x nodes: max rel {rel.max():.1e}, mean rel {rel.mean():.1e} "
              f"(target 1e-3: ratio {rel.max() / 1e-3:.2f}); frozen nodes {1e3 * tf:.1f} ms "
              f"({t / tf:.1f}x faster than adaptive)")


if __name__ == "__main__":
    main()

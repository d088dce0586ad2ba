"""The local model's slopes and their noise: the camera paths' orders 1-2 reweighted from one
trace (``PathTracer.trace_at``, since stop 38) against one trace per finite-difference point
with the same random numbers (before), in one run.  (docs/multiple_scattering.md, "The local
model".)

For each seed, the term's per-order images at a point and at its two finite-difference
points (log kappa_t + step, atanh g + step; ``FullTransport.refresh``'s), both ways; the
photons' orders >= 3 are the same in both (one trace, reweighted).  Printed per liquid and
way: CPU seconds per local model (median over the seeds), d log(glow) / d log kappa_t and
d log(glow) / d atanh g per seed (glow: the sum over the sample pixels at the albedo), and
the per-pixel noise of each derivative: the median over the lit pixels of its standard
error (from the batches) over the pixel's value.

Run: python docs/studies/ms_local_slopes.py [N_PATHS] [SEEDS]   (defaults 1024, 4)
(16 x 12 px, bin 1, 16 batches; Lowfat Milk 16 and 64 ml, channel G)
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np

from fitmedia.forward.ms_light import LIGHT_FROM_ORDER
from fitmedia.forward.multiple import MultipleScattering
from fitmedia.medium import medium_by_name
from fitmedia.spec import parse_spec

STEP = 0.05


def _spec():
    fx = 375.0 * 16 / 200.0
    return parse_spec({
        "fitmedia_spec": 1, "name": "study",
        "tank": {"inner_size": [300, 250, 300], "front_wall": {"thickness": 6.0, "ior": 1.5},
                 "walls": "black"},
        "medium": {"ior": 1.33},
        "camera": {"size": [16, 12], "fx": fx, "fy": fx, "cx": 8, "cy": 6,
                   "position": [0, 0, 900], "look_at": [0, 0, 0], "up": [0, 1, 0]},
        "light": {"type": "bulb", "position": [40, 10, 30], "radius": 6}},
        require_images=False)


def _separate(ms: MultipleScattering, points, seed: int, a: float) -> list[np.ndarray]:
    """``orders_at`` with the camera paths traced once per point (the code before stop 38)."""
    cam = [ms._camera_orders((p,), seed, a, LIGHT_FROM_ORDER - 1)[0] for p in points]
    n_ph = ms.n_paths * ms.tracer.n_pix
    lights = ms.photons.trace(*points[0], n_ph, seed, ms.batches, 400, a,
                              from_order=LIGHT_FROM_ORDER, variants=tuple(points[1:]))
    for r, lt in zip(cam, lights):
        lt[:, : r.shape[1]] += r[:, :LIGHT_FROM_ORDER]
    last = max(max(np.flatnonzero(r.any(axis=(0, 2))).max(initial=1), 1) for r in lights)
    return [r[:, : last + 1] for r in lights]


def _slopes(runs: list[np.ndarray], a: float) -> tuple[float, float, float, float]:
    """d log glow / d log kt, d log glow / d atanh g, and each derivative's per-pixel noise."""
    k = min(r.shape[1] for r in runs)
    pw = a ** np.arange(k)
    pw[0] = 0.0
    img = [np.tensordot(r[:, :k], pw, axes=([1], [0])) for r in runs]  # (batches, pixels)
    base = img[0].mean(axis=0)
    lit = base > 0
    out, noise = [], []
    for other in img[1:]:
        d = (other - img[0]) / STEP
        out.append(d.mean(axis=0)[lit].sum() / base[lit].sum())
        se = d.std(axis=0, ddof=1)[lit] / math.sqrt(d.shape[0])
        noise.append(float(np.median(se / base[lit])))
    return out[0], out[1], noise[0], noise[1]


def main() -> None:
    n_paths = int(sys.argv[1]) if len(sys.argv) > 1 else 1024
    seeds = range(int(sys.argv[2]) if len(sys.argv) > 2 else 4)
    spec = _spec()
    for ml in (16.0, 64.0):
        med = medium_by_name("Lowfat Milk").scaled(ml / 23000)
        kt = float(med.kappa_a[1] + med.kappa_s[1])
        a, g = float(med.kappa_s[1]) / kt, float(med.g[1])
        points = ((kt, g), (kt * math.exp(STEP), g), (kt, math.tanh(math.atanh(g) + STEP)))
        ms = MultipleScattering(spec, None, channels=("G",), bin=1, n_paths=n_paths, batches=16)
        for name, run in (("one trace per point", lambda s: _separate(ms, points, s, a)),
                          ("reweighted", lambda s: ms.orders_at(*points[0], points[1:], seed=s,
                                                                rr_albedo=a))):
            cpu, rows = [], []
            for s in seeds:
                t0 = time.process_time()
                runs = run(s)
                cpu.append(time.process_time() - t0)
                rows.append(_slopes(runs, a))
            r = np.array(rows)
            print(f"Lowfat Milk {ml:g} ml, camera 1-2 {name}: {np.median(cpu):.2f} s CPU; "
                  f"d log glow / d log kt {', '.join(f'{v:.2f}' for v in r[:, 0])}; "
                  f"/ d atanh g {', '.join(f'{v:.2f}' for v in r[:, 1])}; per-pixel noise "
                  f"{np.median(r[:, 2]):.2f}, {np.median(r[:, 3]):.2f}", flush=True)


if __name__ == "__main__":
    main()

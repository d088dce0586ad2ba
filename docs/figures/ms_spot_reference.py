"""Mitsuba 3 reference for a spot's multiple-scattering term (tests/data/ms_spot_reference.json).

The canonical spot's place and direction (capture_specs/spot.yaml) with a 20 degree cone, the
canonical tank and camera at 32 x 24 px (tests/conftest.py: geometry_dict), channel G of Lowfat
Milk at 4 and 16 ml in 23 l.  Orders >= 2 are Mitsuba's all-orders render minus its orders-0-1
render (max_depth from single_scattering_depth) with the same random numbers, summed over the
image; the standard error from 16 independent batches of the all-orders render.  Mitsuba's point
light is reached only from vertices inside the cone, so its orders >= 2 are noisy and heavy-
tailed (65536 samples per pixel: 5-22 % on the sum, depending on the seed): hence the many
samples here, once, and a stored result for the test.

    python docs/figures/ms_spot_reference.py [--spp 1048576]   # ~10 min on 2 cores
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

CASES = {"Lowfat Milk 4 ml": (0.0027, 0.99, 0.902), "Lowfat Milk 16 ml": (0.0107, 0.995, 0.902)}
LIGHT = {"type": "spot", "position": [120, 10, 30], "direction": [-1, 0, -0.3], "cutoff_deg": 20}


def main() -> None:
    from conftest import make_spec

    from fitmedia.forward.mitsuba import MitsubaModel, single_scattering_depth
    from fitmedia.util import atomic_write_text

    ap = argparse.ArgumentParser()
    ap.add_argument("--spp", type=int, default=1 << 20)
    ap.add_argument("--batches", type=int, default=16)
    ap.add_argument("--out", default=str(ROOT / "tests" / "data" / "ms_spot_reference.json"))
    a = ap.parse_args()
    spec = make_spec(width=32, height=24, light=LIGHT)
    out = {"_settings": {"light": LIGHT, "size": [32, 24], "spp": a.spp, "batches": a.batches,
                         "channel": "G", "seed": 7}}
    for name, (kt, albedo, g) in CASES.items():
        t0 = time.perf_counter()
        args = ([kt * (1 - albedo)], [kt * albedo], [g], [1.0])
        imgs = [MitsubaModel(spec, None, spp=a.spp, max_depth=d, seed=7, channels=("G",))
                .render_with_error(*args, batches=a.batches)
                for d in (single_scattering_depth(spec), -1)]
        single, total = float(imgs[0][0].sum()), float(imgs[1][0].sum())
        out[name] = {"kappa_t": kt, "albedo": albedo, "g": g, "single": single,
                     "single_se": float(math.sqrt((imgs[0][1] ** 2).sum())), "total": total,
                     "multiple": total - single,
                     "multiple_se": float(math.sqrt((imgs[1][1] ** 2).sum())),
                     "wall_s": round(time.perf_counter() - t0, 1)}
        print(name, out[name], flush=True)
    atomic_write_text(a.out, json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()

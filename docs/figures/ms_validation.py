"""Mitsuba 3 reference for the multiple-scattering term (docs/multiple_scattering.md).

For each case, the canonical tank and bulb seen by a 48 x 36 px camera (tests/conftest.py's
make_spec(width=48, height=36)), G channel, is rendered with Mitsuba's volpath at all depths
and at single_scattering_depth (orders 0 + 1), 16384 spp in 16 batches with the same seeds.
The glow (pixels that do not see the bulb, analytic order 1 above 1e-3 of its brightest) is
summed per batch; the means and standard errors go to tests/data/ms_mitsuba_reference.json,
which tests/test_multiple.py::test_total_against_mitsuba reads.

Regenerate:  python docs/figures/ms_validation.py            (about 3 CPU-minutes per case)
             python docs/figures/ms_validation.py --from DIR (reuse DIR/<case>.npz renders)
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
CASES = [("Lowfat Milk", 16), ("Espresso", 8), ("Lowfat Milk", 64)]
SPP, BATCHES, CHANNEL = 16384, 16, 1


def _spec():
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import make_spec

    return make_spec(width=48, height=36)


def render(spec, medium) -> dict:
    """Batches (16, H, W) of the full and the single-scattering render of one channel."""
    from fitmedia.forward.mitsuba import MitsubaModel, single_scattering_depth

    k = CHANNEL
    args = (medium.kappa_a[k:k + 1], medium.kappa_s[k:k + 1], medium.g[k:k + 1], np.ones(1))
    out = {}
    for name, depth in (("full", -1), ("single", single_scattering_depth(spec))):
        model = MitsubaModel(spec, None, spp=SPP, max_depth=depth, seed=7, channels=("G",))
        out[name] = model._batches(*args, BATCHES)[..., 0]
    return out


def glow_sums(spec, medium, imgs: dict) -> dict:
    from fitmedia.forward.single import SingleScattering

    k = CHANNEL
    kt, a, g = float(medium.kappa_t[k]), float(medium.albedo[k]), float(medium.g[k])
    ss = SingleScattering(spec, None, channels=("G",))
    single = ss.render([kt * (1 - a)], [kt * a], [g], [1.0])[..., 0]
    bulb = ss.render([kt], [0.0], [g], [1.0])[..., 0] > 0
    glow = ~bulb & (single > 1e-3 * single[~bulb].max())
    f, s = imgs["full"][:, glow].sum(1), imgs["single"][:, glow].sum(1)
    se = lambda x: float(x.std(ddof=1) / np.sqrt(len(x)))  # noqa: E731
    return {"kappa_t": kt, "albedo": a, "g": g, "n_glow": int(glow.sum()),
            "total": float(f.mean()), "total_se": se(f),
            "single": float(s.mean()), "single_se": se(s),
            "multiple": float((f - s).mean()), "multiple_se": se(f - s),
            "analytic_single": float(single[glow].sum()), "spp": SPP, "batches": BATCHES}


def main(argv: list[str]) -> None:
    from fitmedia.medium import medium_by_name

    spec = _spec()
    src = Path(argv[argv.index("--from") + 1]) if "--from" in argv else None
    out = {}
    for name, ml in CASES:
        medium = medium_by_name(name).scaled(ml / 23000)
        key = f"{name} {ml} ml"
        if src is not None:
            with np.load(src / f"{name.replace(' ', '_')}_{ml}.npz") as f:
                imgs = {"full": f["full"], "single": f["single"]}
        else:
            imgs = render(spec, medium)
        out[key] = glow_sums(spec, medium, imgs)
        print(key, json.dumps(out[key]), flush=True)
    out["_settings"] = {"size": [48, 36], "channel": "G", "integrator": "volpath", "seed": 7,
                        "definition": "sums over the glow pixels; se = sd of 16 batch sums / 4"}
    (ROOT / "tests" / "data" / "ms_mitsuba_reference.json").write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main(sys.argv[1:])

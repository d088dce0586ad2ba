"""Time of the analytic single-scattering image against Mitsuba's at 1 % noise.

Usage::

    python bench/forward_mitsuba.py [--light bulb|spot] [--size 64x48] [--g 0.5]

What it does, in one run, on the canonical capture (capture_specs/<light>.yaml,
camera scaled to --size) with diluted milk (kappa_a 1e-5 /mm, kappa_s 0.01 /mm):

1. Analytic model (fitmedia.forward.single.SingleScattering, default settings,
   one channel): construction time once, then the median wall time of 5
   ``render`` calls.
2. Mitsuba at the single-scattering depth (MitsubaModel, volpath, one
   channel): a pilot render of 1024 samples per pixel in 16 batches gives the
   per-pixel relative standard error over the glow (pixels whose ray passes
   more than 18 mm from the light, above 1e-3 of the brightest glow pixel; 1e-2
   for the spot); its root mean square over the glow scales as 1/sqrt(spp),
   which gives the spp for 1 % noise.  That render is then timed (warm: the
   JIT kernels were compiled by the pilot).  If it would take longer than
   --max-seconds it is timed at a fraction of the spp and scaled (said so).
3. The ratio Mitsuba time / analytic time.

All times are wall-clock seconds (time.perf_counter) on this machine; the
Mitsuba variant, the CPU count and the load average are printed with them.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fitmedia.forward.mitsuba import MitsubaModel, single_scattering_depth  # noqa: E402
from fitmedia.forward.single import SingleScattering  # noqa: E402
from fitmedia.geometry import pixel_grid, trace_to_water  # noqa: E402
from fitmedia.spec import Spec, parse_spec  # noqa: E402

PILOT_SPP, BATCHES, TARGET = 1024, 16, 0.01


def canonical_spec(light: str, size: tuple[int, int]) -> Spec:
    data = yaml.safe_load((ROOT / "capture_specs" / f"{light}.yaml").read_text())
    cam = data["camera"]
    s = size[0] / cam["size"][0]
    cam.update(size=list(size), fx=cam["fx"] * s, fy=cam["fy"] * s, cx=cam["cx"] * s,
               cy=cam["cy"] * s)
    return parse_spec(data, source=f"capture_specs/{light}.yaml (scaled)", require_images=False)


def glow_mask(spec: Spec, analytic: np.ndarray, floor: float) -> np.ndarray:
    x, y = pixel_grid(spec.camera)
    r = trace_to_water(spec.camera, spec.tank, spec.medium_ior, x[..., 0], y[..., 0])
    u = spec.light.position - r.origin
    s0 = np.einsum("...i,...i->...", u, r.direction)
    h = np.linalg.norm(u - s0[..., None] * r.direction, axis=-1)
    inside = (h > 18.0) & (r.factor > 0)
    return inside & (analytic > floor * analytic[inside].max())


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--light", choices=("bulb", "spot"), default="bulb")
    ap.add_argument("--size", default="64x48", help="image size WxH (default 64x48)")
    ap.add_argument("--g", type=float, default=0.5)
    ap.add_argument("--max-seconds", type=float, default=300.0,
                    help="longest Mitsuba render timed directly (default 300 s)")
    args = ap.parse_args(argv)
    size = tuple(int(v) for v in args.size.lower().split("x"))
    spec = canonical_spec(args.light, size)
    ka, ks, g = 1e-5, 0.01, args.g
    print(f"fitmedia forward-model benchmark: {spec.source}, {size[0]}x{size[1]} px, "
          f"one channel, kappa_a={ka:g} /mm, kappa_s={ks:g} /mm, g={g:g}; "
          f"{os.cpu_count()} CPU cores, load average {os.getloadavg()[0]:.1f} at start")

    t0 = time.perf_counter()
    single = SingleScattering(spec, channels=("R",))
    t_build_a = time.perf_counter() - t0
    single.render(ka, ks, g, 1.0)  # warm-up (first call builds caches)
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        single.render(ka, ks, g, 1.0)
        times.append(time.perf_counter() - t0)
    t_a = float(np.median(times))
    print(f"analytic single scattering: {t_a * 1e3:.1f} ms per image (median of 5 renders; "
          f"construction {t_build_a * 1e3:.0f} ms, once per geometry)")

    mask = glow_mask(spec, SingleScattering(spec, channels=("R",), supersample=4)
                     .render(ka, ks, g, 1.0)[..., 0], 1e-3 if args.light == "bulb" else 1e-2)
    depth = single_scattering_depth(spec)
    t0 = time.perf_counter()
    pilot = MitsubaModel(spec, spp=PILOT_SPP, max_depth=depth, channels=("R",))
    mean, err = pilot.render_with_error(ka, ks, g, 1.0, batches=BATCHES)
    t_pilot = time.perf_counter() - t0
    rel = err[..., 0][mask] / np.maximum(mean[..., 0][mask], 1e-300)
    noise = float(np.sqrt(np.mean(rel**2)))
    spp = int(math.ceil(PILOT_SPP * (noise / TARGET) ** 2))
    print(f"Mitsuba {pilot.variant}, volpath max_depth={depth}: pilot {PILOT_SPP} spp gives "
          f"{100 * noise:.2f} % RMS per-pixel noise over {mask.sum()} glow pixels "
          f"({t_pilot:.1f} s with scene load and JIT compile) -> {spp} spp for 1 %")

    # the pilot model has compiled its kernels: time warm renders with it
    t0 = time.perf_counter()
    pilot.spp = PILOT_SPP
    pilot.render(ka, ks, g, 1.0)
    per_spp = (time.perf_counter() - t0) / PILOT_SPP
    if per_spp * spp <= args.max_seconds:
        pilot.spp = spp
        t0 = time.perf_counter()
        pilot.render(ka, ks, g, 1.0)
        t_m, how = time.perf_counter() - t0, "timed directly, warm"
    else:
        frac = max(PILOT_SPP, int(args.max_seconds / per_spp / 2))
        pilot.spp = frac
        t0 = time.perf_counter()
        pilot.render(ka, ks, g, 1.0)
        t_m = (time.perf_counter() - t0) * spp / frac
        how = f"timed warm at {frac} spp and scaled linearly"
    print(f"Mitsuba single scattering at 1 % noise: {t_m:.2f} s per image ({spp} spp, {how})")
    print(f"ratio Mitsuba / analytic: {t_m / t_a:.0f} x (wall-clock time per image, one channel; "
          f"load average {os.getloadavg()[0]:.1f} at the end: other processes inflate both times)")


if __name__ == "__main__":
    main()

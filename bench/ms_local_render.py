"""What the local model's order-major layout (fitmedia.forward.multiple._order_major) and the
excess variance's pair products (``MultipleScattering.upsampled_products``) do to the cost of
one full-transport render in the sampler.

A FullTransport model of the canonical bulb binned 2x (100 x 75 px, the term traced at the
fit's bin, ``trace_bin``: 2, 256 paths per sample pixel), Lowfat Milk 16 ml in 23 l, channel
G, refreshed once at the truth and its analytic part's quadrature frozen there (as a fit's
``ChannelProblem.adapt`` does).  Then ``REPEATS`` calls of ``render_with_variance`` (what the
likelihood calls at every posterior evaluation) at an albedo a little off the refresh point,
with the order-major array (now) and with the sum over the orders done as before
(``np.tensordot`` over the middle axis of each (batches, K, h*w) array, the reference); then
with the excess variance summed over pairs of sample pixels (now) and with every batch's two
images upsampled to the camera and multiplied (the reference, as before 2026-12-04 stop 35).
The images and variances are checked to agree.  Printed: ms per call of each, their ratios,
the number of orders K, all measured in this run.  ``BIN`` (environment, default the fit's
``trace_bin``) traces at another bin; ``--size 200 150`` is the canonical camera (bin 4),
the size of bench/fit_full.py.

Usage:  python bench/ms_local_render.py [repeats] [--size W H]    (default 20, 100 x 75)
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from unittest import mock

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fitmedia.forward import multiple  # noqa: E402
from fitmedia.forward.multiple import FullTransport, MultipleScattering  # noqa: E402
from fitmedia.inference.full import trace_bin  # noqa: E402
from fitmedia.medium import medium_by_name  # noqa: E402
from fitmedia.spec import parse_spec  # noqa: E402


def tensordot_major(loc: dict) -> np.ndarray:
    """The reference: the same (K, 3, batches, h*w) array, made by copying on every call as
    ``np.tensordot`` over the orders did."""
    return np.stack([loc[n] for n in multiple.LOCAL_PARTS]).transpose(2, 0, 1, 3).copy()


def formed_products(ms, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The reference for ``upsampled_products``: both (n, H*W) images formed and multiplied."""
    return np.sum(ms.upsample_rows(a) * ms.upsample_rows(b), axis=0)


def timed(ft, args, repeats: int) -> tuple[float, tuple[np.ndarray, np.ndarray]]:
    out = ft.render_with_variance(*args)
    t = time.perf_counter()
    for _ in range(repeats):
        ft.render_with_variance(*args)
    return (time.perf_counter() - t) / repeats, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("repeats", type=int, nargs="?", default=20)
    ap.add_argument("--size", type=int, nargs=2, default=(100, 75), metavar=("W", "H"))
    a = ap.parse_args()
    repeats = a.repeats
    raw = yaml.safe_load((ROOT / "capture_specs" / "bulb.yaml").read_text())
    cam = raw["camera"]
    f = a.size[0] / cam["size"][0]
    cam.update(size=list(a.size), fx=cam["fx"] * f, fy=cam["fy"] * f, cx=cam["cx"] * f,
               cy=cam["cy"] * f)
    raw.pop("images", None)
    spec = parse_spec(raw, require_images=False)
    m = medium_by_name("Lowfat Milk").scaled(16 / 23000)
    ka, ks, g = m.kappa_a[1] + spec.water_kappa_a[1], m.kappa_s[1], m.g[1]
    ft = FullTransport(spec, None, channels=("G",), seed=1,
                       bin=int(os.environ.get("BIN", 0)) or trace_bin(spec.camera))
    t = time.perf_counter()
    ft.refresh([ka], [ks], [g])
    ft.single.freeze_nodes([ka + ks], [g])  # as a fit does (ChannelProblem.adapt)
    print(f"refresh (3 traces): {time.perf_counter() - t:.1f} s; orders K = "
          f"{ft._local[0]['batches'].shape[1]}, sample pixels {ft._local[0]['batches'].shape[2]}")
    args = ([ka * 1.05], [ks * 0.99], [g], [1.0])
    print(f"{a.size[0]} x {a.size[1]} px, bin {ft.ms.bin}")
    now, (img, exc) = timed(ft, args, repeats)
    with mock.patch.object(multiple, "_order_major", tensordot_major):
        ref, (img_ref, _) = timed(ft, args, repeats)
    np.testing.assert_allclose(img, img_ref, rtol=1e-12, atol=0)
    print(f"render_with_variance: {now * 1e3:.1f} ms per call order-major, {ref * 1e3:.1f} ms "
          f"copying per call (reference); ratio {now / ref:.2f}")
    with mock.patch.object(MultipleScattering, "upsampled_products", formed_products):
        ref2, (_, exc_ref) = timed(ft, args, repeats)
    np.testing.assert_allclose(exc, exc_ref, rtol=1e-9, atol=1e-12 * np.abs(exc_ref).max())
    print(f"render_with_variance: {now * 1e3:.1f} ms per call with the excess's pair products, "
          f"{ref2 * 1e3:.1f} ms with the images formed (reference); ratio {now / ref2:.2f}")


if __name__ == "__main__":
    main()

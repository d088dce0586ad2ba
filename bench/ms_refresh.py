"""Cost of one refresh of the full-transport local model (``FullTransport.refresh``: the term
traced at the refresh point and at its two finite-difference points), this checkout against
another one (``--reference DIR``, e.g. a ``git worktree`` of an older commit), in one run.

The canonical bulb (``--size``, default the canonical 200 x 150, traced at the fit's bin),
Lowfat Milk 16 ml in 23 l, channel G, at the truth, ``--paths`` per sample pixel (default the
fit's 256).  Each tree refreshes ``--repeats`` times in a subprocess of its own (one at a
time); printed: the fastest wall and CPU time of each, their ratio, and the largest
difference between the two trees' local models relative to the largest value (0 when the
change does not touch the estimate).

Usage:  python bench/ms_refresh.py [--reference DIR] [--size W H] [--paths N] [--repeats R]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def measure(size: tuple[int, int], paths: int, repeats: int, out: Path) -> None:
    """In this process (the tree on sys.path): refresh ``repeats`` times; timings to stdout as
    JSON, the local model's arrays to ``out``."""
    import yaml

    from fitmedia.forward.multiple import FullTransport
    from fitmedia.inference.full import trace_bin
    from fitmedia.medium import medium_by_name
    from fitmedia.spec import parse_spec

    raw = yaml.safe_load((ROOT / "capture_specs" / "bulb.yaml").read_text())
    cam = raw["camera"]
    f = size[0] / cam["size"][0]
    cam.update(size=list(size), fx=cam["fx"] * f, fy=cam["fy"] * f, cx=cam["cx"] * f,
               cy=cam["cy"] * f)
    raw.pop("images", None)
    spec = parse_spec(raw, require_images=False)
    m = medium_by_name("Lowfat Milk").scaled(16 / 23000)
    ka, ks, g = m.kappa_a[1] + spec.water_kappa_a[1], m.kappa_s[1], m.g[1]
    ft = FullTransport(spec, None, channels=("G",), seed=1, bin=trace_bin(spec.camera))
    ft.ms.n_paths = paths
    walls, cpus = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        ft.refresh(np.array([ka]), np.array([ks]), np.array([g]))
        walls.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
    loc = ft._local[0]
    np.savez(out, **{k: loc[k] for k in ("batches", "d_kt", "d_g")})
    print(json.dumps({"wall": min(walls), "cpu": min(cpus)}))


def run_tree(tree: Path, a, out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree))
    cmd = [sys.executable, str(Path(__file__).resolve()), "--measure", str(out),
           "--size", *map(str, a.size), "--paths", str(a.paths), "--repeats", str(a.repeats)]
    res = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reference", type=Path)
    ap.add_argument("--size", type=int, nargs=2, default=(200, 150), metavar=("W", "H"))
    ap.add_argument("--paths", type=int, default=256)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--measure", type=Path, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.measure:
        sys.path.insert(0, os.getcwd())
        measure(tuple(a.size), a.paths, a.repeats, a.measure)
        return
    with tempfile.TemporaryDirectory() as tmp:
        here = run_tree(ROOT, a, Path(tmp) / "here.npz")
        print(f"{a.size[0]} x {a.size[1]} px, {a.paths} paths per sample pixel, channel G: "
              f"this tree {here['wall']:.1f} s wall, {here['cpu']:.1f} s CPU per refresh")
        if a.reference is None:
            return
        ref = run_tree(a.reference.resolve(), a, Path(tmp) / "ref.npz")
        h, r = np.load(Path(tmp) / "here.npz"), np.load(Path(tmp) / "ref.npz")
        diff = max(float(np.max(np.abs(h[k] - r[k]))) / max(float(np.max(np.abs(r[k]))), 1e-300)
                   for k in r.files)
        print(f"reference {a.reference}: {ref['wall']:.1f} s wall, {ref['cpu']:.1f} s CPU; "
              f"ratio {here['wall'] / ref['wall']:.2f} wall, {here['cpu'] / ref['cpu']:.2f} "
              f"CPU; local models differ by {diff:.1e} of their largest value")


if __name__ == "__main__":
    main()

"""chi2/pixel at the MAP of single-scattering fits: what the misfit guard's allowance rests on.

Captures of the canonical tank at reduced sizes (``tests/conftest.py``'s geometry, fx scaled
with the width), made three ways:

* ``single``: fitmedia's own single-scattering model (``fitmedia synth``), the fit's model;
* ``mitsuba_ss``: Mitsuba 3 at ``max_depth = single_scattering_depth`` (orders 0 and 1 only),
  an independent single-scattering renderer with its own Monte Carlo noise;
* ``full``: Mitsuba 3 with all orders (``fitmedia synth --model full``).

Each is fitted per channel by ``fit_channel`` with the sampler off (the MAP of
``fitmedia fit --model single --no-mcmc``); a row per channel: chi2/pixel at the MAP, the
pixel count, kappa_s and g against the truth.  ``mitsuba_ss`` against ``full`` at the same
spp separates the Monte Carlo noise of a render from the missing multiple scattering.

  python docs/studies/misfit_study.py study --out rows.jsonl      (docs/results.md, "trust")
  python docs/studies/misfit_study.py captures tests/data/misfit  (the test's captures)
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import tempfile
import time
from pathlib import Path

import yaml

from fitmedia.inference.fit import FitOptions, channel_args, fit_channel, prepare
from fitmedia.medium import medium_by_name
from fitmedia.spec import CHANNELS, dump_spec, load_spec, parse_spec
from fitmedia.synth import synthesize

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))
from conftest import geometry_dict  # noqa: E402  (the tests' canonical geometry)

#: the test's captures: (folder, medium, ml, how, spp, seed); 32 x 24 px, channel G
TEST_CAPTURES = (("milk_full", "Lowfat Milk", 16.0, "full", 1024, 1),
                 ("milk_mitsuba_ss", "Lowfat Milk", 16.0, "mitsuba_ss", 1024, 1))
TEST_SIZE = (32, 24)

def make_capture(out: Path, medium: str, ml: float, how: str, *, size: tuple[int, int],
                 spp: int = 256, seed: int = 0, channels: list[str] | None = None) -> Path:
    """A synthetic capture in ``out`` (capture.yaml, images, truth.json); ``how`` is
    ``single``, ``full`` or ``mitsuba_ss`` (Mitsuba with scattering orders 0 and 1 only)."""
    spec = parse_spec(geometry_dict(*size), require_images=False)
    if how != "mitsuba_ss":
        path = synthesize(spec, out, medium_by_name(medium), [ml], seed=seed, model=how,
                          spp=spp, medium_name=medium)
        return _restrict(path, channels)
    import fitmedia.forward.mitsuba as fm

    full = fm.MitsubaModel
    fm.MitsubaModel = functools.partial(full, max_depth=fm.single_scattering_depth(spec))
    try:
        path = synthesize(spec, out, medium_by_name(medium), [ml], seed=seed, model="full",
                          spp=spp, medium_name=medium)
    finally:
        fm.MitsubaModel = full
    truth = json.loads((out / "truth.json").read_text())
    truth["model"] = "mitsuba single scattering (max_depth = single_scattering_depth)"
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return _restrict(path, channels)


def _restrict(spec_path: Path, channels: list[str] | None) -> Path:
    """Fit only ``channels`` of the capture (the spec's optional ``channels``)."""
    if channels:
        raw = yaml.safe_load(spec_path.read_text())
        raw["channels"] = channels
        dump_spec(raw, spec_path)
    return spec_path

def fit_rows(spec_path: Path, medium: str, tag: dict) -> list[dict]:
    """The MAP of every channel of the capture; one row each."""
    prep = prepare(load_spec(spec_path))
    med = medium_by_name(medium)
    rows = []
    for ch in prep.spec.channels:
        r = fit_channel(*channel_args(prep, ch, FitOptions(mcmc=False, progress=False), None))
        chi2, n = r["chi2"]
        ci = CHANNELS.index(ch)
        rows.append({**tag, "ch": ch, "chi2_per_pixel": chi2 / n, "n_pixels": n,
                     "kappa_s_rel_err": r["map"]["kappa_s"] / med.kappa_s[ci] - 1,
                     "g": r["map"]["g"], "g_true": float(med.g[ci])})
    return rows

STUDY = ([("single", "Lowfat Milk", 16.0, s, w) for s in (1, 2) for w in (32, 48)]
         + [("single", "Espresso", 8.0, 1, 48)]
         + [(how, m, ml, 1, 32) for m, ml in (("Lowfat Milk", 16.0), ("Espresso", 8.0))
            for how in ("mitsuba_ss", "full")]
         + [("full", "White Grapefruit Juice", 160.0, 1, 32)]
         + [("full", "Lowfat Milk", ml, 1, 32) for ml in (4.0, 1.6)])


def study(a) -> None:
    done = set()
    if Path(a.out).exists():
        done = {(r["how"], r["medium"], r["ml"], r["seed"], r["width"])
                for r in map(json.loads, open(a.out))}
    with open(a.out, "a") as out:
        for how, medium, ml, seed, width in STUDY:
            if (how, medium, ml, seed, width) in done:
                continue
            with tempfile.TemporaryDirectory() as tmp:
                t0 = time.perf_counter()
                path = make_capture(Path(tmp), medium, ml, how, size=(width, width * 3 // 4),
                                    spp=a.spp, seed=seed)
                t1 = time.perf_counter()
                tag = {"how": how, "medium": medium, "ml": ml, "seed": seed, "width": width,
                       "spp": a.spp if how != "single" else None, "render_s": t1 - t0}
                for row in fit_rows(path, medium, tag):
                    out.write(json.dumps(row) + "\n")
                out.flush()

def captures(a) -> None:
    for name, medium, ml, how, spp, seed in TEST_CAPTURES:
        t0 = time.perf_counter()
        make_capture(Path(a.dir) / name, medium, ml, how, size=TEST_SIZE, spp=spp, seed=seed,
                     channels=["G"])
        print(f"{name}: {time.perf_counter() - t0:.1f} s")

def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("study")
    s.add_argument("--out", required=True)
    s.add_argument("--spp", type=int, default=1024)
    s.set_defaults(func=study)
    c = sub.add_parser("captures")
    c.add_argument("dir")
    c.set_defaults(func=captures)
    a = p.parse_args()
    a.func(a)

if __name__ == "__main__":
    main()

"""Round trips at 4x and 10x the 2006 dilutions, single against full transport, with the
sampler (docs/inference.md, "4x and 10x the 2006 dilutions").

For each liquid and volume: a capture of the canonical bulb binned 2x (100 x 75 px) rendered
by ``fitmedia synth --model hybrid --spp 1024`` (analytic orders 0-1 plus fitmedia's own
multiple-scattering term), then ``fitmedia fit --model single`` and ``--model full`` with
the defaults.  Prints one markdown row per fit: errors of the posterior median against the
truth (R / G / B; ``*`` where the truth is outside the central 90 % interval), chi2/pixel,
exit code with its reasons, wall time.  Resumable: a capture or fit already in OUT is kept.

Run: python docs/studies/dilution_round_trips.py OUT [CASES]   (about 80 min on 2 cores)
CASES: ``4x10x`` (default, the 8 cases below), ``2006`` (the 2006 dilutions of Lowfat Milk,
Espresso and White Grapefruit Juice), ``2006rm`` (Regular Milk 60 ml, the fourth: its
``synth`` alone took 42 min at stop 28; docs/inference.md, "Dense milk: going on from the
restart"), or a comma-separated list of case indices into the 4x10x list.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
#: (liquid, ml in 23 l, seed): 4x and 10x the 2006 dilutions of issue 15's four liquids
CASES = [("Lowfat Milk", 4, 41), ("Espresso", 2, 42), ("White Grapefruit Juice", 40, 43),
         ("Regular Milk", 15, 44), ("Lowfat Milk", 1.6, 45), ("Espresso", 0.8, 46),
         ("White Grapefruit Juice", 16, 47), ("Regular Milk", 6, 48)]
#: the 2006 dilutions (Narasimhan et al. 2006's table) of three of them
CASES_2006 = [("Lowfat Milk", 16, 51), ("Espresso", 8, 52), ("White Grapefruit Juice", 160, 53)]
CASES_2006_RM = [("Regular Milk", 60, 61)]
#: short names for the reasons in results.json's trust
REASONS = (("does not describe", "misfit"), ("did not settle", "unsettled"),
           ("second full-transport", "restart"), ("paths per", "last refreshes"),
           ("other sign", "other g"), ("traced again", "seed shift"),
           ("did not converge", "sampler"), ("would be", "single check"))


def geometry(out: Path) -> Path:
    """The canonical bulb spec with its camera binned 2x."""
    spec = yaml.safe_load((ROOT / "capture_specs" / "bulb.yaml").read_text())
    cam = spec["camera"]
    cam.update(size=[100, 75], fx=cam["fx"] / 2, fy=cam["fy"] / 2, cx=cam["cx"] / 2,
               cy=cam["cy"] / 2)
    path = out / "geo100.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def row(d: Path, model: str, rc: int, wall: float) -> str:
    t = json.loads((d / "cap" / "truth.json").read_text())
    u, r = t["undiluted"], json.loads((d / model / "results.json").read_text())
    cells = []
    for q in ("kappa_t", "kappa_s", "g", "kappa_s_reduced"):
        out = []
        for ch in "RGB":
            e = r["parameters"][q][ch]
            truth = u["kappa_s"][ch] * (1 - u["g"][ch]) if q == "kappa_s_reduced" else u[q][ch]
            v, lo, hi = e.get("median", e["map"]), e.get("q05"), e.get("q95")
            star = "" if lo is None or lo <= truth <= hi else "*"
            out.append(f"{v - truth:+.3f}{star}" if q == "g" else f"{100 * (v / truth - 1):+.0f}{star}")
        cells.append(" / ".join(out))
    chi = r["trust"].get("misfit", {})
    c2 = " / ".join(f"{chi.get(ch, {}).get('chi2_per_pixel', float('nan')):.2f}" for ch in "RGB")
    why = sorted({next((lab for key, lab in REASONS if key in x), "other")
                  for x in r["trust"]["reasons"]})
    return (f"| {t['medium']} {t['images'][0]['ml']:g} | {model} | {' | '.join(cells)} | {c2} | "
            f"{rc}{' (' + ', '.join(why) + ')' if why else ''} | {wall:.0f} s |")


def cases(which: str) -> list[tuple[str, float, int]]:
    """The cases named by the command line's CASES argument (module docstring)."""
    if which == "2006":
        return CASES_2006
    if which == "2006rm":
        return CASES_2006_RM
    if which == "4x10x":
        return CASES
    return [CASES[int(i)] for i in which.split(",")]


def main():
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    geo = geometry(out)
    fm = [sys.executable, "-m", "fitmedia.cli"]
    for liquid, ml, seed in cases(sys.argv[2] if len(sys.argv) > 2 else "4x10x"):
        d = out / f"{liquid.replace(' ', '_')}_{ml:g}"
        if not (d / "cap" / "capture.yaml").exists():
            subprocess.run(fm + ["synth", str(geo), "--medium", liquid, "--ml", str(ml), "--out",
                                 str(d / "cap"), "--seed", str(seed), "--model", "hybrid",
                                 "--spp", "1024"], check=True, capture_output=True)
        for model in ("single", "full"):
            done = d / f"{model}.json"
            if not done.exists():
                t0 = time.perf_counter()
                rc = subprocess.run(fm + ["fit", str(d / "cap" / "capture.yaml"), "--out",
                                          str(d / model), "--model", model, "--seed", "1",
                                          "--quiet"], capture_output=True).returncode
                tmp = done.with_suffix(".tmp")
                tmp.write_text(json.dumps({"rc": rc, "wall_s": time.perf_counter() - t0}))
                tmp.replace(done)
            info = json.loads(done.read_text())
            print(row(d, model, info["rc"], info["wall_s"]), flush=True)


if __name__ == "__main__":
    main()

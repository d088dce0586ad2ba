"""Is a round trip's offset the model's or its camera noise's?  (docs/validation.md, "Regular
Milk's kappa_t at 32 x 24 px followed up".)

For one round of ``fitmedia validate`` (its folder ROUND holds round.json and capture/;
without capture/, the camera noise is GEOMETRY's ``noise`` block and step 1's noise check is
left out: a round kept by docs/studies/coverage_rounds.py, or one not run yet whose round.json
holds its task's identity):

1. its noise-free twin: ``synth`` with the round's liquid, volumes, seed, synth model and
   paths and no camera noise (``CameraNoise(0, 0)``: the same clean images and
   multiple-scattering term), fitted MAP-only (``--no-mcmc``, the round's fit seed) with a
   constant variance per pixel (gain 0, read_var = the camera's shot variance at the medium
   image's median pixel).  Its error against the truth is the model chain's (term, local
   model, refreshes, optimiser), without noise.  The camera's own noise model would not do:
   with no residuals its log-variance term pulls every pixel's model down (docs/inference.md,
   "The 100 x 75 px misses followed up").
   The round's images minus the twin's, over the camera's sd, are printed: the capture's
   noise, which should be white with mean 0 and sd 1.
2. N captures made from the twin's clean images with fresh camera noise (the round's gain
   and read variance, drawn anew on every image and the clear water), each fitted by the whole
   pipeline (the round's model, MAP and MCMC) in channel CH alone.  Printed: the mean error of
   the posterior median and the MAP against the truth with its standard error, the scatter
   of the medians against the posterior sd (sd of z), and the coverage of the 90 % intervals.

A capture that was fitted is not fitted again (delete OUT/... to redo it).
Run: python docs/studies/noise_realisations.py ROUND GEOMETRY OUT CH N
     (e.g. OUT/round_0003 geom32.yaml study B 30: at 32 x 24 px, ~3 min for the twin and
     ~50 s a realisation on 2 cores); N = 0 makes and fits the twin alone
"""
from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import tifffile
import yaml

from fitmedia.inference.result import FitOptions
from fitmedia.medium import medium_by_name
from fitmedia.pipeline import fit
from fitmedia.spec import load_spec
from fitmedia.synth import SATURATION, CameraNoise, synthesize


def twin(rj: dict, camera: CameraNoise, geometry: Path, out: Path) -> Path:
    """The noise-free twin (made once) of the round ``rj`` (its round.json) whose camera noise
    is ``camera``, with a constant-variance noise block."""
    spec_path = out / "twin" / "capture.yaml"
    if not spec_path.exists():
        synthesize(load_spec(geometry, require_images=False), out / "twin",
                   medium_by_name(rj["medium"]), list(rj["ml"]), seed=rj["seed"],
                   model=rj["synth_model"], spp=rj["synth_spp"], medium_name=rj["medium"],
                   noise=CameraNoise(gain=0.0, read_var=0.0))
        raw = yaml.safe_load(spec_path.read_text())
        img = tifffile.imread(out / "twin" / raw["images"][0]["path"])
        raw["noise"] = {"gain": 0.0, "read_var": float(camera.gain * np.median(img))}
        spec_path.write_text(yaml.safe_dump(raw))
    return spec_path


def options(rj: dict, seed: int, mcmc: bool) -> FitOptions:
    """The fit options of the round ``rj`` (its round.json) with ``seed`` and ``mcmc``."""
    o = rj["options"]
    return FitOptions(model=o["model"], seed=seed, mcmc=mcmc, robust=o["robust"],
                      global_evals=o["global_evals"], progress=False, workers=1)


def image_entries(raw: dict) -> list[dict]:
    """The image entries of a capture spec ``raw``: its images and the clear water."""
    return raw["images"] + [raw["calibration"]["clear_water"]]


def realisation(twin_spec: Path, camera: CameraNoise, out: Path, ch: str, i: int) -> Path:
    """Capture ``i``: the twin's clean images with fresh ``camera`` noise, channel ``ch``."""
    raw = yaml.safe_load(twin_spec.read_text())
    shutil.rmtree(out, ignore_errors=True)
    (out / "images").mkdir(parents=True)
    rng = np.random.default_rng([7, i])
    for entry in image_entries(raw):
        clean = tifffile.imread(twin_spec.parent / entry["path"]).astype(float)
        noisy = np.minimum(camera.apply(clean, rng), SATURATION).astype(np.float32)
        tifffile.imwrite(out / entry["path"], noisy, photometric="rgb")
    raw.update(noise={"gain": camera.gain, "read_var": camera.read_var}, channels=[ch])
    (out / "capture.yaml").write_text(yaml.safe_dump(raw))
    return out / "capture.yaml"


def noise_check(round_dir: Path, twin_spec: Path, camera: CameraNoise) -> None:
    """The round's images minus the twin's over the camera's sd: mean, sd and the sd of 5 x 5
    block means per channel (white noise of the stated size: 0, 1 and 0.2)."""
    raw = yaml.safe_load(twin_spec.read_text())
    for entry in image_entries(raw):
        clean = tifffile.imread(twin_spec.parent / entry["path"]).astype(float)
        noisy = tifffile.imread(round_dir / "capture" / entry["path"]).astype(float)
        r = (noisy - clean) / np.sqrt(camera.gain * clean + camera.read_var)
        h, w = r.shape[0] // 5 * 5, r.shape[1] // 5 * 5
        blocks = r[:h, :w].reshape(h // 5, 5, w // 5, 5, -1).mean(axis=(1, 3))
        print(f"{entry['path']} minus the twin's, in camera sd: " + ", ".join(
            f"{c} mean {r[..., i].mean():+.3f} sd {r[..., i].std():.3f} "
            f"blocks {blocks[..., i].std():.3f}"
            for i, c in enumerate("RGB")), flush=True)


def true_values(truth: dict, ch: str) -> dict[str, float]:
    """The true kappa_t, kappa_s, g and kappa_s' = kappa_s (1 - g) in channel ``ch``."""
    out = {q: truth[q][ch] for q in ("kappa_t", "kappa_s", "g")}
    out["kappa_s_reduced"] = out["kappa_s"] * (1.0 - out["g"])
    return out


def errors(res: dict, truth: dict, ch: str, key: str) -> dict[str, float]:
    """log(value / truth) of kappa_t, kappa_s and kappa_s' (g: value - truth) at ``key``."""
    p = res["parameters"]
    return {q: float(p[q][ch][key] - t if q == "g" else np.log(p[q][ch][key] / t))
            for q, t in true_values(truth, ch).items()}


def summary(results: list[dict], truth: dict, ch: str) -> None:
    """Mean error (median and MAP), sd of z and 90 % coverage over the realisations."""
    print(f"{len(results)} realisations, channel {ch}; exit 0 in "
          f"{sum(r['trust']['ok'] for r in results)}")
    med = [errors(r, truth, ch, "median") for r in results]
    map_ = [errors(r, truth, ch, "map") for r in results]
    for q, t in true_values(truth, ch).items():
        e, m = np.array([d[q] for d in med]), np.array([d[q] for d in map_])
        x = [r["parameters"][q][ch] for r in results]
        z = np.array([(p["median"] - t) / p["std"] for p in x])
        cover = np.mean([p["q05"] <= t <= p["q95"] for p in x])
        s = 1.0 if q == "g" else 100.0
        print(f"  {q}: median's error {s * e.mean():+.3f} (se {s * e.std(ddof=1) / np.sqrt(len(e)):.3f}),"
              f" MAP's {s * m.mean():+.3f}; sd of the medians {s * e.std(ddof=1):.3f}; "
              f"mean z {z.mean():+.2f}, sd z {z.std(ddof=1):.2f}; 90 % coverage {cover:.2f}"
              f"{'' if q == 'g' else '  (errors in %)'}")


def main() -> None:
    round_dir, geometry, out = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
    ch, n = sys.argv[4], int(sys.argv[5])
    rj = json.loads((round_dir / "round.json").read_text())
    has_capture = (round_dir / "capture" / "capture.yaml").is_file()
    noise_from = round_dir / "capture" / "capture.yaml" if has_capture else geometry
    camera = CameraNoise(**yaml.safe_load(noise_from.read_text())["noise"])
    spec_path = twin(rj, camera, geometry, out)
    truth = json.loads((spec_path.parent / "truth.json").read_text())["undiluted"]
    if has_capture:
        noise_check(round_dir, spec_path, camera)
    else:  # a round known by its record alone (docs/studies/coverage_rounds.py's KEEP)
        print(f"{round_dir}: no capture/, so no noise check; camera noise from {geometry}")
    if not (out / "twin_fit" / "results.json").exists():
        fit(spec_path, out / "twin_fit", options(rj, rj["seed"], False), report=False)
    res = json.loads((out / "twin_fit" / "results.json").read_text())
    twin_errors = {c: errors(res, truth, c, "map") for c in res["channels"]}
    print("noise-free twin, MAP minus truth: " + ", ".join(
        f"{c} kappa_t {100 * e['kappa_t']:+.2f} % g {e['g']:+.4f}" for c, e in twin_errors.items()),
        flush=True)
    results = []
    for i in range(n):
        d = out / f"r{i:03d}"
        if not (d / "fit" / "results.json").exists():
            fit(realisation(spec_path, camera, d / "cap", ch, i), d / "fit",
                options(rj, 1000 + i, True), report=False)
        results.append(json.loads((d / "fit" / "results.json").read_text()))
        print(f"realisation {i}: kappa_t {100 * errors(results[-1], truth, ch, 'median')['kappa_t']:+.2f} %",
              flush=True)
    if results:  # N = 0: the twin alone
        summary(results, truth, ch)


if __name__ == "__main__":
    main()

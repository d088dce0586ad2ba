"""Posterior (MCMC) calibration at one point: many noise draws of one clean synthetic image
(canonical 64 x 48 spec), each with a redrawn calibration, fitted with fit_channel (MAP + emcee,
default settings); one JSON line per draw with kappa_t's and g's posterior z and PIT and the
Laplace vs posterior standard deviation of atanh g.

  python docs/studies/mcmc_study.py MEDIUM ML CHANNEL DRAWS SEED > out.jsonl
  (docs/validation.md: "Lowfat Milk" 20 G 20 700 and Espresso 16 R 21 500)
"""
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
from fitmedia.medium import medium_by_name
from fitmedia.synth import synthesize, CameraNoise
from fitmedia.spec import load_spec, CHANNELS
from fitmedia.forward.single import SingleScattering
from fitmedia.inference.fit import FitOptions, prepare, fit_channel
name, ml, ch, n, seed0 = sys.argv[1], float(sys.argv[2]), sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
geo = load_spec(ROOT / "capture_specs" / "bulb_64x48.yaml", require_images=False)
med = medium_by_name(name)
with tempfile.TemporaryDirectory() as tmp:
    spec = load_spec(synthesize(geo, tmp, med, [ml], seed=1))
    prep = prepare(spec)
c = ml / 23000
clean = SingleScattering(spec, None, channels=CHANNELS, supersample=2).render(
    np.asarray(med.kappa_a) * c, np.asarray(med.kappa_s) * c, med.g, 1.0)
gain, rv = prep.noise["R"]
truth = med.as_dict()
ci = CHANNELS.index(ch)
rng = np.random.default_rng(seed0)
for k in range(n):
    img = CameraNoise(gain, rv).apply(clean, rng)
    bcal = 1.0 + prep.brightness_rel_sd[ch] * rng.normal()
    r = fit_channel(spec, ch, [img[..., ci]], [prep.images[0].valid[..., ci]], bcal,
                    prep.brightness_rel_sd[ch], prep.noise[ch], FitOptions(mcmc=True, seed=k, progress=False), seed=seed0 + k)
    u = r["samples"]
    ph = r["space"].physical_samples(u)
    mp = r["map"]
    lap = np.sqrt(np.diag(r["laplace_cov"])) if r["laplace_cov"] is not None else [np.nan] * 4
    out = {"k": k, "converged": bool(r["converged"])}
    for q, j in (("kappa_t", 0), ("g", 2)):
        s = ph[q]; t = truth[q][ch]
        out[q] = {"map": mp[q], "median": float(np.median(s)), "std": float(np.std(s)),
                  "pit": float(np.mean(s < t)), "z": float((np.median(s) - t) / np.std(s))}
    tu = np.arctanh(truth["g"][ch])
    out["g_u"] = {"z_map_lap": float((r["x_map"][2] - tu) / lap[2]), "z_post": float((np.median(u[:, 2]) - tu) / np.std(u[:, 2])),
                  "sd_lap": float(lap[2]), "sd_post": float(np.std(u[:, 2]))}
    print(json.dumps(out), flush=True)

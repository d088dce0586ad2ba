"""How much the multiple-scattering term's Monte Carlo realisation moves a full-transport
MAP, and how its per-pixel error behaves (docs/inference.md, "Measured state").

For tests/data/misfit/milk_full (Mitsuba 3 full-transport render, 32 x 24 px, channel G,
Lowfat Milk 16 ml in 23 l), with the local model of the term built AT THE TRUTH from each
of 8 seeds, the MAP is polished from the truth (no further refresh): the spread of these
MAPs is the realisation's effect alone.  Also printed: the term's per-pixel relative
standard deviation between seeds against the error each render states (16 batches).

Run: python docs/studies/ms_realisation.py [N_PATHS] [GUIDE_ORDERS]   (about 1 CPU-minute)
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from fitmedia.forward import ms_paths
from fitmedia.forward.multiple import FullTransport
from fitmedia.inference import fit as F
from fitmedia.inference.likelihood import ChannelProblem, Observation
from fitmedia.inference.optimize import find_map
from fitmedia.inference.params import ChannelParams, ParameterSpace
from fitmedia.spec import load_spec

CAP = Path(__file__).resolve().parents[2] / "tests" / "data" / "misfit" / "milk_full"
SEEDS = range(11, 19)


def problem(cap: Path = CAP):
    """(spec, channel, channel index, brightness, space, problem) of a one-image capture's
    first channel, with the model and noise of ``fitmedia fit``."""
    spec = load_spec(cap / "capture.yaml")
    prep = F.prepare(spec)
    ch = spec.channels[0]
    ci = F.CHANNELS.index(ch)
    im = prep.images[0]
    gmap, rmap = prep.noise_maps["images[0]"]
    model = F._model(spec, 0, ch, F.FitOptions(mcmc=False, progress=False))
    obs = [Observation(model, im.data[..., ci], im.valid[..., ci] & model.support,
                       spec.images[0].concentration, gmap[..., ci], rmap[..., ci])]
    b = prep.brightness[ch]
    space = ParameterSpace(free_brightness=True, brightness_guess=b,
                           brightness_rel_sd=prep.brightness_rel_sd[ch], background_sd=None,
                           priors=spec.priors)
    prob = ChannelProblem(obs, space, None, prep.noise[ch], water_kappa_a=spec.water_kappa_a[ci])
    return spec, ch, ci, b, space, prob


def at_truth(cap: Path):
    """:func:`problem` with the truth: (spec, channel, channel index, brightness, space,
    problem adapted at the truth, truth.json's undiluted values, the truth's vector, the
    analytic model)."""
    spec, ch, ci, b, space, prob = problem(cap)
    t = json.loads((cap / "truth.json").read_text())["undiluted"]
    xt = space.to_vector(ChannelParams(t["kappa_t"][ch], t["albedo"][ch], t["g"][ch], b))
    prob.adapt(xt)
    o = prob.obs[0]
    return spec, ch, ci, b, space, prob, t, xt, getattr(o.model, "single", o.model)


def main():
    n_paths = int(sys.argv[1]) if len(sys.argv) > 1 else 256
    if len(sys.argv) > 2:
        ms_paths.GUIDE_ORDERS = int(sys.argv[2])
    spec, ch, ci, b, space, prob = problem()
    t = json.loads((CAP / "truth.json").read_text())["undiluted"]
    xt = space.to_vector(ChannelParams(t["kappa_t"][ch], t["albedo"][ch], t["g"][ch], b))
    prob.adapt(xt)
    rows, terms, errs = [], [], []
    for seed in SEEDS:
        o = prob.obs[0]
        o.model = FullTransport(spec, 0, channels=(ch,), seed=seed, bin=1, n_paths=n_paths,
                                single=getattr(o.model, "single", o.model))
        prob.refresh_models(xt)
        prob.adapt(xt)
        c = spec.images[0].concentration
        img, var = o.model.ms_part([c * t["kappa_a"][ch] + spec.water_kappa_a[ci]],
                                   [c * t["kappa_s"][ch]], [t["g"][ch]], [b])
        terms.append(img[..., 0])
        errs.append(np.sqrt(var[..., 0]))
        c2, n = prob.chi2(xt)
        r = find_map(prob.log_posterior, xt, space.lower, space.upper, global_evals=0)
        p = space.to_params(r.x)
        rows.append((p.kappa_t / t["kappa_t"][ch] - 1, p.kappa_s / t["kappa_s"][ch] - 1,
                     p.g - t["g"][ch], c2 / n))
        print(f"seed {seed}: kappa_t {rows[-1][0]:+.3f} kappa_s {rows[-1][1]:+.3f} "
              f"g {rows[-1][2]:+.3f} chi2/pixel at the truth {rows[-1][3]:.2f}", flush=True)
    R = np.array(rows)
    A = np.array(terms)
    m = A.mean(0)
    glow = m > 1e-3 * m.max()
    rel = A.std(0, ddof=1)[glow] / m[glow]
    stated = np.mean(errs, axis=0)[glow] / m[glow]
    print(f"{n_paths} paths per pixel, GUIDE_ORDERS {ms_paths.GUIDE_ORDERS}: MAP over "
          f"{len(SEEDS)} seeds: mean {np.round(R[:, :3].mean(0), 3)}, sd "
          f"{np.round(R[:, :3].std(0, ddof=1), 3)} (kappa_t, kappa_s relative; g absolute); "
          f"term per glow pixel: relative sd between seeds median {np.median(rel):.3f}, "
          f"stated median {np.median(stated):.3f}")


if __name__ == "__main__":
    main()

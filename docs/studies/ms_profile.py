"""Is a full-transport fit's posterior right far from its MAP?  (docs/validation.md, "Round
18's R followed up".)

The sampler of ``fitmedia fit --model full`` runs on the local model of the multiple-
scattering term built at the MAP (first order in log kappa_t and atanh g).  Along the
straight line from a fit's MAP to the truth in (log kappa_t, atanh g), at fractions F of the
way, this prints the log posterior (logit albedo and log brightness maximised at each point)
relative to that at the first F (0: the MAP), two ways, per seed of the term:

* ``local``: the local model built at the MAP, as the sampler has it;
* ``refreshed``: the term traced anew at each point (its own local model there), the
  nearest thing to the posterior with the exact term at that many paths.

With an exact term the two agree near the MAP and part by the term's curvature away from it;
their difference across seeds, and how it falls with the paths, says how far the sampler's
tails follow the term's noise.  A difference of 3 units along the line is about 2.5 sd.

Run: python docs/studies/ms_profile.py CAPTURE_DIR RESULTS_JSON [PATHS] [SEEDS] [F,...]
(CAPTURE_DIR with truth.json; the fit's first channel; SEEDS comma-separated, 0 = the fit's
own; defaults 4096, 0, 0,0.25,0.5,1.0; about a minute per seed at 16 x 12 px and 4096 paths)
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from fitmedia.inference import fit as F
from fitmedia.inference.full import use_full_transport
from fitmedia.inference.optimize import find_map
from fitmedia.inference.params import ChannelParams
from ms_realisation import at_truth  # docs/studies/ is on sys.path when this file is run


def profile(prob, space, x: np.ndarray) -> float:
    """The log posterior at ``x`` with logit albedo and log brightness maximised."""
    def lp(v):
        y = x.copy()
        y[1], y[3] = v
        return prob.log_posterior(y)

    idx = [1, 3]
    return find_map(lp, x[idx], space.lower[idx], space.upper[idx], global_evals=0).log_posterior


def main():
    cap, resf = Path(sys.argv[1]), Path(sys.argv[2])
    paths = int(sys.argv[3]) if len(sys.argv) > 3 else 4096
    seeds = [int(s) for s in (sys.argv[4] if len(sys.argv) > 4 else "0").split(",")]
    fs = [float(f) for f in (sys.argv[5] if len(sys.argv) > 5 else "0,0.25,0.5,1").split(",")]
    spec, ch, _, _, space, prob, _, xt, _ = at_truth(cap)
    res = json.loads(resf.read_text())
    p = res["parameters"]
    xm = space.to_vector(ChannelParams(p["kappa_t"][ch]["map"], p["albedo"][ch]["map"],
                                       p["g"][ch]["map"],
                                       res["diagnostics"]["channels"][ch]["brightness"]))
    own, _ = F._ms_seeds(res["seed"], ch)
    print(f"channel {ch}; F = " + " ".join(f"{f:g}" for f in fs))
    for s in seeds:
        t0 = time.time()
        use_full_transport(prob, spec, ch, seed=own if s == 0 else s)
        for o in prob.obs:
            o.model.ms.n_paths = paths
        prob.refresh_models(xm)
        prob.adapt(xm)
        local = [profile(prob, space, xm + f * (xt - xm)) for f in fs]
        fresh = []
        for f in fs:
            x = xm + f * (xt - xm)
            prob.refresh_models(x)
            prob.adapt(x)
            fresh.append(profile(prob, space, x))
        print(f"seed {s}, {paths} paths: local " + " ".join(f"{v - local[0]:+.2f}" for v in local)
              + " | refreshed " + " ".join(f"{v - fresh[0]:+.2f}" for v in fresh)
              + f" ({time.time() - t0:.0f} s)", flush=True)


if __name__ == "__main__":
    main()

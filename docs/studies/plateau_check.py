"""A MAP away from the truth on a noise-free capture: the posterior's maximum there, or a
search that stopped?  (docs/validation.md, "Round 9's R on its noise-free twin".)

For a capture CAP (capture.yaml, e.g. docs/studies/noise_realisations.py's twin), its fit FIT
(samples.npz: ``CH/map_unconstrained``), channel CH and the true medium (CAP's truth.json):
the full model's log posterior with its local model rebuilt at each point
(``full.log_posterior_rebuilt``: the same random numbers wherever it is built) along the
straight line in the sampler's coordinates (log kappa_t, logit albedo, atanh g; the MAP's
other coordinates held) from the MAP (t = 0) to the truth (t = 1), for the term's seeds
SEEDS (the fit's own first: ``seed`` in results.json).  The truth above the MAP
says the search stopped short; below, the images (through the model chain) prefer the MAP.
Then the truth is polished (BOBYQA, as a refresh polishes) with the local model built there,
and the log posterior at its end is printed with its values: where the model's maximum near
the truth lies.

Run: python docs/studies/plateau_check.py CAP/capture.yaml FIT CH [SEED ...]
     (100 x 75 px: about a minute a point on 2 loaded cores)
"""
from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from fitmedia.inference.fit import channel_args, channel_problem, prepare
from fitmedia.inference.full import log_posterior_rebuilt, use_full_transport
from fitmedia.inference.optimize import find_map
from fitmedia.inference.result import FitOptions
from fitmedia.spec import load_spec


def describe(space, x: np.ndarray) -> str:
    p = space.to_params(x)
    return (f"kappa_t {p.kappa_t:.5f} albedo {p.albedo:.4f} kappa_s {p.kappa_s:.5f} "
            f"kappa_a {p.kappa_a:.5f} g {p.g:.4f}")


def probes(problem, x_map: np.ndarray) -> None:
    """With the local model built at the MAP (as the refresh that ended there had it): the log
    posterior at full.off_the_plateau's probes (kappa_s and g held) and at the same albedos
    with kappa_t and g held, minus the MAP's."""
    from scipy.special import expit

    from fitmedia.inference.full import PLATEAU_PROBES

    lp0 = log_posterior_rebuilt(problem, x_map)
    for held in ("kappa_s", "kappa_t"):
        out = []
        for la in PLATEAU_PROBES:
            x = x_map.copy()
            x[1] = la
            if held == "kappa_s":
                x[0] += np.log(expit(x_map[1])) - np.log(expit(la))
            out.append(f"logit albedo {la:g}: {problem.log_posterior(x) - lp0:+.2f}")
        print(f"probes with {held} and g held, minus the MAP's: " + ", ".join(out), flush=True)


def main(argv: list[str]) -> None:
    cap, fit_dir, ch = Path(argv[0]), Path(argv[1]), argv[2]
    res = json.loads((fit_dir / "results.json").read_text())
    seeds = [int(s) for s in argv[3:]] or [int(res["seed"])]
    truth = json.loads((cap.parent / "truth.json").read_text())["undiluted"]
    spec = load_spec(cap)
    opt = FitOptions(model="full", mcmc=False, seed=seeds[0])
    a = channel_args(prepare(spec), ch, opt, None)
    setup = channel_problem(spec, ch, a[2], a[3], a[4], a[5], a[6], opt, a[11])
    problem, space = setup.problem, setup.space
    x_map = np.load(fit_dir / "samples.npz")[f"{ch}/map_unconstrained"]
    kt, ks = truth["kappa_t"][ch], truth["kappa_s"][ch]
    x_true = x_map.copy()
    here = space.to_params(x_map)  # its brightness and background kept
    x_true[:3] = space.to_vector(replace(here, kappa_t=kt, albedo=ks / kt, g=truth["g"][ch]))[:3]
    print(f"MAP:   {describe(space, x_map)}\ntruth: {describe(space, x_true)}", flush=True)
    for s in seeds:
        use_full_transport(problem, spec, ch, seed=s)
        lp = {t: log_posterior_rebuilt(problem, x_map + t * (x_true - x_map))
              for t in (0.0, 0.25, 0.5, 0.75, 1.0)}
        print(f"term seed {s}: log posterior minus the MAP's along MAP -> truth: " + ", ".join(
            f"t={t:g} {v - lp[0.0]:+.2f}" for t, v in lp.items()), flush=True)
    use_full_transport(problem, spec, ch, seed=seeds[0])
    probes(problem, x_map)
    log_posterior_rebuilt(problem, x_true)  # the local model built at the truth
    end = find_map(problem.log_posterior, x_true, space.lower, space.upper, global_evals=0,
                   laplace=False)
    print(f"polished from the truth (term seed {seeds[0]}): {describe(space, end.x)}, log "
          f"posterior {log_posterior_rebuilt(problem, end.x) - log_posterior_rebuilt(problem, x_map):+.2f}"
          " against the MAP's", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])

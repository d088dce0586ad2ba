"""The noise of the restart check's log-posterior comparison (inference/full.py: restart_delta)
over the term's seed (docs/inference.md, "The restart's log posterior: its noise").

For a capture CAP and its full fit FIT (results.json, samples.npz), channel CH: Delta_s =
log_posterior_rebuilt(x1) - log_posterior_rebuilt(x0) with the term of seed s (common random
numbers within a seed; the loop's paths and grid), x0 the fit's MAP, x1 moved K posterior
sd along log kappa_t (the other coordinates held); printed per K: mean, sd and values over
the seeds 1..N.

Run: python docs/studies/restart_delta_noise.py CAP/capture.yaml FIT CH K1,K2,... N
     (e.g. bench/fit_full.py's capture and fit_full, R, 0.06,1,3, 6: about 5 min on 2 cores)
"""
import sys
from pathlib import Path
import numpy as np
from fitmedia.inference.fit import channel_args, channel_problem, prepare
from fitmedia.inference.full import use_full_transport, log_posterior_rebuilt
from fitmedia.inference.result import FitOptions
from fitmedia.spec import load_spec

cap, fit, ch = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
ks = [float(k) for k in sys.argv[4].split(",")]
seeds = range(1, int(sys.argv[5]) + 1)
spec = load_spec(cap)
opt = FitOptions(model="full", mcmc=False)
a = channel_args(prepare(spec), ch, opt, None)
setup = channel_problem(spec, ch, a[2], a[3], a[4], a[5], a[6], opt, a[11])
problem = setup.problem
z = np.load(fit / "samples.npz")
x0 = z[f"{ch}/map_unconstrained"]
sd = np.std(z[f"{ch}/unconstrained"], axis=0)
print("posterior sd of the sampler's coordinates", np.round(sd, 4), flush=True)
for k in ks:
    x1 = x0.copy()
    x1[0] += k * sd[0]
    d = []
    for s in seeds:
        use_full_transport(problem, spec, ch, seed=s)
        d.append(log_posterior_rebuilt(problem, x1) - log_posterior_rebuilt(problem, x0))
    d = np.array(d)
    print(f"K {k:g} sd in log kappa_t: Delta over {len(d)} seeds: mean {d.mean():+.2f}, sd {d.std(ddof=1):.2f}, values {np.round(d, 2).tolist()}", flush=True)

"""The refresh loop's map near the truth, and its Jacobian (docs/inference.md, "Why the
refreshes creep on dense milk").

The loop (inference/full.py: ``refine_map``) maps a refresh point a to F(a), the polish of
the posterior whose multiple-scattering term is the local model built at a (linear in
log kappa_t and atanh g, exact in the albedo).  A fixed point of F is a stationary point of
the posterior with the term itself, and the loop converges to it only where the Jacobian
F' has its eigenvalues inside the unit circle.  To first order
F' = (H + R)^-1 R, with H the posterior's Hessian (of minus its log) and R = sum_pixels
w r T'', the residuals r (weights w) times the term's second derivatives, which the
linear local model lacks: where R is comparable to H along the similarity ridge (H small
there), F' can have an eigenvalue near or beyond 1, and the loop creeps or walks away.  A
local model with the term's second derivatives (``quad``) removes R from F' (Newton's
method), up to their Monte Carlo noise.

This script builds one channel's problem as ``fitmedia fit --model full`` does, puts the
term's paths at ``FACTOR`` times the loop's (8: the last refreshes' paths and grid,
``more_paths``), evaluates F at the truth and at the truth +- DELTA in log kappa_t and in
atanh g (5 refreshes and polishes, on the fit's random numbers), and prints F's central-
difference Jacobian in those two coordinates, its eigenvalues and eigenvectors (also in
Laplace sd).  MODE: ``forward`` (the code's local model: forward differences of step 0.05),
``central`` (central differences, the same linear model) or ``quad`` (central differences
plus the second derivatives and the cross term, from one trace reweighted to 5 points).
The Jacobian holds the change of the term's realisation between the points as well (the
same seed, other paths): read eigenvalues to about +-0.3 at DELTA of a few sd.

Run: python docs/studies/refresh_contraction.py CAPTURE MODE FACTOR DELTA [CHANNEL]
(CAPTURE: a folder from ``fitmedia synth``, with truth.json; CHANNEL default G)
"""
import json
import math
import sys
import time

import numpy as np

from fitmedia.forward import multiple as MS
from fitmedia.inference import fit as F
from fitmedia.inference import full
from fitmedia.inference.optimize import find_map
from fitmedia.inference.params import ChannelParams
from fitmedia.inference.result import FitOptions
from fitmedia.spec import load_spec

cap, mode, factor, delta = sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
ch = sys.argv[5] if len(sys.argv) > 5 else "G"


def refresh_other(self, kappa_a, kappa_s, g, brightness=None, quad=False):
    """``FullTransport.refresh`` with central differences, and with ``quad`` the second
    derivatives and the cross term too (one trace reweighted to 4 or 5 points)."""
    c = len(self.channels)
    ka, ks, gg, _ = MS.check_render_args(c, kappa_a, kappa_s, g, 1.0 if brightness is None else brightness)
    keys = [self._trace_key(ka[k], ks[k], gg[k]) for k in range(c)]
    self._term_table = None
    local = []
    for k in range(c):
        kt, a = ka[k] + ks[k], ks[k] / (ka[k] + ks[k])
        eta, s = math.atanh(gg[k]), self.step
        pts = ((kt * math.exp(s), gg[k]), (kt, math.tanh(eta + s)),
               (kt * math.exp(-s), gg[k]), (kt, math.tanh(eta - s)))
        r = self.ms.orders_at(kt, gg[k], pts + (((kt * math.exp(s), math.tanh(eta + s)),)
                                                if quad else ()), seed=self.seed, rr_albedo=a)
        loc = {"kt": kt, "eta": eta, "batches": r[0], "d_kt": (r[1] - r[3]) / (2 * s),
               "d_g": (r[2] - r[4]) / (2 * s), "key": keys[k]}
        if quad:
            loc.update(d_kk=(r[1] - 2 * r[0] + r[3]) / s ** 2, d_gg=(r[2] - 2 * r[0] + r[4]) / s ** 2,
                       d_kg=(r[5] - r[1] - r[2] + r[0]) / s ** 2)
        local.append(MS._with_order_major(loc))
    self._local = local
    self._var0 = self.ms_part(ka, ks, gg, np.ones(c), excess=True, variance=False)[2]


def refresh_central(self, *args):
    refresh_other(self, *args)


def refresh_quad(self, *args):
    refresh_other(self, *args, quad=True)


def steps_quad(loc, kt, g):
    """``FullTransport._steps`` for the quadratic local model's six parts (its excess variance
    keeps the linear parts' form: ``ms_part`` pairs only the first three)."""
    h1, h2 = math.log(kt / loc["kt"]), math.atanh(g) - loc["eta"]
    return (1.0, h1, h2, h1 * h1 / 2, h2 * h2 / 2, h1 * h2)


if mode == "central":
    MS.FullTransport.refresh = refresh_central
if mode == "quad":
    MS.LOCAL_PARTS = ("batches", "d_kt", "d_g", "d_kk", "d_gg", "d_kg")
    MS.FullTransport.refresh = refresh_quad
    MS.FullTransport._steps = staticmethod(steps_quad)
spec = load_spec(cap + "/capture.yaml")
t = json.load(open(cap + "/truth.json"))["undiluted"]
opts = FitOptions(model="full", seed=1, mcmc=False)
prep = F.prepare(spec)
a = F.channel_args(prep, ch, opts, None)
setup = F.channel_problem(a[0], a[1], a[2], a[3], a[4], a[5], a[6], opts, a[11])
problem, space = setup.problem, setup.space
ms_seed, _ = F._ms_seeds(1, ch)
full.use_full_transport(problem, spec, ch, seed=ms_seed)
for o in problem.obs:
    o.model.ms.n_paths *= factor
    if factor > 1:
        o.model.rebin(full.final_bin(o.model.ms.camera))
x0 = space.to_vector(ChannelParams(t["kappa_t"][ch], t["albedo"][ch], t["g"][ch],
                                   setup.guess_b if setup.free else None))


def Fmap(at):
    t0 = time.time()
    problem.refresh_models(at)
    problem.adapt(at)
    lo, hi = full._trust_region(space, at, full.TRUST_STEP)
    new = find_map(problem.log_posterior, np.clip(at, lo, hi), lo, hi, global_evals=0)
    print(f"F({np.round(at, 4)}) = {np.round(new.x, 4)}  lp {new.log_posterior:.2f}  {time.time() - t0:.0f} s", flush=True)
    return new


f0 = Fmap(x0)
cov = f0.cov
idx = [0, 2]
sd = np.sqrt(np.diag(cov)[idx]) if cov is not None else None
print("Laplace sd (log kt, atanh g):", sd)
J = np.zeros((2, 2))
for j, i in enumerate(idx):
    xp, xm = x0.copy(), x0.copy()
    xp[i] += delta
    xm[i] -= delta
    J[:, j] = (Fmap(xp).x[idx] - Fmap(xm).x[idx]) / (2 * delta)
print(mode, "factor", factor, "fixed-point offset from truth (sd):", (f0.x[idx] - x0[idx]) / sd)
w, V = np.linalg.eig(J); print("Jacobian of F:", np.round(J, 3).tolist(), "eigenvalues", np.round(w, 3), "vectors (cols)", np.round(V, 3).tolist(), "in sd units", np.round(V / sd[:, None], 2).tolist())

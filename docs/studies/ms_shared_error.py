"""Does the full-transport posterior cover the truth when the multiple-scattering term is
traced with other random numbers?  (docs/inference.md, "Full transport".)

A capture rendered with fitmedia's own term at many paths (``synth --model hybrid``, so
its render noise is far below the fit's term error) is fitted with the local model of
the term built AT THE TRUTH from each of several seeds, the MAP polished from the truth
(no further refresh): the spread of these MAPs is the term's realisation alone.  Printed
per seed: the errors of kappa_t and g, their z = error / Laplace sd (log kappa_t,
atanh g), and z = error / sqrt(Laplace variance + the term's jackknife variance)
(``inference.full.term_jackknife``).  A calibrated covariance gives z with rms near 1.

Run: python docs/studies/ms_shared_error.py CAPTURE_DIR [N_PATHS] [SEEDS]
(CAPTURE_DIR: a one-image, one-channel capture with truth.json; ~1 CPU-minute per seed)
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from fitmedia.forward.multiple import FullTransport
from fitmedia.inference import fit as F
from fitmedia.inference.full import term_jackknife
from fitmedia.inference.optimize import find_map
from ms_realisation import at_truth  # docs/studies/ is on sys.path when this file is run

import fitmedia.forward.multiple as _multiple

#: camera pixels per traced sample pixel (the fit's own: inference.full.trace_bin; 1 here
#: unless STUDY_BIN says otherwise)
BIN = int(os.environ.get("STUDY_BIN", 1))

if os.environ.get("STUDY_LFO"):  # photons from this order on (default: LIGHT_FROM_ORDER)
    _multiple.LIGHT_FROM_ORDER = int(os.environ["STUDY_LFO"])


def _variant(prob, o, spec, t, ch, b):
    """STUDY_VAR=zero: no term variance in the likelihood, nor the excess of
    ChannelProblem.log_likelihood; =smooth: the term's relative
    variance pooled over the glow times the square of the term smoothed (sigma 2 px), so that
    a pixel's weight does not follow its own realisation; =noderiv: the term held at its value
    at the truth; =drefN: the finite differences from an independent trace at N paths (nearly
    exact derivatives), the term itself from the seed's; =drefN+zero: both."""
    import os

    from scipy import ndimage

    mode = os.environ.get("STUDY_VAR", "")
    if not mode:
        return
    if mode.startswith("noderiv"):  # the term held at its value at the truth
        # noderiv+zero: and no term variance in the likelihood; +avg: the term the mean of
        # STUDY_NAVG (16) traces at n_paths with seeds from STUDY_AVG0 (700); +exact: one
        # trace at STUDY_NREF (4096) paths; both with no term variance either
        then = mode.partition("+")[2]
        if then == "avg":
            n = int(os.environ.get("STUDY_NAVG", 16))
            first = int(os.environ.get("STUDY_AVG0", 700))
            _fixed_term(o, spec, t, ch, b, [(first + s, o.model.ms.n_paths) for s in range(n)])
        elif then == "exact":
            _fixed_term(o, spec, t, ch, b, [(999, int(os.environ.get("STUDY_NREF", 4096)))])
        for loc in o.model._local:
            if loc is not None:
                loc["d_kt"] = 0 * loc["batches"]
                loc["d_g"] = 0 * loc["batches"]
        if then:
            prob._model_var[0] = 0.0
            o.model.render_with_variance = None  # nor its excess (the plain likelihood)
        return
    if mode.startswith("dref"):  # derivatives from an independent trace at many paths
        n_ref, _, then = mode[4:].partition("+")  # e.g. dref4096+zero
        ref = FullTransport(spec, 0, channels=(ch,), seed=999, bin=BIN, n_paths=int(n_ref),
                            single=o.model.single)
        ci = F.CHANNELS.index(ch)
        c = spec.images[0].concentration
        ref.refresh([c * t["kappa_a"][ch] + spec.water_kappa_a[ci]], [c * t["kappa_s"][ch]],
                    [t["g"][ch]], [b])
        for loc, r in zip(o.model._local, ref._local):
            k = min(loc["batches"].shape[1], r["d_kt"].shape[1])
            for name in ("d_kt", "d_g"):
                new = np.zeros_like(loc[name])
                new[:, :k] = r[name][:, :k]
                loc[name] = new
        # the likelihood's term variance again, from the local model with these derivatives
        _, var = o.model.ms_part([c * t["kappa_a"][ch] + spec.water_kappa_a[ci]],
                                 [c * t["kappa_s"][ch]], [t["g"][ch]], [b])
        prob._model_var[0] = var[..., 0].ravel()[o.flat_idx] * o.model.ms.bin ** 2
        mode = then
        if not mode:
            return
    if mode == "zero":
        prob._model_var[0] = 0.0
        o.model.render_with_variance = None  # nor its excess (the plain likelihood)
        return
    ci = F.CHANNELS.index(ch)
    c = spec.images[0].concentration
    img, var = o.model.ms_part([c * t["kappa_a"][ch] + spec.water_kappa_a[ci]],
                               [c * t["kappa_s"][ch]], [t["g"][ch]], [b])
    m, v = img[..., 0], var[..., 0]
    glow = m > 1e-2 * m.max()
    rel = np.median(v[glow] / m[glow] ** 2)
    ms = ndimage.gaussian_filter(m, 2.0)
    prob._model_var[0] = (rel * ms**2 * o.model.ms.bin**2).ravel()[o.flat_idx]


def _fixed_term(o, spec, t, ch, b, traces):
    """Replace the local model's per-order batches by the mean of ``traces`` ((seed, paths)
    pairs) built at the truth."""
    ci = F.CHANNELS.index(ch)
    c = spec.images[0].concentration
    medium = ([c * t["kappa_a"][ch] + spec.water_kappa_a[ci]], [c * t["kappa_s"][ch]],
              [t["g"][ch]], [b])
    runs = []
    for seed, n_paths in traces:
        ref = FullTransport(spec, 0, channels=(ch,), seed=seed, bin=BIN, n_paths=n_paths,
                            single=o.model.single)
        ref.refresh(*medium)
        runs.append(ref._local[0]["batches"])
    k = max(x.shape[1] for x in runs)
    o.model._local[0]["batches"] = np.mean(
        [np.pad(x, ((0, 0), (0, k - x.shape[1]), (0, 0))) for x in runs], axis=0)


def main():
    cap = Path(sys.argv[1])
    n_paths = int(sys.argv[2]) if len(sys.argv) > 2 else 256
    first = int(os.environ.get("STUDY_SEED0", 11))  # the capture's own seed: its very term
    seeds = range(first, first + (int(sys.argv[3]) if len(sys.argv) > 3 else 8))
    spec, ch, _, b, space, prob, t, xt, single = at_truth(cap)
    o = prob.obs[0]
    rows = []
    for seed in seeds:
        o.model = FullTransport(spec, 0, channels=(ch,), seed=seed, bin=BIN, n_paths=n_paths,
                                single=single, step=float(os.environ.get("STUDY_STEP", 0.05)),
                                batches=int(os.environ.get("STUDY_BATCHES", 16)))
        o.model.ms.smooth = float(os.environ.get("STUDY_SMOOTH", o.model.ms.smooth))
        prob.refresh_models(xt)
        prob.adapt(xt)
        _variant(prob, o, spec, t, ch, b)
        prob.robust = bool(os.environ.get("STUDY_ROBUST"))  # Student-t, as fit --robust
        c2, n = prob.chi2(xt)
        r = find_map(prob.log_posterior, xt, space.lower, space.upper, global_evals=0)
        jk = term_jackknife(prob, r)

        lap = np.diag(r.cov)[[0, 2]]
        tot = lap + np.diag(jk)[[0, 2]]
        e = r.x[[0, 2]] - xt[[0, 2]]
        p = space.to_params(r.x)
        rows.append((p.kappa_t / t["kappa_t"][ch] - 1, p.g - t["g"][ch], *(e / np.sqrt(lap)),
                     *(e / np.sqrt(tot)), *np.sqrt(np.diag(jk)[[0, 2]] / lap), c2 / n))
        print(f"seed {seed}: kappa_t {rows[-1][0]:+.3f} g {rows[-1][1]:+.3f}; z Laplace "
              f"{rows[-1][2]:+.2f} {rows[-1][3]:+.2f}; z with the jackknife {rows[-1][4]:+.2f} "
              f"{rows[-1][5]:+.2f}; jackknife sd / Laplace sd {rows[-1][6]:.2f} {rows[-1][7]:.2f}; "
              f"chi2/pixel at the truth {rows[-1][8]:.2f}", flush=True)
    R = np.array(rows)
    rms = np.sqrt(np.mean(R[:, 2:6] ** 2, axis=0))
    print(f"{n_paths} paths, {len(R)} seeds: kappa_t error mean {R[:, 0].mean():+.4f} sd "
          f"{R[:, 0].std(ddof=1):.4f}; g error mean {R[:, 1].mean():+.4f} sd "
          f"{R[:, 1].std(ddof=1):.4f}; z rms (log kappa_t, atanh g): Laplace {rms[0]:.2f} "
          f"{rms[1]:.2f}, with the jackknife {rms[2]:.2f} {rms[3]:.2f}; chi2/pixel at the truth "
          f"{R[:, 8].min():.2f}-{R[:, 8].max():.2f}")


if __name__ == "__main__":
    main()

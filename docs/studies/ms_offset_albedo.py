"""Where does the full-transport fit's low offset at 256 paths per sample pixel come from?
(docs/inference.md, "The term's variance in the residuals".)

On a one-image, one-channel capture with truth.json (``synth --model hybrid`` at many
paths), the local model is built at the truth and its finite differences set to zero, the
term's variance left out of the likelihood, and the MAP polished from the truth; the term is
replaced by chosen mixtures of traces at 256 paths:

* ``lam``: the mean of 16 traces plus lambda times (one trace - that mean), lambda in 0,
  0.25, 0.5, 1, -1: how the MAP answers the size of one trace's error;
* ``held``: the same with the albedo held at the truth;
* ``where``: one trace's error kept only in a part of the pixels (by the term's level) or
  of the orders (2; >= 3);
* ``white``: the mean of 16 traces, and Gaussian noise of one trace's per-pixel sd added to
  the data instead.

Run: python docs/studies/ms_offset_albedo.py CAPTURE_DIR MODE   (~1-2 CPU-minutes per mode
at 48 x 36; the 19 traces are kept in CAPTURE_DIR/../ms_offset_traces.npz)
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from fitmedia.forward.multiple import FullTransport
from fitmedia.inference.optimize import find_map
from ms_realisation import at_truth  # docs/studies/ is on sys.path when this file is run


def setup(cap: Path):
    spec, ch, ci, b, space, prob, t, xt, single = at_truth(cap)
    o = prob.obs[0]
    c = spec.images[0].concentration
    medium = ([c * t["kappa_a"][ch] + spec.water_kappa_a[ci]], [c * t["kappa_s"][ch]],
              [t["g"][ch]], [b])

    def batches(seed):
        r = FullTransport(spec, 0, channels=(ch,), seed=seed, bin=1, n_paths=256, single=single)
        r.refresh(*medium)
        return r._local[0]["batches"]

    cache = cap.parent / "ms_offset_traces.npz"
    if cache.exists():
        traces = dict(np.load(cache))
    else:
        one = {f"s{s}": batches(s) for s in (11, 12, 13)}
        avg = [batches(700 + s) for s in range(16)]
        k = max(x.shape[1] for x in avg + list(one.values()))
        pad = lambda x: np.pad(x, ((0, 0), (0, k - x.shape[1]), (0, 0)))  # noqa: E731
        traces = {name: pad(x) for name, x in one.items()}
        traces["avg"] = np.mean([pad(x) for x in avg], axis=0)
        np.savez(cache, **traces)
    o.model = FullTransport(spec, 0, channels=(ch,), seed=1, bin=1, n_paths=256, single=single)
    o.model.refresh(*medium)
    return spec, ch, t, space, prob, o, xt, traces, medium


def main():
    cap, mode = Path(sys.argv[1]), sys.argv[2]
    spec, ch, t, space, prob, o, xt, T, medium = setup(cap)
    loc = o.model._local[0]
    lo, hi = space.lower.copy(), space.upper.copy()
    if mode == "held":
        lo[1], hi[1] = xt[1] - 1e-6, xt[1] + 1e-6

    def polish(batch, label):
        loc["batches"] = batch
        loc["d_kt"] = loc["d_g"] = 0 * batch
        prob._model_var[0] = 0.0
        o.model.render_with_variance = None  # the plain likelihood: no excess either
        r = find_map(prob.log_posterior, xt, lo, hi, global_evals=0, laplace=False)
        p = space.to_params(r.x)
        print(f"{label}: kappa_t {p.kappa_t / t['kappa_t'][ch] - 1:+.4f} g {p.g - t['g'][ch]:+.4f}"
              f" logit albedo {r.x[1]:.2f} (truth {xt[1]:.2f})", flush=True)

    if mode in ("lam", "held"):
        for s in (("s11",) if mode == "lam" else ("s11", "s12", "s13")):
            for lam in ((0.0, 0.25, 0.5, 1.0, -1.0) if mode == "lam" else (0.0, 1.0)):
                polish(T["avg"] + lam * (T[s] - T["avg"]), f"{mode} {s} lambda {lam:+.2f}")
    elif mode == "where":
        albedo = t["kappa_s"][ch] / t["kappa_t"][ch]
        pw = albedo ** np.arange(T["avg"].shape[1])
        pw[0] = 0.0
        tot = np.tensordot(T["avg"].mean(0), pw, axes=([0], [0]))
        lit = tot > 0.01 * tot.max()
        order = np.argsort(-np.where(lit, tot, -1))
        n = lit.sum()
        for s in ("s11", "s12"):
            e = T[s] - T["avg"]
            for name, idx in (("brightest 10 %", order[: n // 10]),
                              ("next 40 %", order[n // 10: n // 2]), ("rest", order[n // 2: n])):
                m = np.zeros(tot.shape, bool)
                m[idx] = True
                polish(T["avg"] + e * m, f"where {s} {name} of the glow")
            for name, ords in (("order 2", slice(2, 3)), ("orders >= 3", slice(3, None))):
                em = np.zeros_like(e)
                em[:, ords] = e[:, ords]
                polish(T["avg"] + em, f"where {s} {name}")
    elif mode == "white":
        loc["batches"] = T["s11"]
        loc["d_kt"] = loc["d_g"] = 0 * T["s11"]
        sd = np.sqrt(o.model.ms_part(*medium)[1][..., 0].ravel()[o.flat_idx])
        values = o.values.copy()
        for rep in range(4):
            o.values = values + np.random.default_rng(rep).normal(0.0, sd)
            polish(T["avg"], f"white noise {rep} in the data")
        o.values = values
    else:
        raise SystemExit(f"mode: lam, held, where or white, not {mode!r}")


if __name__ == "__main__":
    main()

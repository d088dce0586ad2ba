"""Where does a round trip's bias come from?  Many noise draws of one clean synthetic image,
each fitted by a local MAP search started at the truth, scored with the Laplace standard
deviation (z = (MAP - truth) / sd in the sampler's coordinates: log kappa_t, logit albedo,
atanh g, log brightness).

Each draw also redraws the clear-water calibration: the brightness prior's centre is
1 + rel_sd x N(0, 1) (the calibration is itself calibrated: over the 100-round validation its
z had mean -0.04 and sd 0.99, docs/validation.md).

Conditions (command line):
  --fix-albedo      the albedo held at its true value (the other parameters free)
  --fix-brightness  the brightness held at its true value, no prior
  --noise gauss     Gaussian noise with the likelihood's variance instead of Poisson-Gaussian
  --likelihood poisson   the shifted-Poisson likelihood (Snyder et al. 1993) instead of the
                    Gaussian one with the variance at the model

Example (docs/validation.md, "Where the bias comes from"):
  python docs/studies/bias_study.py "Lowfat Milk" 20 --draws 150
  python docs/studies/bias_study.py "Lowfat Milk" 20 --draws 150 --fix-albedo
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from fitmedia.forward.single import SingleScattering
from fitmedia.inference.fit import FitOptions, _model, prepare
from fitmedia.inference.likelihood import ChannelProblem, Observation
from fitmedia.inference.optimize import find_map, laplace_covariance
from fitmedia.inference.params import ChannelParams, ParameterSpace
from fitmedia.medium import medium_by_name
from fitmedia.spec import CHANNELS, load_spec
from fitmedia.synth import CameraNoise, synthesize

ROOT = Path(__file__).resolve().parents[2]
NAMES = ("log_kappa_t", "logit_albedo", "atanh_g", "log_brightness")


def shifted_poisson(self, u):
    """log L of (data / gain + read_var / gain^2) ~ Poisson(model / gain + read_var / gain^2)."""
    s = self.read_var / self.gain ** 2
    total = 0.0
    for o, img in zip(self.obs, self.render(u)):
        lam = np.maximum(img.ravel()[o.flat_idx], 0) / self.gain + s
        n = np.maximum(o.values / self.gain + s, 0)
        total += float(np.sum(n * np.log(lam) - lam))
    return total


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("medium")
    ap.add_argument("ml", type=float)
    ap.add_argument("--channels", default="RGB")
    ap.add_argument("--draws", type=int, default=100)
    ap.add_argument("--seed", type=int, default=2024)
    ap.add_argument("--spec", default=str(ROOT / "capture_specs" / "bulb_64x48.yaml"))
    ap.add_argument("--fix-albedo", action="store_true")
    ap.add_argument("--fix-brightness", action="store_true")
    ap.add_argument("--noise", choices=("poisson", "gauss"), default="poisson")
    ap.add_argument("--likelihood", choices=("gauss", "poisson"), default="gauss")
    a = ap.parse_args(argv)
    if a.likelihood == "poisson":
        ChannelProblem.log_likelihood = shifted_poisson
    med = medium_by_name(a.medium)
    truth = med.as_dict()
    with tempfile.TemporaryDirectory() as tmp:
        spec = load_spec(synthesize(load_spec(a.spec, require_images=False), tmp, med, [a.ml],
                                    seed=1))
        prep = prepare(spec)  # noise, mask and the calibration's standard error
    c = a.ml / 23000.0
    clean = SingleScattering(spec, None, channels=CHANNELS, supersample=2).render(
        np.asarray(med.kappa_a) * c, np.asarray(med.kappa_s) * c, med.g, 1.0)  # as synth does
    rng = np.random.default_rng(a.seed)
    z = {ch: [] for ch in a.channels}
    for _ in range(a.draws):
        gain, rv = prep.noise[a.channels[0]]
        img = (clean + rng.normal(size=clean.shape) * np.sqrt(gain * clean + rv)
               if a.noise == "gauss" else CameraNoise(gain, rv).apply(clean, rng))
        for ch in a.channels:
            ci = CHANNELS.index(ch)
            model = _model(spec, 0, ch, FitOptions())
            obs = [Observation(model, img[..., ci], prep.images[0].valid[..., ci] & model.support,
                               c)]
            rel_sd = prep.brightness_rel_sd[ch]
            b_cal = 1.0 + rel_sd * rng.normal()
            if a.fix_brightness:
                space = ParameterSpace()
                problem = ChannelProblem(obs, space, 1.0, prep.noise[ch])
            else:
                space = ParameterSpace(free_brightness=True, brightness_guess=b_cal,
                                       brightness_rel_sd=rel_sd)
                problem = ChannelProblem(obs, space, None, prep.noise[ch])
            kt, ks = truth["kappa_t"][ch], truth["kappa_s"][ch]
            xt = space.to_vector(ChannelParams(kt, ks / kt, truth["g"][ch],
                                               None if a.fix_brightness else 1.0))
            free = np.ones(len(xt), bool)
            if a.fix_albedo:
                free[1] = False

            def lp(v, _x=xt.copy(), _free=free, _p=problem):
                x = _x.copy()
                x[_free] = v
                return _p.log_posterior(x)

            problem.adapt(xt)
            lo, hi = space.lower[free], space.upper[free]
            res = find_map(lp, xt[free], lo, hi, global_evals=0, laplace=False)
            cov = laplace_covariance(lp, res.x, lo, hi)
            row = np.full(4, np.nan)
            if cov is not None:
                idx = np.flatnonzero(free)
                row[idx] = (res.x - xt[free]) / np.sqrt(np.diag(cov))
            z[ch].append(row)
    print(f"{a.medium} {a.ml:g} ml, {a.draws} draws, noise {a.noise}, likelihood {a.likelihood}"
          f"{', albedo fixed' if a.fix_albedo else ''}"
          f"{', brightness fixed' if a.fix_brightness else ''}")
    print("channel  " + "  ".join(f"{n:>22s}" for n in NAMES) + "   (mean z / sd z)")
    for ch, rows in z.items():
        arr = np.array(rows)
        cells = []
        for j in range(4):
            col = arr[:, j][np.isfinite(arr[:, j])]
            cells.append(f"{col.mean():+6.2f} / {col.std():4.2f}".rjust(22) if len(col) else
                         "-".rjust(22))
        print(f"{ch:7s}  " + "  ".join(cells))


if __name__ == "__main__":
    main()

"""Is a full-transport interval at 100 x 75 px as wide as the camera noise makes the values
scatter?  (docs/inference.md, "The 100 x 75 px misses followed up".)

For one capture of ``dilution_round_trips.py`` (its folder CASE holds cap/): its noise-free twin
(``synth`` with the same liquid, volume and seed and no camera noise: the same clean image and
multiple-scattering term), channel CH.  The full model's local model is built once at the
truth (term seed 1) and kept, so that only the camera noise varies: N realisations of the
synth's Poisson-Gaussian noise on the clean image, each fitted (MAP from the truth, no
refresh), give the MAP's sampling scatter; then the capture's own noise (its image minus the
twin: the same term) is fitted the same way.  Printed: the scatter of kappa_t, kappa_s and
atanh g against the Laplace sd, and where the capture's own noise puts the values.

A noise-free image fitted with the camera's noise model in the likelihood is no test of the
model: with no residuals, the likelihood's log-variance term pulls every pixel's model down
(measured on Lowfat Milk 1.6 ml: kappa_s' 12 % low, 3.5-6.7 sd; docs/inference.md).

Run: python docs/studies/camera_noise_scatter.py CASE LIQUID ML SEED CH N
     (e.g. OUT/Lowfat_Milk_1.6 "Lowfat Milk" 1.6 45 G 50: ~10 CPU-minutes)
"""
from __future__ import annotations

import glob
import json
import sys
from pathlib import Path

import numpy as np
import tifffile
import yaml

from fitmedia.inference.fit import channel_args, channel_problem, prepare
from fitmedia.inference.full import use_full_transport
from fitmedia.inference.optimize import find_map
from fitmedia.inference.params import ChannelParams
from fitmedia.inference.result import FitOptions
from fitmedia.medium import medium_by_name
from fitmedia.spec import load_spec
from fitmedia.synth import CameraNoise, synthesize


def twin(case: Path, liquid: str, ml: float, seed: int) -> Path:
    """The noise-free twin of case/cap (made once), with the capture's noise model in its spec."""
    path = case / "nf" / "capture.yaml"
    if not path.exists():
        cap = yaml.safe_load((case / "cap" / "capture.yaml").read_text())
        geo = case / "geo.yaml"
        geo.write_text(yaml.safe_dump({k: v for k, v in cap.items()
                                       if k not in ("images", "calibration", "synthetic")}))
        synthesize(load_spec(geo, require_images=False), case / "nf", medium_by_name(liquid), [ml],
                   seed=seed, model=cap["synthetic"]["model"], spp=1024,
                   noise=CameraNoise(gain=0.0, read_var=0.0), medium_name=liquid)
        raw = yaml.safe_load(path.read_text())
        raw["noise"] = cap["noise"]
        path.write_text(yaml.safe_dump(raw))
    return path


def values(x: np.ndarray) -> np.ndarray:
    """kappa_t, kappa_s and atanh g of a parameter vector."""
    kt = np.exp(x[0])
    return np.array([kt, kt / (1.0 + np.exp(-x[1])), x[2]])


def error(x: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Relative errors of kappa_t and kappa_s, absolute of atanh g, of ``x`` against ``truth``
    (``values`` of the true parameters)."""
    v = values(x)
    return np.r_[v[:2] / truth[:2] - 1.0, v[2] - truth[2]]


def main() -> None:
    case, liquid, ml, seed, ch, n = (Path(sys.argv[1]), sys.argv[2], float(sys.argv[3]),
                                     int(sys.argv[4]), sys.argv[5], int(sys.argv[6]))
    spec = load_spec(twin(case, liquid, ml, seed))
    opt = FitOptions(model="full", mcmc=False)
    a = channel_args(prepare(spec), ch, opt, None)
    setup = channel_problem(spec, ch, a[2], a[3], a[4], a[5], a[6], opt, a[11])
    problem, space = setup.problem, setup.space
    u = json.loads((case / "cap" / "truth.json").read_text())["undiluted"]
    x = space.to_vector(ChannelParams(u["kappa_t"][ch], u["kappa_s"][ch] / u["kappa_t"][ch],
                                      u["g"][ch], 1.0 if setup.free else None))
    use_full_transport(problem, spec, ch, seed=1)
    problem.refresh_models(x)
    problem.adapt(x)
    o, camera = problem.obs[0], CameraNoise(*spec.noise)  # the synth's noise
    clean, truth = o.values.copy(), values(x)
    rng = np.random.default_rng([seed, n])
    rel = []
    for i in range(n):
        o.values = camera.apply(clean, rng)
        r = find_map(problem.log_posterior, x, space.lower, space.upper, global_evals=0,
                     laplace=False)
        rel.append(error(r.x, truth))
        print(f"realisation {i}: kappa_t {100 * rel[-1][0]:+.2f} %, kappa_s "
              f"{100 * rel[-1][1]:+.2f} %, atanh g {rel[-1][2]:+.4f}", flush=True)
    rel = np.array(rel)
    ci = "RGB".index(ch)
    img = tifffile.imread(glob.glob(str(case / "cap" / "images" / "medium_*.tiff"))[0])
    o.values = img.astype(float)[..., ci].ravel()[o.flat_idx]
    own = find_map(problem.log_posterior, x, space.lower, space.upper, global_evals=0)
    d = error(own.x, truth)
    sd = rel.std(axis=0, ddof=1)
    print(f"{n} realisations, MAP minus truth: mean kappa_t {100 * rel[:, 0].mean():+.2f} %, "
          f"kappa_s {100 * rel[:, 1].mean():+.2f} %, atanh g {rel[:, 2].mean():+.4f}; sd "
          f"{100 * sd[0]:.2f} %, {100 * sd[1]:.2f} %, {sd[2]:.4f}")
    if own.cov is not None:
        print("Laplace sd of log kappa_t, logit albedo, atanh g at the capture's MAP:",
              np.round(np.sqrt(np.diag(own.cov))[:3], 4))
    print(f"the capture's own noise: kappa_t {100 * d[0]:+.2f} %, kappa_s {100 * d[1]:+.2f} % "
          f"({d[1] / sd[1]:+.1f} sd of the scatter), atanh g {d[2]:+.4f} ({d[2] / sd[2]:+.1f} sd)")


if __name__ == "__main__":
    main()

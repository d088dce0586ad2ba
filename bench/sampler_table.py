"""What the sampler's tables (``ChannelProblem.tabulated``: the analytic image's, and for the
full model since 2026-12-07 the multiple-scattering term's) do to the cost of one posterior
evaluation and of a chain, against the images computed, in one run.

A capture of the canonical bulb (``--size``, default the canonical 200 x 150), Lowfat Milk 16
ml in 23 l, made with ``fitmedia synth --model hybrid`` (a bench capture of bench/fit_full.py
is reused with ``--capture``); channel G's problem built as ``fitmedia fit`` builds it.
Single scattering at its MAP (``search_map``, as the fit finds it), with ``--full`` also the
full-transport model at the truth (its term traced once there, the fit's paths and bin), the
quadrature frozen there and the Laplace covariance taken there.  Measured, each with and
without the table:

1. one log-posterior evaluation (mean over ``--evals`` points drawn from the Laplace
   approximation); and the largest difference of the log posterior;
2. an emcee chain of ``--steps`` steps (16 walkers, the fit's moves, the same seed), and the
   largest difference between the two chains' samples (identical chains: the accept
   decisions did not change); and the share of its renders the table served.

Usage:  python bench/sampler_table.py [--size W H] [--capture DIR] [--full] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from fit_full import scaled_spec  # noqa: E402

from fitmedia.inference import fit as F  # noqa: E402
from fitmedia.inference.optimize import laplace_covariance  # noqa: E402
from fitmedia.inference.params import ChannelParams  # noqa: E402
from fitmedia.inference.result import FitOptions  # noqa: E402
from fitmedia.inference.sample import run_chain  # noqa: E402
from fitmedia.spec import load_spec  # noqa: E402


def capture(a) -> Path:
    if a.capture:
        return Path(a.capture) / "capture.yaml"
    cap = a.out / "capture"
    if not (cap / "capture.yaml").exists():
        geo = scaled_spec(a.out, tuple(a.size))
        subprocess.run([sys.executable, "-m", "fitmedia.cli", "synth", str(geo), "--medium",
                        "Lowfat Milk", "--ml", "16", "--model", "hybrid", "--spp", "256",
                        "--seed", "1", "--out", str(cap)], cwd=ROOT, check=True)
    return cap / "capture.yaml"


def per_eval(problem, x, cov, pts) -> tuple[float, float, float]:
    """(ms without, ms with the table, largest log-posterior difference) over ``pts``."""
    def timed():
        problem.log_posterior(x)
        t = time.perf_counter()
        out = [problem.log_posterior(p) for p in pts]
        return (time.perf_counter() - t) / len(pts) * 1e3, np.array(out)

    t0, exact = timed()
    with problem.tabulated(x, cov) as use:
        if use.logl_error is None:
            raise SystemExit("the table was refused")
        if use.term_logl_error is not None:
            print(f"  the term's table: check's largest log-likelihood difference "
                  f"{use.term_logl_error:.1e} (the image table's {use.logl_error:.1e})")
        t1, tab = timed()
    return t0, t1, float(np.max(np.abs(tab - exact)))


def chain(problem, x, cov, space, steps: int, table: bool):
    def run():
        t = time.perf_counter()
        c = run_chain(problem.log_posterior, x, cov, space.lower, space.upper,
                      rng=np.random.default_rng(5), n_tau=1e6, max_steps=steps,
                      progress=False, redraw=F.albedo_redraw(space, x, cov))
        return time.perf_counter() - t, c.chain

    if not table:
        return run() + (None, None)
    with problem.tabulated(x, cov) as use:
        return run() + (use.share, use.term_share)


def compare(label: str, problem, space, x, steps: int, n_evals: int) -> None:
    """Both measurements at ``x`` (quadrature frozen there, Laplace covariance there)."""
    problem.adapt(x)
    cov = laplace_covariance(problem.log_posterior, x, space.lower, space.upper)
    pts = np.random.default_rng(3).multivariate_normal(x, cov, size=n_evals)
    pts = np.clip(pts, space.lower + 1e-9, space.upper - 1e-9)
    t0, t1, d = per_eval(problem, x, cov, pts)
    print(f"{label}, one evaluation: {t0:.2f} ms computed, {t1:.2f} ms from the table, "
          f"ratio {t1 / t0:.3f}; largest log-posterior difference {d:.1e}")
    (c0, ch0, _, _), (c1, ch1, share, term) = (chain(problem, x, cov, space, steps, t)
                                               for t in (False, True))
    served = "" if term is None else f", the term's table {term:.0%}"
    print(f"{label}, a chain of {steps} steps x 16 walkers: {c0:.1f} s computed, {c1:.1f} s "
          f"with the tables (the image table served {share:.0%} of the renders{served}), "
          f"ratio {c1 / c0:.3f}; largest sample difference {np.max(np.abs(ch0 - ch1)):.1e}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, nargs=2, default=(200, 150), metavar=("W", "H"))
    ap.add_argument("--capture", help="a capture directory to reuse (capture.yaml, truth.json)")
    ap.add_argument("--evals", type=int, default=100)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--full", action="store_true")
    ap.add_argument("--out", type=Path, default=Path("out/bench_sampler_table"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    path = capture(a)
    truth = json.loads((path.parent / "truth.json").read_text())["undiluted"]
    spec = load_spec(path)
    prep = F.prepare(spec)
    opts = FitOptions(model="single", progress=False)
    args = F.channel_args(prep, "G", opts, None)
    setup = F.channel_problem(*args[:8], args[11], args[12])
    problem, space = setup.problem, setup.space
    kt, ks, g = (truth[k]["G"] for k in ("kappa_t", "kappa_s", "g"))
    truth_x = space.to_vector(ChannelParams(kt, ks / kt, g, prep.brightness["G"]
                                            if setup.free else None))
    w, h = spec.camera.width, spec.camera.height
    print(f"{w} x {h} px, channel G, {len(problem.obs)} image(s)")
    res, _ = F.search_map(setup, opts, np.random.default_rng(0))
    compare("single (at its MAP)", problem, space, res.x, a.steps, a.evals)
    if a.full:
        from fitmedia.inference.full import use_full_transport

        use_full_transport(problem, spec, "G", seed=1)
        t = time.perf_counter()
        problem.refresh_models(truth_x)
        print(f"full: the term traced once at the truth in {time.perf_counter() - t:.0f} s")
        compare("full (at the truth)", problem, space, truth_x, a.steps, a.evals)


if __name__ == "__main__":
    main()

"""Is the sampler's posterior as wide as the log posterior says?  Three independent estimates of
one channel's posterior standard deviations, in the sampler's coordinates, against the
Laplace approximation at the MAP:

* importance sampling from a Student-t (10 degrees of freedom) on the Laplace covariance;
* a long random-walk Metropolis chain (proposal 2.38^2 / d x the Laplace covariance);
* emcee with a given move mix (DE only, as fitmedia runs it; DE + snooker, as until
  2026-11-22; stretch), 16 walkers from the Laplace ball.

  python docs/studies/sampler_width_study.py CAPTURE.yaml R [--rwm-steps 30000]

(docs/validation.md, "The sampler's width", used the captures of a `fitmedia validate` run.)
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.stats import multivariate_t

import fitmedia.inference.fit as fit_module
from fitmedia.inference.fit import FitOptions, channel_args, fit_channel, prepare
from fitmedia.inference.sample import initial_ball
from fitmedia.spec import load_spec


def channel_posterior(spec_path: str, channel: str):
    """The channel's log posterior (quadrature nodes as the sampler has them), MAP and Laplace
    covariance, through ``fit_channel`` with the sampler off."""
    problems = []
    build = fit_module.ChannelProblem

    def keep(*args, **kw):
        problems.append(build(*args, **kw))
        return problems[-1]

    fit_module.ChannelProblem = keep
    try:
        prep = prepare(load_spec(spec_path))
        r = fit_channel(*channel_args(prep, channel, FitOptions(mcmc=False, progress=False),
                                      None))
    finally:
        fit_module.ChannelProblem = build
    return problems[-1].log_posterior, r["x_map"], r["laplace_cov"], r["space"]


def main(argv=None) -> None:
    import emcee

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("spec")
    ap.add_argument("channel")
    ap.add_argument("--rwm-steps", type=int, default=30000)
    ap.add_argument("--emcee-steps", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    f, x0, cov, space = channel_posterior(a.spec, a.channel)
    lap = np.sqrt(np.diag(cov))
    d = len(x0)
    rng = np.random.default_rng(a.seed)
    print(f"parameters {space.names}; Laplace sd {np.round(lap, 4)}; ratios below are sd / Laplace")

    q = multivariate_t(x0, 1.3**2 * cov, df=10, seed=rng)
    xs = q.rvs(3000)
    lw = np.array([f(x) for x in xs]) - q.logpdf(xs)
    w = np.exp(lw - lw.max())
    w /= w.sum()
    m = w @ xs
    print(f"importance sampling: {np.round(np.sqrt(w @ (xs - m) ** 2) / lap, 3)} "
          f"(ESS {1 / np.sum(w**2):.0f} of 3000)")

    step = np.linalg.cholesky(cov) * 2.38 / np.sqrt(d)
    x, fx, chain, acc = x0.copy(), f(x0), [], 0
    for _ in range(a.rwm_steps):
        y = x + step @ rng.standard_normal(d)
        fy = f(y)
        if np.log(rng.random()) < fy - fx:
            x, fx, acc = y, fy, acc + 1
        chain.append(x.copy())
    chain = np.array(chain)[a.rwm_steps // 15:]
    print(f"random-walk Metropolis ({a.rwm_steps} steps, acceptance {acc / a.rwm_steps:.2f}): "
          f"{np.round(chain.std(0) / lap, 3)}")

    mixes = {"DE only (fitmedia)": emcee.moves.DEMove(),
             "DE 0.8 + snooker 0.2": [(emcee.moves.DEMove(), 0.8),
                                      (emcee.moves.DESnookerMove(), 0.2)],
             "stretch": emcee.moves.StretchMove()}
    for name, moves in mixes.items():
        s = emcee.EnsembleSampler(16, d, f, moves=moves)
        s._random = np.random.RandomState(a.seed)
        s.run_mcmc(initial_ball(x0, cov, space.lower, space.upper, 16, rng), a.emcee_steps,
                   progress=False)
        c = s.get_chain(discard=100, flat=True)
        print(f"emcee, {name}: {np.round(c.std(0) / lap, 3)} "
              f"(tau {np.round(s.get_autocorr_time(tol=0), 1)})")


if __name__ == "__main__":
    main()

"""The sampler on posteriors whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from fitmedia.inference.optimize import find_map
from fitmedia.inference.sample import run_chain

MEAN = np.array([1.0, -2.0, 0.5])
COV = np.array([[1.0, 0.6, 0.0], [0.6, 2.0, -0.3], [0.0, -0.3, 0.5]])
PREC = np.linalg.inv(COV)
LO, HI = np.full(3, -30.0), np.full(3, 30.0)


def log_gauss(x):
    d = np.asarray(x) - MEAN
    return -0.5 * d @ PREC @ d


def test_sampler_recovers_a_known_gaussian(rng):
    """Analytic posterior: a correlated 3-D normal.  Mean within 5 Monte Carlo standard errors,
    standard deviations within 10 %, marginal KS test, acceptance fraction sensible; the chain
    runs to 50 autocorrelation times and says it converged."""
    res = run_chain(log_gauss, MEAN + 0.5, None, LO, HI, rng=rng, progress=False, n_tau=50,
                    max_steps=20000)
    assert res.converged, res.reason
    assert res.n_steps >= 50 * np.max(res.tau)
    n_eff = len(res.samples) * res.thin / np.max(res.tau)
    se = np.sqrt(np.diag(COV) / n_eff)
    assert np.all(np.abs(res.samples.mean(0) - MEAN) < 5 * se)
    np.testing.assert_allclose(res.samples.std(0), np.sqrt(np.diag(COV)), rtol=0.1)
    np.testing.assert_allclose(np.corrcoef(res.samples.T)[0, 1], 0.6 / np.sqrt(2), atol=0.08)
    ks = stats.kstest(res.samples[::4, 2], "norm", args=(MEAN[2], np.sqrt(COV[2, 2])))
    assert ks.pvalue > 1e-3
    assert 0.1 < res.acceptance_fraction < 0.9


def test_sampler_negative_control_reports_not_converged(rng):
    """Negative control: a step cap far below 50 tau must be reported as not converged."""
    res = run_chain(log_gauss, MEAN, None, LO, HI, rng=rng, progress=False, max_steps=150,
                    check_every=50)
    assert not res.converged
    assert "step cap" in res.reason
    assert res.n_steps == 150


def test_map_finds_the_mode_and_laplace_covariance():
    """Analytic: the MAP of a normal is its mean and the Laplace covariance is its covariance."""
    res = find_map(log_gauss, np.zeros(3), LO, HI, global_evals=200, seed=1)
    np.testing.assert_allclose(res.x, MEAN, atol=1e-4)
    np.testing.assert_allclose(res.cov, COV, rtol=1e-3, atol=1e-4)


def test_sampler_is_reproducible_with_a_seed():
    a = run_chain(log_gauss, MEAN, None, LO, HI, rng=np.random.default_rng(3), progress=False,
                  max_steps=200)
    b = run_chain(log_gauss, MEAN, None, LO, HI, rng=np.random.default_rng(3), progress=False,
                  max_steps=200)
    np.testing.assert_array_equal(a.samples, b.samples)


def test_resume_continues_exactly(tmp_path):
    """Checkpoint: a chain stopped at 300 steps and resumed to 600 is identical, step for step,
    to one run to 600 without a stop (the sampler's random state is in the checkpoint)."""
    kw = dict(progress=False, n_tau=1e6)  # never "converged": run to the cap
    whole = run_chain(log_gauss, MEAN, None, LO, HI, rng=np.random.default_rng(5), max_steps=600,
                      checkpoint=tmp_path / "a.npz", **kw)
    run_chain(log_gauss, MEAN, None, LO, HI, rng=np.random.default_rng(5), max_steps=300,
              checkpoint=tmp_path / "b.npz", **kw)
    resumed = run_chain(log_gauss, MEAN, None, LO, HI, rng=np.random.default_rng(99),
                        max_steps=600, checkpoint=tmp_path / "b.npz", resume=True, **kw)
    assert resumed.n_steps == 600
    np.testing.assert_array_equal(np.load(tmp_path / "b.npz")["chain"],
                                  np.load(tmp_path / "a.npz")["chain"])
    np.testing.assert_array_equal(resumed.samples, whole.samples)


@pytest.mark.parametrize("u", [np.array([0.3, 4.0, 0.8]), np.array([-3.0, 12.0, 1.9])])
def test_optimizer_objective_is_the_sampler_log_probability(u, tmp_path, seed):
    """One function: the value the optimizer maximises is the log-posterior the sampler uses."""
    from fitmedia.inference.fit import prepare
    from fitmedia.inference.likelihood import ChannelProblem, Observation
    from fitmedia.inference.params import ParameterSpace
    from fitmedia.forward.single import SingleScattering
    from fitmedia.medium import medium_by_name
    from fitmedia.spec import load_spec
    from fitmedia.synth import synthesize
    from conftest import make_spec

    spec_path = synthesize(make_spec(width=40, height=30), tmp_path, medium_by_name("Espresso"),
                           [8], seed=seed)
    spec = load_spec(spec_path)
    prep = prepare(spec)
    obs = [Observation(SingleScattering(spec, 0, channels=("G",)), prep.images[0].data[..., 1],
                       prep.images[0].valid[..., 1], spec.images[0].concentration)]
    problem = ChannelProblem(obs, ParameterSpace(), 1.0, prep.noise["G"])
    seen = []
    find_map(lambda x: seen.append((x.copy(), problem.log_posterior(x))) or seen[-1][1], u,
             problem.space.lower, problem.space.upper, global_evals=0, local_evals=5)
    x, v = seen[0]
    assert v == problem.log_posterior(x)
    assert np.isfinite(v)

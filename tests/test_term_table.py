"""The sampler's table of the multiple-scattering term (``forward/ms_table.py: TermTable``,
``FullTransport.tabulate_term``, ``ChannelProblem.tabulated``).

Correctness is by comparison with the term computed from the whole local model
(``FullTransport.ms_part``, itself checked against numpy's covariances in
tests/test_mc_excess.py), on local models of known structure (random per-order batches,
no tracing): the image must be that one to rounding anywhere (the table keeps it exact); the
excess variance is a polynomial of degree 2 (K - 1) in the albedo for K orders, so with
fewer orders than half the table's points it must be reproduced to rounding between the
points too (which catches a wrong weight, step or factor), and with many orders over the
whole albedo range to the interpolation's accuracy.  Renders the table must not serve (an
albedo outside its interval, another local model, a batch left out) must be the computed
ones bit for bit, and the problem-level check must keep the log posterior within its stated
tolerance and refuse tables that cannot meet it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import make_spec

from fitmedia.forward import ms_table
from fitmedia.forward.multiple import FullTransport
from fitmedia.inference import likelihood
from fitmedia.inference.likelihood import ChannelProblem, Observation
from fitmedia.inference.params import ChannelParams, ParameterSpace

KT, G = 0.02, 0.8  # the local model's refresh point (1/mm, anisotropy)


def _pair(rng, orders: int, bin: int = 2, batches: int = 8):
    """Two models with the same synthetic local model: (to be tabulated, computed)."""
    spec = make_spec(width=8 * bin, height=6 * bin)
    pair = [FullTransport(spec, None, channels=("G",), bin=bin, n_paths=16, batches=batches)
            for _ in range(2)]
    npix = pair[0].ms.low_shape[0] * pair[0].ms.low_shape[1]
    base = rng.gamma(2.0, 1.0, (batches, orders, npix)) * 0.9 ** np.arange(orders)[:, None]
    parts = {"batches": base, "d_kt": 0.5 * base + rng.normal(0.0, 0.3, base.shape),
             "d_g": -0.2 * base + rng.normal(0.0, 0.3, base.shape)}
    for ft in pair:
        ft._local = [{"kt": KT, "eta": math.atanh(G), **{k: v.copy() for k, v in parts.items()}}]
        ft._var0 = ft.ms_part([KT * 0.1], [KT * 0.9], [G], [1.0], excess=True,
                              variance=False)[2]
    return pair


def _args(albedo, dk=0.0, dg=0.0, brightness=2.0):
    kt = KT * math.exp(dk)
    return ([kt * (1 - albedo)], [kt * albedo], [math.tanh(math.atanh(G) + dg)], [brightness])


def _close(got, want, rtol):
    for a, b in zip(got, want):
        scale = np.max(np.abs(b))
        assert np.max(np.abs(a - b)) <= rtol * scale, np.max(np.abs(a - b)) / scale


@pytest.mark.parametrize("bin", [1, 2])
def test_table_gives_the_computed_term_where_the_polynomial_is_exact(rng, bin):
    """6 orders: the excess is of degree 10 < 16 points in the albedo, so the table must give
    ``render_with_variance`` of the computed model to rounding at any albedo in its interval
    and any step in log kappa_t and atanh g (the image is exact by construction)."""
    tab, ref = _pair(rng, orders=6, bin=bin)
    tab.tabulate_term((0.2, 1.0))
    for albedo, dk, dg in ((0.2, 0.0, 0.0), (1.0, 0.3, -0.2), (0.537, -0.25, 0.1),
                           (0.93, 0.05, 0.4), (0.61, 0.0, -0.3)):
        _close(tab.render_with_variance(*_args(albedo, dk, dg)),
               ref.render_with_variance(*_args(albedo, dk, dg)), 1e-10)
    assert tab._term_table.used == 5 and tab._term_table.outside == 0


def test_table_interpolates_many_orders_over_every_albedo(rng):
    """18 orders (the bench capture's; degree 34 in the albedo) over the whole of [0, 1]: the
    16 points no longer make the excess exact, but between them it stays within 1e-3 of its
    largest value (measured with seed 0: 8e-5 for 18 orders, 2e-4 for 24, 1e-3 for 40; the
    bound leaves room for other seeds; on the bench's capture 7e-5 log-likelihood units,
    module docstring), which the problem's check then judges in likelihood units; the image
    stays exact."""
    tab, ref = _pair(rng, orders=18)
    tab.tabulate_term((0.0, 1.0))
    for albedo in np.linspace(0.013, 0.997, 17):
        got, want = (m.render_with_variance(*_args(albedo, 0.1, -0.1)) for m in (tab, ref))
        _close(got[:1], want[:1], 1e-12)
        _close(got[1:], want[1:], 1e-3)


def test_what_the_table_does_not_serve_is_computed(rng):
    """An albedo outside the interval, a batch left out (the jackknife) and another local
    model (a refresh, or one put back by ``models_kept``) give the computed term bit for bit;
    ``rebin`` and ``untabulate_term`` drop the table; a bad interval is refused."""
    tab, ref = _pair(rng, orders=6)
    tab.tabulate_term((0.5, 0.9))
    for args in (_args(0.95), _args(0.3, 0.1)):
        for a, b in zip(tab.render_with_variance(*args), ref.render_with_variance(*args)):
            assert np.array_equal(a, b)
    assert tab._term_table.outside == 2 and tab._term_table.used == 0
    tab.leave_out = ref.leave_out = 3
    for a, b in zip(tab.render_with_variance(*_args(0.7)), ref.render_with_variance(*_args(0.7))):
        assert np.array_equal(a, b)
    tab.leave_out = ref.leave_out = None
    tab._local = [dict(tab._local[0])]  # another local model (the same numbers)
    for a, b in zip(tab.render_with_variance(*_args(0.7)), ref.render_with_variance(*_args(0.7))):
        assert np.array_equal(a, b)
    assert tab._term_table.used == 0
    tab.untabulate_term()
    assert tab._term_table is None
    tab.tabulate_term((0.5, 0.9))
    tab.rebin(1)
    assert tab._term_table is None
    with pytest.raises(ValueError):
        ref.tabulate_term((0.9, 0.9))


def _problem(rng, orders: int, concentrations=(1.0,), water_kappa_a: float = 0.0):
    """A problem of one or more images (a dilution series: each its own model and local
    model, at ``concentrations`` of a liquid whose undiluted extinction is ``KT``)."""
    space = ParameterSpace()
    truth = space.to_vector(ChannelParams(KT, 0.9, G))
    gain, read = 1e-4, 1e-6
    obs = []
    for c in concentrations:
        tab, _ = _pair(rng, orders=orders)
        kt = c * KT + water_kappa_a
        clean = tab.render([kt - c * KT * 0.9], [c * KT * 0.9], [G], [1.0])[..., 0]
        data = clean + rng.normal(size=clean.shape) * np.sqrt(gain * clean + read)
        obs.append(Observation(tab, data, tab.support, c))
    problem = ChannelProblem(obs, space, 1.0, (gain, read), water_kappa_a=water_kappa_a)
    problem.adapt(truth)
    return problem, truth


@pytest.mark.parametrize("concentrations, water", [((1.0,), 0.0), ((1.0, 0.5), 0.002)])
def test_problem_term_tables_keep_the_log_posterior(rng, concentrations, water):
    """Within ``tabulated`` the log posterior (both tables) is the computed one to the stated
    tolerance at points across the box, the reported errors add to less than it, the term's
    tables served them, and afterwards no table is left.  Also for two images of a dilution
    series in water that absorbs (each image's albedo range is its own: c kappa_s over
    c kappa_t + the water's kappa_a)."""
    problem, x = _problem(rng, orders=12, concentrations=concentrations,
                          water_kappa_a=water)
    cov = np.diag([0.01, 0.02, 0.01]) ** 2  # narrow in the albedo: each image its own range
    pts = [x + rng.uniform(-8, 8, 3) * np.sqrt(np.diag(cov)) for _ in range(20)]
    exact = [problem.log_posterior(p) for p in pts]
    with problem.tabulated(x, cov) as use:
        assert use.term_logl_error is not None
        assert (use.logl_error or 0.0) + use.term_logl_error < likelihood.TABLE_LOGL_TOL
        tables = [o.model._term_table for o in problem.obs]
        assert all(t is not None for t in tables) and len(use.term_tables) == len(tables)
        n0 = [t.used for t in tables]
        got = [problem.log_posterior(p) for p in pts]
        assert [t.used for t in tables] == [n + len(pts) for n in n0]
    assert np.max(np.abs(np.subtract(got, exact))) < likelihood.TABLE_LOGL_TOL
    assert all(o.model._term_table is None for o in problem.obs)


def test_problem_refuses_term_tables_that_miss_the_tolerance(rng, monkeypatch):
    """Two points in the albedo for 40 orders over a wide box cannot pass the check: no term
    table is kept, ``term_logl_error`` is None, and the log posterior is the computed one bit
    for bit (the analytic image's table is kept out by unfrozen quadrature); without a
    covariance nothing is tabulated."""
    problem, x = _problem(rng, orders=40)
    problem.obs[0].model.single.unfreeze_nodes()
    cov = np.diag([0.01, 2.0, 0.01]) ** 2
    pts = [x + rng.uniform(-4, 4, 3) * np.sqrt(np.diag(cov)) for _ in range(5)]
    exact = [problem.log_posterior(p) for p in pts]
    monkeypatch.setattr(ms_table, "TERM_TABLE_POINTS", 2)
    with problem.tabulated(x, cov) as use:
        assert use.term_logl_error is None and use.term_share is None
        assert use.logl_error is None and problem.obs[0].model._term_table is None
        assert [problem.log_posterior(p) for p in pts] == exact
    monkeypatch.undo()
    with problem.tabulated(x, None) as use:
        assert use.term_logl_error is None and problem.obs[0].model._term_table is None


def test_a_spots_term_is_not_tabulated(rng):
    """A spot's term (camera paths alone) has no excess variance to tabulate: ``tabulate_term``
    refuses it, and ``tabulated`` reports no term table (None, not an error of 0 from a check
    that compared nothing with nothing)."""
    spot = {"type": "spot", "position": [40, 10, 30], "direction": [0, 0, 1], "cutoff_deg": 20}
    spec = make_spec(width=16, height=12, light=spot)
    ft = FullTransport(spec, None, channels=("G",), bin=2, n_paths=16, batches=8)
    npix = ft.ms.low_shape[0] * ft.ms.low_shape[1]
    base = rng.gamma(2.0, 1.0, (8, 4, npix))
    ft._local = [{"kt": KT, "eta": math.atanh(G), "batches": base, "d_kt": 0.5 * base,
                  "d_g": -0.2 * base}]
    assert ft.ms.photons is None and not ft.can_tabulate_term()
    with pytest.raises(ValueError):
        ft.tabulate_term((0.5, 1.0))
    space = ParameterSpace()
    x = space.to_vector(ChannelParams(KT, 0.9, G))
    clean = ft.render(*_args(0.9, brightness=1.0))[..., 0]
    problem = ChannelProblem([Observation(ft, clean + 1e-3, ft.support, 1.0)], space, 1.0,
                             (1e-4, 1e-6))
    problem.adapt(x)
    with problem.tabulated(x, np.diag([0.01, 0.02, 0.01]) ** 2) as use:
        assert use.term_logl_error is None and use.term_tables == []

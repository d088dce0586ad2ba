"""The sampler's table of the analytic image (``SingleScattering.tabulate``,
``ChannelProblem.tabulated``).

Correctness is by comparison with the computed image, evaluated independently of the table
(the same model with no table): at the table's own grid points the interpolation must
reproduce it to rounding (which catches a mix-up of the grid's axes or rows), between
them to the interpolation's accuracy, and outside the box the render must be the computed
one, bit for bit.  The problem-level check must keep the log posterior within its stated
tolerance and refuse tables that cannot meet it.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_spec

from fitmedia.forward.single import SingleScattering
from fitmedia.inference import likelihood
from fitmedia.inference.likelihood import ChannelProblem, Observation
from fitmedia.inference.params import ChannelParams, ParameterSpace

KT, G = 0.02, 0.8  # the extinction (1/mm) and anisotropy the quadrature is frozen at
BOX = ((np.log(KT) - 0.1, np.log(KT) + 0.1), (np.arctanh(G) - 0.2, np.arctanh(G) + 0.2))


def _models(light=None):
    spec = make_spec(width=40, height=30, light=light)
    pair = [SingleScattering(spec, None, channels=("G",)) for _ in range(2)]
    for m in pair:
        m.freeze_nodes(KT, G)
    pair[0].tabulate(*BOX)
    return pair  # (tabulated, computed)


def _args(log_kt, atanh_g, albedo=0.9, brightness=2.0):
    kt = np.exp(log_kt)
    return (kt * (1 - albedo), kt * albedo, np.tanh(atanh_g), brightness)


@pytest.mark.parametrize("light", [None, {"type": "spot", "position": [40, 10, 30],
                                          "direction": [0, 0, 1], "cutoff_deg": 20}])
def test_table_reproduces_the_computed_image(light):
    """At every grid point (Chebyshev points of the box) to rounding, between them to 1e-6
    of the image's largest value (measured 2.5e-7 at 100 x 75 px over half this box), for
    a bulb (scattered and direct parts) and a spot (no direct part)."""
    tab, ref = _models(light)
    n = len(tab._table.x)
    mid = [0.5 * (a + b) for a, b in BOX]
    half = [0.5 * (b - a) for a, b in BOX]
    for i in range(n):
        for k in range(n):
            args = _args(mid[0] + half[0] * tab._table.x[i], mid[1] + half[1] * tab._table.x[k])
            want = ref.render(*args)
            assert np.max(np.abs(tab.render(*args) - want)) <= 1e-12 * np.max(np.abs(want))
    rng = np.random.default_rng(7)
    for _ in range(10):
        args = _args(*(m + h * rng.uniform(-1, 1) for m, h in zip(mid, half)),
                     albedo=rng.uniform(0.2, 1.0))
        want = ref.render(*args)
        assert np.max(np.abs(tab.render(*args) - want)) <= 1e-6 * np.max(np.abs(want))


def test_outside_the_box_the_image_is_computed():
    """Beyond the box in either coordinate the table is not used: the same image bit for bit;
    freezing the quadrature again drops the table."""
    tab, ref = _models()
    for args in (_args(BOX[0][1] + 0.01, np.arctanh(G)), _args(np.log(KT), BOX[1][0] - 0.01)):
        assert np.array_equal(tab.render(*args), ref.render(*args))
    tab.freeze_nodes(KT, G)
    assert tab._table is None
    with pytest.raises(ValueError):
        tab.tabulate(BOX[0], (1.0, 1.0))  # an empty box


def _problem(rng):
    spec = make_spec(width=40, height=30)
    model = SingleScattering(spec, None, channels=("G",))
    space = ParameterSpace()
    truth = space.to_vector(ChannelParams(KT, 0.9, G))
    ka, ks, g, b = (KT * 0.1, KT * 0.9, G, 1.0)
    clean = model.render(ka, ks, g, b)[..., 0]
    gain, read = 1e-4, 1e-6
    data = clean + rng.normal(size=clean.shape) * np.sqrt(gain * clean + read)
    problem = ChannelProblem([Observation(model, data, model.support, 1.0)], space, b,
                             (gain, read))
    problem.adapt(truth)
    return problem, truth


def test_problem_tables_keep_the_log_posterior(rng):
    """Within ``tabulated`` the log posterior is the computed one to its tolerance (0.01) at
    points up to the box's edge, the reported error is below it, and afterwards no table is
    left."""
    problem, x = _problem(rng)
    cov = np.diag([0.01, 0.04, 0.01]) ** 2
    pts = [x + rng.uniform(-8, 8, 3) * np.sqrt(np.diag(cov)) for _ in range(20)]
    exact = [problem.log_posterior(p) for p in pts]
    with problem.tabulated(x, cov) as use:
        assert use.logl_error is not None and use.logl_error < likelihood.TABLE_LOGL_TOL
        assert problem.obs[0].model._table is not None
        n0 = use.tables[0].used + use.tables[0].outside
        got = [problem.log_posterior(p) for p in pts]
        inside = [abs(p[0] - x[0]) <= 16 * 0.01 and abs(p[2] - x[2]) <= 16 * 0.01 for p in pts]
        # every point is inside the first (16 sd) box, which passed here
        assert all(inside) and use.tables[0].used + use.tables[0].outside == n0 + len(pts)
        assert use.tables[0].outside == 0
    assert np.max(np.abs(np.subtract(got, exact))) < likelihood.TABLE_LOGL_TOL
    assert problem.obs[0].model._table is None


def test_problem_refuses_tables_that_miss_the_tolerance(rng, monkeypatch):
    """A check that no table can pass (a tolerance of 0), or no covariance, leaves the images
    computed: ``tabulated`` yields None and keeps no table."""
    problem, x = _problem(rng)
    cov = np.diag([0.01, 0.04, 0.01]) ** 2
    monkeypatch.setattr(likelihood, "TABLE_LOGL_TOL", 0.0)
    with problem.tabulated(x, cov) as use:
        assert use.logl_error is None and use.share is None
        assert problem.obs[0].model._table is None
    monkeypatch.undo()
    with problem.tabulated(x, None) as use:
        assert use.logl_error is None and problem.obs[0].model._table is None

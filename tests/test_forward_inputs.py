"""One input check for every forward model (fitmedia.forward.base.check_render_args)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_spec

from fitmedia.errors import InputError
from fitmedia.forward.single import SingleScattering

BAD = [((0.01, 0.02, 1.0, 1.0), "g"), ((0.01, 0.02, -1.2, 1.0), "g"),
       ((-1e-3, 0.02, 0.5, 1.0), "kappa_a"), ((0.01, -0.02, 0.5, 1.0), "kappa_s"),
       ((np.nan, 0.02, 0.5, 1.0), "kappa_a"), ((0.01, 0.02, 0.5, np.inf), "brightness"),
       ((0.01, [0.02, 0.03], 0.5, 1.0), "kappa_s")]


def _single():
    return SingleScattering(make_spec(width=16, height=12), channels=("R",))


def _mitsuba():
    from fitmedia.forward.mitsuba import MitsubaModel

    return MitsubaModel(make_spec(width=16, height=12), spp=1, channels=("R",))


@pytest.mark.parametrize("make", [_single, pytest.param(_mitsuba, marks=pytest.mark.mitsuba)],
                         ids=["single", "mitsuba"])
def test_both_models_refuse_the_same_bad_parameters(make):
    """g >= 1 (which the analytic model used to clip silently), negative or non-finite
    coefficients and a wrong number of values: InputError naming the argument, from either
    model; a valid call renders a finite image."""
    model = make()
    for args, field in BAD:
        with pytest.raises(InputError, match=field):
            model.render(*args)
    assert np.all(np.isfinite(model.render(0.0, 0.0, 0.0, 1.0)))

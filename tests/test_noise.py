"""The noise model from the camera to the likelihood: the read-variance floor, per-pixel
variances of brackets, darks and binning, and noise estimation per image."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile

from fitmedia.images import load_entry
from fitmedia.inference.likelihood import ChannelProblem, Observation
from fitmedia.inference.params import ChannelParams, ParameterSpace
from fitmedia.spec import ImageEntry


class FixedModel:
    """A forward model that renders one fixed image times the brightness (for tests of the
    likelihood alone)."""

    channels = ("G",)

    def __init__(self, image: np.ndarray):
        self.image = np.asarray(image, float)
        self.shape = self.image.shape
        self.support = np.ones(self.shape, bool)

    def render(self, kappa_a, kappa_s, g, brightness):
        return (self.image * np.asarray(brightness, float).reshape(-1)[0])[..., None]


def _u(space: ParameterSpace) -> np.ndarray:
    return space.to_vector(ChannelParams(1.0, 0.5, 0.5))


def test_zero_read_variance_is_floored():
    """An estimated read variance of exactly 0 with zero-valued pixels where the model is 0:
    the log-likelihood is finite with no warning (warnings are errors here), and each
    zero pixel's variance is the floor: the float spacing at the data's largest value,
    squared, over 12 (independent: computed here from numpy's spacing)."""
    image = np.zeros((6, 8))
    image[2:4, 3:5] = 1.0
    data = image.copy()
    data[2, 3] = 1.01
    obs = [Observation(FixedModel(image), data, np.ones_like(data, bool), 1.0)]
    space = ParameterSpace()
    problem = ChannelProblem(obs, space, 1.0, (1e-4, 0.0))
    u = _u(space)
    assert np.isfinite(problem.log_likelihood(u))
    floor = np.spacing(1.01) ** 2 / 12
    chi2, n = problem.chi2(u)
    assert n == 48 and chi2 == pytest.approx(0.01 ** 2 / (1e-4 + floor))
    assert problem.variance(0, np.zeros(1))[0] == pytest.approx(floor)


def test_quantisation_floor_of_integer_files(tmp_path):
    """A 16-bit file with read variance 0: the read map is the quantisation variance 1/12
    DN^2 in image units, doubled by a subtracted dark, over the exposure squared."""
    raw = np.full((4, 5, 3), 1000, np.uint16)
    tifffile.imwrite(tmp_path / "a.tif", raw, photometric="rgb")
    tifffile.imwrite(tmp_path / "d.tif", np.full((4, 5, 3), 100, np.uint16), photometric="rgb")
    entry = ImageEntry(paths=(tmp_path / "a.tif",), exposures=(0.5,),
                       darks=(tmp_path / "d.tif",), response="linear")
    img = load_entry(entry, expected_shape=(4, 5))
    gain, read = img.variance_maps(2.0, 0.0)
    np.testing.assert_allclose(read, 2 * (1 / 12) / 0.5 ** 2)
    np.testing.assert_allclose(gain, 2.0 / 0.5)

"""Shared fixtures.  Seeds can be overridden with FITMEDIA_TEST_SEED."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from fitmedia.spec import parse_spec

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def seed() -> int:
    return int(os.environ.get("FITMEDIA_TEST_SEED", "12345"))


@pytest.fixture
def rng(seed) -> np.random.Generator:
    return np.random.default_rng(seed)


def geometry_dict(width=80, height=60, light=None, thickness=6.0):
    """The canonical tank and camera at a reduced resolution (fx scaled with width)."""
    fx = 375.0 * width / 200.0
    return {
        "fitmedia_spec": 1, "name": "test",
        "tank": {"inner_size": [300, 250, 300], "front_wall": {"thickness": thickness, "ior": 1.5},
                 "walls": "black"},
        "medium": {"ior": 1.33},
        "camera": {"size": [width, height], "fx": fx, "fy": fx, "cx": width / 2, "cy": height / 2,
                   "position": [0, 0, 900], "look_at": [0, 0, 0], "up": [0, 1, 0]},
        "light": light or {"type": "bulb", "position": [40, 10, 30], "radius": 6},
    }


def make_spec(**kw):
    return parse_spec(geometry_dict(**kw), require_images=False)


def assert_only_the_sampler_doubted(res) -> None:
    """For a `fitmedia fit` subprocess whose chains stop at --max-steps on purpose (--n-tau 1e6):
    it exits 1 saying that the sampler did not converge, and for no other reason (until
    2026-12-03 such a fit warned and exited 0)."""
    assert res.returncode == 1, res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.startswith("fitmedia: doubtful result:")
             and "cannot be trusted" not in ln]
    assert lines and all("did not converge" in ln for ln in lines), res.stderr

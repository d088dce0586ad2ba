"""`fitmedia synth --model full`: a synthetic capture rendered with Mitsuba."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from conftest import geometry_dict


@pytest.mark.mitsuba
def test_synth_full_writes_a_capture_that_loads(tmp_path):
    """Second model: the full-transport capture has the same outputs as the analytic one, and
    its glow is brighter than single scattering alone (multiple scattering adds light)."""
    from fitmedia.cli import main
    from fitmedia.images import read_image
    from fitmedia.spec import load_spec

    geo = tmp_path / "geo.yaml"
    geo.write_text(yaml.safe_dump(geometry_dict(width=32, height=24)))
    for model in ("full", "single"):
        assert main(["synth", str(geo), "--medium", "Lowfat Milk", "--ml", "16", "--out",
                     str(tmp_path / model), "--model", model, "--spp", "64", "--seed", "1",
                     "--gain", "1e-12", "--read-var", "1e-16"]) == 0
    spec = load_spec(tmp_path / "full" / "capture.yaml")
    truth = json.loads((tmp_path / "full" / "truth.json").read_text())
    assert truth["model"] == "full"
    full, _ = read_image(spec.images[0].paths[0])
    single, _ = read_image(load_spec(tmp_path / "single" / "capture.yaml").images[0].paths[0])
    assert np.all(np.isfinite(full))
    direct = read_image(spec.clear_water.paths[0])[0] > 1e-3
    glow = ~direct & (single > 0)
    assert full[glow].sum() > 1.2 * single[glow].sum()

"""The command line: bad input gives one line naming the field or file and exit code 2,
never a traceback, and nothing half-written."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import yaml

from fitmedia.cli import main
from conftest import ROOT, geometry_dict


def run(args, capsys):
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A small synthetic capture (60 x 45) shared by the tests of this module."""
    d = tmp_path_factory.mktemp("cap")
    spec = d / "geom.yaml"
    spec.write_text(yaml.safe_dump(geometry_dict(width=60, height=45)))
    assert main(["synth", str(spec), "--medium", "Espresso", "--ml", "8", "--out", str(d / "c"),
                 "--seed", "3"]) == 0
    return d / "c"


def _one_line_error(code, err, *words):
    assert code == 2
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0], lines[0]


def _write_spec(capture, tmp_path, mutate):
    data = yaml.safe_load((capture / "capture.yaml").read_text())
    mutate(data)
    for entry in data.get("images", []) + [data["calibration"]["clear_water"]]:
        entry["path"] = str(capture / entry["path"])
    p = tmp_path / "spec.yaml"
    p.write_text(yaml.safe_dump(data))
    return p


@pytest.mark.parametrize("mutate, words", [
    (lambda d: d["camera"].update(sise=[1, 2]), ["camera", "sise"]),
    (lambda d: d["tank"].update(inner_size=[300, -250, 300]), ["tank.inner_size[1]"]),
    (lambda d: d["light"].update(radius=float("nan")), ["light.radius"]),
    (lambda d: d["images"][0].update(path="missing.tiff"), ["images[0].path", "not found"]),
])
def test_fit_rejects_bad_specs(capture, tmp_path, capsys, mutate, words):
    spec = _write_spec(capture, tmp_path, mutate)
    code, out, err = run(["fit", spec, "--out", tmp_path / "o", "--no-mcmc"], capsys)
    _one_line_error(code, err, *words)
    assert not (tmp_path / "o" / "results.json").exists()


def test_fit_rejects_broken_and_nan_images(capture, tmp_path, capsys):
    broken = tmp_path / "broken.tiff"
    broken.write_bytes((capture / "images" / "clear_water.tiff").read_bytes()[:500])
    spec = _write_spec(capture, tmp_path, lambda d: d["images"][0].update(path=str(broken)))
    code, _, err = run(["fit", spec, "--out", tmp_path / "o", "--no-mcmc"], capsys)
    _one_line_error(code, err, "broken.tiff")
    import tifffile
    img = tifffile.imread(capture / "images" / "medium_00_8ml.tiff")
    img[3, 4, 0] = np.nan
    nan = tmp_path / "nan.tiff"
    tifffile.imwrite(nan, img, photometric="rgb")
    spec = _write_spec(capture, tmp_path, lambda d: d["images"][0].update(path=str(nan)))
    code, _, err = run(["fit", spec, "--out", tmp_path / "o2", "--no-mcmc"], capsys)
    _one_line_error(code, err, "nan.tiff", "NaN")


def test_fit_rejects_a_saturated_photo(capture, tmp_path, capsys):
    """A photo saturated almost everywhere cannot be measured: one line, exit 2."""
    spec = _write_spec(capture, tmp_path, lambda d: d["images"][0].update(saturation=1e-12))
    code, _, err = run(["fit", spec, "--out", tmp_path / "o", "--no-mcmc"], capsys)
    _one_line_error(code, err, "saturated")


def test_fit_rejects_a_calibration_with_a_saturated_bulb(capture, tmp_path, capsys):
    import tifffile
    img = tifffile.imread(capture / "images" / "clear_water.tiff")
    sat = tmp_path / "water_sat.tiff"
    tifffile.imwrite(sat, np.minimum(img, 0.05).astype(np.float32), photometric="rgb")
    spec = _write_spec(capture, tmp_path, lambda d: d["calibration"]["clear_water"].update(
        path=str(sat), saturation=0.05))
    code, _, err = run(["fit", spec, "--out", tmp_path / "o", "--no-mcmc"], capsys)
    _one_line_error(code, err, "calibration.clear_water", "saturated")


@pytest.mark.parametrize("args, words", [
    (["--medium", "Lowfat Mlik", "--ml", "16"], ["--medium", "Lowfat Milk"]),
    (["--medium", "Espresso", "--ml", "-3"], ["--ml"]),
    (["--medium", "Espresso", "--ml", "8", "--tank-ml", "0"], ["--tank-ml"]),
    (["--kappa-a", "0.1", "--kappa-s", "1", "--ml", "8"], ["--kappa-a"]),
    (["--kappa-a", "0.1", "--kappa-s", "-1", "--g", "0.5", "--ml", "8"], ["kappa_s"]),
    # until 2026-12-07 a negative read variance wrote NaN pixels (a traceback) and a negative
    # gain a capture that fit refuses
    (["--medium", "Espresso", "--ml", "8", "--read-var=-1e-9"], ["--read-var", ">= 0"]),
    (["--medium", "Espresso", "--ml", "8", "--gain=-2e-5"], ["--gain", ">= 0"]),
])
def test_synth_rejects_bad_arguments(tmp_path, capsys, args, words):
    code, _, err = run(["synth", ROOT / "capture_specs" / "bulb.yaml", "--out", tmp_path / "o"]
                       + args, capsys)
    _one_line_error(code, err, *words)
    assert not (tmp_path / "o" / "capture.yaml").exists()


def test_report_of_a_missing_folder(tmp_path, capsys):
    code, _, err = run(["report", tmp_path / "nothing"], capsys)
    _one_line_error(code, err, "results.json")


def test_fit_map_only_writes_the_contract(capture, tmp_path, capsys):
    """results.json has the fields CAPTURE_SPEC.md requires; MAP only means no sampler fields.
    The model is fit's default, auto, which keeps single scattering for this capture (it
    declares a single-scattering render)."""
    code, out, _ = run(["fit", capture / "capture.yaml", "--out", tmp_path / "o", "--no-mcmc",
                        "--no-report"], capsys)
    assert code == 0 and "results.json" in out
    r = json.loads((tmp_path / "o" / "results.json").read_text())
    assert r["fitmedia_spec"] == 1 and r["model"] == "auto" and r["model_used"] == "single"
    assert r["units"] == {"length": "mm", "kappa": "1/mm"}
    assert r["channels"] == ["R", "G", "B"]
    for q in ("kappa_a", "kappa_s", "g", "kappa_t", "albedo"):
        assert set(r["parameters"][q]) == {"R", "G", "B"}
        assert set(r["parameters"][q]["G"]) == {"map"}
    assert "converged" not in r["diagnostics"]


def test_console_script_help_works_without_heavy_imports():
    """`fitmedia --help` runs as a program and importing the CLI loads neither Mitsuba nor
    matplotlib (no time is measured here: CI's load varies; tests/test_imports.py checks that
    building the parser imports no numpy)."""
    res = subprocess.run([sys.executable, "-m", "fitmedia.cli", "--help"], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0 and "synth" in res.stdout
    res = subprocess.run([sys.executable, "-X", "importtime", "-c", "import fitmedia.cli"],
                         capture_output=True, text=True, timeout=60)
    assert "mitsuba" not in res.stderr and "matplotlib" not in res.stderr

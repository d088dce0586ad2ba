"""Export of a fitted medium (fitmedia.export): Mitsuba 3 dict/XML and pbrt-v4 block carry
the results.json values (undiluted, 1/mm or 1/m), and Mitsuba loads them."""

from __future__ import annotations

import argparse
import json
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from fitmedia.errors import InputError
from fitmedia.cli import add_export_parser
from fitmedia.export import FILES, export_medium, medium_values

CH = ("R", "G", "B")
# Lowfat Milk-like values (1/mm, undiluted): kappa_t, albedo, g per channel
KT = {"R": 0.9126, "G": 1.0748, "B": 1.2500}
ALB = {"R": 0.99989, "G": 0.99978, "B": 0.99931}
G = {"R": 0.932, "G": 0.902, "B": 0.859}


def results(*, with_samples: bool = True) -> dict:
    def entry(v):
        e = {"map": v * 0.99}
        if with_samples:
            e.update(median=v, mean=v, std=0.01 * v, q05=0.98 * v, q16=0.99 * v,
                     q84=1.01 * v, q95=1.02 * v)
        return e

    params = {"kappa_t": {c: entry(KT[c]) for c in CH}, "albedo": {c: entry(ALB[c]) for c in CH},
              "g": {c: entry(G[c]) for c in CH},
              "kappa_a": {c: entry(KT[c] * (1 - ALB[c])) for c in CH},
              "kappa_s": {c: entry(KT[c] * ALB[c]) for c in CH}}
    return {"fitmedia_spec": 1, "model": "single", "units": {"length": "mm", "kappa": "1/mm"},
            "channels": list(CH), "parameters": params, "name": "lowfat milk"}


def _floats(text: str) -> list[float]:
    return [float(x) for x in re.split(r"[,\s]+", text.strip())]


def test_xml_values_match_the_results(tmp_path):
    paths = export_medium(results(), tmp_path)
    assert [p.name for p in paths] == ["medium_mitsuba.json", "medium_mitsuba.xml",
                                       "medium_pbrt.txt"]
    root = ET.parse(paths[1]).getroot()
    assert root.tag == "medium" and root.get("type") == "homogeneous"
    rgb = {e.get("name"): _floats(e.get("value")) for e in root.findall("rgb")}
    np.testing.assert_allclose(rgb["sigma_t"], [KT[c] for c in CH], rtol=1e-8)
    np.testing.assert_allclose(rgb["albedo"], [ALB[c] for c in CH], rtol=1e-8)
    assert float(root.find("float[@name='scale']").get("value")) == 1.0
    phase = root.find("phase")
    assert phase.get("type") == "hg"
    assert float(phase.find("float[@name='g']").get("value")) == pytest.approx(np.mean(list(G.values())))
    text = paths[1].read_text()
    assert "1/mm" in text and "undiluted" in text and "0.9320" in text  # per-channel g stated


def test_json_is_a_mitsuba_dict_with_notes(tmp_path):
    doc = json.loads(export_medium(results(), tmp_path)[0].read_text())
    m = doc["medium"]
    assert m["type"] == "homogeneous" and m["scale"] == 1.0
    assert m["sigma_t"] == {"type": "rgb", "value": pytest.approx([KT[c] for c in CH])}
    assert m["albedo"] == {"type": "rgb", "value": pytest.approx([ALB[c] for c in CH])}
    assert m["phase"] == {"type": "hg", "g": pytest.approx(np.mean(list(G.values())))}
    assert doc["g_per_channel"] == pytest.approx(G)
    assert doc["unit"] == "1/mm" and doc["statistic"] == "median" and doc["concentration"] == 1.0


def test_pbrt_block(tmp_path):
    text = export_medium(results(), tmp_path)[2].read_text()
    comments = [ln for ln in text.splitlines() if ln.startswith("#")]
    assert any("coefficients in 1/mm" in ln for ln in comments)
    assert any("undiluted" in ln and "scale = c" in ln for ln in comments)
    body = " ".join(ln for ln in text.splitlines() if not ln.startswith("#"))
    m = re.fullmatch(r'\s*MakeNamedMedium "(\S+)"\s+"string type" "homogeneous"\s+'
                     r'"rgb sigma_a" \[ ([^\]]+) \]\s+"rgb sigma_s" \[ ([^\]]+) \]\s+'
                     r'"float scale" 1\s+"float g" (\S+)\s*', body)
    assert m, body
    assert m.group(1) == "fitmedia_lowfat_milk"
    kt, alb = np.array([KT[c] for c in CH]), np.array([ALB[c] for c in CH])
    np.testing.assert_allclose(_floats(m.group(2)), kt * (1 - alb), rtol=1e-7)
    np.testing.assert_allclose(_floats(m.group(3)), kt * alb, rtol=1e-8)
    assert float(m.group(4)) == pytest.approx(np.mean(list(G.values())))


def test_scale_to_m_and_map_fallback(tmp_path):
    v = medium_values(results(with_samples=False), scale_to_m=True)
    assert v["statistic"] == "map" and v["unit"] == "1/m"
    np.testing.assert_allclose(v["sigma_t"], [1000 * 0.99 * KT[c] for c in CH])
    np.testing.assert_allclose(v["albedo"], [0.99 * ALB[c] for c in CH])
    text = export_medium(results(), tmp_path, scale_to_m=True)[2].read_text()
    assert "coefficients in 1/m\n" in text and "scene length unit m;" in text


@pytest.mark.parametrize("mutate, words", [
    (lambda r: r["parameters"]["kappa_t"].pop("B"), "parameters.kappa_t.B: missing"),
    (lambda r: r["parameters"].pop("g"), "parameters.g.R: missing"),
    (lambda r: r["parameters"]["g"]["G"].update(median=None), "parameters.g.G.median: got None"),
    (lambda r: r["parameters"]["albedo"]["R"].update(median=1.5), "albedo"),
    (lambda r: r.update(units={"kappa": "1/m"}), "units.kappa"),
    (lambda r: r.pop("parameters"), "parameters: missing"),
])
def test_bad_results_are_input_errors(mutate, words, tmp_path):
    r = results()
    mutate(r)
    with pytest.raises(InputError, match=re.escape(words)):
        export_medium(r, tmp_path)
    assert not any(tmp_path.iterdir())


def _cli(argv):
    p = argparse.ArgumentParser(prog="fitmedia")
    add_export_parser(p.add_subparsers(dest="command", required=True))
    a = p.parse_args([str(x) for x in argv])
    return a.func(a)


def test_cli_export_reads_dir_results_and_writes_beside_it(tmp_path, capsys):
    (tmp_path / "results.json").write_text(json.dumps(results()))
    assert _cli(["export", tmp_path, "--scale-to-m"]) == 0
    assert "medium_pbrt.txt" in capsys.readouterr().out
    doc = json.loads((tmp_path / "medium_mitsuba.json").read_text())
    assert doc["medium"]["sigma_t"]["value"] == pytest.approx([1000 * KT[c] for c in CH])
    with pytest.raises(InputError, match="results.json: file not found"):
        _cli(["export", tmp_path / "nothing"])
    (tmp_path / "results.json").write_text("{broken")
    with pytest.raises(InputError, match="not a readable JSON file"):
        _cli(["export", tmp_path])


@pytest.mark.mitsuba
def test_mitsuba_loads_the_dict_and_the_xml(tmp_path):
    """mi.load_dict takes the JSON's medium and mi.load_string the XML inside a scene; the
    loaded parameters are ours (a mono variant keeps the luminance of the RGB values)."""
    from fitmedia.mitsuba_env import import_mitsuba

    mi = import_mitsuba()
    json_path, xml_path, _ = export_medium(results(), tmp_path)
    medium = mi.load_dict(json.loads(json_path.read_text())["medium"])
    params = mi.traverse(medium)
    kt, alb = np.array([KT[c] for c in CH]), np.array([ALB[c] for c in CH])
    if "mono" in mi.variant():
        lum = np.array([0.212671, 0.715160, 0.072169])  # sRGB luminance, as Mitsuba converts
        kt, alb = np.array([kt @ lum]), np.array([alb @ lum])
    np.testing.assert_allclose(np.ravel(params["sigma_t.value.value"]), kt, rtol=1e-4)
    np.testing.assert_allclose(np.ravel(params["albedo.value.value"]), alb, rtol=1e-4)
    assert float(np.ravel(params["phase_function.g"])[0]) == pytest.approx(
        np.mean(list(G.values())), rel=1e-6)
    assert float(params["scale"]) == 1.0
    scene = mi.load_string(f'<scene version="3.0.0">{xml_path.read_text()}</scene>')
    assert scene is not None


def test_doubtful_fit_is_not_exported_silently(tmp_path, capsys):
    """A fit that said its values cannot be trusted (trust.ok false, exit 1 from fit) is not
    exported without --allow-doubtful (exit 1, nothing written, the reason printed); with it
    the files carry the reason and ``trusted: false`` and export exits 1 too.  A trusted fit
    exports as before (exit 0, ``trusted: true``, no DOUBTFUL line)."""
    reason = "the misfit guard fired in channel G: chi2/pixel 39"
    (tmp_path / "results.json").write_text(json.dumps(
        {**results(), "trust": {"ok": False, "model": "single", "reasons": [reason]}}))
    assert _cli(["export", tmp_path]) == 1
    err = capsys.readouterr().err
    assert reason in err and "export refused" in err and "--allow-doubtful" in err
    assert not any((tmp_path / f).exists() for f in FILES)

    assert _cli(["export", tmp_path, "--allow-doubtful"]) == 1
    assert "marked DOUBTFUL" in capsys.readouterr().out
    doc = json.loads((tmp_path / "medium_mitsuba.json").read_text())
    assert doc["trusted"] is False and reason in doc["comment"][0]
    for f in FILES[1:]:
        assert f"DOUBTFUL: the fit said these values cannot be trusted: {reason}" in \
            (tmp_path / f).read_text()
    ET.fromstring((tmp_path / FILES[1]).read_text())  # the comment keeps the XML well formed

    good = tmp_path / "good"
    good.mkdir()
    (good / "results.json").write_text(json.dumps(
        {**results(), "trust": {"ok": True, "model": "single", "reasons": []}}))
    assert _cli(["export", good]) == 0
    assert json.loads((good / "medium_mitsuba.json").read_text())["trusted"] is True
    assert "DOUBTFUL" not in (good / "medium_pbrt.txt").read_text()

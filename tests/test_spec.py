"""Capture spec v1: the contract's example is accepted; every kind of bad input is rejected
with one message that names the field (CAPTURE_SPEC.md)."""

from __future__ import annotations

import copy
import textwrap

import numpy as np
import pytest

from fitmedia.errors import SpecError
from fitmedia.spec import SpecLoader, load_spec, parse_spec

EXAMPLE = textwrap.dedent("""
    fitmedia_spec: 1
    name: lowfat-milk-16ml
    tank:
      inner_size: [300, 250, 300]     # [x width, y height, z depth], mm
      front_wall: {thickness: 6, ior: 1.5}
      walls: black                    # the other five walls absorb all light
    medium:
      ior: 1.33
    camera:
      size: [200, 150]                # [width, height] in pixels
      fx: 375
      fy: 375
      cx: 100
      cy: 75
      position: [0, 0, 900]
      look_at: [0, 0, 0]
      up: [0, 1, 0]
    light:
      type: bulb                      # isotropic sphere emitter immersed in the medium
      position: [40, 10, 30]
      radius: 6
    images:
      - path: images/milk.tiff        # linear, channels R, G, B
        exposure_s: 1.0
        concentration: 1.0            # optional, default 1
    calibration:
      clear_water: {path: images/water.tiff, exposure_s: 1.0}
    noise:                            # optional; variance = gain * value + read_var
      gain: 0.002
      read_var: 1.0e-6
    channels: [R, G, B]               # optional, default all three
""")


@pytest.fixture
def example(tmp_path):
    (tmp_path / "images").mkdir()
    for name in ("milk.tiff", "water.tiff"):
        (tmp_path / "images" / name).write_bytes(b"placeholder")
    path = tmp_path / "spec.yaml"
    path.write_text(EXAMPLE)
    return path


def test_contract_example_is_accepted(example):
    spec = load_spec(example)
    assert spec.name == "lowfat-milk-16ml"
    assert spec.tank.inner_size == (300, 250, 300)
    assert spec.camera.width == 200 and spec.camera.height == 150
    assert spec.light.type == "bulb" and spec.light.radius == 6
    assert spec.images[0].paths[0] == example.parent / "images" / "milk.tiff"
    assert spec.images[0].concentration == 1.0
    assert spec.noise == (0.002, 1e-6)
    assert spec.channels == ("R", "G", "B")
    f, r, u = spec.camera.frame()
    np.testing.assert_allclose(f, [0, 0, -1])
    np.testing.assert_allclose(r, [1, 0, 0])  # forward x up: image x points along +x
    np.testing.assert_allclose(u, [0, 1, 0])


def test_synthetic_field_is_read(example):
    """The optional ``synthetic.model`` (docs/spec.md): absent on the contract's example
    (None), read where given."""
    import yaml

    assert load_spec(example).synthetic_model is None
    data = yaml.safe_load(EXAMPLE)
    data["synthetic"] = {"model": "single"}
    assert parse_spec(data, source="s.yaml", require_images=False).synthetic_model == "single"


def _data():
    import yaml
    return yaml.safe_load(EXAMPLE)


def _err(data, require_images=False) -> str:
    with pytest.raises(SpecError) as exc:
        parse_spec(data, source="s.yaml", require_images=require_images)
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


@pytest.mark.parametrize("mutate, field, words", [
    (lambda d: d["camera"].update(sise=[1, 2]), "camera", "sise"),
    (lambda d: d["tank"].update(inner_size=[300, -250, 300]), "tank.inner_size[1]", "-250"),
    (lambda d: d["tank"]["front_wall"].update(thickness=-1), "tank.front_wall.thickness", "-1"),
    (lambda d: d["light"].update(radius=float("nan")), "light.radius", "finite"),
    (lambda d: d["camera"]["position"].__setitem__(2, float("inf")), "camera.position[2]", "finite"),
    (lambda d: d["tank"]["front_wall"].update(ior=0.9), "tank.front_wall.ior", "0.9"),
    (lambda d: d["tank"].update(walls="white"), "tank.walls", "white"),
    (lambda d: d["medium"].update(ior=0.5), "medium.ior", "0.5"),
    (lambda d: d["light"].update(radius=0), "light.radius", "0"),
    (lambda d: d["light"].update(type="laser"), "light.type", "laser"),
    (lambda d: d["light"].pop("radius"), "light", "radius"),
    (lambda d: d.update(synthetic={"model": "dual"}), "synthetic.model", "dual"),
    (lambda d: d.update(synthetic={"model": "single", "spp": 4}), "synthetic", "spp"),
    (lambda d: d["images"][0].update(exposure_s=0), "images[0].exposure_s", "0"),
    (lambda d: d["images"][0].update(concentration=-2), "images[0].concentration", "-2"),
    (lambda d: d.update(fitmedia_spec=2), "fitmedia_spec", "2"),
    (lambda d: d.update(channels=["R", "X"]), "channels[1]", "X"),
    (lambda d: d["noise"].update(gain=-1), "noise.gain", "-1"),
    (lambda d: d["camera"].update(size=[200]), "camera.size", "200"),
    (lambda d: d["camera"].update(fx="wide"), "camera.fx", "wide"),
    (lambda d: d["camera"].update(position=[0, 0, 100]), "camera.position", "in front"),
    (lambda d: d["camera"].update(up=[0, 0, 1]), "camera.up", "parallel"),
    (lambda d: d["light"].update(position=[148, 0, 0]), "light.position", "inside"),
    (lambda d: d["tank"].update(front_wal={}), "tank", "did you mean 'front_wall'"),
    (lambda d: d["images"][0].update(light={"position": [0, 0, 500]}), "images[0].light.position",
     "inside"),
])
def test_bad_fields_are_named(mutate, field, words):
    data = _data()
    mutate(data)
    msg = _err(data)
    assert msg.startswith("s.yaml: ")
    assert field in msg and words in msg, msg


def test_spot_light_fields():
    data = _data()
    data["light"] = {"type": "spot", "position": [0, 0, 0], "direction": [0, 0, -2], "cutoff_deg": 10}
    spec = parse_spec(data, require_images=False)
    np.testing.assert_allclose(spec.light.direction, [0, 0, -1])
    data["light"]["cutoff_deg"] = 95
    assert "light.cutoff_deg" in _err(copy.deepcopy(data))
    data["light"]["cutoff_deg"] = 10
    data["light"]["radius"] = 3  # a bulb field on a spot is a typo
    assert "radius" in _err(data)


def test_missing_image_file_is_named(tmp_path):
    path = tmp_path / "spec.yaml"
    path.write_text(EXAMPLE)
    with pytest.raises(SpecError, match=r"images\[0\]\.path: file not found"):
        load_spec(path)
    assert load_spec(path, require_images=False).name == "lowfat-milk-16ml"


def test_geometry_only_spec_may_omit_images():
    data = _data()
    del data["images"], data["calibration"]
    assert parse_spec(data, require_images=False).images == ()
    assert "images" in _err(data, require_images=True)


def test_broken_yaml_and_missing_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("tank: [1, 2\n  camera: {")
    with pytest.raises(SpecError, match="not valid YAML"):
        load_spec(bad)
    with pytest.raises(SpecError, match="file not found"):
        load_spec(tmp_path / "nope.yaml")


_BOMB = "\n".join([f"l0: &l0 [{', '.join(['lol'] * 9)}]"]
                  + [f"l{k}: &l{k} [{', '.join([f'*l{k - 1}'] * 9)}]" for k in range(1, 10)])


@pytest.mark.parametrize("text, words", [
    ("fitmedia_spec: 1\ncamera:\n  fx: 120\n  fy: 120\n  fx: 240\n",
     ["duplicate key 'fx'", "lines 3 and 5", "line 5"]),
    ("fitmedia_spec: 1\n2024: x\n", ["2024", "not text", "line 2"]),
    ("x: " + "[" * 3000 + "]" * 3000 + "\n", ["nested more than 32 levels", "line 1"]),
    (_BOMB, ["expands to more than 10000 values", "aliases"]),
    ("a: &a [1, *a]\n", ["refers to a node that contains it"]),
    ("a: !!python/object/apply:os.system [echo hi]\n", ["not valid YAML", "python/object"]),
])
def test_yaml_that_is_not_a_spec_is_refused_fast(tmp_path, text, words):
    """Duplicate keys (the last one used to win: fx 240 for 120, kappa_s x37), a key that is
    not text, deep nesting (a RecursionError traceback), an alias bomb of 9^10 values (a hang)
    and a cyclic alias are refused with the line, each well under a second; the reference is
    the YAML text itself (lines counted by hand)."""
    import time

    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    t0 = time.perf_counter()
    with pytest.raises(SpecError) as exc:
        load_spec(bad)
    assert time.perf_counter() - t0 < 2.0
    msg = str(exc.value)
    assert "\n" not in msg and all(w in msg for w in words), msg


def test_yaml_anchors_and_merge_keys_within_budget_still_work(tmp_path):
    """An anchor reused for a small value, and a merge key overriding a merged field (not a
    duplicate), load as plain YAML would (yaml.safe_load is the reference)."""
    import yaml

    text = EXAMPLE.replace("position: [0, 0, 900]", "position: &cam [0, 0, 900]") + \
        "name2: &n {a: 1, b: 2}\n"
    data = yaml.load(text, Loader=SpecLoader)
    assert data == yaml.safe_load(text)
    merged = yaml.load("x: &x {a: 1, b: 2}\ny:\n  <<: *x\n  a: 3\n", Loader=SpecLoader)
    assert merged["y"] == {"a": 3, "b": 2}


def test_overrides_and_brackets():
    data = _data()
    data["images"] = [
        {"path": ["a.tiff", "b.tiff"], "exposure_s": [0.1, 1.0], "concentration": 0.5,
         "light": {"position": [0, 0, 0]}, "camera": {"position": [10, 0, 900]}},
        {"path": "c.tiff", "exposure_s": 1.0},
    ]
    spec = parse_spec(data, require_images=False)
    assert spec.images[0].exposures == (0.1, 1.0)
    np.testing.assert_allclose(spec.light_for(0).position, [0, 0, 0])
    assert spec.light_for(0).radius == 6  # merged over the base light
    np.testing.assert_allclose(spec.camera_for(0).position, [10, 0, 900])
    assert spec.camera_for(1) is spec.camera
    data["images"][0]["exposure_s"] = [0.1, 1.0, 2.0]
    assert "images[0].exposure_s" in _err(data)


def test_spec_error_survives_pickling():
    """Errors cross process boundaries (Dask workers, process pools) intact."""
    import pickle

    err = pickle.loads(pickle.dumps(SpecError("s.yaml", "camera.fx", "got -1: must be > 0")))
    assert str(err) == "s.yaml: camera.fx: got -1: must be > 0" and err.field == "camera.fx"

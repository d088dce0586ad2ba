"""Capture spec v1: schema, loading, validation (CAPTURE_SPEC.md).

The schema is a JSON Schema checked by :mod:`jsonschema`; geometric checks
(camera in front of the tank, light inside it) follow in :func:`validate`.
Every problem raises :class:`~fitmedia.errors.SpecError` naming the file and
the field.  Lengths are millimetres, coefficients 1/mm.

Optional extensions (documented in ``docs/spec.md``):

* ``light.radiance`` (bulb) / ``light.intensity`` (spot): known brightness per
  channel, in image units (bulb: radiance in the water; spot: radiant
  intensity in the water, image units x mm^2).
* ``images[].saturation`` / ``calibration.clear_water.saturation``: the raw
  file value at or above which a pixel is saturated.
* ``images[].response: linear | srgb | {curve: FILE}``: how an 8- or 16-bit file encodes
  light (required for them; a curve file: a measured camera response, docs/spec.md).
* ``images[].binning: N``: N x N pixels averaged after decoding (the camera block describes
  the binned image; docs/spec.md, "Binning").
* ``camera.distortion`` / ``images[].camera.distortion``: OpenCV's lens distortion
  (k1, k2, p1, p2, k3); the models render through it (docs/spec.md, "Lens distortion").
"""

from __future__ import annotations

import copy
import difflib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from .errors import SpecError

CHANNELS = ("R", "G", "B")

_num = {"type": "number"}
_vec3 = {"type": "array", "items": _num, "minItems": 3, "maxItems": 3}
_pos3 = {"type": "array", "items": {"type": "number", "exclusiveMinimum": 0},
         "minItems": 3, "maxItems": 3}
_chanval = {"oneOf": [{"type": "number", "exclusiveMinimum": 0},
                      {"type": "array", "items": {"type": "number", "exclusiveMinimum": 0},
                       "minItems": 1, "maxItems": 3}]}
_paths = {"oneOf": [{"type": "string", "minLength": 1},
                    {"type": "array", "items": {"type": "string", "minLength": 1}, "minItems": 1}]}
_exposures = {"oneOf": [{"type": "number", "exclusiveMinimum": 0},
                        {"type": "array", "items": {"type": "number", "exclusiveMinimum": 0},
                         "minItems": 1}]}

CAMERA_SCHEMA = {
    "type": "object", "additionalProperties": False,
    "required": ["size", "fx", "fy", "cx", "cy", "position", "look_at", "up"],
    "properties": {
        "size": {"type": "array", "items": {"type": "integer", "minimum": 1},
                 "minItems": 2, "maxItems": 2},
        "fx": {"type": "number", "exclusiveMinimum": 0},
        "fy": {"type": "number", "exclusiveMinimum": 0},
        "cx": _num, "cy": _num,
        "position": _vec3, "look_at": _vec3, "up": _vec3,
        "distortion": {"type": "object", "additionalProperties": False,
                       "properties": {k: _num for k in ("k1", "k2", "p1", "p2", "k3")}},
    },
}

LIGHT_SCHEMA = {
    "type": "object", "required": ["type"],
    "properties": {"type": {"enum": ["bulb", "spot"]}},
    "allOf": [
        {"if": {"properties": {"type": {"const": "bulb"}}},
         "then": {"additionalProperties": False, "required": ["type", "position", "radius"],
                  "properties": {"type": {}, "position": _vec3,
                                 "radius": {"type": "number", "exclusiveMinimum": 0},
                                 "radiance": _chanval}}},
        {"if": {"properties": {"type": {"const": "spot"}}},
         "then": {"additionalProperties": False,
                  "required": ["type", "position", "direction", "cutoff_deg"],
                  "properties": {"type": {}, "position": _vec3, "direction": _vec3,
                                 "cutoff_deg": {"type": "number", "exclusiveMinimum": 0,
                                                "maximum": 90},
                                 "intensity": _chanval}}},
    ],
}

_sat = {"type": "number", "exclusiveMinimum": 0}
# an image entry's decoding (docs/spec.md: "Non-linear input", "Measured response", "Binning")
# (if/then/else, not oneOf: a mistyped key in the mapping is then named, with the closest one)
_response = {"if": {"type": "object"},
             "then": {"additionalProperties": False, "required": ["curve"],
                      "properties": {"curve": {"type": "string", "minLength": 1}}},
             "else": {"enum": ["linear", "srgb"]}}
_binning = {"type": "integer", "minimum": 1}

IMAGE_SCHEMA = {
    "type": "object", "additionalProperties": False, "required": ["path", "exposure_s"],
    "properties": {
        "path": _paths, "exposure_s": _exposures,
        "concentration": {"type": "number", "exclusiveMinimum": 0},
        "dark": _paths, "mask": {"type": "string", "minLength": 1},
        "flat": {"type": "string", "minLength": 1},
        "light": {"type": "object"}, "camera": {"type": "object"},
        "saturation": _sat, "response": _response, "binning": _binning,
    },
}

SCHEMA = {
    "type": "object", "additionalProperties": False,
    "required": ["fitmedia_spec", "tank", "medium", "camera", "light"],
    "properties": {
        "fitmedia_spec": {"const": 1},
        "name": {"type": "string"},
        "tank": {
            "type": "object", "additionalProperties": False,
            "required": ["inner_size", "front_wall"],
            "properties": {
                "inner_size": _pos3,
                "front_wall": {
                    "type": "object", "additionalProperties": False,
                    "required": ["thickness", "ior"],
                    "properties": {"thickness": {"type": "number", "minimum": 0},
                                   "ior": {"type": "number", "minimum": 1}}},
                "walls": {"const": "black"},
            },
        },
        "medium": {"type": "object", "additionalProperties": False, "required": ["ior"],
                   "properties": {"ior": {"type": "number", "minimum": 1},
                                  "water_kappa_a": {"oneOf": [
                                      {"type": "number", "minimum": 0},
                                      {"type": "array", "items": {"type": "number", "minimum": 0},
                                       "minItems": 1, "maxItems": 3}]}}},
        "priors": {
            "type": "object", "additionalProperties": False,
            "properties": {
                "kappa_t": {"type": "array", "minItems": 2, "maxItems": 2,
                            "items": {"type": "number", "exclusiveMinimum": 0}},
                "albedo": {"type": "array", "minItems": 2, "maxItems": 2,
                           "items": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1}},
                "g": {"type": "array", "minItems": 2, "maxItems": 2,
                      "items": {"type": "number", "exclusiveMinimum": -1, "exclusiveMaximum": 1}},
                "brightness_rel_sd": {"type": "number", "exclusiveMinimum": 0},
                "background_sd": {"type": "number", "exclusiveMinimum": 0},
            },
        },
        "camera": CAMERA_SCHEMA,
        "light": LIGHT_SCHEMA,
        "images": {"type": "array", "minItems": 1, "items": IMAGE_SCHEMA},
        "calibration": {
            "type": "object", "additionalProperties": False, "required": ["clear_water"],
            "properties": {"clear_water": {
                "type": "object", "additionalProperties": False,
                "required": ["path", "exposure_s"],
                "properties": {"path": _paths, "exposure_s": _exposures, "dark": _paths,
                               "flat": {"type": "string", "minLength": 1},
                               "saturation": _sat, "response": _response,
                               "binning": _binning}}},
        },
        "noise": {"type": "object", "additionalProperties": False,
                  "required": ["gain", "read_var"],
                  "properties": {"gain": {"type": "number", "minimum": 0},
                                 "read_var": {"type": "number", "minimum": 0},
                                 "exposure_s": {"type": "number", "exclusiveMinimum": 0}}},
        "channels": {"type": "array", "items": {"enum": list(CHANNELS)},
                     "minItems": 1, "maxItems": 3, "uniqueItems": True},
        # optional: what rendered a synthetic capture's images (fitmedia synth; docs/spec.md)
        "synthetic": {"type": "object", "additionalProperties": False, "required": ["model"],
                      "properties": {"model": {"enum": ["single", "full", "hybrid"]}}},
    },
}


@dataclass(frozen=True)
class Tank:
    inner_size: tuple[float, float, float]
    wall_thickness: float
    wall_ior: float

    @property
    def half(self) -> np.ndarray:
        return 0.5 * np.asarray(self.inner_size, dtype=float)


@dataclass(frozen=True)
class Camera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    #: OpenCV's (k1, k2, p1, p2, k3) on normalised coordinates; None: none (all zero)
    #: (docs/spec.md, "Lens distortion"; fitmedia.distortion)
    distortion: tuple[float, float, float, float, float] | None = None

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(forward, right, true_up) unit vectors per CAPTURE_SPEC.md."""
        f = self.look_at - self.position
        f = f / np.linalg.norm(f)
        r = np.cross(f, self.up)
        r = r / np.linalg.norm(r)
        return f, r, np.cross(r, f)


@dataclass(frozen=True)
class Light:
    type: str
    position: np.ndarray
    radius: float = 0.0
    direction: np.ndarray | None = None
    cutoff_deg: float = 90.0
    brightness: tuple[float, ...] | None = None  # bulb radiance or spot intensity, per channel


@dataclass(frozen=True)
class ImageEntry:
    paths: tuple[Path, ...]
    exposures: tuple[float, ...]
    concentration: float = 1.0
    darks: tuple[Path, ...] = ()
    mask: Path | None = None
    saturation: float | None = None
    response: str | None = None
    flat: Path | None = None  # flat-field image (docs/spec.md, "Flat field")
    binning: int = 1  # N x N pixels averaged after decoding (docs/spec.md, "Binning")
    response_curve: Path | None = None  # response "curve": its file (images/response.py)
    camera: Camera | None = None
    light: Light | None = None


@dataclass(frozen=True)
class Spec:
    source: str
    name: str
    tank: Tank
    medium_ior: float
    camera: Camera
    light: Light
    images: tuple[ImageEntry, ...] = ()
    clear_water: ImageEntry | None = None
    noise: tuple[float, float] | None = None
    noise_exposure: float | None = None  # exposure (s) the noise block refers to (docs/spec.md)
    channels: tuple[str, ...] = CHANNELS
    water_kappa_a: tuple[float, float, float] = (0.0, 0.0, 0.0)
    priors: dict = field(default_factory=dict)
    #: the forward model that rendered a synthetic capture (``synthetic.model``), else None
    synthetic_model: str | None = None
    raw: dict = field(default_factory=dict, repr=False, compare=False)

    def camera_for(self, i: int) -> Camera:
        return self.images[i].camera or self.camera

    def light_for(self, i: int) -> Light:
        return self.images[i].light or self.light


def _field_path(path) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def _schema_check(data: Any, schema: dict, where: str, prefix: str = "") -> None:
    import jsonschema

    validator = jsonschema.Draft202012Validator(schema)
    errors = list(validator.iter_errors(data))
    if not errors:
        return
    err = jsonschema.exceptions.best_match(errors)
    # descend into the most specific error of a oneOf/anyOf/if-then
    while err.context:
        err = jsonschema.exceptions.best_match(err.context)
    fpath = _field_path(list(err.absolute_path))
    if prefix:
        fpath = f"{prefix}.{fpath}" if fpath else prefix
    if err.validator == "additionalProperties":
        allowed = sorted(err.schema.get("properties", {}))
        extra = sorted(set(err.instance) - set(allowed))
        hint = difflib.get_close_matches(extra[0], allowed, n=1)
        msg = f"unknown field '{extra[0]}'" + (f" (did you mean '{hint[0]}'?)" if hint else "")
        msg += f"; allowed: {', '.join(allowed)}"
        raise SpecError(where, fpath or "(top level)", msg)
    if err.validator == "required":
        raise SpecError(where, fpath or "(top level)", err.message.replace("is a required property",
                                                                          "is required but missing"))
    raise SpecError(where, fpath or "(top level)", f"got {err.instance!r}: {err.message}")


def _check_finite(data: Any, where: str, path: tuple = ()) -> None:
    """NaN and infinity pass JSON-Schema bounds (comparisons with NaN are false): reject them."""
    if isinstance(data, dict):
        for k, v in data.items():
            _check_finite(v, where, path + (k,))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            _check_finite(v, where, path + (i,))
    elif isinstance(data, float) and not np.isfinite(data):
        raise SpecError(where, _field_path(list(path)), f"got {data}: must be a finite number")


def _camera(d: dict, where: str = "<spec>", fld: str = "camera") -> Camera:
    cam = Camera(width=int(d["size"][0]), height=int(d["size"][1]), fx=float(d["fx"]),
                 fy=float(d["fy"]), cx=float(d["cx"]), cy=float(d["cy"]),
                 position=np.asarray(d["position"], float), look_at=np.asarray(d["look_at"], float),
                 up=np.asarray(d["up"], float))
    return _with_distortion(cam, d.get("distortion"), where, f"{fld}.distortion")


def _with_distortion(cam: Camera, dist: dict | None, where: str, fld: str) -> Camera:
    """``cam`` with the spec's ``distortion`` block (keys absent are 0; all zero: None),
    refused when the map is not one-to-one over the image (docs/spec.md, "Lens distortion")."""
    from dataclasses import replace

    from .distortion import KEYS, check_monotonic

    coeffs = tuple(float((dist or {}).get(k, 0.0)) for k in KEYS)
    if not any(coeffs):
        return cam
    why = check_monotonic(coeffs, cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    if why:
        given = ", ".join(f"{k} {v:g}" for k, v in zip(KEYS, coeffs) if v)
        raise SpecError(where, fld, f"got {given}: not monotonic over the {cam.width} x "
                        f"{cam.height} image: {why}")
    return replace(cam, distortion=coeffs)


def _channel_values(v, channels: tuple[str, ...], where: str, fld: str) -> tuple[float, ...]:
    vals = [float(v)] * 3 if np.isscalar(v) else [float(x) for x in v]
    if len(vals) == 1:
        vals = vals * 3
    if len(vals) != 3:
        raise SpecError(where, fld, f"expected one value or three (R, G, B), got {len(vals)}")
    return tuple(vals)


def _light(d: dict, where: str, fld: str) -> Light:
    bright = d.get("radiance", d.get("intensity"))
    bright = None if bright is None else _channel_values(bright, CHANNELS, where, fld)
    if d["type"] == "bulb":
        return Light("bulb", np.asarray(d["position"], float), radius=float(d["radius"]),
                     brightness=bright)
    direction = np.asarray(d["direction"], float)
    n = np.linalg.norm(direction)
    if not n > 0:
        raise SpecError(where, f"{fld}.direction", f"got {d['direction']}: must be a non-zero vector")
    return Light("spot", np.asarray(d["position"], float), direction=direction / n,
                 cutoff_deg=float(d["cutoff_deg"]), brightness=bright)


def _aslist(v) -> list:
    return list(v) if isinstance(v, list) else [v]


def _image_entry(d: dict, base: Path, where: str, fld: str, spec_cam: dict, spec_light: dict,
                 check_files: bool) -> ImageEntry:
    paths = [base / p for p in _aslist(d["path"])]
    exps = [float(e) for e in _aslist(d["exposure_s"])]
    if len(exps) == 1 and len(paths) > 1:
        exps = exps * len(paths)
    if len(exps) != len(paths):
        raise SpecError(where, f"{fld}.exposure_s",
                        f"{len(exps)} exposures for {len(paths)} paths; give one per path")
    darks = [base / p for p in _aslist(d["dark"])] if "dark" in d else []
    if darks and len(darks) not in (1, len(paths)):
        raise SpecError(where, f"{fld}.dark", f"{len(darks)} dark frames for {len(paths)} paths")
    mask = base / d["mask"] if "mask" in d else None
    flat = base / d["flat"] if "flat" in d else None
    response, curve = d.get("response"), None
    if isinstance(response, dict):
        response, curve = "curve", base / response["curve"]
    if check_files:
        for key, lst in (("path", paths), ("dark", darks), ("mask", [mask] if mask else []),
                         ("flat", [flat] if flat else []),
                         ("response.curve", [curve] if curve else [])):
            for p in lst:
                if not p.is_file():
                    raise SpecError(where, f"{fld}.{key}", f"file not found: {p}")
    cam = light = None
    if "camera" in d:
        merged = {**spec_cam, **d["camera"]}
        _schema_check(merged, CAMERA_SCHEMA, where, f"{fld}.camera")
        cam = _camera(merged, where, f"{fld}.camera")
    if "light" in d:
        merged = {**spec_light, **d["light"]}
        if merged.get("type") != spec_light.get("type"):
            merged = dict(d["light"])
        _schema_check(merged, LIGHT_SCHEMA, where, f"{fld}.light")
        light = _light(merged, where, f"{fld}.light")
    return ImageEntry(paths=tuple(paths), exposures=tuple(exps),
                      concentration=float(d.get("concentration", 1.0)), darks=tuple(darks),
                      mask=mask, saturation=d.get("saturation"), response=response,
                      flat=flat, binning=int(d.get("binning", 1)), response_curve=curve,
                      camera=cam, light=light)


def _check_geometry(spec: Spec, where: str) -> None:
    half = spec.tank.half
    front_outer = half[2] + spec.tank.wall_thickness
    cams = [("camera", spec.camera)] + [(f"images[{i}].camera", im.camera)
                                        for i, im in enumerate(spec.images) if im.camera]
    for fld, cam in cams:
        if not cam.position[2] > front_outer:
            raise SpecError(where, f"{fld}.position",
                            f"got {cam.position.tolist()}: the camera must be in air in front of the "
                            f"front wall (z > {front_outer:g} mm)")
        fwd = cam.look_at - cam.position
        if np.linalg.norm(fwd) == 0:
            raise SpecError(where, f"{fld}.look_at", "equals camera.position")
        if np.linalg.norm(np.cross(fwd / np.linalg.norm(fwd), cam.up)) < 1e-6:
            raise SpecError(where, f"{fld}.up", f"got {cam.up.tolist()}: parallel to the view direction")
        if not fwd[2] < 0:
            raise SpecError(where, f"{fld}.look_at", "the camera must look towards the tank (-z)")
    lights = [("light", spec.light)] + [(f"images[{i}].light", im.light)
                                        for i, im in enumerate(spec.images) if im.light]
    for fld, light in lights:
        margin = light.radius if light.type == "bulb" else 0.0
        if np.any(np.abs(light.position) + margin >= half):
            what = "the bulb (position +- radius)" if light.type == "bulb" else "the light"
            raise SpecError(where, f"{fld}.position",
                            f"got {light.position.tolist()}: {what} must lie inside the tank "
                            f"interior |x|<{half[0]:g}, |y|<{half[1]:g}, |z|<{half[2]:g} mm")


def parse_spec(data: Any, *, source: str = "<spec>", base: Path | None = None,
               require_images: bool = True) -> Spec:
    """Validate a spec already parsed from YAML and return a :class:`Spec`.

    Parameters
    ----------
    data : dict
        The parsed YAML document.
    source : str
        Name used in error messages (normally the file path).
    base : Path, optional
        Folder that relative image paths are resolved against.
    require_images : bool
        When true, ``images`` must be present and every file must exist.
    """
    where = source
    base = Path(".") if base is None else Path(base)
    if not isinstance(data, dict):
        raise SpecError(where, "", "the spec must be a YAML mapping")
    _check_finite(data, where)
    _schema_check(data, SCHEMA, where)
    if require_images and "images" not in data:
        raise SpecError(where, "images", "is required but missing (at least one image)")
    t = data["tank"]
    tank = Tank(tuple(float(x) for x in t["inner_size"]), float(t["front_wall"]["thickness"]),
                float(t["front_wall"]["ior"]))
    channels = tuple(data.get("channels", CHANNELS))
    camera = _camera(data["camera"], where)  # before the images' overrides, which inherit it
    images = tuple(_image_entry(d, base, where, f"images[{i}]", data["camera"], data["light"],
                                require_images)
                   for i, d in enumerate(data.get("images", [])))
    cw = None
    if "calibration" in data:
        cw = _image_entry(data["calibration"]["clear_water"], base, where,
                          "calibration.clear_water", data["camera"], data["light"], require_images)
    noise = None
    if "noise" in data:
        noise = (float(data["noise"]["gain"]), float(data["noise"]["read_var"]))
        if noise[0] == 0 and noise[1] == 0:
            raise SpecError(where, "noise", "gain and read_var are both 0: the variance would be 0")
    priors = dict(data.get("priors", {}))
    for key in ("kappa_t", "albedo", "g"):
        if key in priors and not priors[key][0] < priors[key][1]:
            raise SpecError(where, f"priors.{key}", f"got {priors[key]}: need [low, high] with low < high")
    water = data["medium"].get("water_kappa_a", 0.0)
    spec = Spec(source=source, name=str(data.get("name", Path(source).stem)), tank=tank,
                medium_ior=float(data["medium"]["ior"]), camera=camera,
                light=_light(data["light"], where, "light"), images=images, clear_water=cw,
                noise=noise, noise_exposure=(data.get("noise") or {}).get("exposure_s"),
                channels=channels,
                water_kappa_a=_channel_values(water, CHANNELS, where, "medium.water_kappa_a"),
                priors=priors, synthetic_model=(data.get("synthetic") or {}).get("model"),
                raw=copy.deepcopy(data))
    _check_geometry(spec, where)
    return spec


#: Deepest nesting of a spec's YAML (the contract's deepest field is 4 levels down)
MAX_YAML_DEPTH = 32
#: Most nodes a spec's YAML may expand to, aliases counted at every use (a spec has ~100;
#: a "billion laughs" alias bomb expands to 1e9 and would hang every walk of the data)
MAX_YAML_NODES = 10_000


class _SpecYAMLError(yaml.MarkedYAMLError):
    """A spec's YAML that is valid YAML but not acceptable as a spec (docs/spec.md, "YAML")."""


class SpecLoader(yaml.SafeLoader):
    """yaml.SafeLoader that refuses, with the line: duplicate keys (naming both lines), keys
    that are not strings (``2024: x``), nesting deeper than :data:`MAX_YAML_DEPTH`, and aliases
    that expand the document beyond :data:`MAX_YAML_NODES` nodes or refer to themselves."""

    def __init__(self, stream):
        super().__init__(stream)
        self._depth = 0

    def compose_node(self, parent, index):
        self._depth += 1
        try:
            if self._depth > MAX_YAML_DEPTH:
                raise _SpecYAMLError(problem=f"nested more than {MAX_YAML_DEPTH} levels deep",
                                     problem_mark=self.peek_event().start_mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def get_single_node(self):
        node = super().get_single_node()
        if node is not None:
            _check_expansion(node)
        return node

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                line = key_node.start_mark.line + 1
                if not isinstance(key, str):
                    raise _SpecYAMLError(problem=f"the key {key!r} is not text ({type(key).__name__}"
                                         "): field names are words", problem_mark=key_node.start_mark)
                if key in seen:
                    raise _SpecYAMLError(problem=f"duplicate key '{key}' (lines {seen[key]} and "
                                         f"{line}); give each field once",
                                         problem_mark=key_node.start_mark)
                seen[key] = line
        return super().construct_mapping(node, deep=deep)


def _check_expansion(root: yaml.Node) -> None:
    """Refuse a node graph (aliases share nodes) whose expanded tree has more than
    MAX_YAML_NODES nodes or MAX_YAML_DEPTH levels, or a cycle; linear in the graph's size
    (sizes memoised per node, iterative: no recursion limit)."""
    size: dict[int, tuple[int, int]] = {}  # id(node) -> (expanded nodes, expanded depth)
    stack: list[tuple[yaml.Node, bool]] = [(root, False)]
    open_: set[int] = set()
    while stack:
        node, done = stack.pop()
        kids = ([n for pair in node.value for n in pair] if isinstance(node, yaml.MappingNode)
                else node.value if isinstance(node, yaml.SequenceNode) else [])
        if done:
            open_.discard(id(node))
            n = 1 + sum(size[id(k)][0] for k in kids)
            d = 1 + max((size[id(k)][1] for k in kids), default=0)
            if n > MAX_YAML_NODES or d > MAX_YAML_DEPTH:
                what = (f"expands to more than {MAX_YAML_NODES} values" if n > MAX_YAML_NODES
                        else f"is nested more than {MAX_YAML_DEPTH} levels deep")
                raise _SpecYAMLError(problem=f"the document {what} through its aliases (*name); "
                                     "write the values out", problem_mark=node.start_mark)
            size[id(node)] = (n, d)
            continue
        if id(node) in size:
            continue
        if id(node) in open_:
            raise _SpecYAMLError(problem="an alias refers to a node that contains it",
                                 problem_mark=node.start_mark)
        open_.add(id(node))
        stack.append((node, True))
        stack.extend((k, False) for k in kids if id(k) not in size)


def load_spec(path: str | Path, *, require_images: bool = True) -> Spec:
    """Read and validate a capture spec file (YAML, read by :class:`SpecLoader`)."""
    path = Path(path)
    if not path.is_file():
        raise SpecError(str(path), "", "file not found")
    try:
        data = yaml.load(path.read_text(), Loader=SpecLoader)  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        loc = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        what = "YAML not accepted" if isinstance(exc, _SpecYAMLError) else "not valid YAML"
        raise SpecError(str(path), "", f"{what}: {loc}{getattr(exc, 'problem', exc)}") from None
    except UnicodeDecodeError:
        raise SpecError(str(path), "", "not a text file") from None
    return parse_spec(data, source=str(path), base=path.parent, require_images=require_images)


def dump_spec(data: dict, path: str | Path) -> None:
    """Write a spec dict as YAML atomically."""
    from .util import atomic_write_text

    atomic_write_text(path, yaml.safe_dump(data, sort_keys=False, default_flow_style=None))

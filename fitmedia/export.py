"""Export a fitted medium to renderers: a Mitsuba 3 ``homogeneous`` medium (Python dict
as JSON, and XML) and a pbrt-v4 ``MakeNamedMedium`` block.

The values are those of ``results.json``: the undiluted liquid (concentration 1), in
1/mm, so a scene whose unit is the millimetre uses them as they are; a scene in metres
takes ``scale_to_m=True`` (1/m).  To render the liquid diluted to concentration c
(ml of liquid / ml of water), set the renderer's ``scale`` to c: both renderers
multiply the coefficients by it.

Which numbers: the posterior medians of ``kappa_t`` and ``albedo`` (the sampler's own
coordinates, so their medians belong together), or their MAP when no sampler ran.
Mitsuba takes ``sigma_t`` and ``albedo``; pbrt takes ``sigma_a = sigma_t (1 - albedo)``
and ``sigma_s = sigma_t albedo``, so both describe the same medium (these can differ
from the medians of ``kappa_a`` and ``kappa_s`` by a fraction of their posterior spread).
Both renderers' Henyey-Greenstein phase takes one scalar g: the mean over the channels
is written, and the per-channel values are stated beside it.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING
from xml.sax.saxutils import quoteattr

from .errors import InputError
from .spec import CHANNELS

if TYPE_CHECKING:  # pragma: no cover
    from .inference.result import FitResult
from .util import atomic_write_text

MM_PER_M = 1000.0
FILES = ("medium_mitsuba.json", "medium_mitsuba.xml", "medium_pbrt.txt")


def medium_values(results: Mapping, *, scale_to_m: bool = False) -> dict:
    """The renderer values of a fit (a :class:`~fitmedia.inference.result.FitResult` or its
    results.json dict).

    Parameters
    ----------
    results : FitResult or dict
        A fit (``parameters.{kappa_t,albedo,g}.{R,G,B}`` with ``median`` or ``map``;
        ``units.kappa`` of ``1/mm``).
    scale_to_m : bool
        Coefficients in 1/m instead of 1/mm.

    Returns
    -------
    dict
        ``sigma_t``, ``albedo``, ``sigma_a``, ``sigma_s``, ``g`` (lists of 3, R G B; the
        coefficients in ``unit``), ``g_mean``, ``statistic`` (``"median"`` or ``"map"``),
        ``unit`` (``"1/mm"`` or ``"1/m"``), ``name``, ``doubts`` (:func:`doubts`: why the
        fit said its values cannot be trusted; empty when it did not).
    """
    if not isinstance(results, Mapping) or not isinstance(results.get("parameters"), dict):
        raise InputError("results.json: parameters: missing; expected the output of fitmedia fit")
    unit = (results.get("units") or {}).get("kappa", "1/mm")
    if unit != "1/mm":
        raise InputError(f"results.json: units.kappa: got {unit!r}, expected '1/mm'")
    p = results["parameters"]
    entries = {}
    for q in ("kappa_t", "albedo", "g"):
        for ch in CHANNELS:
            e = p.get(q, {}).get(ch) if isinstance(p.get(q), dict) else None
            if not isinstance(e, dict) or not ({"median", "map"} & set(e)):
                raise InputError(f"results.json: parameters.{q}.{ch}: missing; the export needs "
                                 "all three channels R, G, B")
            entries[q, ch] = e
    stat = "median" if all("median" in e for e in entries.values()) else "map"
    vals = {}
    for (q, ch), e in entries.items():
        v = e[stat]
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
            raise InputError(f"results.json: parameters.{q}.{ch}.{stat}: got {v!r}, expected a "
                             "finite number")
        vals[q, ch] = float(v)
    factor = MM_PER_M if scale_to_m else 1.0
    kt = [vals["kappa_t", c] * factor for c in CHANNELS]
    alb = [vals["albedo", c] for c in CHANNELS]
    g = [vals["g", c] for c in CHANNELS]
    if min(kt) < 0 or not all(0 <= a <= 1 for a in alb) or max(abs(x) for x in g) >= 1:
        raise InputError(f"results.json: parameters: kappa_t {kt}, albedo {alb}, g {g}: need "
                         "kappa_t >= 0, 0 <= albedo <= 1, -1 < g < 1")
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(results.get("name") or "medium")).strip("_")
    return {"sigma_t": kt, "albedo": alb, "sigma_a": [t * (1 - a) for t, a in zip(kt, alb)],
            "sigma_s": [t * a for t, a in zip(kt, alb)], "g": g, "g_mean": sum(g) / len(g),
            "statistic": stat, "unit": "1/m" if scale_to_m else "1/mm",
            "name": f"fitmedia_{name or 'medium'}", "doubts": doubts(results)}


def doubts(results: Mapping) -> list[str]:
    """The reasons for which the fit said its values cannot be trusted (results.json's
    ``trust``: ``ok`` false); empty for a trusted fit or one from before the verdict."""
    trust = results.get("trust") or {}
    if trust.get("ok", True):
        return []
    return list(trust.get("reasons") or ["results.json: trust.ok is false"])


def _header(v: dict) -> list[str]:
    length = "m" if v["unit"] == "1/m" else "mm"
    stat = "posterior median" if v["statistic"] == "median" else "MAP (no posterior samples)"
    g = ", ".join(f"{c} {x:.4f}" for c, x in zip(CHANNELS, v["g"]))
    warn = [f"DOUBTFUL: the fit said these values cannot be trusted: {r}" for r in v["doubts"]]
    return warn + [f"fitmedia export: {v['name']}, homogeneous medium, {stat} of results.json",
            f"units: scene length unit {length}; coefficients in {v['unit']}",
            ("concentration: undiluted liquid (1); to render a dilution c (ml liquid / ml water) "
             "set scale = c"),
            (f"HG g: one value for all channels, the mean {v['g_mean']:.4f} of the per-channel "
             f"values ({g})"),
            "sigma_a = sigma_t (1 - albedo), sigma_s = sigma_t albedo (R, G, B)"]


def mitsuba_dict(v: dict) -> dict:
    """The Mitsuba 3 plugin dict of a ``homogeneous`` medium (``mi.load_dict`` takes it)."""
    return {"type": "homogeneous",
            "sigma_t": {"type": "rgb", "value": v["sigma_t"]},
            "albedo": {"type": "rgb", "value": v["albedo"]},
            "scale": 1.0,
            "phase": {"type": "hg", "g": v["g_mean"]}}


def _num(x: float) -> str:
    return f"{x:.9g}"


def mitsuba_xml(v: dict) -> str:
    """The same medium as a Mitsuba 3 XML ``<medium>`` element, with a comment header."""
    rgb = {k: ", ".join(_num(x) for x in v[k]) for k in ("sigma_t", "albedo")}
    comment = "\n".join("     " + re.sub(r"-{2,}", "-", line) for line in _header(v))
    return (f"<!--\n{comment}\n-->\n"
            f"<medium type=\"homogeneous\" id={quoteattr(v['name'])}>\n"
            f"    <rgb name=\"sigma_t\" value=\"{rgb['sigma_t']}\"/>\n"
            f"    <rgb name=\"albedo\" value=\"{rgb['albedo']}\"/>\n"
            f"    <float name=\"scale\" value=\"1\"/>\n"
            f"    <phase type=\"hg\">\n"
            f"        <float name=\"g\" value=\"{_num(v['g_mean'])}\"/>\n"
            f"    </phase>\n"
            f"</medium>\n")


def pbrt_block(v: dict) -> str:
    """A pbrt-v4 ``MakeNamedMedium`` block of type ``homogeneous``, with a comment header."""
    def rgb(k: str) -> str:
        return "[ " + " ".join(_num(x) for x in v[k]) + " ]"

    head = "".join(f"# {line}\n" for line in _header(v))
    return (f"{head}MakeNamedMedium \"{v['name']}\"\n"
            f"    \"string type\" \"homogeneous\"\n"
            f"    \"rgb sigma_a\" {rgb('sigma_a')}\n"
            f"    \"rgb sigma_s\" {rgb('sigma_s')}\n"
            f"    \"float scale\" 1\n"
            f"    \"float g\" {_num(v['g_mean'])}\n")


def export_medium(results: Mapping, out_dir: str | Path, *, scale_to_m: bool = False
                  ) -> list[Path]:
    """Write the fitted medium of ``results`` for Mitsuba 3 and pbrt-v4 into ``out_dir``.

    Parameters
    ----------
    results : FitResult or dict
        A fit or its results.json dict (undiluted liquid, 1/mm).
    out_dir : str or Path
        Receives ``medium_mitsuba.json`` (``{"medium": <mi.load_dict input>, ...}`` with the
        units, the statistic, the per-channel g and ``trusted`` beside it; a doubtful fit's
        reasons open every file's comment), ``medium_mitsuba.xml`` (a
        ``<medium>`` element for a scene file) and ``medium_pbrt.txt`` (a
        ``MakeNamedMedium`` block), each written atomically.
    scale_to_m : bool
        Coefficients in 1/m for a scene in metres (default 1/mm, a scene in millimetres).

    Returns
    -------
    list of Path
        The three files, in that order.
    """
    v = medium_values(results, scale_to_m=scale_to_m)
    out = Path(out_dir)
    paths = [out / f for f in FILES]
    doc = {"comment": _header(v), "trusted": not v["doubts"], "unit": v["unit"],
           "statistic": v["statistic"],
           "concentration": 1.0, "g_per_channel": dict(zip(CHANNELS, v["g"])),
           "sigma_a": v["sigma_a"], "sigma_s": v["sigma_s"],
           "load": "mi.load_dict(json.load(open(path))['medium'])", "medium": mitsuba_dict(v)}
    atomic_write_text(paths[0], json.dumps(doc, indent=2) + "\n")
    atomic_write_text(paths[1], mitsuba_xml(v))
    atomic_write_text(paths[2], pbrt_block(v))
    return paths


def read_results(directory: str | Path) -> FitResult:
    """The fit in ``directory/results.json`` (:meth:`FitResult.from_json`); a missing or
    broken file is an InputError naming it."""
    from .inference.result import FitResult

    return FitResult.from_json(Path(directory) / "results.json")

"""The HTML report of a fit: one self-contained file (figures embedded as base64 PNG).

:func:`write_report` reads what ``fitmedia fit SPEC --out DIR`` writes
(``results.json``, ``samples.npz``, ``fit_images.npz``; CAPTURE_SPEC.md) and
writes ``DIR/report.html``.  The file is written in ASCII (non-ASCII characters
as HTML character references), so it reads the same whatever the locale.
"""

from __future__ import annotations

import datetime as _dt
import html
import json
import math
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ..trust import RESTART_DELTA, sampler_reasons
from ..version import __version__
from ..errors import InputError
from ..regimes import INFORMATIVE_OPTICAL_DEPTH
from ..util import atomic_write_text
from .plots import finite_or_none as _num
from .plots import prior_bound_flags

QUANTITIES = ("kappa_a", "kappa_s", "kappa_t", "albedo", "g")
KAPPAS = ("kappa_a", "kappa_s", "kappa_t", "kappa_s_reduced")
LABELS = {"kappa_a": "&kappa;<sub>a</sub> absorption", "kappa_s": "&kappa;<sub>s</sub> scattering",
          "kappa_t": "&kappa;<sub>t</sub> extinction", "g": "g (HG anisotropy)",
          "albedo": "albedo &kappa;<sub>s</sub>/&kappa;<sub>t</sub>",
          "kappa_s_reduced": "&kappa;<sub>s</sub>&prime; = &kappa;<sub>s</sub>(1&minus;g) reduced "
                             "scattering"}
G_UNCONSTRAINED = "g unconstrained: the medium hardly scatters in this channel"
KS_ZERO = "&kappa;<sub>s</sub> consistent with zero"
CHI2_WARN = (0.5, 2.0)  # chi2 per pixel outside this range is flagged (without results' trust)
KS_G_NOT_SEPARABLE = ("&kappa;<sub>s</sub> and g not separately measured (the images constrain "
                      "&kappa;<sub>s</sub>&prime; = &kappa;<sub>s</sub>(1&minus;g)): read "
                      "&kappa;<sub>t</sub> and &kappa;<sub>s</sub>&prime;, not &kappa;<sub>s</sub>, "
                      "g, &kappa;<sub>a</sub> = &kappa;<sub>t</sub> &minus; &kappa;<sub>s</sub> or "
                      "the albedo on their own (greyed below)")
#: the quantities that move with g where kappa_s and g are not separately measured
NOT_MEASURED_ALONE = ("kappa_a", "kappa_s", "g", "albedo")

CSS = """
body { font-family: sans-serif; max-width: 1250px; margin: 1em auto; padding: 0 1em;
       color: #222; line-height: 1.4; }
h1 { font-size: 1.5em; border-bottom: 2px solid #444; }
h2 { font-size: 1.2em; border-bottom: 1px solid #aaa; margin-top: 2em; }
table { border-collapse: collapse; margin: 0.5em 0 1em 0; font-size: 0.92em; }
th, td { border: 1px solid #bbb; padding: 0.2em 0.6em; text-align: left; vertical-align: top; }
td.num { text-align: right; font-family: monospace; white-space: nowrap; }
th { background: #f3f3f3; } tr.chan th { background: #e8e8e8; } tr.permetre td { color: #555; }
tr.alone td { color: #aaa; }
td:first-child { white-space: nowrap; }
td.num .txt { white-space: normal; font-family: sans-serif; }
.warn { background: #fff3cd; border: 1px solid #d9a400; padding: 0.4em 0.8em; margin: 0.3em 0; }
.untrusted { background: #fde2e2; border: 3px solid #c00000; padding: 0.5em 1em;
             margin: 0.8em 0; }
.untrusted h2 { color: #a40000; border: none; margin: 0 0 0.3em 0; }
.trusted { background: #e6f4e6; border: 1px solid #3a8a3a; padding: 0.4em 0.8em; margin: 0.5em 0; }
.flag { color: #a40000; font-weight: normal; margin-left: 1em; } .bad { color: #a40000; }
.muted { color: #666; font-size: 0.9em; }
img { max-width: 100%; border: 1px solid #ddd; margin: 0.3em 0; }
dl.meta { display: grid; grid-template-columns: max-content auto; gap: 0.1em 1em; }
dl.meta dt { font-weight: bold; } dl.meta dd { margin: 0; }
"""


# ---------------------------------------------------------------------------------------------
# loading


def _require(path: Path) -> Path:
    if not path.is_file():
        raise InputError(f"{path}: file not found (the report needs the output of "
                         f"`fitmedia fit SPEC --out {path.parent}`)")
    return path


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    _require(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: not a readable .npz file ({exc})") from exc


def load_outputs(out_dir: str | Path) -> tuple[dict, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Read ``results.json``, ``samples.npz`` and ``fit_images.npz`` from ``out_dir``.

    Raises
    ------
    InputError
        A file is missing or unreadable (the message names it).
    """
    out = Path(out_dir)
    rpath = _require(out / "results.json")
    try:
        results = json.loads(rpath.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{rpath}: not a readable JSON file ({exc})") from exc
    if not isinstance(results, dict) or "parameters" not in results:
        raise InputError(f"{rpath}: expected a fitmedia results object with 'parameters'")
    _check_rows(results, rpath)
    return results, _load_npz(out / "samples.npz"), _load_npz(out / "fit_images.npz")


def _check_rows(results: dict, rpath: Path) -> None:
    """Every row of the estimates table is there: a list of ``channels`` and, for each, every
    quantity of :data:`QUANTITIES` with its ``map`` (a missing row was silently left out)."""
    chans, params = results.get("channels"), results.get("parameters")
    if not isinstance(chans, list) or not chans or not isinstance(params, dict):
        raise InputError(f"{rpath}: 'channels' (a list of R, G, B) and 'parameters' are needed")
    for q in QUANTITIES:
        for ch in chans:
            entry = (params.get(q) or {}).get(ch) if isinstance(params.get(q), dict) else None
            if not isinstance(entry, dict) or "map" not in entry:
                raise InputError(f"{rpath}: parameters.{q}.{ch}"
                                 f"{'.map' if isinstance(entry, dict) else ''} is missing; the "
                                 "report would leave out its row (rerun `fitmedia fit`)")


# ---------------------------------------------------------------------------------------------
# number formatting


def format_sig(x: float | None, digits: int = 4) -> str:
    """``x`` with ``digits`` significant digits, positional for 1e-4 <= |x| < 1e6."""
    if x is None or not math.isfinite(x):
        return "&mdash;"
    if x == 0:
        return "0"
    e = math.floor(math.log10(abs(x)))
    if -4 <= e < 6:
        return f"{x:.{max(0, digits - 1 - e)}f}"
    return f"{x:.{digits - 1}e}"


def _decimals_near_one(x: float) -> int:
    """Decimals that show the first two digits of 1 - x (albedo 0.99997 -> 6)."""
    return min(12, max(4, 1 - math.floor(math.log10(abs(1.0 - x)))))


def format_estimate(entry: dict, scale: float = 1.0) -> dict[str, str]:
    """The table cells of one quantity of one channel.

    Parameters
    ----------
    entry : dict
        ``results["parameters"][quantity][channel]``: ``map`` and, when a sampler
        ran, ``median``, ``q05``, ``q16``, ``q84``, ``q95``.
    scale : float
        Multiplies every value (1000 converts 1/mm to 1/m).

    Returns
    -------
    dict
        ``estimate`` (the median, or the MAP when no sampler ran), ``q68`` and ``q90``
        ("lo &ndash; hi", or "&mdash;"), ``map``.  With an interval the values are given
        to two significant digits of the 68 % interval's width (in scientific notation
        below 1e-3 and from 1e6); where the interval spans more than a factor 10 to three
        significant digits each.
    """
    v = {k: (None if _num(entry.get(k)) is None else _num(entry.get(k)) * scale)
         for k in ("map", "median", "q05", "q16", "q84", "q95")}
    qs = [v[k] for k in ("q05", "q16", "q84", "q95")]
    if v["median"] is None or any(q is None for q in qs):
        m = v["map"]
        text = (f"{m:.{_decimals_near_one(m)}f}" if m is not None and 0.99 < m < 1.0
                else format_sig(m))
        return {"estimate": text, "q68": "&mdash;", "q90": "&mdash;", "map": text}
    lo, hi = min(qs + [v["median"]]), max(qs + [v["median"]])
    width = v["q84"] - v["q16"]
    # a width within rounding of 0 (equal samples: 1e-16 or 0 depending on the CPU's sums) has
    # no digits to give: compared with the values' scale, as fitmedia.validate.is_degenerate
    if lo > 0 and hi / lo > 10 or width <= 1e-9 * max(abs(lo), abs(hi)):
        def f(x: float | None) -> str:
            return format_sig(x, 3)
    elif max(abs(lo), abs(hi)) < 1e-3 or max(abs(lo), abs(hi)) >= 1e6:
        e_width = math.floor(math.log10(width))

        def f(x: float | None) -> str:  # scientific, to 2 digits of the width
            if x is None or x == 0:
                return format_sig(x)
            return f"{x:.{max(1, math.floor(math.log10(abs(x))) - e_width + 1)}e}"
    else:
        dec = min(12, max(0, 1 - math.floor(math.log10(width))))
        near_one = 0.9 < v["median"] < 1.0 and hi <= 1.0  # an albedo: show digits of 1 - x

        def f(x: float | None) -> str:
            if x is None:
                return "&mdash;"
            return f"{x:.{max(dec, _decimals_near_one(x)) if near_one and x < 1 else dec}f}"
    return {"estimate": f(v["median"]), "q68": f"{f(v['q16'])} &ndash; {f(v['q84'])}",
            "q90": f"{f(v['q05'])} &ndash; {f(v['q95'])}", "map": f(v["map"])}


def _cell(x: Any, digits: int = 4) -> str:
    """A table cell's text for a value of any JSON type."""
    if x is None:
        return "&mdash;"
    if isinstance(x, bool):
        return "yes" if x else '<span class="bad">NO</span>'
    if isinstance(x, int):
        return str(x)
    if isinstance(x, float):
        text = format_sig(x, digits)
        if "e" in text:  # 2.000e-05 -> 2e-05
            mant, exp = text.split("e")
            text = mant.rstrip("0").rstrip(".") + "e" + exp
        return text
    if isinstance(x, (list, dict)):
        return f'<span class="txt">{html.escape(json.dumps(x))}</span>'
    return f'<span class="txt">{html.escape(str(x))}</span>'


def _table(header: list[str], rows: list[list[str]], num_from: int = 1, *,
           drop_empty: bool = False) -> str:
    """An HTML table; cells from column ``num_from`` on are right-aligned numbers.

    With ``drop_empty`` the columns from ``num_from`` on that are empty in every row
    are left out.
    """
    if drop_empty and rows:
        keep = [j for j in range(len(header))
                if j < num_from or any(r[j] != "&mdash;" for r in rows)]
        header = [header[j] for j in keep]
        rows = [[r[j] for j in keep] for r in rows]
    head = "".join(f"<th>{h}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f'<td class="num">{c}</td>' if j >= num_from else f"<td>{c}</td>"
                         for j, c in enumerate(r)) + "</tr>\n" for r in rows)
    return f"<table><tr>{head}</tr>\n{body}</table>\n"


# ---------------------------------------------------------------------------------------------
# sections


def _channel_flags(results: dict, ch: str, samples: dict[str, np.ndarray] | None = None
                   ) -> list[str]:
    info = results.get("diagnostics", {}).get("channels", {}).get(ch, {})
    flags = prior_bound_flags(samples, ch) if samples else []
    if info.get("g_constrained") is False:
        flags.append(G_UNCONSTRAINED)
    if info.get("kappa_s_consistent_with_zero") is True:
        flags.append(KS_ZERO)
    if info.get("kappa_a_upper_limit_only") is True:
        flags.append("&kappa;<sub>a</sub> not resolved (its 90 % interval spans more than a "
                     "decade): read its q95 as an upper limit")
    lo, hi = INFORMATIVE_OPTICAL_DEPTH
    if info.get("optical_depth_regime") == "thin":
        flags.append(f"too dilute: optical depth light-to-wall below {lo:g} in every image; the "
                     "intervals of &kappa;<sub>t</sub> and &kappa;<sub>a</sub> follow the prior "
                     "more than the data (docs/validation.md); add liquid")
    elif info.get("optical_depth_regime") == "dense":
        flags.append(f"too dense: optical depth light-to-wall above {hi:g} in every image; the "
                     "light is hidden and g's interval follows the prior (docs/validation.md); "
                     "dilute")
    if info.get("converged") is False:
        flags.append("sampler not converged: intervals unreliable")
    modes = [m for m in info.get("g_modes") or [] if isinstance(m, dict)]
    if modes:
        both = min(_num(m.get("weight")) or 0.0 for m in modes) >= 0.005
        flags.append("two modes of g (forward and backward scattering fit almost equally well), "
                     "both sampled: " + ", ".join(
                         f"g &asymp; {_fmt(m.get('g_map'), '.2f')} with probability "
                         f"{_fmt(m.get('weight'), '.3f')}" for m in modes)
                     + ("; the 99 % intervals reach into both; add liquid to separate them"
                        if both else "; the smaller holds &lt; 0.5 %, outside the 99 % intervals"))
    if info.get("kappa_s_g_separable") is False:
        flags.append(KS_G_NOT_SEPARABLE)
    flags.extend(_chi2_flags(results, ch, info))
    return flags


def _chi2_flags(results: dict, ch: str, info: dict) -> list[str]:
    """The misfit guard's verdict on channel ``ch`` (results.json ``trust.misfit``); an old
    results.json without it: chi2/pixel outside ``CHI2_WARN``.  chi2/pixel below
    ``CHI2_WARN[0]`` is flagged either way (the noise model overstates the noise)."""
    chi2 = _num(info.get("chi2_per_pixel"))
    check = ((results.get("trust") or {}).get("misfit") or {}).get(ch)
    if chi2 is None:
        return []
    if isinstance(check, dict) and check.get("ok") is False:
        return [f"&chi;&sup2;/pixel = {chi2:.3g}, above the {_fmt(check.get('limit'), '.3g')} "
                "that the noise model allows: the model does not describe the images"]
    if isinstance(check, dict) and chi2 >= CHI2_WARN[0]:
        return []
    if not CHI2_WARN[0] <= chi2 <= CHI2_WARN[1]:
        return [f"&chi;&sup2;/pixel = {chi2:.3g}: the model does not match the data within "
                "the noise model"]
    return []


def _fmt(value: Any, spec: str) -> str:
    v = _num(value)
    return "?" if v is None else format(v, spec)


def _header(results: dict, rpath: Path, folder: str | Path | None = None) -> str:
    wall = _num(results.get("wall_time_s"))
    wall_txt = "&mdash;" if wall is None else f"{wall:.1f} s ({wall / 60:.1f} min)"
    if results.get("date"):
        date = html.escape(str(results["date"]))
    else:
        mtime = _dt.datetime.fromtimestamp(rpath.stat().st_mtime).astimezone()
        date = (f"{mtime:%Y-%m-%d %H:%M:%S %Z} "
                "<span class='muted'>(time results.json was written)</span>")
    version = html.escape(str(results.get("fitmedia_version", "unknown")))
    if version != __version__:
        version += f" <span class='muted'>(report written by {__version__})</span>"
    items = [
        ("Capture", html.escape(str(results.get("name", "")))),
        ("Spec", f"<code>{html.escape(str(results.get('spec', '')))}</code>"),
        ("Output folder", f"<code>{html.escape(str(folder or rpath.parent))}</code>"),
        ("Model", html.escape(str(results.get("model", "")))),
        ("Date of fit", date),
        ("fitmedia version", version),
        ("Wall time", wall_txt),
        ("Seed", _cell(results.get("seed"))),
        ("Channels", html.escape(" ".join(map(str, results.get("channels", []))))),
    ]
    meta = "".join(f"<dt>{k}</dt><dd>{v}</dd>" for k, v in items)
    return (f"<h1>fitmedia report: {html.escape(str(results.get('name', '')))}</h1>\n"
            + _trust_box(results) + f'<dl class="meta">{meta}</dl>\n')


def _model_text(results: dict) -> str:
    """The forward model: ``model``, and ``model_used`` where it differs (``--model auto``)."""
    model, used = results.get("model"), results.get("model_used")
    return str(model) if used in (None, model) else f"{model} (used: {used})"


def _trust_causes(results: dict) -> str:
    """Common causes of an untrusted result, for the model that was used; none where every
    reason is a sampler that did not converge (its reason says what to do)."""
    trust = results.get("trust") or {}
    reasons, kinds = trust.get("reasons") or [], trust.get("reason_kinds")
    chans = (results.get("diagnostics") or {}).get("channels") or {}
    if kinds is not None and len(kinds) == len(reasons):  # since 2026-12-03
        if reasons and set(kinds) == {"sampler"}:
            return ""
    elif reasons and set(reasons) <= set(sampler_reasons(chans)):  # an older results.json
        return ""
    if results.get("model_used", results.get("model")) == "full":
        return ("With full transport: the multiple-scattering term's Monte Carlo error, which "
                "moves the fit by more than its intervals (docs/inference.md, 'Full transport "
                "in the fit'); a wrong geometry or concentration in the spec; a wrong noise "
                "model. See the residual images below.")
    return ("Common causes: multiple scattering, which the single-scattering model leaves out "
            "(dilute further, or fit with <code>--model full</code>; "
            "docs/multiple_scattering.md); a wrong geometry or concentration in the spec; a "
            "wrong noise model. See the residual images below.")


#: the caption under the multiple-scattering table (_ms_section)
_MS_CAPTION = (
    '<p class="muted">Share: the multiple-scattering term over the glow (pixels off the bulb), '
    "with its Monte Carlo standard error; the moves are those of the fit in posterior sd "
    "of log &kappa;<sub>t</sub> and atanh g; the move with other random numbers is in "
    "units of the sd the term's error (its jackknife, included in the intervals) gives "
    "it; a second fit far from the first means the images do not decide between them, "
    "unless its log posterior, beyond the term's own noise over seeds, is more than "
    f"{RESTART_DELTA:g} below the MAP's (the images "
    f"decide against it); where it is more than {RESTART_DELTA:g} above, or where the "
    "first fit's refreshes did not settle but crept towards where the second one ended, "
    "the refreshes went on from "
    "there; where the fit did not describe the images (the misfit guard), it was scanned "
    "from other starts and the better fit kept; the last "
    "refreshes trace more paths, which removes most of the offset the term's own noise "
    "gives the values, and their move is how far that went; a share of that move may "
    "remain, and is in the intervals as the offset's sd (docs/inference.md); with single "
    "scattering, the rise of &chi;&sup2;/pixel is what the term would cause were it in "
    "the images, which the misfit guard sees only where it is well above the guard's "
    "room (docs/results.md, 'The single-scattering check').</p>\n")


def _ms_section(results: dict) -> str:
    """The multiple-scattering term per channel (``--model full`` / ``auto``, and the single-
    scattering check of ``--model single``), as a table."""
    chans = results.get("diagnostics", {}).get("channels", {})
    ms = {ch: info["multiple_scattering"] for ch, info in chans.items()
          if isinstance(info.get("multiple_scattering"), dict)}
    if not ms:
        return ""

    def per_image(v: Any, se: Any = None) -> str:
        if not isinstance(v, list):
            return _cell(v)
        errs = se if isinstance(se, list) and len(se) == len(v) else [None] * len(v)
        return ", ".join(format_sig(x, 3) + ("" if e is None else f" &plusmn; {format_sig(e, 2)}")
                         for x, e in zip(v, errs))

    fields = [
        ("Model used", lambda i, c: _cell(chans[c].get("model_used"))),
        ("Why (--model auto)", lambda i, c: _cell(i.get("auto_reason"))),
        ("Share of the glow (per image)", lambda i, c: per_image(i.get("share"), i.get("share_se"))),
        ("Share at the single-scattering MAP", lambda i, c: per_image(
            i.get("share_at_single_scattering_map"))),
        ("Rise of &chi;&sup2;/pixel were it in the images (single scattering)",
         lambda i, c: _cell(_num(i.get("chi2_excess_if_present")), 3)),
        ("Capture declares a single-scattering render",
         lambda i, c: _yes_no(i.get("capture_declared_single_scattering_render"))),
        ("Refreshes of the term", lambda i, c: _cell(i.get("refreshes"))),
        ("Refreshes settled", lambda i, c: _cell(i.get("converged"))),
        ("Last move [posterior sd]", lambda i, c: _cell(_num((i.get("moves_sd") or [None])[-1]), 3)),
        ("Move with other random numbers", lambda i, c: _cell(_num(i.get("seed_shift_sd")), 3)),
        ("Term's error: sd of log &kappa;<sub>t</sub>, atanh g", lambda i, c: _term_sd_cell(
            i.get("term_sd"))),
        ("Second fit from beyond the MAP: distance [sd]",
         lambda i, c: _cell(_num(i.get("restart_shift_sd")), 3)),
        ("Second fit: &kappa;<sub>t</sub>, g", lambda i, c: _restart_cell(i.get("restart_values"))),
        ("Second fit: log posterior minus the MAP's",
         lambda i, c: _cell(_num(i.get("restart_delta_log_posterior")), 3)),
        ("Refreshes went on from the second fit", lambda i, c: _yes_no(i.get("restart_adopted"))),
        ("Misfit: scanned from other starts, &chi;&sup2;/pixel before, after",
         lambda i, c: _scan_cell(i.get("misfit_scan"))),
        ("Last refreshes: paths per sample pixel", lambda i, c: _cell(i.get("final_paths"))),
        ("Their move: &kappa;<sub>t</sub> [relative], g", lambda i, c: _final_move_cell(
            i.get("final_move"))),
        ("Offset that may remain: sd of log &kappa;<sub>t</sub>, atanh g",
         lambda i, c: _term_sd_cell(i.get("offset_sd"))),
    ]
    rows = [[label] + [get(info, c) for c, info in ms.items()] for label, get in fields]
    rows = [r for r in rows if any(x != "&mdash;" for x in r[1:])]
    return ("<h2>Multiple scattering</h2>\n"
            + _table(["Field"] + [f"Channel {html.escape(c)}" for c in ms], rows)
            + _MS_CAPTION)


def _term_sd_cell(sd: Any) -> str:
    """results.json's ``term_sd`` (sd per sampler coordinate): those of log kappa_t and atanh g."""
    if not isinstance(sd, dict):
        return "&mdash;"
    return ", ".join(_cell(_num(sd.get(k)), 2) for k in ("log_kappa_t", "atanh_g"))


def _final_move_cell(v: Any) -> str:
    """results.json's ``final_move``: kappa_t's relative change (per cent), g's change."""
    if not isinstance(v, dict) or _num(v.get("kappa_t")) is None or _num(v.get("g")) is None:
        return "&mdash;"
    return f"{100 * _num(v['kappa_t']):+.1f} %, {_num(v['g']):+.3f}"


def _yes_no(v: Any) -> str:
    """A flag's cell: yes, no, or a dash where results.json does not have it."""
    return {True: "yes", False: "no"}.get(v, "&mdash;")


def _scan_cell(v: Any) -> str:
    """The misfit scan's cell (results.json's ``misfit_scan``): chi2/pixel before and after,
    and whether its fit was kept."""
    if not isinstance(v, dict):
        return "&mdash;"
    return (f"{_cell(_num(v.get('chi2_per_pixel_before')), 3)}, "
            f"{_cell(_num(v.get('chi2_per_pixel_after')), 3)} "
            f"({'kept' if v.get('used') else 'not kept'})")


def _restart_cell(v: Any) -> str:
    if not isinstance(v, dict):
        return "&mdash;"
    return f"{_cell(_num(v.get('kappa_t')), 4)}, {_cell(_num(v.get('g')), 3)}"


def _trust_box(results: dict) -> str:
    """results.json's ``trust`` at the top of the report: a red box with the reasons when the
    misfit guard fired, a green line when it passed, its notes (kappa_s and g not separately
    measured) below."""
    trust = results.get("trust")
    if not isinstance(trust, dict):
        return ('<div class="warn" id="trust">This results.json has no <code>trust</code> '
                "verdict (written by an older fitmedia): the misfit guard was not applied; "
                "check &chi;&sup2;/pixel under Sampler diagnostics.</div>\n")
    model = html.escape(_model_text(results))
    notes = "".join(f'<div class="warn"><b>Note:</b> {html.escape(str(n))}</div>\n'
                    for n in trust.get("notes") or [])
    if trust.get("ok") is False:
        items = "".join(f"<li>{html.escape(str(r))}</li>" for r in trust.get("reasons") or [])
        return ('<div class="untrusted" id="trust"><h2>Do not use these values</h2>\n'
                f"<p>Model: <b>{model}</b>. The values below are biased or uncertain by an "
                "amount their intervals do not show (<code>fitmedia fit</code> exited with "
                f"code 1).</p>\n<ul>{items}</ul>\n<p>{_trust_causes(results)}</p></div>\n" + notes)
    return (f'<div class="trusted" id="trust"><b>Misfit check passed</b> (model <b>{model}</b>): '
            "&chi;&sup2;/pixel at the MAP within what the noise model allows in every channel "
            "and image.</div>\n" + notes)


def _warnings(results: dict, samples: dict[str, np.ndarray]) -> str:
    notes = results.get("notes") or []
    lines = [f'<div class="warn"><b>Note:</b> {html.escape(str(n))}</div>' for n in notes]
    diag = results.get("diagnostics", {})
    if diag.get("converged") is False:
        bad = [c for c, i in diag.get("channels", {}).items() if i.get("converged") is False]
        lines.append('<div class="warn"><b>Warning:</b> the sampler did not converge'
                     + (f" in channel(s) {html.escape(', '.join(bad))}" if bad else "")
                     + "; the intervals are not reliable (see Sampler diagnostics).</div>")
    if "converged" not in diag:
        lines.append('<div class="warn"><b>No sampler ran</b> (MAP only, <code>--no-mcmc</code>): '
                     "the table gives MAP values without uncertainties.</div>")
    for ch in results.get("channels", []):
        for flag in _channel_flags(results, ch, samples):
            if not flag.startswith("sampler") and flag != KS_G_NOT_SEPARABLE:  # in the trust box
                lines.append(f'<div class="warn"><b>Channel {html.escape(ch)}:</b> {flag}</div>')
    return "\n".join(lines)


def _estimates(results: dict, samples: dict[str, np.ndarray]) -> str:
    params = results.get("parameters", {})
    chans = results.get("channels") or list(params.get("kappa_s", {}))
    sampled = any("median" in params.get(q, {}).get(c, {}) for q in QUANTITIES for c in chans)
    est = "Median" if sampled else "MAP"
    header = (f"<tr><th>Quantity</th><th>Unit</th><th>{est}</th>"
              + ("<th>68 % interval<br>(q16 &ndash; q84)</th><th>90 % interval<br>"
                 "(q05 &ndash; q95)</th><th>MAP</th>" if sampled else "") + "</tr>\n")
    ncol = 6 if sampled else 3
    rows = []
    for ch in chans:
        flags = "".join(f'<span class="flag">{f}</span>'
                        for f in _channel_flags(results, ch, samples))
        rows.append(f'<tr class="chan"><th colspan="{ncol}">Channel {html.escape(ch)}{flags}'
                    "</th></tr>\n")
        info = results.get("diagnostics", {}).get("channels", {}).get(ch, {})
        ridge = info.get("kappa_s_g_separable") is False
        for q in QUANTITIES + ("kappa_s_reduced",):
            entry = params.get(q, {}).get(ch)
            if entry is None:
                continue
            units = [("1/mm", 1.0), ("1/m", 1000.0)] if q in KAPPAS else [("unitless", 1.0)]
            for unit, scale in units:
                c = format_estimate(entry, scale)
                if entry.get("source") == "laplace" and "q05" in entry:  # kappa_s', --no-mcmc
                    lo, hi = (format_sig(entry[k] * scale, 3) for k in ("q05", "q95"))
                    c["estimate"] += f' <span class="txt">(90 %: {lo} &ndash; {hi}, Laplace)</span>'
                classes = (["permetre"] if scale != 1.0 else []) + (
                    ["alone"] if ridge and q in NOT_MEASURED_ALONE else [])
                if "alone" in classes:
                    c["estimate"] += ' <span class="txt">(not separately measured)</span>'
                cls = f' class="{" ".join(classes)}"' if classes else ""
                cells = [c["estimate"]] + ([c["q68"], c["q90"], c["map"]] if sampled else [])
                rows.append(f"<tr{cls} data-channel=\"{html.escape(ch)}\" data-quantity=\"{q}\" "
                            f"data-unit=\"{unit}\"><td>{LABELS[q]} <code>{q}</code></td>"
                            f"<td>{unit}</td>" + "".join(f'<td class="num">{x}</td>' for x in cells)
                            + "</tr>\n")
    concs = [i.get("concentration") for i in results.get("images", [])]
    conc_txt = ", ".join(format_sig(_num(c), 3) for c in concs)
    return (
        "<h2>Estimates</h2>\n"
        "<p><b>All values are of the undiluted liquid (concentration 1)</b>"
        + (f"; the photographed dilutions had concentrations {conc_txt}" if concs else "")
        + ". &kappa; in 1/mm and in 1/m (1/m = 1/mm &times; 1000); albedo and g are unitless. "
        + "&kappa;<sub>s</sub>&prime; = &kappa;<sub>s</sub>(1&minus;g) is always given: in a "
          "dense medium the images constrain it and &kappa;<sub>t</sub>, not &kappa;<sub>s</sub> "
          "and g on their own (the similarity relation). "
        + ("Median of the posterior with its central 68 % and 90 % intervals; MAP = maximum "
           "a posteriori. Each interval holds both the posterior's under the albedo prior (half "
           "flat in log &kappa;<sub>a</sub>, half uniform in the albedo) and the one under its "
           "uniform half alone: where the images leave &kappa;<sub>a</sub> unresolved, the "
           "first crowds &kappa;<sub>a</sub> towards 0 (docs/inference.md)." if sampled else
           "No sampler ran: MAP (maximum a posteriori) values only, no intervals.")
        + "</p>\n<table>" + header + "".join(rows) + "</table>\n")


def _corner_section(results: dict, samples: dict[str, np.ndarray]) -> str:
    from .plots import channel_corner_plots

    parts = ["<h2>Posterior (corner plots)</h2>\n"]
    for ch, uri, n, dropped in channel_corner_plots(results, samples):
        note = (f" {dropped} of {n} samples left out (a plotted value not finite)."
                if dropped else "")
        parts.append(f'<h3>Channel {html.escape(ch)}</h3>\n<img alt="corner plot channel '
                     f'{html.escape(ch)}" src="{uri}">\n<p class="muted">{n} samples. Dashed '
                     "lines: 16, 50 and 84 % quantiles; blue lines: MAP; contours: 0.5, 1, 1.5 "
                     f"and 2 &sigma; of a 2-d normal; axes cover the central 99.5 %.{note}</p>\n")
    if len(parts) == 1:
        parts.append("<p>No posterior samples (no sampler ran, <code>--no-mcmc</code>): "
                     "no corner plots.</p>\n")
    return "".join(parts)


def _images_section(results: dict, images: dict[str, np.ndarray]) -> str:
    from .plots import fit_image_plots

    rows = [[str(i), "<br>".join(f"<code>{html.escape(str(p))}</code>" for p in im.get("path", [])),
             format_sig(_num(im.get("concentration")), 4), _cell(im.get("n_saturated")),
             _cell(im.get("n_masked"))] for i, im in enumerate(results.get("images", []))]
    parts = ["<h2>Data, model and residuals</h2>\n",
             _table(["#", "Path(s)", "Concentration", "Saturated pixels", "Masked pixels"], rows,
                    num_from=2),
             f"<p>Model: <b>{html.escape(_model_text(results))}</b>. Per channel: data and "
             "model at the MAP on a shared logarithmic colour scale (values below its lower end "
             "drawn darkest)"
             + ("; the model's single- and multiple-scattering parts beside it"
                if any(k.startswith("ms_") for k in images) else
                " (this model gives no separate multiple-scattering part)")
             + "; residual (data &minus; model)/&sigma; with "
             + ("&sigma;&sup2; the fit's own variance of each pixel (camera noise at the model"
                + (", plus the multiple-scattering term's Monte Carlo variance"
                   if any(k.startswith("ms_") for k in images) else "") + ")"
                if any(k.startswith("var_") for k in images) else
                "&sigma;&sup2; = gain&middot;model + read_var")
             + ", scale fixed at &plusmn;5. Grey: pixels not used in the fit.</p>\n"]
    for i, uri in fit_image_plots(results, images):
        parts.append(f'<img alt="data, model and residual of image {i}" src="{uri}">\n' if uri
                     else f"<p class='bad'>Image {i}: fit_images.npz lacks its data, model or "
                     "valid array.</p>\n")
    return "".join(parts)


def _preview_section(results: dict) -> str:
    """The spec's geometry over each image (fitmedia.preview; docs/preview.md), or one line
    saying why not (the spec or an image not reachable from here)."""
    from ..preview import report_section

    return report_section(results)


_DIAG_KEYS = ("converged", "reason", "n_steps", "autocorr_time", "acceptance_fraction", "burn_in",
              "thin", "n_samples", "chi2_per_pixel", "n_pixels", "map_log_posterior",
              "n_evals_map", "g_constrained", "kappa_s_consistent_with_zero", "model_used",
              "multiple_scattering")  # the last two: _ms_section
_CALIB_KEYS = ("brightness", "brightness_calibrated", "brightness_calibration_rel_sd")


def _diagnostics_section(results: dict) -> str:
    diag = results.get("diagnostics", {})
    chans = diag.get("channels", {})
    parts = ["<h2>Sampler diagnostics</h2>\n"]
    if "converged" in diag:
        parts.append(_table(["Converged", "Steps", "Max. autocorrelation time [steps]",
                             "Mean acceptance fraction"],
                            [[_cell(diag.get("converged")), _cell(diag.get("n_steps")),
                              _cell(diag.get("autocorr_time_max"), 3),
                              _cell(diag.get("acceptance_fraction"), 3)]], num_from=1))
    else:
        parts.append("<p>No sampler ran (MAP only).</p>\n")
    names: list[str] = []
    for info in chans.values():
        for n in (info.get("autocorr_time") or {}):
            if n not in names:
                names.append(n)

    def steps_per_tau(info: dict) -> float | None:
        taus = [t for t in (_num(x) for x in (info.get("autocorr_time") or {}).values()) if t]
        steps = _num(info.get("n_steps"))
        return steps / max(taus) if steps is not None and taus else None

    fields: list[tuple[str, Any]] = [
        ("Converged", lambda i: _cell(i.get("converged"))),
        ("Reason", lambda i: _cell(i.get("reason"))),
        ("Steps", lambda i: _cell(i.get("n_steps"))),
    ] + [(f"&tau; <code>{html.escape(n)}</code> [steps]",
          lambda i, n=n: _cell(_num((i.get("autocorr_time") or {}).get(n)), 3)) for n in names] + [
        ("Chain length / max &tau;", lambda i: _cell(steps_per_tau(i), 3)),
        ("Acceptance fraction", lambda i: _cell(_num(i.get("acceptance_fraction")), 3)),
        ("Burn-in [steps]", lambda i: _cell(i.get("burn_in"))),
        ("Thin [steps]", lambda i: _cell(i.get("thin"))),
        ("Samples kept", lambda i: _cell(i.get("n_samples"))),
        ("&chi;&sup2;/pixel at the MAP", lambda i: _cell(_num(i.get("chi2_per_pixel")), 4)),
        ("Pixels fitted", lambda i: _cell(i.get("n_pixels"))),
        ("MAP log posterior", lambda i: _cell(_num(i.get("map_log_posterior")), 8)),
        ("MAP evaluations", lambda i: _cell(i.get("n_evals_map"))),
        ("g constrained", lambda i: _cell(i.get("g_constrained"))),
        ("&kappa;<sub>s</sub> consistent with zero", lambda i: (
            "&mdash;" if i.get("kappa_s_consistent_with_zero") is None
            else "yes" if i["kappa_s_consistent_with_zero"] else "no")),
    ]
    rows = [[label] + [get(info) for info in chans.values()] for label, get in fields]
    if "converged" not in diag:  # MAP only: leave out the sampler's rows
        rows = [r for r in rows if any(c != "&mdash;" for c in r[1:])]
    parts.append("<h3>Per channel</h3>\n"
                 + _table(["Field"] + [f"Channel {html.escape(c)}" for c in chans], rows))
    parts.append('<p class="muted">&tau;: integrated autocorrelation time in steps, per sampled '
                 "(unconstrained) parameter; &chi;&sup2;/pixel at the MAP (about 1 when the "
                 "noise model holds).</p>\n")
    extra = [[html.escape(ch), html.escape(k), _cell(v)] for ch, info in chans.items()
             for k, v in info.items() if k not in _DIAG_KEYS + _CALIB_KEYS]
    if extra:
        parts.append("<h3>Other diagnostics</h3>\n" + _table(["Channel", "Field", "Value"], extra,
                                                             num_from=2))
    return "".join(parts)


def _calibration_section(results: dict, samples: dict[str, np.ndarray]) -> str:
    cal = results.get("calibration", {})
    chans = results.get("diagnostics", {}).get("channels", {})
    rows = []
    for ch in results.get("channels", []):
        info = chans.get(ch, {})
        b = samples.get(f"{ch}/brightness")
        post = "&mdash;"
        if b is not None and len(b):
            q = np.percentile(b, [16, 50, 84])
            post = f"{format_sig(q[1])} ({format_sig(q[0])} &ndash; {format_sig(q[2])})"
        rows.append([html.escape(ch),
                     _cell(_num(cal.get("brightness", {}).get(ch, info.get("brightness"))), 5),
                     _cell(_num(info.get("brightness_calibrated")), 5),
                     _cell(_num(info.get("brightness_calibration_rel_sd")), 3), post])
    noise = results.get("noise", {})
    nrows = []
    for ch, nz in noise.get("per_channel", {}).items():
        rv = _num(nz.get("read_var"))
        nrows.append([html.escape(ch), _cell(_num(nz.get("gain"))), _cell(rv),
                      _cell(None if rv is None or rv < 0 else math.sqrt(rv), 3)])
    return (
        "<h2>Calibration and noise model</h2>\n"
        "<p>Light brightness source: "
        f"<b>{html.escape(str(cal.get('brightness_source', 'unknown')))}"
        "</b>. Brightness in image units (bulb: radiance in the water; spot: radiant intensity "
        "&times; mm&sup2;).</p>\n"
        + _table(["Channel", "Brightness (fixed, or MAP when fitted)", "Clear-water calibration",
                  "Calibration rel. s.d.", "Posterior median (16 &ndash; 84 %)"], rows,
                 drop_empty=True)
        + f"<p>Noise model: variance = gain &middot; mean + read_var (image units); source: "
          f"<b>{html.escape(str(noise.get('source', 'unknown')))}</b>.</p>\n"
        + _table(["Channel", "Gain [image units]", "read_var [image units&sup2;]",
                  "Read noise &sigma; [image units]"], nrows))


# ---------------------------------------------------------------------------------------------


def render_report(out_dir: str | Path, folder: str | Path | None = None) -> str:
    """The report's HTML text for the fit output in ``out_dir`` (see :func:`write_report`)."""
    out = Path(out_dir)
    results, samples, images = load_outputs(out)
    now = _dt.datetime.now().astimezone()
    body = "\n".join([
        _header(results, out / "results.json", folder),
        _warnings(results, samples),
        _estimates(results, samples),
        _corner_section(results, samples),
        _images_section(results, images),
        _ms_section(results),
        _preview_section(results),
        _diagnostics_section(results),
        _calibration_section(results, samples),
        f'<p class="muted">Report written {now:%Y-%m-%d %H:%M:%S %Z} by fitmedia {__version__} '
        "from results.json, samples.npz and fit_images.npz.</p>",
    ])
    title = html.escape(f"fitmedia report: {results.get('name', '')}")
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            f"<title>{title}</title>\n<style>{CSS}</style>\n</head>\n<body>\n{body}\n</body>\n"
            "</html>\n")


def write_report(out_dir: str | Path, folder: str | Path | None = None) -> Path:
    """Write ``out_dir/report.html`` from the fit output in ``out_dir`` and return its path.

    Parameters
    ----------
    out_dir : str or Path
        A folder written by ``fitmedia fit SPEC --out DIR``: ``results.json``,
        ``samples.npz`` and ``fit_images.npz`` (CAPTURE_SPEC.md).  A MAP-only fit
        (``--no-mcmc``, no posterior samples) gives a report without intervals and
        corner plots.
    folder : str or Path, optional
        The folder the report names as the output folder (default ``out_dir``): ``fit``
        writes into a staging folder that is moved to ``--out`` at the end.

    Returns
    -------
    Path
        The report, one self-contained HTML file (figures embedded as base64 PNG),
        written atomically.

    Raises
    ------
    InputError
        One of the three files is missing or unreadable; the message names it.
    """
    text = render_report(out_dir, folder)
    path = Path(out_dir) / "report.html"
    atomic_write_text(path, text.encode("ascii", "xmlcharrefreplace").decode("ascii"))
    return path

"""Figures of the HTML report (posterior corner plots, data / model / residual images) and
the checks on the posterior samples that go with them.

Every figure is a bare :class:`matplotlib.figure.Figure` rendered with the Agg
canvas (no pyplot state, no backend switch in the caller's process) and returned
as a base64 PNG ``data:`` URI, so the report is one self-contained file.
matplotlib and corner are imported inside the functions that need them.
"""

from __future__ import annotations

import base64
import io
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.figure import Figure

RESIDUAL_LIMIT = 5.0  # the residual colour scale is fixed at +-5 standard deviations
LOG_RANGE = 1e-5      # darkest shown value of the data/model scale, relative to the brightest
INVALID_GREY = "0.6"  # colour of pixels that the fit did not use
DPI = 90


def new_figure(width_in: float, height_in: float, *, constrained: bool = True) -> Figure:
    """A figure on the Agg canvas, independent of pyplot and of the active backend."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=DPI,
                 layout="constrained" if constrained else None)
    FigureCanvasAgg(fig)
    return fig


def figure_to_data_uri(fig: Figure) -> str:
    """Render ``fig`` as PNG and return it as a ``data:image/png;base64,...`` URI."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


# ---------------------------------------------------------------------------------------------
# corner plots


@dataclass
class Axis:
    """One corner-plot axis: the plotted values, the plotted MAP value and the label."""

    values: np.ndarray
    map_value: float | None
    label: str


def _spans_decades(x: np.ndarray) -> bool:
    """True when the central 90 % of the positive values ``x`` spans more than a factor 10."""
    lo, hi = np.percentile(x, [5, 95])
    return bool(lo > 0 and hi / lo > 10.0)


def _log10(x: np.ndarray | float | None, floor: float = 1e-300) -> np.ndarray | float | None:
    if x is None:
        return None
    return np.log10(np.maximum(x, floor))


def corner_axes(samples: dict[str, np.ndarray], map_values: dict[str, float | None]
                ) -> list[Axis]:
    """Readable axes for the corner plot of one channel.

    Parameters
    ----------
    samples : dict of str to ndarray of shape (n,)
        Physical samples ``kappa_t`` (1/mm), ``albedo``, ``g`` and optionally ``brightness``.
    map_values : dict of str to float or None
        The MAP estimate of the same quantities (drawn as lines), None where unknown.

    Returns
    -------
    list of Axis
        ``kappa_t`` in 1/mm, or log10 of it when the posterior spans decades; ``albedo``,
        or log10(1 - albedo) when the albedo is above 0.99 (milk: 0.9999) or 1 - albedo
        spans decades, or log10 albedo when it is below 0.01 or spans decades; ``g``;
        and the brightness (image units) when it was sampled.
    """
    axes = []
    kt = np.asarray(samples["kappa_t"], float)
    if _spans_decades(kt):
        axes.append(Axis(np.log10(kt), _log10(map_values.get("kappa_t")),
                         r"$\log_{10}\,\kappa_t$  ($\kappa_t$ in 1/mm)"))
    else:
        axes.append(Axis(kt, map_values.get("kappa_t"), r"$\kappa_t$  [1/mm]"))
    a = np.asarray(samples["albedo"], float)
    a_map = map_values.get("albedo")
    if np.median(a) > 0.99 or np.median(a) > 0.5 and _spans_decades(1.0 - a):
        r_map = None if a_map is None else _log10(1.0 - a_map, 1e-16)
        axes.append(Axis(_log10(1.0 - a, 1e-16), r_map,
                         r"$\log_{10}(1-\mathrm{albedo})$"))
    elif np.median(a) < 0.01 or np.median(a) <= 0.5 and _spans_decades(a):
        axes.append(Axis(_log10(a), _log10(a_map), r"$\log_{10}\,\mathrm{albedo}$"))
    else:
        axes.append(Axis(a, a_map, "albedo  (unitless)"))
    axes.append(Axis(np.asarray(samples["g"], float), map_values.get("g"),
                     "g  (unitless)"))
    if "brightness" in samples:
        b = np.asarray(samples["brightness"], float)
        if _spans_decades(b):
            axes.append(Axis(np.log10(b), _log10(map_values.get("brightness")),
                             r"$\log_{10}$ brightness  (image units)"))
        else:
            axes.append(Axis(b, map_values.get("brightness"), "brightness  [image units]"))
    return axes


def _ranges(data: np.ndarray) -> list[tuple[float, float]]:
    """Plot ranges per column: the central 99.5 % of the samples plus 5 % either side (a
    few stragglers of a short chain do not squash the plot), widened where a column is
    (nearly) constant, which corner would otherwise refuse."""
    out = []
    for col in data.T:
        lo, hi = (float(v) for v in np.percentile(col, [0.25, 99.75]))
        lo, hi = lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo)
        if not hi > lo:
            pad = 1e-6 * max(abs(lo), 1.0)
            lo, hi = lo - pad, hi + pad
        out.append((lo, hi))
    return out


def corner_figure(samples: dict[str, np.ndarray], map_values: dict[str, float | None],
                  title: str) -> tuple[Figure, int]:
    """Corner plot of one channel's posterior.

    Parameters
    ----------
    samples, map_values
        See :func:`corner_axes`.
    title : str
        Figure title.

    Returns
    -------
    fig : Figure
    n_dropped : int
        Samples left out because a plotted value was not finite.
    """
    with warnings.catch_warnings():
        # arviz (imported by corner) announces its refactor once a day with a FutureWarning
        warnings.filterwarnings("ignore", category=FutureWarning, module=r"arviz(\..*)?$")
        import corner

    axes = corner_axes(samples, map_values)
    data = np.column_stack([ax.values for ax in axes])
    finite = np.all(np.isfinite(data), axis=1)
    n_dropped = int(np.sum(~finite))
    data = data[finite]
    k = data.shape[1]
    fig = new_figure(2.9 * k + 0.8, 2.9 * k + 0.8, constrained=False)
    truths = [ax.map_value if ax.map_value is not None and np.isfinite(ax.map_value) else None
              for ax in axes]
    few = len(data) < 50
    corner.corner(
        data, fig=fig, bins=10 if few else 25, smooth=None if few else 1.0, range=_ranges(data),
        labels=[ax.label for ax in axes], label_kwargs={"fontsize": 10},
        quantiles=[0.16, 0.5, 0.84], truths=truths, truth_color="tab:blue",
        plot_contours=not few, plot_density=not few, quiet=True, max_n_ticks=4,
        use_math_text=True, labelpad=0.08,
    )
    fig.suptitle(title, fontsize=11)
    return fig, n_dropped


# ---------------------------------------------------------------------------------------------
# data / model / residual images


def log_range(data: np.ndarray, model: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
    """The shared (vmin, vmax) of the logarithmic data/model colour scale of one channel.

    vmax is the brightest valid model or data value (the data's 99.99th percentile, so
    a hot pixel does not set it); vmin the 1st percentile of the positive valid model
    values, but at most ``LOG_RANGE`` below vmax.  Data below vmin (noise, negative
    values) are drawn with the darkest colour.
    """
    d = data[valid]
    m = model[valid]
    hi_candidates = [float(np.max(m))] if m.size else []
    if d.size:
        hi_candidates.append(float(np.percentile(d, 99.99)))
    vmax = max([v for v in hi_candidates if np.isfinite(v)] + [0.0])
    if vmax <= 0:
        vmax = 1.0
    pos = m[m > 0]
    vmin = float(np.percentile(pos, 1)) if pos.size else 0.0
    vmin = min(max(vmin, vmax * LOG_RANGE), vmax * 0.5)
    return vmin, vmax


def standardised_residual(data: np.ndarray, model: np.ndarray, gain: float, read_var: float
                          ) -> np.ndarray:
    """(data - model) / sqrt(gain * model + read_var), the fit's noise model at the model."""
    var = gain * np.maximum(model, 0.0) + read_var
    with np.errstate(divide="ignore", invalid="ignore"):
        return (data - model) / np.sqrt(var)


def image_figure(data: np.ndarray, model: np.ndarray, valid: np.ndarray, channels: list[str],
                 noise: dict[str, dict], title: str, ms: np.ndarray | None = None,
                 var: np.ndarray | None = None) -> tuple[Figure, dict[str, float]]:
    """Data, model and standardised residual of one image, one row per channel; with ``ms``
    also the model's single- and multiple-scattering parts (model - ms and ms).

    Parameters
    ----------
    data, model : ndarray of shape (H, W, C)
        Exposure-normalised image and the fitted model image (linear image units).
    valid : ndarray of bool, shape (H, W, C)
        Pixels used in the fit; the others are drawn grey.
    channels : list of str
        Channel names of the last axis.
    noise : dict
        ``{channel: {"gain": float, "read_var": float}}`` (results.json ``noise.per_channel``).
    title : str
        Figure title.
    ms : ndarray of shape (H, W, C), optional
        The multiple-scattering part of ``model`` (fit_images.npz ``ms_{i}``).
    var : ndarray of shape (H, W, C), optional
        The fit's own variance per pixel (fit_images.npz ``var_{i}``: camera noise per pixel
        plus a Monte Carlo model's variance); without it, ``noise``'s scalar model.

    Returns
    -------
    fig : Figure
    chi2 : dict of str to float
        Mean squared standardised residual over the valid pixels, per channel
        (NaN where no pixel is valid).
    """
    from matplotlib import colormaps
    from matplotlib.colors import LogNorm, Normalize

    h, w = data.shape[:2]
    n = len(channels)
    ncol = 3 if ms is None else 5
    panel_w = 3.6 if ms is None else 2.8
    fig = new_figure(ncol * panel_w + 1.6, n * (panel_w * h / w + 0.55) + 0.5)
    axes = fig.subplots(n, ncol, squeeze=False)
    cmap = colormaps["magma"].with_extremes(bad=INVALID_GREY)
    rcmap = colormaps["RdBu_r"].with_extremes(bad=INVALID_GREY)
    chi2 = {}
    for k, ch in enumerate(channels):
        d, m, v = data[..., k], model[..., k], valid[..., k] & np.isfinite(data[..., k])
        vmin, vmax = log_range(d, m, v)
        norm = LogNorm(vmin=vmin, vmax=vmax, clip=True)
        nz = noise.get(ch, {})
        gain, read_var = float(nz.get("gain", np.nan)), float(nz.get("read_var", np.nan))
        if var is None:
            r = standardised_residual(d, m, gain, read_var)
        else:
            with np.errstate(divide="ignore", invalid="ignore"):
                r = (d - m) / np.sqrt(var[..., k])
        rv = r[v & np.isfinite(r)]
        chi2[ch] = float(np.mean(rv**2)) if rv.size else float("nan")
        n_bad = int(np.sum(~v))
        panels = [(d, "data"), (m, "model")]
        if ms is not None:
            panels += [(m - ms[..., k], "single scattering"), (ms[..., k], "multiple scattering")]
        for j, (img, name) in enumerate(panels):
            shown = np.ma.masked_array(np.maximum(img, vmin), mask=~v)
            im = axes[k, j].imshow(shown, cmap=cmap, norm=norm, interpolation="nearest")
            axes[k, j].set_title(f"{ch}: {name}", fontsize=10)
        cb = fig.colorbar(im, ax=axes[k, :-1], shrink=0.9, extend="min", pad=0.01)
        cb.set_label("value [image units]\n(log scale, shared)", fontsize=8)
        shown_r = np.ma.masked_array(np.nan_to_num(r), mask=~(v & np.isfinite(r)))
        imr = axes[k, -1].imshow(shown_r, cmap=rcmap,
                                 norm=Normalize(-RESIDUAL_LIMIT, RESIDUAL_LIMIT),
                                 interpolation="nearest")
        # the grey count on a line of its own: on one line the title ran into the
        # colour bar beside it (seen at 5 panels a row, 2026-12-06)
        axes[k, -1].set_title(f"{ch}: residual, χ²/pixel = {chi2[ch]:.3g}"
                             + (f"\n{n_bad} px grey (not fitted)" if n_bad else ""), fontsize=10)
        cbr = fig.colorbar(imr, ax=axes[k, -1], shrink=0.9, extend="both", pad=0.01)
        cbr.set_label("(data − model) / σ\n[standard deviations]", fontsize=8)
        for ax in axes[k]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle(title, fontsize=11)
    return fig, chi2


# ---------------------------------------------------------------------------------------------
# the report's figures from the fit output


def finite_or_none(x: object) -> float | None:
    """``float(x)``, or None where that fails or is not finite."""
    try:
        v = float(x)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return v if np.isfinite(v) else None


def prior_bound_flags(samples: dict[str, np.ndarray], ch: str) -> list[str]:
    """Warnings (HTML) for the parameters of channel ``ch`` whose MAP or posterior median
    lies at a bound of the prior (within 2 % of the prior's range).

    Reads ``names``, ``{ch}/map_unconstrained`` and ``{ch}/unconstrained`` of samples.npz
    and the bounds in :mod:`fitmedia.inference.params`.
    """
    from ..inference.params import ATANH_G_BOUNDS, LOG_KT_BOUNDS, LOGIT_ALBEDO_BOUNDS

    bounds = {"log_kappa_t": LOG_KT_BOUNDS, "logit_albedo": LOGIT_ALBEDO_BOUNDS,
              "atanh_g": ATANH_G_BOUNDS}
    names = [str(n) for n in samples.get("names", [])]
    points = [samples.get(f"{ch}/map_unconstrained")]
    if f"{ch}/unconstrained" in samples and len(samples[f"{ch}/unconstrained"]):
        points.append(np.median(samples[f"{ch}/unconstrained"], axis=0))
    flags = []
    for k, name in enumerate(names):
        if name not in bounds:
            continue
        lo, hi = bounds[name]
        vals = [float(p[k]) for p in points if p is not None and len(p) > k]
        at = [b for b in (lo, hi) if any(abs(v - b) < 0.02 * (hi - lo) for v in vals)]
        if name == "logit_albedo" and hi in at:
            flags.append("albedo at the prior's upper bound: &kappa;<sub>a</sub> is below what "
                         "the data resolve; read its q95 as an upper limit")
        elif at:
            flags.append(f"<code>{name}</code> at the prior's bound {at[0]:.3g}: "
                         "not constrained by the data there")
    return flags


def channel_corner_plots(results: dict, samples: dict[str, np.ndarray]
                         ) -> list[tuple[str, str, int, int]]:
    """Corner plots of the channels that have posterior samples.

    Parameters
    ----------
    results : dict
        results.json; the MAP values are drawn as lines.
    samples : dict of str to ndarray
        samples.npz (keys ``"{channel}/{quantity}"``).

    Returns
    -------
    list of (channel, PNG data URI, number of samples, number left out as not finite)
    """
    out = []
    params = results.get("parameters", {})
    for ch in results.get("channels", []):
        phys = {q: samples[f"{ch}/{q}"] for q in ("kappa_t", "albedo", "g", "brightness")
                if f"{ch}/{q}" in samples}
        if not all(q in phys and len(phys[q]) for q in ("kappa_t", "albedo", "g")):
            continue
        maps = {q: finite_or_none(params.get(q, {}).get(ch, {}).get("map"))
                for q in ("kappa_t", "albedo", "g")}
        maps["brightness"] = finite_or_none(results.get("diagnostics", {}).get("channels", {})
                                            .get(ch, {}).get("brightness"))
        n = len(phys["kappa_t"])
        fig, dropped = corner_figure(phys, maps, f"Channel {ch}: posterior of the undiluted liquid")
        out.append((str(ch), figure_to_data_uri(fig), n, dropped))
    return out


def fit_image_plots(results: dict, images: dict[str, np.ndarray]) -> list[tuple[int, str | None]]:
    """Data / model / residual figure of each fitted image.

    Parameters
    ----------
    results : dict
        results.json (noise model, concentrations).
    images : dict of str to ndarray
        fit_images.npz: ``data_{i}``, ``model_{i}``, ``valid_{i}`` of shape (H, W, C) and
        ``channels``; optionally ``ms_{i}``, the multiple-scattering part of ``model_{i}``
        (a model that has one), shown beside it with the single-scattering part, and
        ``var_{i}``, the fit's variance per pixel (the residual's sigma^2; fits written
        before 2026-12-02 lack it and get results.json's scalar noise model).

    Returns
    -------
    list of (image index, PNG data URI or None where an array is missing)
    """
    chans = [str(c) for c in images.get("channels", results.get("channels", []))]
    noise = results.get("noise", {}).get("per_channel", {})
    info = results.get("images", [])
    n_img = sum(1 for k in images if k.startswith("data_"))
    out: list[tuple[int, str | None]] = []
    for i in range(n_img):
        keys = (f"data_{i}", f"model_{i}", f"valid_{i}")
        if not all(k in images for k in keys):
            out.append((i, None))
            continue
        conc = finite_or_none(info[i].get("concentration")) if i < len(info) else None
        title = f"Image {i}" + ("" if conc is None else f" (concentration {conc:.4g})")
        fig, _ = image_figure(images[keys[0]], images[keys[1]], images[keys[2]].astype(bool),
                              chans, noise, title, ms=images.get(f"ms_{i}"),
                              var=images.get(f"var_{i}"))
        out.append((i, figure_to_data_uri(fig)))
    return out

"""Share of multiple scattering in the glow of the canonical capture (docs/multiple_scattering.md).

For each liquid at the dilutions of Narasimhan et al. (2006) in the 23 l tank, render the
canonical bulb capture (capture_specs/bulb.yaml at 96 x 72 px) with Mitsuba 3 twice with the
same random numbers: single scattering (max_depth = single_scattering_depth) and all orders
(max_depth = -1).  The share of multiple scattering is (all - single) / all, summed over the
glow (pixels that do not see the bulb and whose value is above 1e-3 of the brightest glow
pixel), per channel.  The Monte Carlo standard error comes from 8 independent batches.

Regenerate:  python docs/figures/make_ms_share.py   (writes ms_share.json, ms_share_maps.npz and
ms_share.png here; ``--plot-only`` redraws the figure from the two saved files)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
CASES = [("Lowfat Milk", 16), ("Espresso", 8), ("Merlot", 1500), ("White Grapefruit Juice", 160)]
SPP = 1024


def main() -> None:
    import yaml

    from fitmedia.forward.mitsuba import MitsubaModel, single_scattering_depth
    from fitmedia.medium import medium_by_name
    from fitmedia.spec import parse_spec

    raw = yaml.safe_load((ROOT / "capture_specs" / "bulb.yaml").read_text())
    raw["camera"].update(size=[96, 72], fx=180.0, fy=180.0, cx=48.0, cy=36.0)
    spec = parse_spec(raw, require_images=False)
    single = MitsubaModel(spec, None, spp=SPP, max_depth=single_scattering_depth(spec), seed=7)
    full = MitsubaModel(spec, None, spp=SPP, max_depth=-1, seed=7)
    direct = MitsubaModel(spec, None, spp=64, max_depth=single_scattering_depth(spec) - 1, seed=7)
    out, maps = {}, {}
    for name, ml in CASES:
        m = medium_by_name(name).scaled(ml / 23000)
        args = (m.kappa_a, m.kappa_s, m.g, np.ones(3))
        bulb = direct.render(*args) > 0
        s_b = single._batches(*args, 8)  # (8, H, W, 3): independent batches, same seeds in both
        f_b = full._batches(*args, 8)
        s_img, f_img = s_b.mean(0), f_b.mean(0)
        res = {}
        for k, ch in enumerate("RGB"):
            if m.kappa_s[k] == 0:
                res[ch] = {"share": None, "note": "kappa_s = 0: no glow"}
                continue
            glow = ~bulb[..., k] & (s_img[..., k] > 1e-3 * s_img[..., k][~bulb[..., k]].max())
            # batches: share per batch for the error
            share = 1 - s_img[..., k][glow].sum() / f_img[..., k][glow].sum()
            per = 1 - s_b[..., k][:, glow].sum(1) / f_b[..., k][:, glow].sum(1)
            res[ch] = {"share": float(share), "share_err": float(per.std(ddof=1) / np.sqrt(len(per))),
                       "n_pixels": int(glow.sum()),
                       "kappa_t_tank": float(m.kappa_t[k]), "albedo": float(m.albedo[k]),
                       "g": float(m.g[k])}
        out[f"{name} {ml} ml"] = res
        k = 0  # the red channel: every case has a glow there (Merlot's G and B have kappa_s = 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            maps[f"{name} {ml} ml"] = np.where(bulb[..., k], np.nan,
                                               1 - s_img[..., k] / f_img[..., k])
        print(name, ml, {c: (None if v["share"] is None else round(v["share"], 3))
                         for c, v in res.items()}, flush=True)
    out["_settings"] = {"spp": SPP, "size": [96, 72], "variant": full.variant,
                        "definition": "1 - sum(single) / sum(all orders) over the glow pixels"}
    (HERE / "ms_share.json").write_text(json.dumps(out, indent=2) + "\n")
    np.savez_compressed(HERE / "ms_share_maps.npz", names=np.array(list(maps)),
                        maps=np.stack(list(maps.values())))
    plot(maps, out)


def plot(maps: dict, out: dict) -> None:
    """Maps of the red channel's share per pixel (own colour-bar axis), then the glow-summed
    share per channel as bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(maps)
    fig = plt.figure(figsize=(3.2 * n + 5.5, 3.6))
    grid = fig.add_gridspec(1, n + 3, width_ratios=[1] * n + [0.06, 0.4, 1.5], wspace=0.15)
    for k, (name, m) in enumerate(maps.items()):
        ax = fig.add_subplot(grid[0, k])
        im = ax.imshow(m, vmin=0, vmax=1, cmap="magma")
        ax.set_title(f"{name}\n(R) multiple / all orders", fontsize=9)
        ax.axis("off")
    fig.colorbar(im, cax=fig.add_subplot(grid[0, n]), label="share (unitless)")
    ax = fig.add_subplot(grid[0, n + 2])  # column n + 1: room for the colour bar's label
    names = list(maps)
    for k, (ch, col) in enumerate(zip("RGB", ("tab:red", "tab:green", "tab:blue"))):
        vals = [out[nm][ch]["share"] or 0.0 for nm in names]
        ax.bar(np.arange(len(names)) + (k - 1) * 0.27, vals, 0.27, color=col, label=ch)
    labels = []
    for nm in names:  # "White Grapefruit Juice 160 ml" -> "Grapefruit\n160 ml"
        liquid, vol, unit = nm.rsplit(" ", 2)
        labels.append(f"{liquid.replace('White Grapefruit Juice', 'Grapefruit')}\n{vol} {unit}")
    ax.set_xticks(range(len(names)), labels, fontsize=7)
    ax.set_ylabel("multiple-scattering share of the glow", fontsize=8)
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8)
    fig.savefig(HERE / "ms_share.png", dpi=110, bbox_inches="tight")


def plot_saved() -> None:
    out = json.loads((HERE / "ms_share.json").read_text())
    with np.load(HERE / "ms_share_maps.npz") as f:
        maps = dict(zip(f["names"].tolist(), f["maps"]))
    plot(maps, out)


if __name__ == "__main__":
    import sys

    plot_saved() if "--plot-only" in sys.argv[1:] else main()

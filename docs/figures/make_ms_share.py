"""Share of multiple scattering in the glow of the canonical capture (docs/multiple_scattering.md).

For each liquid at the dilutions of Narasimhan et al. (2006) in the 23 l tank, render the
canonical bulb capture (capture_specs/bulb.yaml at 96 x 72 px) with Mitsuba 3 twice with the
same random numbers: single scattering (max_depth = single_scattering_depth) and all orders
(max_depth = -1).  The share of multiple scattering is (all - single) / all, summed over the
glow (pixels that do not see the bulb and whose value is above 1e-3 of the brightest glow
pixel), per channel.  The Monte Carlo standard error comes from 8 independent batches.

Regenerate:  python docs/figures/make_ms_share.py   (writes ms_share.json and ms_share.png here)
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
        g = 1
        with np.errstate(invalid="ignore", divide="ignore"):
            maps[f"{name} {ml} ml"] = np.where(bulb[..., g], np.nan,
                                               1 - s_img[..., g] / f_img[..., g])
        print(name, ml, {c: (None if v["share"] is None else round(v["share"], 3))
                         for c, v in res.items()}, flush=True)
    out["_settings"] = {"spp": SPP, "size": [96, 72], "variant": full.variant,
                        "definition": "1 - sum(single) / sum(all orders) over the glow pixels"}
    (HERE / "ms_share.json").write_text(json.dumps(out, indent=2) + "\n")
    plot(maps, out)


def plot(maps: dict, out: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(maps) + 1, figsize=(4 * (len(maps) + 1), 3.4))
    for ax, (name, m) in zip(axes, maps.items()):
        im = ax.imshow(m, vmin=0, vmax=1, cmap="magma")
        ax.set_title(f"{name}\n(G) multiple / all", fontsize=9)
        ax.axis("off")
    fig.colorbar(im, ax=axes[:-1], fraction=0.02)
    ax = axes[-1]
    names = list(maps)
    for k, (ch, col) in enumerate(zip("RGB", ("tab:red", "tab:green", "tab:blue"))):
        vals = [out[n][ch]["share"] or 0.0 for n in names]
        ax.bar(np.arange(len(names)) + (k - 1) * 0.27, vals, 0.27, color=col, label=ch)
    ax.set_xticks(range(len(names)), [n.replace(" ", "\n", 1) for n in names], fontsize=7)
    ax.set_ylabel("share of multiple scattering in the glow")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=8)
    fig.savefig(HERE / "ms_share.png", dpi=110, bbox_inches="tight")


if __name__ == "__main__":
    main()

"""The bias of a single-scattering fit against the multiple-scattering share of the glow:
the measurement behind ``fitmedia.inference.full.AUTO_SHARE`` (``--model auto``).

Captures of Lowfat Milk and Espresso at several dilutions are rendered with
``fitmedia synth --model hybrid`` (the analytic single scattering plus fitmedia's own
multiple-scattering term, 1024 paths per pixel), fitted with ``--model single --no-mcmc``;
each row gives the share (from results' tracer at the single MAP, channel G) and the MAP's
error in kappa_s, kappa_t and g against the truth.

    python docs/studies/auto_threshold.py OUT_DIR [--size 32 24]

Writes OUT_DIR/auto_threshold.jsonl (one line per capture, resumable) and prints the table.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

from fitmedia.cli import main as fitmedia

CASES = [("Lowfat Milk", ml) for ml in (0.25, 0.5, 1.0, 2.0, 4.0)] + \
        [("Espresso", ml) for ml in (0.5, 1.0, 2.0)]


def run(out: Path, size: tuple[int, int]) -> list[dict]:
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
    from conftest import geometry_dict

    out.mkdir(parents=True, exist_ok=True)
    geom = out / "geom.yaml"
    geom.write_text(yaml.safe_dump(geometry_dict(*size)))
    rows_path = out / "auto_threshold.jsonl"
    done = [json.loads(x) for x in rows_path.read_text().splitlines()] if rows_path.exists() else []
    for medium, ml in CASES:
        if any(r["medium"] == medium and r["ml"] == ml for r in done):
            continue
        cap, fit = out / f"{medium}_{ml}".replace(" ", "_"), out / f"fit_{medium}_{ml}".replace(" ", "_")
        fitmedia(["synth", str(geom), "--medium", medium, "--ml", str(ml), "--model", "hybrid",
                  "--spp", "1024", "--seed", "5", "--out", str(cap)])
        spec = yaml.safe_load((cap / "capture.yaml").read_text())
        spec["channels"] = ["G"]
        (cap / "capture.yaml").write_text(yaml.safe_dump(spec))
        fitmedia(["fit", str(cap / "capture.yaml"), "--out", str(fit), "--model", "auto",
                  "--no-mcmc", "--no-report", "--quiet"])
        truth = json.loads((cap / "truth.json").read_text())["undiluted"]
        res = json.loads((fit / "results.json").read_text())
        ch = res["diagnostics"]["channels"]["G"]
        p = res["parameters"]
        row = {"medium": medium, "ml": ml,
               "share": ch["multiple_scattering"]["share_at_single_scattering_map"][0],
               "model_used": ch["model_used"]}
        # the single-scattering MAP: refit with --model single (auto may have switched)
        fitmedia(["fit", str(cap / "capture.yaml"), "--out", str(fit) + "_single", "--model",
                  "single", "--no-mcmc", "--no-report", "--quiet"])
        p = json.loads((Path(str(fit) + "_single") / "results.json").read_text())["parameters"]
        for q in ("kappa_s", "kappa_t"):
            row[f"{q}_error"] = p[q]["G"]["map"] / truth[q]["G"] - 1
        row["g_error"] = p["g"]["G"]["map"] - truth["g"]["G"]
        row["chi2_per_pixel"] = ch["chi2_per_pixel"]
        done.append(row)
        with rows_path.open("a") as f:
            f.write(json.dumps(row) + "\n")
    return done


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--size", type=int, nargs=2, default=(32, 24))
    a = ap.parse_args()
    print("| liquid, ml in 23 l | MS share (G) | kappa_s error | kappa_t error | g error |")
    print("|---|---|---|---|---|")
    for r in run(a.out, tuple(a.size)):
        print(f"| {r['medium']} {r['ml']} | {r['share']:.3f} | {r['kappa_s_error']:+.1%} | "
              f"{r['kappa_t_error']:+.1%} | {r['g_error']:+.3f} |")

"""How much of the refresh loop's noise offset is left after the last refreshes?

The full-transport fit refreshes its local model at 256 paths per sample pixel until it
settles, then ``more_paths`` traces 16 times the paths (at most 3 refreshes) and the values
are taken from there (docs/inference.md, "Full transport").  The fixed point's offset from the
term's own noise falls with the paths as paths^-p; ``trust.FINAL_MOVE_SD`` assumes p between
1/3 and 1/2 (up to two thirds of the last move left), one study at the truth gave p ~ 0.7.

This study runs ``fitmedia fit`` in-process with ``more_paths`` replaced by a ladder of
stages, each multiplying the paths again (``STUDY_STAGES``, default ``16:3,4:2``: 16 times
with at most 3 refreshes, then 4 times more with at most 2), and writes each stage's MAP,
its posterior sd (Laplace plus the term's jackknife) and the move from the stage before to
``stages_<channel>.json`` in the output folder.  With moves m1 (256 -> 4096) and m2 (4096 ->
16384) along one direction, m2 / m1 = 16^-p (1 - 4^-p) / (1 - 16^-p) gives p, and the
offset left at 4096 paths is about m2 / (1 - 4^-p).

Run: python docs/studies/ms_final_stages.py CAPTURE_YAML OUT_DIR [fit options...]
(a one-channel capture keeps it to one fit; the last stages of a 200 x 150 capture cost
~35 s per refresh at 4096 paths and ~140 s at 16384 on one core)
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

import fitmedia.inference.full as full
from fitmedia.cli import main as cli_main

STAGES = [tuple(int(v) for v in s.split(":"))
          for s in os.environ.get("STUDY_STAGES", "16:3,4:2").split(",")]
_original = full.more_paths


def _row(problem, res, before, paths, info) -> dict:
    jack = full.term_jackknife(problem, res)
    cov = full._cov_or_ridge(problem, res)
    sd = np.sqrt(np.diag(cov + (jack if jack is not None else 0.0))) if cov is not None else None
    return {"paths": paths, "x": res.x.tolist(), "kappa_t": float(np.exp(res.x[0])),
            "g": float(np.tanh(res.x[2])), "sd": None if sd is None else sd.tolist(),
            "move_sd": full.distance_sd(problem, res, before, jack),
            "move_log_kappa_t": float(res.x[0] - before[0]),
            "move_g": float(np.tanh(res.x[2]) - np.tanh(before[2])),
            "refreshes": info.refreshes, "moves_sd": info.moves_sd}


def staged(problem, space, res, **_):
    """``more_paths`` as a ladder of stages; returns what the last stage gives."""
    rows = [{"paths": None, "x": res.x.tolist(), "kappa_t": float(np.exp(res.x[0])),
             "g": float(np.tanh(res.x[2]))}]
    infos = []
    for factor, refreshes in STAGES:
        before = res.x
        res, info, paths = _original(problem, space, res, factor=factor, max_refresh=refreshes)
        rows.append(_row(problem, res, before, paths, info))
        infos.append(info)
        print(f"stage x{factor}: {paths} paths, kappa_t {rows[-1]['kappa_t']:.5g}, g "
              f"{rows[-1]['g']:.5f}, move {rows[-1]['move_sd']:.3g} sd", flush=True)
    out = Path(os.environ["STUDY_OUT"])
    ch = os.environ.get("STUDY_CHANNEL", "G")
    (out / f"stages_{ch}.json").write_text(json.dumps(rows, indent=1))
    last = infos[-1]
    last.refreshes = sum(i.refreshes for i in infos)
    last.moves_sd = [m for i in infos for m in i.moves_sd]
    return res, last, paths


if __name__ == "__main__":
    spec, out, *rest = sys.argv[1:]
    Path(out).mkdir(parents=True, exist_ok=True)
    os.environ["STUDY_OUT"] = str(Path(out).resolve())
    full.more_paths = staged
    sys.exit(cli_main(["fit", spec, "--out", str(Path(out) / "fit"), "--no-report", *rest]))

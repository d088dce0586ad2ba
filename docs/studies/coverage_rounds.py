"""Run chosen rounds of a ``fitmedia validate`` run, and keep each finished round's record
where it outlives the machine (docs/validation.md, "A coverage run at 100 x 75 pixels").

A coverage run at 100 x 75 px takes about 8 hours of the 2-core VM, longer than any one
session, and a session's VM (with its run folder) is not kept.  This script runs the rounds
it is told to of exactly the run ``fitmedia validate ARGS`` would make (same tasks, seeds,
ml and options: :func:`fitmedia.batch.validation_tasks`), and copies each finished round's
round.json to KEEP/round_NNNN.json; before it starts, the records in KEEP are put back into
the run folder, so that finished rounds are not run again.  Once KEEP holds every round,
``fitmedia validate ARGS`` reads them all back as finished and writes the coverage table:
a round's record holds its scores, which is all the table needs.

Run: python docs/studies/coverage_rounds.py KEEP ROUND [ROUND ...] -- VALIDATE-ARGS
     (rounds run in the order given) e.g. docs/studies/coverage100 12 13 14 -- --rounds 30 --media Espresso
     "White Grapefruit Juice" "Lowfat Milk" "Regular Milk" --optical-depth 0.3 3
     --spec docs/studies/geom100.yaml --model full --workers 2 --seed 2212 --out out
"""
from __future__ import annotations

import json
import shutil
import sys
from functools import partial
from pathlib import Path

from fitmedia.batch import _run_round, run_tasks, validation_tasks
from fitmedia.cli import _fit_options, build_parser


def restore(keep: Path, out: Path) -> int:
    """Put KEEP's round records back into the run folder ``out``; how many."""
    n = 0
    for rec in sorted(keep.glob("round_*.json")):
        target = out / rec.stem / "round.json"
        if not target.is_file():
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(rec, target)
            n += 1
    return n


def run_and_keep(task, keep: Path) -> dict:
    """Run one round (a Dask task) and, when it finished, copy its round.json to ``keep``
    at once (so a round that finished outlives a run stopped before the others)."""
    rec = _run_round(task)
    src = Path(task.out) / "round.json"
    if rec.get("status") == "done" and src.is_file():
        shutil.copyfile(src, keep / f"round_{task.index:04d}.json")
    return rec


def main(argv: list[str]) -> int:
    split = argv.index("--")
    keep, wanted = Path(argv[0]), [int(i) for i in argv[1:split]]
    a = build_parser().parse_args(["validate", *argv[split + 1:]])
    keep.mkdir(parents=True, exist_ok=True)
    print(f"restored {restore(keep, Path(a.out))} round records from {keep}")
    tasks, done = validation_tasks(a.media, a.rounds, a.out, ml=a.ml, geometry=a.spec,
                                   seed=a.seed, options=_fit_options(a), tank_ml=a.tank_ml,
                                   optical_depth=a.optical_depth, synth_model=a.synth_model,
                                   synth_spp=a.synth_spp)
    todo = sorted((t for t in tasks if t.index in wanted), key=lambda t: wanted.index(t.index))
    print(f"finished earlier: {sorted(done)}; running: {[t.index for t in todo]}")
    for rec in run_tasks(partial(run_and_keep, keep=keep.resolve()), todo,
                         scheduler=a.scheduler, n_workers=a.workers, progress=not a.quiet,
                         desc="rounds"):
        print(json.dumps({k: rec.get(k) for k in ("index", "medium", "ml", "status",
                                                   "wall_time_s", "error")}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""The main jobs as library functions (the CLI only parses arguments and calls these)."""

from __future__ import annotations

import time
from pathlib import Path

from .inference.fit import FitOptions, prepare, run_channels
from .inference.identity import run_identity
from .inference.results import build_results, write_outputs
from .spec import load_spec
from .util import check_output_dir, staged_output_dir

#: The chains' checkpoints in a fit's output folder (one per channel, ``_mode2`` for a second
#: mode of g); ``--resume`` continues them
CHECKPOINT_GLOB = "checkpoint_*.npz"


def check_resumable(out: Path, identity: dict) -> None:
    """Refuse, before any work, every checkpoint in ``out`` that ``--resume`` cannot continue:
    empty, truncated, wrong-shaped, or written by a run of another identity (another spec,
    other images, model, options or fitmedia version).  An InputError names the file and
    what differs; nothing is removed."""
    from .inference.sample import check_checkpoint

    for path in sorted(out.glob(CHECKPOINT_GLOB)) if out.is_dir() else []:
        check_checkpoint(path, identity)


def capture_identity(spec_path: str | Path, options: FitOptions) -> dict:
    """The run identity a fit of ``spec_path`` with ``options`` has (the spec parsed and the
    images loaded, no fitting): to tell whether an earlier fit's results.json is this one's."""
    spec = load_spec(spec_path)
    prep = prepare(spec)
    return run_identity(spec, prep.images, prep.clear, options)


def _remove_other_checkpoints(out: Path, fits: dict[str, dict]) -> None:
    """Remove checkpoints in ``out`` that this finished run did not write (e.g. a second mode
    of g an earlier run into the same folder sampled): each checkpoint left belongs to the
    results beside it."""
    mine = {f"checkpoint_{ch}.npz" for ch in fits}
    mine |= {f"checkpoint_{ch}_mode2.npz" for ch, f in fits.items() if "chain_mode2" in f}
    for path in out.glob(CHECKPOINT_GLOB):
        if path.name not in mine:
            path.unlink(missing_ok=True)


def fit(spec_path: str | Path, out_dir: str | Path, options: FitOptions = FitOptions(), *,
        report: bool = True) -> dict:
    """Fit a capture spec and write results.json (and report.html) into ``out_dir``.

    ``out_dir`` is checked first (:func:`fitmedia.util.check_output_dir`); with
    ``options.resume`` its checkpoints are checked against this run's identity after the
    images are loaded and before any fitting (:func:`check_resumable`).  The chains'
    checkpoints are written into ``out_dir`` as the sampler runs (a killed fit leaves only
    them, for ``--resume``); the results are written into a temporary folder and moved into
    ``out_dir`` at the end (:func:`fitmedia.util.staged_output_dir`).
    """
    t0 = time.perf_counter()
    out = check_output_dir(out_dir)
    spec = load_spec(spec_path)
    prep = prepare(spec)
    identity = run_identity(spec, prep.images, prep.clear, options)
    if options.mcmc and options.resume:
        check_resumable(out, identity)
    fits = run_channels(prep, options, out if options.mcmc else None, identity)
    results = build_results(prep, fits, options)
    results["run_identity"] = identity
    results["wall_time_s"] = time.perf_counter() - t0
    with staged_output_dir(out_dir) as stage:
        write_outputs(stage, prep, fits, results)
        if report:
            from .report import write_report

            write_report(stage)
    if options.mcmc:
        _remove_other_checkpoints(out, fits)
    return results

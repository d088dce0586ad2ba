"""The main jobs as library functions (the CLI only parses arguments and calls these)."""

from __future__ import annotations

import time
from pathlib import Path

from .inference.fit import FitOptions, prepare, run_channels
from .inference.results import build_results, write_outputs
from .spec import load_spec


def fit(spec_path: str | Path, out_dir: str | Path, options: FitOptions = FitOptions(), *,
        report: bool = True) -> dict:
    """Fit a capture spec and write results.json (and report.html) into ``out_dir``."""
    t0 = time.perf_counter()
    spec = load_spec(spec_path)
    prep = prepare(spec)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fits = run_channels(prep, options, out if options.mcmc else None)
    results = build_results(prep, fits, options)
    results["wall_time_s"] = time.perf_counter() - t0
    write_outputs(out, prep, fits, results)
    if report:
        from .report import write_report

        write_report(out)
    return results

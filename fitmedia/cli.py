"""Command-line interface: each subcommand calls one library function.

Bad input (an InputError) prints one line and exits with code 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from .errors import InputError
from .inference.result import FitOptions  # stdlib only: no numpy for --help

#: the defaults of every fit option the CLI offers: FitOptions' own
DEFAULTS = FitOptions()


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {v}")
    return v


def _finite(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if v != v or v in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def _positive_finite(text: str) -> float:
    v = _finite(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return v


def _seed(text: str) -> int:
    """A random seed: an integer >= 0 (numpy refuses negative seeds, after the output folder
    was made)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {v}")
    return v


def _out_dir(text: str) -> str:
    """An output folder: not empty (an empty --out wrote everything into the current folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a folder, got {text!r}")
    return text


def _thickness(text: str) -> float:
    return float("inf") if text.strip().lower() in ("inf", "infinity") else _finite(text)


def cmd_synth(a) -> int:
    from .medium import Medium, medium_by_name
    from .spec import load_spec
    from .synth import CameraNoise, synthesize

    spec = load_spec(a.spec, require_images=False)
    explicit = [a.kappa_a, a.kappa_s, a.g]
    if a.medium and any(x is not None for x in explicit):
        raise InputError("--medium and --kappa-a/--kappa-s/--g: give one or the other")
    if a.medium:
        medium, name = medium_by_name(a.medium), a.medium
    elif all(x is not None for x in explicit):
        vals = [(x * 3 if len(x) == 1 else x) for x in explicit]
        for flag, v in zip(("--kappa-a", "--kappa-s", "--g"), vals):
            if len(v) != 3:
                raise InputError(f"{flag}: expected 1 or 3 values (R G B), got {len(v)}")
        medium, name = Medium(*vals), "custom"
    else:
        raise InputError("give --medium NAME or all of --kappa-a, --kappa-s and --g")
    path = synthesize(spec, a.out, medium, a.ml, tank_ml=a.tank_ml, seed=a.seed, model=a.model,
                      spp=a.spp, brightness=a.brightness, medium_name=name,
                      noise=CameraNoise(a.gain, a.read_var))
    print(f"wrote synthetic capture {path} (truth in {Path(a.out) / 'truth.json'})")
    for note in json.loads((Path(a.out) / "truth.json").read_text()).get("notes", []):
        print(f"note: {note}")
    return 0


def cmd_fit(a) -> int:
    from .inference.fit import FitOptions
    from .pipeline import fit

    opts = FitOptions(model=a.model, seed=a.seed, mcmc=not a.no_mcmc, robust=a.robust,
                      background=a.background,
                      n_tau=a.n_tau, max_steps=a.max_steps, workers=a.workers, resume=a.resume,
                      progress=not a.quiet)
    res = fit(a.spec, a.out, opts, report=not a.no_report)
    out = Path(a.out)
    print(f"wrote {out / 'results.json'}" + ("" if a.no_report else f" and {out / 'report.html'}"))
    from .trust import model_lines, print_values, print_verdict

    for line in model_lines(res):
        print(line)
    print_values(res)
    return print_verdict(res)


def cmd_report(a) -> int:
    from .report import write_report

    path = write_report(a.dir)
    print(f"wrote {path}")
    return 0


def cmd_demo(a) -> int:
    """Fit the bundled default capture (synthetic/default, shipped as package data)."""
    from .data import bundled_path
    from .inference.fit import FitOptions
    from .pipeline import fit

    spec = bundled_path("synthetic", "default", "capture.yaml")
    res = fit(spec, a.out, FitOptions(seed=a.seed, progress=not a.quiet))
    print(f"wrote {Path(a.out) / 'results.json'} and {Path(a.out) / 'report.html'} "
          f"({res['wall_time_s']:.0f} s)")
    from .trust import model_lines, print_verdict

    for line in model_lines(res):
        print(line)
    return print_verdict(res)  # 1 when the misfit guard fired


def cmd_doctor(a) -> int:
    from .mitsuba_env import doctor_report

    print(doctor_report())
    return 0


def cmd_slab(a) -> int:
    from .slab import slab_rt

    res = slab_rt(a.albedo, a.optical_thickness, a.g, a.n, mu0=a.mu0, spp=a.spp, seed=a.seed)
    if a.json:
        print(json.dumps({k: float(res[k]) for k in ("R", "T", "R_err", "T_err")}))
    else:
        print(f"R = {res['R']:.5f} +- {res['R_err']:.5f}\nT = {res['T']:.5f} +- {res['T_err']:.5f}")
    return 0


# ------------------------------------------------ validate, fit-many, export (batch.py, export.py)
def _fit_options(a, **kw) -> FitOptions:
    """FitOptions of validate and fit-many from their runner arguments."""
    from .inference.fit import FitOptions

    return FitOptions(seed=a.seed, max_steps=a.max_steps, n_tau=a.n_tau, progress=not a.quiet,
                      model=a.model, **kw)


def _add_runner_args(p, model: str = DEFAULTS.model) -> None:
    p.add_argument("--scheduler", default=None,
                   help="Dask scheduler address (tcp://host:8786); default: a local cluster; "
                        "'serial' (batch.SERIAL): no Dask, one task after the other in this "
                        "process")
    p.add_argument("--workers", type=_positive_int, default=2,
                   help="worker processes of the local cluster (default 2)")
    p.add_argument("--max-steps", type=_positive_int, default=DEFAULTS.max_steps)
    p.add_argument("--n-tau", type=_finite, default=DEFAULTS.n_tau,
                   help="chain length in autocorr. times")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--model", choices=["single", "full", "auto"], default=model,
                   help=f"forward model of every fit (as for fit; default {model})")


def add_validate_parser(sub) -> None:
    """Add ``fitmedia validate`` to the subparsers ``sub``."""
    p = sub.add_parser("validate", help="synthetic round trips on Dask; coverage of the "
                                        "credible intervals (docs/validation.md)")
    p.add_argument("--rounds", type=_positive_int, required=True)
    p.add_argument("--media", nargs="+", required=True, metavar="NAME",
                   help="liquids of the Narasimhan 2006 table, used in turn")
    p.add_argument("--out", type=_out_dir, required=True)
    p.add_argument("--seed", type=_seed, default=0)
    p.add_argument("--spec", default=None, help="geometry spec (default capture_specs/bulb.yaml)")
    p.add_argument("--ml", type=_finite, nargs="+", default=None,
                   help="ml per image of every round (default: drawn in 8-240 per round)")
    p.add_argument("--tank-ml", type=_finite, default=23000.0)
    p.add_argument("--synth-model", choices=["single", "hybrid", "full"], default=None,
                   help="how each capture is rendered (as synth --model); default single for "
                        "--model single, else hybrid (docs/validation.md)")
    p.add_argument("--synth-spp", type=_positive_int, default=None,
                   help="paths per pixel of the hybrid term (default 16384) or Mitsuba's spp "
                        "(default 256)")
    p.add_argument("--optical-depth", type=_finite, nargs=2, default=None, metavar=("LO", "HI"),
                   help="draw each round's ml so that the G channel's optical depth from the "
                        "light to the front wall is log-uniform in LO-HI (instead of 8-240 ml)")
    _add_runner_args(p, model="single")  # round trips of the single fit on its own renders
    p.set_defaults(func=cmd_validate)


def cmd_validate(a) -> int:
    """Exit code 0 when the criteria are met, 1 when not (the table says which)."""
    from .batch import validate

    res = validate(a.media, a.rounds, a.out, ml=a.ml, geometry=a.spec, seed=a.seed,
                   scheduler=a.scheduler, n_workers=a.workers, options=_fit_options(a),
                   tank_ml=a.tank_ml, optical_depth=a.optical_depth,
                   synth_model=a.synth_model, synth_spp=a.synth_spp)
    print(res.table, end="")
    print(f"wrote {', '.join(str(f) for f in res.files)}")
    return 0 if res.passed else 1


def add_fit_many_parser(sub) -> None:
    """Add ``fitmedia fit-many`` to the subparsers ``sub``."""
    p = sub.add_parser("fit-many", help="fit many captures on Dask; summary.json")
    p.add_argument("specs", nargs="+", metavar="SPEC")
    p.add_argument("--out", type=_out_dir, required=True)
    p.add_argument("--seed", type=_seed, default=0)
    p.add_argument("--no-mcmc", action="store_true", help="MAP only, no posterior sampling")
    p.add_argument("--no-report", action="store_true")
    _add_runner_args(p)
    p.set_defaults(func=cmd_fit_many)


def cmd_fit_many(a) -> int:
    """Exit code 0 when every capture was fitted, 2 when some failed (one line each), else 1
    when the misfit guard fired on some (their reasons on stderr)."""
    from .batch import fit_many

    recs = fit_many(a.specs, a.out, scheduler=a.scheduler, n_workers=a.workers,
                    options=_fit_options(a, mcmc=not a.no_mcmc), report=not a.no_report)
    for r in recs:
        if r["status"] == "failed":
            print(f"fitmedia: error: {r['name']}: {r['error']}", file=sys.stderr)
        else:
            print(f"{r['name']}: {r['status']} ({r['out']})")
            for reason in (r.get("trust") or {}).get("reasons") or []:
                print(f"fitmedia: doubtful result: {r['name']}: {reason}", file=sys.stderr)
    print(f"wrote {Path(a.out) / 'summary.json'}")
    if any(r["status"] == "failed" for r in recs):
        return 2
    return 1 if any((r.get("trust") or {}).get("ok") is False for r in recs) else 0


def add_export_parser(sub) -> None:
    """Add ``fitmedia export`` to the subparsers ``sub``."""
    p = sub.add_parser("export", help="write DIR/results.json's medium for Mitsuba 3 and pbrt-v4")
    p.add_argument("dir", help="a fit's output folder (reads results.json, writes beside it)")
    p.add_argument("--scale-to-m", action="store_true",
                   help="coefficients in 1/m for a scene in metres (default 1/mm)")
    p.add_argument("--allow-doubtful", action="store_true",
                   help="export a fit that said its values cannot be trusted (exit 1 from fit): "
                        "the files then say so, and export exits 1 too")
    p.set_defaults(func=cmd_export)


def add_calibrate_parser(sub) -> None:
    """Add ``fitmedia calibrate`` to the subparsers ``sub`` (issue 16; fitmedia/calibrate.py)."""
    p = sub.add_parser("calibrate", help="camera intrinsics, distortion and pose in the tank "
                                         "frame from photographs of a ChArUco board")
    p.add_argument("images", nargs="+", help="photographs of the board against the front wall")
    p.add_argument("--board", required=True, help="board description (YAML, docs/calibrate.md)")
    p.add_argument("--out", required=True, help="the camera block to write (YAML)")
    p.set_defaults(func=cmd_calibrate)


def cmd_calibrate(a) -> int:
    from .calibrate import run_calibrate

    return run_calibrate(images=a.images, board=a.board, out=a.out)


def add_preview_parser(sub) -> None:
    """Add ``fitmedia preview`` to the subparsers ``sub`` (issue 16; fitmedia/preview.py)."""
    p = sub.add_parser("preview", help="draw the spec's tank, wall and light over each image")
    p.add_argument("spec")
    p.add_argument("--out", required=True, help="PNG to write")
    p.set_defaults(func=cmd_preview)


def cmd_preview(a) -> int:
    from .preview import run_preview

    return run_preview(spec=a.spec, out=a.out)


def cmd_export(a) -> int:
    from .export import doubts, export_medium, read_results
    from .util import check_output_dir

    results = read_results(a.dir)
    reasons = doubts(results)
    for r in reasons:
        print(f"fitmedia: doubtful result: {r}", file=sys.stderr)
    if reasons and not a.allow_doubtful:
        print(f"fitmedia: export refused: the fit in {a.dir} said its values cannot be trusted "
              "(above); --allow-doubtful writes them anyway, marked as such", file=sys.stderr)
        return 1
    check_output_dir(a.dir, "DIR")  # the exports are written beside results.json
    paths = export_medium(results, a.dir, scale_to_m=a.scale_to_m)
    print("wrote " + ", ".join(str(p) for p in paths) + (" (marked DOUBTFUL)" if reasons else ""))
    return 1 if reasons else 0


# long: one add_argument per option of the subcommands synth, fit, report, demo, doctor, slab
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fitmedia", description=__doc__.splitlines()[0])
    p.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("synth", help="render a synthetic capture from a geometry spec")
    s.add_argument("spec", help="capture spec (only its geometry is used)")
    s.add_argument("--medium", help="a liquid of the Narasimhan 2006 table, e.g. 'Lowfat Milk'")
    s.add_argument("--kappa-a", type=_finite, nargs="+", help="undiluted kappa_a, 1/mm (1 or 3)")
    s.add_argument("--kappa-s", type=_finite, nargs="+", help="undiluted kappa_s, 1/mm (1 or 3)")
    s.add_argument("--g", type=_finite, nargs="+", help="HG anisotropy (1 or 3 values)")
    s.add_argument("--ml", type=_finite, nargs="+", required=True,
                   help="ml of liquid per image (several: a dilution series)")
    s.add_argument("--tank-ml", type=_finite, default=23000.0, help="water in the tank, ml")
    s.add_argument("--out", type=_out_dir, required=True)
    s.add_argument("--seed", type=_seed, default=0)
    s.add_argument("--model", choices=["single", "full", "hybrid"], default="single",
                   help="single: analytic orders 0-1; full: Mitsuba 3, all orders; hybrid: "
                        "analytic orders 0-1 plus fitmedia's own multiple-scattering term")
    s.add_argument("--spp", type=_positive_int, default=256, help="samples per pixel (full)")
    s.add_argument("--brightness", type=_finite, nargs="+",
                   help="bulb radiance or spot intensity (image units)")
    s.add_argument("--gain", type=_finite, default=2.0e-5, help="noise: variance per unit value")
    s.add_argument("--read-var", type=_finite, default=1.0e-9, help="noise: read variance")
    s.set_defaults(func=cmd_synth)

    f = sub.add_parser("fit", help="fit a capture and write results.json and report.html")
    f.add_argument("spec")
    f.add_argument("--out", type=_out_dir, required=True)
    f.add_argument("--model", choices=["single", "full", "auto"], default=DEFAULTS.model,
                   help="single: analytic single scattering; full: plus the multiple-scattering "
                        "term, refreshed around the MAP; auto: full when the term's share of the "
                        "glow at the single-scattering MAP is above 2 %%, or, for a spot, when "
                        "a scan of the full model finds the single fit's values undetermined "
                        "(default; single for a capture that declares a single-scattering "
                        "render)")
    f.add_argument("--seed", type=_seed, default=DEFAULTS.seed)
    f.add_argument("--no-mcmc", action="store_true", help="MAP only, no posterior sampling")
    f.add_argument("--no-report", action="store_true")
    f.add_argument("--robust", action="store_true", help="Student-t likelihood (outliers)")
    f.add_argument("--background", action="store_true",
                   help="fit an additive background offset per channel (normal prior)")
    f.add_argument("--n-tau", type=_positive_finite, default=DEFAULTS.n_tau,
                   help="chain length in autocorr. times")
    f.add_argument("--max-steps", type=_positive_int, default=DEFAULTS.max_steps)
    f.add_argument("--workers", type=_positive_int, default=DEFAULTS.workers)
    f.add_argument("--resume", action="store_true", help="continue from the chains in --out")
    f.add_argument("--quiet", action="store_true", help="no progress bars")
    f.set_defaults(func=cmd_fit)

    r = sub.add_parser("report", help="write DIR/report.html from DIR/results.json")
    r.add_argument("dir")
    r.set_defaults(func=cmd_report)

    d = sub.add_parser("demo", help="fit the bundled default capture (synthetic/default)")
    d.add_argument("--out", type=_out_dir, default="out/demo")
    d.add_argument("--seed", type=_seed, default=0)
    d.add_argument("--quiet", action="store_true")
    d.set_defaults(func=cmd_demo)

    doc = sub.add_parser("doctor", help="which Mitsuba variant and libLLVM work here, and why")
    doc.set_defaults(func=cmd_doctor)

    sl = sub.add_parser("slab", help="R and T of a slab with Mitsuba (check of the medium code)")
    sl.add_argument("--albedo", type=_finite, required=True)
    sl.add_argument("--optical-thickness", type=_thickness, required=True)
    sl.add_argument("--g", type=_finite, required=True)
    sl.add_argument("--n", type=_finite, required=True)
    sl.add_argument("--mu0", type=_finite, default=1.0)
    sl.add_argument("--spp", type=_positive_int, default=None)
    sl.add_argument("--seed", type=_seed, default=0)
    sl.add_argument("--json", action="store_true")
    sl.set_defaults(func=cmd_slab)

    add_validate_parser(sub)
    add_fit_many_parser(sub)
    add_export_parser(sub)
    add_calibrate_parser(sub)
    add_preview_parser(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    a = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if a.verbose else logging.WARNING,
                        format="fitmedia: %(message)s")
    try:
        return int(a.func(a) or 0)
    except InputError as exc:
        print(f"fitmedia: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("fitmedia: interrupted (a fit resumes with --resume)", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())

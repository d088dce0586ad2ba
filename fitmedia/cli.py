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
    from .trust import print_values, print_verdict

    print_values(res)
    if "converged" in res["diagnostics"] and not res["diagnostics"]["converged"]:
        print("warning: the sampler did not converge; see diagnostics in results.json",
              file=sys.stderr)
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
    return 0


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
    s.add_argument("--model", choices=["single", "full"], default="single")
    s.add_argument("--spp", type=_positive_int, default=256, help="samples per pixel (full)")
    s.add_argument("--brightness", type=_finite, nargs="+",
                   help="bulb radiance or spot intensity (image units)")
    s.add_argument("--gain", type=_finite, default=2.0e-5, help="noise: variance per unit value")
    s.add_argument("--read-var", type=_finite, default=1.0e-9, help="noise: read variance")
    s.set_defaults(func=cmd_synth)

    f = sub.add_parser("fit", help="fit a capture and write results.json and report.html")
    f.add_argument("spec")
    f.add_argument("--out", type=_out_dir, required=True)
    f.add_argument("--model", choices=["single"], default="single")
    f.add_argument("--seed", type=_seed, default=0)
    f.add_argument("--no-mcmc", action="store_true", help="MAP only, no posterior sampling")
    f.add_argument("--no-report", action="store_true")
    f.add_argument("--robust", action="store_true", help="Student-t likelihood (outliers)")
    f.add_argument("--background", action="store_true",
                   help="fit an additive background offset per channel (normal prior)")
    f.add_argument("--n-tau", type=_positive_finite, default=50.0,
                   help="chain length in autocorr. times")
    f.add_argument("--max-steps", type=_positive_int, default=20000)
    f.add_argument("--workers", type=_positive_int, default=None)
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

    from .batch import add_fit_many_parser, add_validate_parser
    from .export import add_export_parser

    add_validate_parser(sub)
    add_fit_many_parser(sub)
    add_export_parser(sub)
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

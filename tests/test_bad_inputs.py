"""Bad input never gives a wrong number, a traceback or a hang (issue 17): the image sanity
checks against the noise model, and the bad-input corpus (tests/bad_inputs/make_corpus.py)
run through the real entry point."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest

from fitmedia.errors import ImageError
from fitmedia.images import LoadedImage, checks
from conftest import ROOT

_corpus_spec = importlib.util.spec_from_file_location(
    "make_corpus", ROOT / "tests" / "bad_inputs" / "make_corpus.py")
corpus = sys.modules.setdefault("make_corpus", importlib.util.module_from_spec(_corpus_spec))
_corpus_spec.loader.exec_module(corpus)  # registered first: its dataclasses look it up

READ_VAR = 1e-9  # the synthetic camera's (fitmedia.synth.DEFAULT_READ_VAR), sd 3.2e-5


def _image(data: np.ndarray) -> LoadedImage:
    return LoadedImage(data=data, valid=np.ones(data.shape, bool), n_saturated=0, n_masked=0,
                       source="x.tiff")


def _dilute(rng, shape=(90, 120)) -> np.ndarray:
    """Read noise everywhere (half the pixels negative) and a faint glow on 2 % of the pixels,
    the shape of a thin dilution's photo."""
    data = rng.normal(0.0, np.sqrt(READ_VAR), shape + (3,))
    data[:9, :24] += 0.01
    return data


def test_a_dilute_capture_passes_and_its_negation_does_not(rng):
    """Second model: pure normal read noise puts 2.9e-7 of its pixels below -5 sd, so a
    dilute photo (half its pixels negative) passes; the same photo negated (its glow far
    below 0, nothing far above) and one with a whole-image offset of -6 sd are refused, the
    latter accepted when the spec's background prior covers it."""
    data = _dilute(rng)
    checks.check_values(_image(data), (0, 1, 2), "RGB")
    checks.check_negative(_image(data), (0, 1, 2), "RGB", [READ_VAR] * 3)
    for bad in (-np.abs(data), data - 6 * np.sqrt(READ_VAR)):
        with pytest.raises(ImageError, match="x.tiff: channel R: .* below"):
            checks.check_negative(_image(bad), (0, 1, 2), "RGB", [READ_VAR] * 3)
    checks.check_negative(_image(data - 6 * np.sqrt(READ_VAR)), (0, 1, 2), "RGB", [READ_VAR] * 3,
                          background_sd=3 * np.sqrt(READ_VAR))


def test_a_dilute_capture_is_lit_and_pure_noise_is_not(rng):
    """Second model: pure normal read noise puts 2.9e-7 of its pixels above 5 sd, so a black
    frame (read noise only) has no lit pixel and is refused as black, or, when pixels are
    saturated, as a glow with no unsaturated sample; the dilute photo's faint glow (2 % of the
    pixels at 300 sd) passes."""
    data = _dilute(rng)
    read = np.full(data.shape, READ_VAR)
    checks.check_lit(_image(data), (0, 1, 2), "RGB", read)
    noise = rng.normal(0.0, np.sqrt(READ_VAR), data.shape)
    with pytest.raises(ImageError, match="x.tiff: channel R: 0 of 10800 .* a black image"):
        checks.check_lit(_image(noise), (0, 1, 2), "RGB", read)
    sat = LoadedImage(data=noise, valid=np.ones(noise.shape, bool), n_saturated=40, n_masked=0,
                      source="x.tiff", exposures=(1.0, 0.1))
    with pytest.raises(ImageError, match="no unsaturated sample of the glow: its 40 saturated "
                                         "pixels are saturated in every frame"):
        checks.check_lit(sat, (0, 1, 2), "RGB", read)


@pytest.mark.parametrize("scale, words", [
    (0.0, "0 at every usable pixel"),
    (1e304, "e+302 per second after dividing by exposure_s"),  # exposure_s 1e-300 s, ~0.01
    (1e-303, "e-305 per second after dividing by exposure_s"),  # exposure_s 1e300 s
    (np.inf, "non-finite"),
])
def test_values_outside_what_a_photo_holds_are_refused(rng, scale, words):
    """All-zero, overflowing, underflowing and infinite images are refused naming the file
    and the channel (limits: VALUE_RANGE, by hand from the float64 range)."""
    with np.errstate(all="ignore"):
        data = _dilute(rng) * scale
    data[0, 0] = 0.01 * scale if np.isfinite(scale) else np.inf
    with pytest.raises(ImageError, match="x.tiff: channel R") as exc:
        checks.check_values(_image(np.abs(data) if scale == 0 else data), (0, 1, 2), "RGB")
    assert words in str(exc.value)


def test_the_bundled_captures_pass_the_checks():
    """The captures fitmedia ships (synthetic/default: the demo) are prepared without a
    refusal: the checks never refuse a legitimate capture."""
    from fitmedia.inference.fit import prepare
    from fitmedia.spec import load_spec

    prep = prepare(load_spec(ROOT / "synthetic" / "default" / "capture.yaml"))
    assert len(prep.images) >= 1 and prep.clear is not None


@pytest.mark.parametrize("camera, words", [
    ({"position": [600, 0, 300], "look_at": [600, 0, 0]},
     "crosses the front wall's plane at x = 301"),
    ({"look_at": [900, 0, 0]}, "projects outside the image"),
])
def test_an_unseen_bulb_is_named_for_what_it_is(camera, words):
    """A camera that cannot see the bulb is told why, not 'saturated, take a shorter exposure'.
    By hand: from (600, 0, 300) the line to the bulb (40, 10, 30) crosses the wall's outer plane
    z = 156 at x = 600 - 560 * 144 / 270 = 301 mm, outside |x| < 150; a camera turned 56 degrees
    away puts the bulb off a 80 x 60 image.  The model agrees that no pixel sees it."""
    from fitmedia.forward.single import SingleScattering
    from fitmedia.inference.fit import why_bulb_unseen
    from fitmedia.spec import parse_spec
    from conftest import geometry_dict

    d = geometry_dict()
    d["camera"].update(camera)
    spec = parse_spec(d, require_images=False)
    assert words in why_bulb_unseen(spec)
    unit = SingleScattering(spec, None, channels=("R",)).render(
        np.zeros(1), np.zeros(1), np.zeros(1), np.ones(1))
    assert not unit.max() > 0


@pytest.mark.parametrize("width, height, synth_mb", [(64, 48, 156), (200, 150, 321),
                                                     (400, 300, 863)])
def test_memory_estimate_against_measured_peaks(width, height, synth_mb):
    """fitmedia.memory.estimate_peak('synth') within 10 % of the peak resident set measured
    with /usr/bin/time -v for `fitmedia synth` of 2 images at these sizes (fitmedia/memory.py
    gives the runs); the fit's estimate is at least the 262 MB measured for the whole MAP fit
    at 64 x 48 with one worker, and grows with the workers.  With the multiple-scattering
    tracer (every bulb fit since 2026-12-02: the single-scattering check), it is at least the
    1262616 kB measured for ``fit --model single --no-mcmc --workers 1`` of a bulb capture at
    64 x 48, and ``synth --model hybrid``'s at least the 1147296 kB measured there
    (fitmedia/memory.py); without the tracer's term both were 4-7 times below.  At 200 x 150
    the synth estimate also holds for ``synth --model full`` (Mitsuba, 256 spp): 284004 kB
    measured for the canonical bulb, 287912 kB for the canonical spot (stop 25)."""
    from fitmedia.memory import estimate_peak
    from fitmedia.spec import parse_spec
    from conftest import geometry_dict

    d = geometry_dict(width=width, height=height)
    spec = parse_spec(d, require_images=False)
    assert estimate_peak(spec, "synth") / 2**20 == pytest.approx(synth_mb, rel=0.1)
    d["images"] = [{"path": f"m{k}.tiff", "exposure_s": 1.0} for k in range(2)]
    d["calibration"] = {"clear_water": {"path": "w.tiff", "exposure_s": 1.0}}
    spec = parse_spec(d, require_images=False)
    one, three = estimate_peak(spec, "fit", workers=1), estimate_peak(spec, "fit", workers=3)
    assert one / 2**20 >= 262 and three > one
    assert estimate_peak(spec, "fit", workers=1, tracer=False) / 2**20 >= 262
    if (width, height) == (64, 48):  # the sizes the tracer's peaks were measured at
        assert one >= 1262616 * 1024  # /usr/bin/time -v's maximum resident set, kB
        assert estimate_peak(spec, "synth", tracer=True) >= 1147296 * 1024
    if (width, height) == (200, 150):  # synth --model full's peaks, Mitsuba at 256 spp
        assert estimate_peak(parse_spec(geometry_dict(width=width, height=height),
                                        require_images=False), "synth") >= 287912 * 1024


def test_a_spec_beyond_the_memory_limit_is_refused_up_front(monkeypatch):
    """A 40000 x 25000 camera (1e9 pixels) is refused with the figure and the limit (5.7e3
    GiB by hand: 137 MB + 6.1 kB x 1e9); the limit follows FITMEDIA_MAX_MEMORY_GB, 0 turns the
    check off, and a value that is not a positive number is refused naming the variable."""
    from fitmedia.errors import InputError
    from fitmedia.memory import check_memory
    from fitmedia.spec import parse_spec
    from conftest import geometry_dict

    huge = parse_spec(geometry_dict(width=40000, height=25000), require_images=False)
    monkeypatch.setenv("FITMEDIA_MAX_MEMORY_GB", "64")
    with pytest.raises(InputError, match=r"5\.68e\+03 GiB .* limit of 64 GiB"):
        check_memory(huge, "synth")
    monkeypatch.setenv("FITMEDIA_MAX_MEMORY_GB", "0")
    check_memory(huge, "synth")
    monkeypatch.setenv("FITMEDIA_MAX_MEMORY_GB", "-3")
    with pytest.raises(InputError, match="FITMEDIA_MAX_MEMORY_GB: got '-3'"):
        check_memory(huge, "synth")


@pytest.mark.parametrize("argv, words", [
    (["fit", "s.yaml", "--out", "{o}", "--n-tau", "-1"], "--n-tau: expected a positive number"),
    (["fit", "s.yaml", "--out", "{o}", "--n-tau", "0"], "--n-tau: expected a positive number"),
    (["synth", "s.yaml", "--medium", "Espresso", "--ml", "8", "--out", "{o}", "--seed", "-1"],
     "--seed: expected an integer >= 0"),
    (["synth", "s.yaml", "--medium", "Espresso", "--ml", "8", "--out", ""],
     "--out: expected a folder"),
    (["fit-many", "s.yaml", "--out", "{o}", "--seed", "-1"], "--seed: expected an integer >= 0"),
])
def test_bad_arguments_are_refused_before_anything_is_made(tmp_path, capsys, argv, words):
    """Arguments numpy or the sampler would take (n_tau <= 0: a chain that stops at once) or
    fail on after the output folder was made (seed -1), and an empty --out (everything was
    written into the current folder): exit 2 from argparse, the option named, nothing made."""
    from fitmedia.cli import main

    with pytest.raises(SystemExit) as exc:
        main([a.replace("{o}", str(tmp_path / "o")) for a in argv])
    assert exc.value.code == 2 and words in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_report_names_a_missing_row(tmp_path):
    """A results.json without one channel's g (the report dropped the row silently) is refused
    naming parameters.g.G; a complete one passes the check (reference: the rows by hand)."""
    import json

    from fitmedia.errors import InputError
    from fitmedia.report.html import load_outputs

    params = {q: {c: {"map": 0.5} for c in "RGB"}
              for q in ("kappa_a", "kappa_s", "kappa_t", "albedo", "g")}
    del params["g"]["G"]
    (tmp_path / "results.json").write_text(json.dumps({"channels": list("RGB"),
                                                       "parameters": params}))
    with pytest.raises(InputError, match=r"results.json: parameters\.g\.G is missing"):
        load_outputs(tmp_path)
    params["g"]["G"] = {"map": 0.5}
    (tmp_path / "results.json").write_text(json.dumps({"channels": list("RGB"),
                                                       "parameters": params}))
    with pytest.raises(InputError, match="samples.npz: file not found"):
        load_outputs(tmp_path)


@pytest.fixture(scope="module")
def corpus_base(tmp_path_factory):
    """The corpus's shared 16 x 12 capture (tests/bad_inputs/make_corpus.py make_base)."""
    root = tmp_path_factory.mktemp("corpus")
    return root, corpus.make_base(root)


#: corpus cases run as real subprocesses (python -m fitmedia.cli: interpreter start-up, C-level
#: stderr, the environment, a hang killed by the timeout), one or more per risky class; the
#: others run through fitmedia.cli.main in the test's process (run_in_process), which proves
#: the same exit code, message, one line and no traceback for ~1 s less CPU each
SUBPROCESS_CASES = {"alias_bomb", "deep_nesting", "unsafe_tag", "truncated_image",
                    "raw_truncated", "huge_fit", "unknown_medium", "empty_checkpoint",
                    "bad_memory_env"}


def run_in_process(case, d, base, capfd, caplog, monkeypatch):
    """``case`` through :func:`fitmedia.cli.main` in this process, as make_corpus.run_case runs
    it in a subprocess: the case's folder as the working directory, its environment, a timer
    for the timeout (a hang), stderr captured at the file descriptor (C libraries' complaints
    too), log records of level WARNING and up as the lines `python -m` would print for them,
    and any uncaught exception (a warning is one under pytest) as its traceback."""
    import logging
    import signal
    import subprocess
    import traceback

    from fitmedia.cli import main

    def hang(*_):
        raise TimeoutError(f"no answer in {case.timeout:g} s (a hang)")

    argv = [a.replace("{d}", str(d)).replace("{base}", str(base.parent)) for a in case.argv]
    monkeypatch.chdir(d)
    for k, v in case.env.items():
        monkeypatch.setenv(k, v)
    capfd.readouterr()
    caplog.clear()
    old = signal.signal(signal.SIGALRM, hang)
    signal.setitimer(signal.ITIMER_REAL, case.timeout)
    trace = ""
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse: usage, then the error line
        code = 0 if exc.code is None else exc.code
    except Exception:  # noqa: BLE001 - a traceback is what the case must not give
        code, trace = 1, traceback.format_exc()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    logged = "".join(f"fitmedia: {r.getMessage()}\n" for r in caplog.records
                     if r.levelno >= logging.WARNING)
    err = capfd.readouterr().err
    return subprocess.CompletedProcess(argv, code, "", logged + err + trace)


@pytest.mark.slow
@pytest.mark.parametrize("case", corpus.cases(), ids=lambda c: c.name)
def test_bad_input_corpus(corpus_base, case, capfd, caplog, monkeypatch):
    """Each case of the bad-input corpus through the real entry point: its exit code, the words
    of its one-line message, no traceback, an answer within the case's timeout (10 s: no
    hang), and nothing left in its --out folder.  The reference is the case table itself
    (make_corpus.py), written from issue 17.  ``SUBPROCESS_CASES`` run as
    ``python -m fitmedia.cli`` in a subprocess, the others through ``fitmedia.cli.main`` in
    this process (``run_in_process``; since 2026-12-01, docs/testing.md "Test costs")."""
    root, base = corpus_base
    d = corpus.build_case(case, root, base)
    if case.name in SUBPROCESS_CASES:
        res, _ = corpus.run_case(case, d, base)
    else:
        res = run_in_process(case, d, base, capfd, caplog, monkeypatch)
    assert corpus.problems(case, res, d) == [], res.stderr


def test_every_subprocess_case_is_in_the_corpus():
    """The names in SUBPROCESS_CASES are corpus cases (a renamed case would silently move to
    the in-process runs); reference: the case table."""
    assert SUBPROCESS_CASES <= {c.name for c in corpus.cases()}


@pytest.mark.parametrize("cores, channels, expected", [(2, 3, 3), (2, 1, 1), (1, 3, 1),
                                                       (2, 4, 2), (1, 2, 1),
                                                       (16, 3, 3), (None, 3, 1)])
def test_default_workers_and_the_memory_estimate_agree(monkeypatch, cores, channels, expected):
    """The channels fitted at once by default (fitmedia.memory.default_workers): one process
    per channel where there are fewer channels than twice the cores (3 on 2: all at once, so
    that none runs alone at the end), else one per core; and the fit's memory estimate counts
    that many processes
    (it refuses a fit up front by that figure)."""
    from fitmedia.memory import default_workers, estimate_peak
    from fitmedia.spec import parse_spec
    from conftest import geometry_dict

    monkeypatch.setattr("os.cpu_count", lambda: cores)
    assert default_workers(channels) == expected
    spec = parse_spec(geometry_dict(width=64, height=48), require_images=False)
    n = len(spec.channels)
    assert estimate_peak(spec, "fit") == estimate_peak(spec, "fit",
                                                       workers=default_workers(n, spec))


def test_default_workers_stay_one_per_core_where_more_would_not_fit_in_memory(monkeypatch):
    """More processes than cores (3 channels on 2 cores) only where the memory estimate for
    them is within the limit: with FITMEDIA_MAX_MEMORY_GB between the estimates for 2 and 3
    processes, the default is 2 and the fit is not refused (check_memory); above both, 3.
    Reference: estimate_peak at an explicit worker count, the limit set between its values."""
    from fitmedia.memory import ENV_LIMIT, check_memory, default_workers, estimate_peak
    from fitmedia.spec import parse_spec
    from conftest import geometry_dict

    monkeypatch.setattr("os.cpu_count", lambda: 2)
    spec = parse_spec(geometry_dict(width=64, height=48), require_images=False)
    assert len(spec.channels) == 3
    two, three = (estimate_peak(spec, "fit", workers=w) for w in (2, 3))
    assert two < three
    monkeypatch.setenv(ENV_LIMIT, str((two + three) / 2 / 2**30))
    assert default_workers(3, spec) == 2 and default_workers(3) == 3
    check_memory(spec, "fit")  # not refused: one process per core fits
    monkeypatch.setenv(ENV_LIMIT, str(1.01 * three / 2**30))
    assert default_workers(3, spec) == 3


def test_the_memory_check_counts_the_workers_asked_for(monkeypatch, tmp_path, capsys):
    """`fit --workers N`'s memory check counts N processes (at most one per channel), not the
    default: with FITMEDIA_MAX_MEMORY_GB between the estimates for 1 and 3 processes, three
    workers are refused up front (exit 2, one line naming --workers, before any image is
    read) and one worker passes the check.  Reference: estimate_peak at explicit worker
    counts, the limit set between its values (before, --workers was ignored: the default's
    figure was checked either way)."""
    from fitmedia.cli import main
    from fitmedia.data import bundled_path
    from fitmedia.memory import ENV_LIMIT, check_memory, estimate_peak
    from fitmedia.spec import load_spec

    spec_path = bundled_path("synthetic", "default", "capture.yaml")
    spec = load_spec(spec_path)
    one, three = (estimate_peak(spec, "fit", workers=w) for w in (1, 3))
    assert estimate_peak(spec, "fit", workers=8) == three  # no more processes than channels
    monkeypatch.setenv(ENV_LIMIT, str((one + three) / 2 / 2**30))
    check_memory(spec, "fit", workers=1)
    code = main(["fit", str(spec_path), "--workers", "3", "--no-mcmc", "--out",
                 str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--workers" in err[0] and "GiB" in err[0]
    assert not (tmp_path / "out" / "results.json").exists()

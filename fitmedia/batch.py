"""Many fits at once on Dask: synthetic validation (round trips synth -> fit over media
and dilutions, scored for the calibration of the credible intervals) and fitting a list
of captures.  Each task (a round, a capture) writes its own folder and fits its channels
serially (``FitOptions(workers=1)``; Dask gives the parallelism, one task per
single-threaded worker process).  A task's result depends only on its inputs and seed,
not on where or when it ran: a cluster, a laptop and ``scheduler="serial"`` (this
process, no Dask) give the same numbers, and a rerun skips what is finished.
Dask, tqdm and matplotlib are imported inside the functions that use them.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import BlackImageError, InputError
from .inference.result import read_result
from .util import check_output_dir, write_json

#: validate's default paths per pixel of a ``hybrid`` capture's multiple-scattering term: far
#: more than the fit's last term (4096), whose realisation error a capture's own must stay
#: well below (docs/validation.md: at 4096 an Espresso 29 ml capture, 32 x 24 px, put the
#: fit's values at the truth 4-7 % low in kappa_t; at 16384, within 1.5 %)
HYBRID_SPP = 16384

if TYPE_CHECKING:  # pragma: no cover  (imported in the functions: `fitmedia --help` stays fast)
    from .inference.result import FitOptions, FitResult
    from .validate import Score, ValidationResult

#: Geometry used by :func:`validate` when none is given (full size, 200 x 150 pixels).
DEFAULT_GEOMETRY = Path(__file__).resolve().parent / "data" / "capture_specs" / "bulb.yaml"
#: Volume of liquid drawn per round when ``ml`` is not given: log-uniform in this range, ml.
ML_RANGE = (8.0, 240.0)
#: ``scheduler`` value that runs every task in this process, one after the other, without Dask.
SERIAL = "serial"
#: Fit options that may differ between a finished round and a rerun that resumes it.
_FREE_OPTIONS = ("seed", "workers", "progress", "resume")


#: identity fields of a round that older round.json files lack, with the value they had
_ROUND_DEFAULTS = {"synth_model": "single", "synth_spp": 256}


@dataclass(frozen=True)
class RoundTask:
    """One synthetic round trip: what to synthesise, where, with which seed."""

    index: int
    medium: str
    ml: tuple[float, ...]
    seed: int
    geometry: str
    geometry_sha256: str
    tank_ml: float
    out: str
    options: FitOptions
    synth_model: str = "single"  # how the capture is rendered (synth --model)
    synth_spp: int = 256  # its paths per pixel (hybrid) or samples per pixel (full)

    def identity(self) -> dict:
        """The fields a finished round must share with this task to be reused."""
        return {"medium": self.medium, "ml": list(self.ml), "seed": self.seed,
                "tank_ml": self.tank_ml, "geometry_sha256": self.geometry_sha256,
                "synth_model": self.synth_model, "synth_spp": self.synth_spp,
                "options": {k: v for k, v in asdict(self.options).items()
                            if k not in _FREE_OPTIONS}}


# ---------------------------------------------------------------------------------------------
# running tasks: in this process, on a local cluster or on an existing scheduler


@contextmanager
def dask_client(scheduler: str | None, n_workers: int) -> Iterator[Any]:
    """A ``distributed.Client``: on a new ``LocalCluster`` (``scheduler`` None) of
    ``n_workers`` single-threaded worker processes, or connected to ``scheduler`` (an
    address such as ``tcp://10.0.0.5:8786``).  Both are closed on exit.

    Local workers start without Dask's default ``MALLOC_TRIM_THRESHOLD_=65536``, with which
    a fit's large numpy temporaries are returned to the OS and paged in again: one 40 x 30
    round took 50-60 s of CPU instead of 19-21 s (Dask 2026.8, 2-core Linux VM).  The environment
    Dask's nanny writes into this process (OMP_NUM_THREADS=1 ...) is restored on exit.
    """
    import dask
    from distributed import Client, LocalCluster

    if scheduler is None:
        saved = dict(os.environ)
        if not logging.getLogger("fitmedia").isEnabledFor(logging.INFO):
            logging.getLogger("distributed").setLevel(logging.WARNING)  # start-up chatter
        try:
            # dashboard on a free port (":0"): nothing listens on a fixed port, so no "port in
            # use" warning (dashboard_address=None does not disable it: dask/distributed#8136)
            with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_":
                                  None}), \
                    LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                                 dashboard_address=":0") as cluster, Client(cluster) as client:
                yield client
        finally:
            for k in set(os.environ) - set(saved):
                del os.environ[k]
            os.environ.update(saved)
        return
    try:
        client = Client(scheduler)
    except (OSError, TimeoutError, ValueError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"--scheduler: cannot connect to {scheduler!r}: {first}") from None
    with client:
        yield client


def run_tasks(fn: Callable[[Any], dict], tasks: Sequence[Any], *, scheduler: str | None,
              n_workers: int, progress: bool, desc: str, done: int = 0) -> list[dict]:
    """``[fn(t) for t in tasks]`` in that order, on Dask unless ``scheduler`` is ``"serial"``;
    ``fn`` must be importable by the workers.  A tqdm bar counts ``done`` earlier tasks too."""
    from tqdm.auto import tqdm

    out: list[dict] = [{} for _ in tasks]
    if not tasks:
        return out
    if scheduler == SERIAL:
        with tqdm(total=len(tasks) + done, initial=done, desc=desc, unit="task",
                  disable=not progress) as bar:
            for i, t in enumerate(tasks):
                out[i] = fn(t)
                bar.update()
        return out
    from distributed import as_completed

    with dask_client(scheduler, n_workers) as client, \
            tqdm(total=len(tasks) + done, initial=done, desc=desc, unit="task",
                 disable=not progress) as bar:
        futures = client.map(fn, list(tasks), pure=False)
        where = {f.key: i for i, f in enumerate(futures)}
        for fut in as_completed(futures):
            out[where[fut.key]] = fut.result()
            bar.update()
    return out


def _check_runner(scheduler: str | None, n_workers: int) -> None:
    if scheduler is not None and (not isinstance(scheduler, str) or not scheduler.strip()):
        raise InputError(f"--scheduler: got {scheduler!r}: expected an address "
                         f"(tcp://host:8786) or {SERIAL!r}")
    if scheduler is None and not _is_int(n_workers, 1):
        raise InputError(f"--workers: got {n_workers!r}: expected a positive integer")


def _read_json(path: Path) -> dict | None:
    """The JSON object in ``path``, or None when it is missing or unreadable (half-written)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


# ---------------------------------------------------------------------------------------------
# validation


def round_seed_and_ml(seed: int, index: int, ml: Sequence[float] | None,
                      ml_range: tuple[float, float] = ML_RANGE) -> tuple[int, tuple]:
    """The seed of round ``index`` and its ml (``ml`` if given, else one volume drawn
    log-uniformly in ``ml_range``, to 0.1 ml), both from ``SeedSequence([seed, index])``
    so they depend on the round's number only, not on the scheduling or the number of rounds."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, index]))
    round_seed = int(rng.integers(2**31 - 1))
    if ml is None:
        drawn = float(np.exp(rng.uniform(np.log(ml_range[0]), np.log(ml_range[1]))))
        return round_seed, (round(drawn, 1),)
    return round_seed, tuple(float(v) for v in ml)


def score_round(out: Path, medium_name: str, ml: Sequence[float]) -> list[Score]:
    """Score a round from its files (round/fit/samples.npz, the medium's table values),
    as :func:`fitmedia.validate.round_trip` does; used when a round's fit finished but
    its round.json was not written."""
    from .medium import medium_by_name
    from .validate import score_fit

    return score_fit(out / "fit", medium_by_name(medium_name), list(ml), name=medium_name,
                     spec=out / "capture" / "capture.yaml")


def _run_round(task: RoundTask) -> dict:
    """Run (or finish) one round; returns its record and writes round.json.  Dask task."""
    from .medium import medium_by_name
    from .spec import load_spec
    from .validate import round_trip

    out = Path(task.out)
    out.mkdir(parents=True, exist_ok=True)  # capture/ and fit/ then stage inside it, not beside OUT
    record: dict = {"index": task.index, "dir": out.name, **task.identity()}
    t0 = time.perf_counter()
    try:
        truth = _read_json(out / "capture" / "truth.json")
        fitted = read_result(out / "fit" / "results.json")
        if fitted and truth and truth.get("seed") == task.seed \
                and truth.get("medium") == task.medium \
                and not _identity_differs(fitted, out / "capture" / "capture.yaml", task.options):
            scores = score_round(out, task.medium, task.ml)
        else:
            geometry = load_spec(task.geometry, require_images=False)
            scores = round_trip(geometry, medium_by_name(task.medium), list(task.ml), out,
                                seed=task.seed, options=task.options, tank_ml=task.tank_ml,
                                name=task.medium, synth_model=task.synth_model,
                                synth_spp=task.synth_spp)
    except BlackImageError as exc:  # a capture with no glow (dense end of ML_RANGE): no score
        return {**record, "status": "skipped", "error": str(exc)}
    except InputError as exc:
        return {**record, "status": "failed", "error": str(exc)}
    results = read_result(out / "fit" / "results.json")
    record.update(status="done", wall_time_s=time.perf_counter() - t0,
                  scores=[asdict(s) for s in scores], trust=_trust_summary(results),
                  run_identity=results.run_identity if results else None)
    write_json(out / "round.json", record)
    return record


def _identity_differs(results: FitResult, spec: str | Path, options: FitOptions) -> list[str]:
    """What differs between the run identity in an earlier fit's ``results`` and a fit of
    ``spec`` with ``options`` now (:mod:`fitmedia.inference.identity`); empty: the same."""
    from .inference.identity import identity_differences
    from .pipeline import capture_identity

    return identity_differences(results.run_identity, capture_identity(spec, options))


def _finished_round(task: RoundTask) -> dict | None:
    """The record of a finished round in the task's folder, or None; a finished round of a
    different medium, ml, seed, geometry or fit options is an error (a reused ``out_dir``)."""
    from .validate import SCORED

    rec = _read_json(Path(task.out) / "round.json")
    if rec is None or rec.get("status") != "done":
        return None
    mine = json.loads(json.dumps(task.identity()))
    # rounds written before the synthesis model was recorded were synthesised by 'single'
    theirs = {k: rec.get(k, _ROUND_DEFAULTS.get(k)) for k in mine}
    # an option added to FitOptions after the round ran: it ran with the default
    defaults = asdict(type(task.options)())
    old = theirs["options"] if isinstance(theirs["options"], dict) else {}
    theirs["options"] = {k: old.get(k, defaults[k]) for k in mine["options"]}
    if theirs != mine:
        diff = ", ".join(f"{k} {theirs[k]!r} (now {mine[k]!r})" for k in mine if theirs[k] != mine[k])
        raise InputError(f"--out: {task.out} holds a finished round with {diff}; "
                         "use a new --out folder or the same settings")
    scores = rec.get("scores") or []
    if scores and (any(s.get("optical_depth") is None or "trusted" not in s for s in scores)
                   or {s["quantity"] for s in scores} != set(SCORED)):
        # scored before scores carried the optical depth, the fit's trust or kappa_s': score it
        # again from its files
        rec["scores"] = [asdict(s) for s in score_round(Path(task.out), task.medium, task.ml)]
        write_json(Path(task.out) / "round.json", {**rec, "status": "done"})
    return {**rec, "status": "done earlier"}


def _is_int(x: Any, lowest: int) -> bool:
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool) and x >= lowest


def synth_choice(fit_model: str, synth_model: str | None, synth_spp: int | None
                 ) -> tuple[str, int]:
    """validate's synthesis model and its paths (or samples) per pixel, defaults filled in
    (:func:`validate`); a bad value is an InputError naming the option."""
    model = synth_model or ("single" if fit_model == "single" else "hybrid")
    if model not in ("single", "hybrid", "full"):
        raise InputError(f"--synth-model: expected 'single', 'hybrid' or 'full', got {model!r}")
    spp = synth_spp if synth_spp is not None else (HYBRID_SPP if model == "hybrid" else 256)
    if not _is_int(spp, 16):
        raise InputError(f"--synth-spp: expected an integer >= 16, got {spp!r}")
    return model, int(spp)


def _check_validate_args(media: list[str], rounds: int, ml: list[float] | None, seed: int,
                         tank_ml: float, options: FitOptions) -> list[str]:
    from .medium import medium_by_name

    if not _is_int(rounds, 1):
        raise InputError(f"--rounds: got {rounds!r}: expected a positive integer")
    if not _is_int(seed, 0):
        raise InputError(f"--seed: got {seed!r}: expected an integer >= 0")
    if not media:
        raise InputError("--media: no medium given; name one or more of the Narasimhan 2006 table")
    names = []
    for m in media:
        try:
            names.append(medium_by_name(m).name)
        except InputError as exc:
            raise InputError("--media" + str(exc).removeprefix("--medium")) from None
    if not (np.isfinite(tank_ml) and tank_ml > 0):
        raise InputError(f"--tank-ml: got {tank_ml}: expected a positive volume in ml")
    for v in ml or []:
        if not (np.isfinite(v) and 0 < v < tank_ml):
            raise InputError(f"--ml: got {v}: expected ml of liquid between 0 and {tank_ml:g}")
    if ml is not None and len(ml) == 0:
        raise InputError("--ml: no volume given")
    if not options.mcmc:
        raise InputError("options.mcmc: False: validation scores posterior samples; "
                         "run it with the sampler")
    return names


def ml_range_for_optical_depth(spec, medium_name: str, optical_depth: tuple[float, float],
                               tank_ml: float, channel: str = "G") -> tuple[float, float]:
    """The ml of ``medium_name`` in ``tank_ml`` that put the tank's optical depth light-to-wall
    (``fitmedia.regimes``, in ``channel``, with the spec's water absorption) at the ends of
    ``optical_depth``; ml log-uniform in this range is optical depth log-uniform in its range."""
    from .medium import medium_by_name
    from .regimes import concentration_for_optical_depth
    from .spec import CHANNELS

    ci = CHANNELS.index(channel)
    kt = float(medium_by_name(medium_name).kappa_t[ci])
    lo, hi = (tank_ml * concentration_for_optical_depth(spec, kt, ci, t) for t in optical_depth)
    if not 0 < lo < hi < tank_ml:
        raise InputError(f"--optical-depth: {optical_depth[0]:g}-{optical_depth[1]:g} needs "
                         f"{lo:.3g}-{hi:.3g} ml of {medium_name} in {tank_ml:g} ml, not possible "
                         "with this spec's water absorption and tank")
    return lo, hi


# long: the numpy-style docstring of its 11 parameters is 45 lines; the body is 14
def validate(media: list[str], rounds: int, out_dir: str | Path, *,
             ml: list[float] | None = None, geometry: str | Path | None = None, seed: int = 0,
             scheduler: str | None = None, n_workers: int = 2,
             options: FitOptions | None = None, tank_ml: float = 23000.0,
             optical_depth: tuple[float, float] | None = None, synth_model: str | None = None,
             synth_spp: int | None = None) -> ValidationResult:
    """Synthetic round trips (synth -> fit) spread over ``media``, scored for coverage.

    Parameters
    ----------
    media : list of str
        Names from the Narasimhan et al. 2006 table; round i uses ``media[i % len(media)]``.
    rounds : int
        Number of round trips (each fits R, G and B: 3 scores per quantity and round).
    out_dir : str or Path
        Round i writes ``out_dir/round_{i:04d}/`` (``capture/``, ``fit/``, ``round.json``);
        then ``coverage.json``, ``coverage.txt``, ``coverage.png``.  A rerun skips finished rounds.
    ml : list of float, optional
        ml of liquid per image of every round (several: a dilution series).  Default: one
        image per round, drawn log-uniformly in 8-240 ml from the round's seed.
    geometry : str or Path, optional
        Capture spec whose geometry is used as given (images, calibration ignored).
        Default ``capture_specs/bulb.yaml`` (200 x 150 pixels: minutes per round).
    seed : int
        Round i's seed is derived from ``(seed, i)`` (:func:`round_seed_and_ml`).
    scheduler : str, optional
        None: a new ``LocalCluster`` of ``n_workers`` single-threaded processes; an address
        (``tcp://host:8786``): that Dask scheduler, whose workers import this fitmedia and see
        ``out_dir`` and ``geometry`` at the same paths; ``"serial"``: in this process, no Dask.
    n_workers : int
        Worker processes of the local cluster.
    options : FitOptions, optional
        Fit settings (default ``FitOptions(model="single")``: validate checks the single-
        scattering fit on its own renders unless told otherwise, where ``fit``'s default is
        ``auto``); in a round ``seed`` becomes the round's,
        ``workers`` 1, ``progress`` False.  ``options.progress`` shows a bar over the rounds.
    tank_ml : float
        Water in the tank, ml.
    optical_depth : (lo, hi), optional
        Instead of 8-240 ml, draw each round's ml so that the G channel's optical depth
        light-to-wall (:mod:`fitmedia.regimes`) is log-uniform in ``lo``-``hi``: a capture
        planned for a regime (docs/validation.md).  Not with ``ml``.
    synth_model : {'single', 'hybrid', 'full'}, optional
        How each capture is rendered (``fitmedia synth --model``).  Default: ``single`` for a
        single-scattering fit, ``hybrid`` (analytic single scattering plus fitmedia's own
        multiple-scattering term, traced with other random numbers than the fit's) for
        ``options.model`` full or auto: Mitsuba's own render noise at any affordable spp is
        above the camera's (docs/validation.md, "Full transport").
    synth_spp : int, optional
        Paths per pixel of the hybrid term (default ``HYBRID_SPP``) or Mitsuba's samples per pixel
        (default 256).

    Returns
    -------
    ValidationResult
    """
    from .inference.result import FitOptions
    from .validate import Score, write_coverage

    options = options or FitOptions(model="single")
    _check_runner(scheduler, n_workers)
    tasks, records = validation_tasks(media, rounds, out_dir, ml=ml, geometry=geometry, seed=seed,
                                      options=options, tank_ml=tank_ml,
                                      optical_depth=optical_depth, synth_model=synth_model,
                                      synth_spp=synth_spp)
    out = Path(os.path.abspath(Path(out_dir).expanduser()))  # as validation_tasks checked it
    ran = run_tasks(_run_round, tasks, scheduler=scheduler, n_workers=n_workers,
                    progress=options.progress, desc="rounds", done=len(records))
    records.update({r["index"]: r for r in ran})
    ordered = [records[i] for i in range(rounds)]
    scores = [Score.from_record(s) for r in ordered for s in r.get("scores", [])]
    return write_coverage(out, ordered, scores)


def validation_tasks(media: list[str], rounds: int, out_dir: str | Path, *, ml, geometry,
                     seed: int, options: FitOptions, tank_ml: float, optical_depth, synth_model,
                     synth_spp) -> tuple[list[RoundTask], dict[int, dict]]:
    """:func:`validate`'s rounds (its arguments, checked): the tasks still to run, and the
    records of the rounds ``out`` holds finished, by index.  A study may run a subset of the
    tasks (docs/studies/coverage_rounds.py); validate then reads them back as finished."""
    from .spec import load_spec

    names = _check_validate_args(media, rounds, ml, seed, tank_ml, options)
    synth_model, synth_spp = synth_choice(options.model, synth_model, synth_spp)
    out = check_output_dir(out_dir)  # each round then writes its folders atomically
    geo = Path(geometry) if geometry is not None else DEFAULT_GEOMETRY
    if geometry is None and not geo.is_file():
        raise InputError(f"--spec: not given, and the default {geo} is not there")
    geo_spec = load_spec(geo, require_images=False)  # bad geometry fails here, before any round
    ranges = _ml_ranges(geo_spec, names, ml, optical_depth, tank_ml)
    sha = hashlib.sha256(geo.read_bytes()).hexdigest()
    tasks, records = [], {}
    for i in range(rounds):
        rseed, rml = round_seed_and_ml(seed, i, ml, ranges[names[i % len(names)]])
        task = RoundTask(i, names[i % len(names)], rml, rseed, str(geo.resolve()), sha,
                         float(tank_ml), str(out / f"round_{i:04d}"),
                         replace(options, seed=rseed, workers=1, progress=False, resume=False),
                         synth_model, synth_spp)
        rec = _finished_round(task)
        if rec is None:
            tasks.append(task)
        else:
            records[i] = rec
    return tasks, records


def _ml_ranges(geo_spec, names: list[str], ml, optical_depth, tank_ml: float) -> dict:
    """Per medium, the range its rounds' ml are drawn from: ``ML_RANGE``, or the ml that put
    the G channel's optical depth at the ends of ``optical_depth``."""
    if optical_depth is None:
        return {n: ML_RANGE for n in names}
    if ml is not None:
        raise InputError("--optical-depth: not with --ml (it chooses the ml)")
    lo, hi = (float(t) for t in optical_depth)
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo < hi):
        raise InputError(f"--optical-depth: got {lo:g} {hi:g}: expected 0 < LO < HI")
    return {n: ml_range_for_optical_depth(geo_spec, n, (lo, hi), tank_ml) for n in names}


# ---------------------------------------------------------------------------------------------
# many captures


@dataclass(frozen=True)
class FitTask:
    spec: str
    name: str
    out: str
    options: FitOptions
    report: bool


def _summary_record(task: FitTask, result: FitResult, status: str) -> dict:
    """fit-many's record of one fitted capture (summary.json)."""
    key, p = result.statistic, result.parameters
    est = {q: {ch: {"value": result.value(q, ch, key), "std": p[q][ch].get("std")}
               for ch in result.channels} for q in ("kappa_a", "kappa_s", "g") if q in p}
    return {"spec": task.spec, "name": task.name, "out": task.out, "status": status,
            "statistic": key, "units": "1/mm (kappa), undiluted", "estimates": est,
            "converged": result.converged, "trust": _trust_summary(result),
            "wall_time_s": result.wall_time_s, "run_identity": result.run_identity}


def _trust_summary(result: FitResult | None) -> dict | None:
    """The misfit guard's verdict of a fit (``ok``, ``reasons``, ``notes``); None for a
    results.json without one."""
    t = result.trust if result is not None else None
    return {k: t.get(k) for k in ("ok", "reasons", "reason_kinds", "notes")} if t else None


def _run_fit(task: FitTask) -> dict:
    """Fit one capture; an InputError is returned as a failed record.  Dask task."""
    from .pipeline import fit

    Path(task.out).parent.mkdir(parents=True, exist_ok=True)  # the fit stages inside OUT
    try:
        results = fit(task.spec, task.out, task.options, report=task.report)
    except InputError as exc:
        return {"spec": task.spec, "name": task.name, "out": task.out, "status": "failed",
                "error": str(exc)}
    return _summary_record(task, results, "done")


def fit_many(specs: list[str | Path], out_dir: str | Path, *, scheduler: str | None = None,
             n_workers: int = 2, options: FitOptions | None = None,
             report: bool = True) -> list[dict]:
    """Fit many captures, as ``fitmedia fit`` does, spread over Dask.

    Parameters
    ----------
    specs : list of str or Path
        Capture i writes ``out_dir/<stem>/`` (stem: the spec's file name without suffix), or
        ``out_dir/<i:04d>_<stem>/`` when two specs share a stem.  A folder that already holds
        a readable results.json of the same run identity (spec, images, options, version:
        :mod:`fitmedia.inference.identity`) is not fitted again; one of another identity is
        an InputError, before any fitting.
    out_dir : str or Path
        Also receives ``summary.json`` (the returned records).
    scheduler, n_workers, options
        As in :func:`validate` (``options.seed`` is used for every capture).
    report : bool
        Also write each fit's report.html.

    Returns
    -------
    list of dict
        Per capture: ``spec``, ``name``, ``out``, ``status`` (``"done"``, ``"done earlier"``
        or ``"failed"`` with the InputError's message in ``error``); for fits
        ``estimates.<kappa_a|kappa_s|g>.<ch>`` (``value``: posterior median, or MAP without
        sampler, 1/mm undiluted; ``std``) and ``converged``.
    """
    if not specs:
        raise InputError("SPEC: no capture spec given")
    from .inference.result import FitOptions

    options = options or FitOptions()
    _check_runner(scheduler, n_workers)
    out = check_output_dir(out_dir)  # each capture's fit then writes its folder atomically
    stems = [Path(s).stem for s in specs]
    unique = len(set(stems)) == len(stems)
    inner = replace(options, workers=1, progress=False)
    records: dict[int, dict] = {}
    todo, where = [], []
    for i, (s, stem) in enumerate(zip(specs, stems)):
        name = stem if unique else f"{i:04d}_{stem}"
        task = FitTask(str(Path(s).resolve()), name, str(out / name), inner, report)
        prior = read_result(out / name / "results.json")
        if prior is not None:
            diff = _identity_differs(prior, task.spec, inner)
            if diff:
                raise InputError(f"--out: {task.out} holds a fit of another run (what differs: "
                                 f"{'; '.join(diff)}); use a new --out folder or remove it")
            records[i] = _summary_record(task, prior, "done earlier")
        else:
            todo.append(task)
            where.append(i)
    ran = run_tasks(_run_fit, todo, scheduler=scheduler, n_workers=n_workers,
                    progress=options.progress, desc="captures", done=len(records))
    records.update(zip(where, ran))
    summary = [records[i] for i in range(len(specs))]
    write_json(out / "summary.json", {"captures": summary,
                                      "n_failed": sum(r["status"] == "failed" for r in summary)})
    return summary


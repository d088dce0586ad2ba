"""Batch runs (fitmedia.batch): validation round trips give the same numbers on a Dask
LocalCluster as in this process, reruns resume, and fit_many records a broken capture
without stopping the others.

These use REDUCED settings: a 40 x 30 pixel geometry and FitOptions(max_steps=300,
n_tau=5).  They check the machinery (seeds, scheduling, resume, files), not the
calibration of the posterior: at this size and chain length the credible intervals are
not expected to cover the truth (docs/validation.md gives the settings of a real run).
One round costs one reduced fit: 12-45 s of CPU on a 2-core VM, depending on the version of
the forward model.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import geometry_dict

from fitmedia import batch, cli
from fitmedia.batch import fit_many, round_seed_and_ml, validate
from fitmedia.errors import InputError
from fitmedia.inference.fit import FitOptions

MEDIA = ["Lowfat Milk", "Espresso"]
OPTIONS = FitOptions(model="single", max_steps=300, n_tau=5, progress=False)  # reduced: see module docstring
# the rounds' ml drawn where the capture is informative: at the default range's dense end
# (Lowfat Milk 169 ml at 40 x 30) a single-scattering capture is black and is skipped
# (test_black_round_is_skipped_not_failed)
OPTICAL_DEPTH = (0.3, 3.0)


@pytest.fixture(scope="module")
def geometry(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("geom") / "geometry.yaml"
    path.write_text(yaml.safe_dump(geometry_dict(width=40, height=30)))
    return path


@pytest.fixture(scope="module")
def serial_run(tmp_path_factory, geometry):
    """Two rounds (one milk, one espresso) in this process, no Dask."""
    out = tmp_path_factory.mktemp("serial")
    return out, validate(MEDIA, 2, out, geometry=geometry, seed=7, scheduler="serial",
                         options=OPTIONS, optical_depth=OPTICAL_DEPTH)


def _key(scores):
    return [(s.medium, s.ml, s.channel, s.quantity, s.median, s.std, s.pit) for s in scores]


def test_dask_local_cluster_gives_the_serial_results(serial_run, geometry, tmp_path):
    """The same seeds on a LocalCluster of 2 worker processes give bit-identical posterior
    medians, standard deviations and PITs as the serial run, and the same coverage files."""
    _, serial = serial_run
    res = validate(MEDIA, 2, tmp_path, geometry=geometry, seed=7, scheduler=None, n_workers=2,
                   options=OPTIONS, optical_depth=OPTICAL_DEPTH)
    assert [r["status"] for r in res.rounds] == ["done", "done"]
    assert len(res.scores) == 2 * 3 * 4  # rounds x channels x (kappa_s, kappa_t, g, kappa_s')
    assert _key(res.scores) == _key(serial.scores)
    assert res.coverage["quantities"] == serial.coverage["quantities"]
    for f in ("coverage.json", "coverage.txt", "coverage.png"):
        assert (tmp_path / f).stat().st_size > 0
    assert (tmp_path / "round_0001" / "fit" / "results.json").is_file()


def test_serial_run_files(serial_run):
    out, res = serial_run
    cov = json.loads((out / "coverage.json").read_text())
    assert set(cov["quantities"]) == {"kappa_s", "kappa_t", "g", "kappa_s_reduced"}
    assert set(cov["media"]) == set(MEDIA)
    for q in cov["quantities"].values():
        assert q["n"] == 6 and set(q["coverage"]) == {"68", "90", "99"}
    assert [r["medium"] for r in cov["rounds"]] == MEDIA
    assert (out / "coverage.txt").read_text() == res.table
    assert "kappa_t" in res.table and "criteria" in res.table
    assert (out / "coverage.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _rerun_fitting_nothing(out: Path, geometry: Path, monkeypatch):
    """serial_run's validate again in ``out``, where fitting any round fails the test."""
    def no_fit(*args, **kwargs):
        raise AssertionError("a finished round was fitted again")

    monkeypatch.setattr("fitmedia.validate.round_trip", no_fit)
    return validate(MEDIA, 2, out, geometry=geometry, seed=7, scheduler="serial",
                    options=OPTIONS, optical_depth=OPTICAL_DEPTH)


def test_rerun_skips_finished_rounds(serial_run, geometry, tmp_path, monkeypatch):
    """A rerun refits nothing: finished rounds are read back; a round whose fit finished but
    whose round.json is missing is rescored from its files, with the same scores."""
    src, first = serial_run
    out = tmp_path / "copy"
    shutil.copytree(src, out)
    (out / "round_0001" / "round.json").unlink()
    before = (out / "round_0001" / "fit" / "results.json").stat().st_mtime_ns
    res = _rerun_fitting_nothing(out, geometry, monkeypatch)
    assert [r["status"] for r in res.rounds] == ["done earlier", "done"]
    assert _key(res.scores) == _key(first.scores)
    assert (out / "round_0001" / "fit" / "results.json").stat().st_mtime_ns == before
    again = validate(MEDIA, 2, out, geometry=geometry, seed=7, scheduler="serial",
                     options=OPTIONS, optical_depth=OPTICAL_DEPTH)
    assert [r["status"] for r in again.rounds] == ["done earlier", "done earlier"]


def test_rounds_known_by_their_records_alone(serial_run, geometry, tmp_path, monkeypatch):
    """A round whose folder holds only its round.json (kept elsewhere and put back, as
    docs/studies/coverage_rounds.py does between sessions) is finished: nothing is fitted
    again and the coverage is the run's own.  ``validation_tasks`` on an empty folder gives
    the tasks the run ran: the medium, ml and seed of each round's record."""
    from fitmedia.batch import validation_tasks

    src, first = serial_run
    tasks, done = validation_tasks(MEDIA, 2, tmp_path / "new", ml=None, geometry=geometry,
                                   seed=7, options=OPTIONS, tank_ml=23000.0,
                                   optical_depth=OPTICAL_DEPTH, synth_model=None,
                                   synth_spp=None)
    assert done == {} and [t.index for t in tasks] == [0, 1]
    for t, r in zip(tasks, first.rounds):
        assert (t.medium, list(t.ml), t.seed) == (r["medium"], r["ml"], r["seed"])
    out = tmp_path / "records"
    for i in range(2):
        (out / f"round_{i:04d}").mkdir(parents=True)
        shutil.copyfile(src / f"round_{i:04d}" / "round.json", out / f"round_{i:04d}" / "round.json")
    res = _rerun_fitting_nothing(out, geometry, monkeypatch)
    assert [r["status"] for r in res.rounds] == ["done earlier", "done earlier"]
    assert _key(res.scores) == _key(first.scores)
    assert res.coverage["quantities"] == first.coverage["quantities"]


def _staging_only(seen: list, above: Path, out: Path):
    """A stand-in for a task's writer: stages ``target`` (util.staged_output_dir), records the
    temporary folder's parent and every path under ``above`` outside ``out``, and stops."""
    from fitmedia.util import staged_output_dir

    def write(target: Path):
        with staged_output_dir(target) as stage:
            seen.append((stage.parent, sorted(str(p.relative_to(above)) for p in above.rglob("*")
                                              if not p.is_relative_to(out))))
            raise InputError("stopped after staging")
    return write


def test_tasks_stage_their_folders_inside_the_output_folder(geometry, capture, tmp_path,
                                                            monkeypatch):
    """A round's capture/ and fit-many's capture folders are written through
    util.staged_output_dir, whose hidden temporary folder lies in its target's nearest
    existing folder.  Until 2026-12-07 a fresh OUT's first tasks staged in the folder above
    OUT (seen in a 100 x 75 px validate run), where a killed task's litter outlived the rerun;
    now the task's folder is made first, and nothing is ever written beside OUT.  Checked on
    the staging itself (no fit): the temporary folder's parent, and what lies outside OUT
    while it exists."""
    seen: list = []
    out = tmp_path / "new" / "val"
    write = _staging_only(seen, tmp_path, out)
    monkeypatch.setattr("fitmedia.validate.round_trip",
                        lambda geometry, medium, ml, round_dir, **kw: write(round_dir / "capture"))
    res = validate(["Espresso"], 2, out, ml=[8.0], geometry=geometry, seed=1,
                   scheduler="serial", options=OPTIONS)
    assert [r["status"] for r in res.rounds] == ["failed", "failed"]
    assert seen == [(out / f"round_{i:04d}", ["new"]) for i in range(2)]
    seen.clear()
    above = tmp_path / "m"
    above.mkdir()
    many = above / "new" / "many"
    write = _staging_only(seen, above, many)
    monkeypatch.setattr("fitmedia.pipeline.fit", lambda spec, target, *a, **kw: write(Path(target)))
    recs = fit_many([capture], many, scheduler="serial", options=MAP_ONLY, report=False)
    assert [r["status"] for r in recs] == ["failed"]
    assert seen == [(many, ["new"])]
    assert not [p for p in tmp_path.rglob(".*")], "a temporary folder was left"


def test_rerun_with_other_settings_in_the_same_folder_is_refused(serial_run, geometry):
    out, _ = serial_run
    with pytest.raises(InputError, match="--out: .*round_0000.*seed"):
        validate(MEDIA, 2, out, geometry=geometry, seed=8, scheduler="serial", options=OPTIONS)
    with pytest.raises(InputError, match="--out: .*round_0000.*options.*'max_steps': 300"):
        validate(MEDIA, 2, out, geometry=geometry, seed=7, scheduler="serial",
                 options=replace(OPTIONS, max_steps=301), optical_depth=OPTICAL_DEPTH)


def test_rounds_from_before_the_synthesis_model_was_recorded(serial_run, geometry, tmp_path):
    """A round.json without ``synth_model``/``synth_spp`` (written before validate could
    render with the full-transport term) was synthesised by 'single' at the default spp: a
    rerun with those settings reuses it, and one that asks for hybrid captures is refused,
    naming the field."""
    src, _ = serial_run
    out = tmp_path / "old"
    shutil.copytree(src, out)
    for rnd in ("round_0000", "round_0001"):
        path = out / rnd / "round.json"
        rec = json.loads(path.read_text())
        assert rec.pop("synth_model") == "single" and rec.pop("synth_spp") == 256
        path.write_text(json.dumps(rec))
    res = validate(MEDIA, 2, out, geometry=geometry, seed=7, scheduler="serial", options=OPTIONS,
                   optical_depth=OPTICAL_DEPTH)
    assert [r["status"] for r in res.rounds] == ["done earlier", "done earlier"]
    with pytest.raises(InputError, match="--out: .*synth_model 'single' \\(now 'hybrid'\\)"):
        validate(MEDIA, 2, out, geometry=geometry, seed=7, scheduler="serial", options=OPTIONS,
                 optical_depth=OPTICAL_DEPTH, synth_model="hybrid")


@pytest.mark.parametrize("missing", ["optical_depth", "trusted", "kappa_s_reduced"])
def test_rounds_scored_without_a_later_field_are_scored_again(serial_run, geometry, tmp_path,
                                                              monkeypatch, missing):
    """A finished round whose round.json predates the optical depth, the fit's trust or the
    kappa_s' score is scored again from its files, not refitted: same scores, the new
    field as a fresh run computes it, and round.json updated."""
    src, first = serial_run
    out = tmp_path / "old"
    shutil.copytree(src, out)
    path = out / "round_0000" / "round.json"
    rec = json.loads(path.read_text())
    if missing == "kappa_s_reduced":
        rec["scores"] = [sc for sc in rec["scores"] if sc["quantity"] != missing]
    else:
        for sc in rec["scores"]:
            del sc[missing]
    path.write_text(json.dumps(rec))
    res = _rerun_fitting_nothing(out, geometry, monkeypatch)
    assert _key(res.scores) == _key(first.scores)
    assert [s.optical_depth for s in res.scores] == [s.optical_depth for s in first.scores]
    assert all(s.optical_depth and s.regime for s in res.scores)
    assert [s.trusted for s in res.scores] == [s.trusted for s in first.scores]
    assert all(isinstance(s.trusted, bool) for s in res.scores)
    stored = json.loads(path.read_text())["scores"]
    assert all(sc["optical_depth"] and "trusted" in sc for sc in stored)
    assert sum(sc["quantity"] == "kappa_s_reduced" for sc in stored) == 3
    assert "regime" in res.table


def test_reduced_scattering_score_from_the_samples(serial_run):
    """The kappa_s' score against kappa_s (1 - g) recomputed here from samples.npz and the
    truth (an independent recomputation of the same definition); its trust is results.json's."""
    out, res = serial_run
    fit = out / "round_0000" / "fit"
    trust = json.loads((fit / "results.json").read_text())["trust"]["ok"]
    rnd = [s for s in res.scores if s.medium == res.rounds[0]["medium"]]
    with np.load(fit / "samples.npz") as smp:
        for s in (s for s in rnd if s.quantity == "kappa_s_reduced"):
            ks = {q: next(x for x in rnd if x.channel == s.channel and x.quantity == q).truth
                  for q in ("kappa_s", "g")}
            red = smp[f"{s.channel}/kappa_s"] * (1 - smp[f"{s.channel}/g"])
            assert s.truth == pytest.approx(ks["kappa_s"] * (1 - ks["g"]), rel=1e-12)
            assert s.median == pytest.approx(float(np.median(red)), rel=1e-12)
            assert s.pit == pytest.approx(float(np.mean(red < s.truth)), abs=1e-12)
    assert all(s.trusted is trust for s in rnd)


def test_round_seeds_depend_on_seed_and_index_only():
    a = [round_seed_and_ml(3, i, None) for i in range(5)]
    assert a[:2] == [round_seed_and_ml(3, i, None) for i in range(2)]
    assert len({s for s, _ in a}) == 5
    assert all(8.0 <= ml[0] <= 240.0 for _, ml in a)
    assert round_seed_and_ml(3, 1, [16, 32])[1] == (16.0, 32.0)
    assert round_seed_and_ml(3, 1, [16])[0] == a[1][0]


def test_optical_depth_design_draws_ml_for_the_regime():
    """--optical-depth LO HI: every round's ml puts the truth's G-channel optical depth
    light-to-wall (fitmedia.regimes) inside LO-HI, and log-uniformly: the drawn depths' log
    mean is near the middle (a Kolmogorov-Smirnov test against log-uniform, 400 draws)."""
    from scipy.stats import kstest

    from fitmedia.batch import ml_range_for_optical_depth
    from fitmedia.medium import medium_by_name
    from fitmedia.spec import parse_spec
    from fitmedia.validate import optical_depths

    spec = parse_spec(geometry_dict(width=16, height=12), require_images=False)
    med = medium_by_name("Espresso")
    rng_ml = ml_range_for_optical_depth(spec, "Espresso", (0.1, 10.0), 23000.0)
    taus = []
    for i in range(400):
        _, (ml,) = round_seed_and_ml(5, i, None, rng_ml)
        d = geometry_dict(width=16, height=12)
        d["images"] = [{"path": "a.tiff", "exposure_s": 1.0, "concentration": ml / 23000}]
        taus.append(optical_depths(parse_spec(d, require_images=False), med, "G")[0])
    taus = np.array(taus)
    assert np.all((taus > 0.1 * 0.99) & (taus < 10.0 * 1.01))  # 0.1 ml rounding
    u = (np.log(taus) - np.log(0.1)) / (np.log(10.0) - np.log(0.1))
    assert kstest(np.clip(u, 0, 1), "uniform").pvalue > 0.01


@pytest.mark.parametrize("kwargs, words", [
    ({"media": ["Lowfat Mlik"]}, "--media: unknown medium 'Lowfat Mlik'"),
    ({"media": []}, "--media"),
    ({"rounds": 0}, "--rounds"),
    ({"seed": -1}, "--seed"),
    ({"ml": [-4.0]}, "--ml: got -4.0"),
    ({"options": FitOptions(mcmc=False)}, "options.mcmc"),
    ({"scheduler": None, "n_workers": 0}, "--workers"),
    ({"geometry": "missing.yaml"}, "missing.yaml"),
    ({"optical_depth": (2.0, 1.0)}, "--optical-depth: got 2 1"),
    ({"optical_depth": (0.1, 1.0), "ml": [16.0]}, "--optical-depth: not with --ml"),
    ({"optical_depth": (0.1, 1e5)}, "--optical-depth: 0.1-100000 needs"),
    ({"synth_model": "hybird"}, "--synth-model: expected 'single', 'hybrid' or 'full'"),
    ({"synth_spp": 3}, "--synth-spp: expected an integer >= 16, got 3"),
])
def test_bad_validate_input_is_an_input_error(kwargs, words, geometry, tmp_path):
    args = {"media": MEDIA, "rounds": 1, "out_dir": tmp_path, "geometry": geometry,
            "scheduler": "serial", "options": OPTIONS}
    args.update(kwargs)
    with pytest.raises(InputError, match=words):
        validate(args.pop("media"), args.pop("rounds"), args.pop("out_dir"), **args)
    assert not any(tmp_path.iterdir())  # nothing ran, nothing written


def test_local_cluster_workers_and_this_process_environment(monkeypatch):
    """Workers start without Dask's MALLOC_TRIM_THRESHOLD_ (a 2x slowdown of fits) and single-
    threaded; the environment Dask's nanny writes into this process is restored afterwards."""
    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    before = dict(os.environ)
    with batch.dask_client(None, 1) as client:
        env = client.run(lambda: {k: os.environ.get(k)
                                  for k in ("MALLOC_TRIM_THRESHOLD_", "OMP_NUM_THREADS")})
    assert list(env.values()) == [{"MALLOC_TRIM_THRESHOLD_": None, "OMP_NUM_THREADS": "1"}]
    assert dict(os.environ) == before


def test_unreachable_scheduler_is_an_input_error():
    import dask

    with pytest.raises(InputError, match="--scheduler: cannot connect to 'tcp://127.0.0.1:1'"), \
            dask.config.set({"distributed.comm.timeouts.connect": "1s"}), \
            batch.dask_client("tcp://127.0.0.1:1", 1):
        pass


@pytest.fixture(scope="module")
def capture(tmp_path_factory, geometry):
    from fitmedia.medium import medium_by_name
    from fitmedia.spec import load_spec
    from fitmedia.synth import synthesize

    d = tmp_path_factory.mktemp("cap")
    return synthesize(load_spec(geometry, require_images=False), d / "good",
                      medium_by_name("Lowfat Milk"), [16], seed=3)


MAP_ONLY = FitOptions(mcmc=False, global_evals=100, progress=False)  # fast: no sampler


@pytest.fixture(scope="module")
def many_run(capture, tmp_path_factory):
    """fit_many on a 2-worker LocalCluster: the good capture (MAP only, for speed) and a
    broken one (an image path that does not exist)."""
    data = yaml.safe_load(capture.read_text())
    data["images"][0]["path"] = "images/missing.tiff"
    broken = capture.parent / "broken.yaml"
    broken.write_text(yaml.safe_dump(data))
    out = tmp_path_factory.mktemp("many")
    specs = [capture, broken]
    return specs, out, fit_many(specs, out, scheduler=None, n_workers=2, options=MAP_ONLY,
                                report=False)


def test_fit_many_records_a_broken_capture_and_fits_the_others(many_run):
    _, out, recs = many_run
    assert [r["status"] for r in recs] == ["done", "failed"]
    assert [r["name"] for r in recs] == ["capture", "broken"]
    assert "images[0].path" in recs[1]["error"] and "\n" not in recs[1]["error"]
    assert recs[0]["statistic"] == "map"
    assert recs[0]["estimates"]["kappa_s"]["G"]["value"] > 0
    assert (out / "capture" / "results.json").is_file()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_failed"] == 1 and summary["captures"][1]["status"] == "failed"


def test_fit_many_rerun_skips_finished_captures(many_run, tmp_path):
    specs, out, recs = many_run
    shutil.copytree(out, tmp_path / "o")
    again = fit_many(specs, tmp_path / "o", scheduler="serial", options=MAP_ONLY, report=False)
    assert [r["status"] for r in again] == ["done earlier", "failed"]
    assert again[0]["estimates"] == recs[0]["estimates"]


def test_fit_many_same_stems_get_numbered_folders(tmp_path):
    recs = fit_many([tmp_path / "a" / "capture.yaml", tmp_path / "b" / "capture.yaml"],
                    tmp_path / "o", scheduler="serial", options=MAP_ONLY)
    assert [r["name"] for r in recs] == ["0000_capture", "0001_capture"]
    assert all(r["status"] == "failed" and "not found" in r["error"] for r in recs)


def _cli(argv: list[str]) -> int:
    """The subcommands as cli.py wires them (add_*_parser, then ``a.func(a)``)."""
    p = argparse.ArgumentParser(prog="fitmedia")
    sub = p.add_subparsers(dest="command", required=True)
    cli.add_validate_parser(sub)
    cli.add_fit_many_parser(sub)
    a = p.parse_args([str(x) for x in argv])
    return a.func(a)


def test_cli_fit_many_exit_code_and_one_line_per_failure(many_run, tmp_path, capsys):
    specs, out, _ = many_run
    shutil.copytree(out, tmp_path / "o")  # the good capture is already fitted there
    # ... with global_evals 100 (fast), which the CLI cannot set: stamp it as the CLI's run
    # (default 400), or the rerun refuses it as a fit of another run (tests/test_resume.py)
    res = tmp_path / "o" / "capture" / "results.json"
    data = json.loads(res.read_text())
    data["run_identity"]["options"]["global_evals"] = FitOptions().global_evals
    res.write_text(json.dumps(data))
    code = _cli(["fit-many", *specs, "--out", tmp_path / "o", "--scheduler", "serial",
                 "--no-mcmc", "--no-report", "--quiet"])
    cap = capsys.readouterr()
    err = cap.err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "broken.yaml" in err[0] and "Traceback" not in cap.err
    assert "capture: done earlier" in cap.out


def test_cli_validate_bad_medium_and_bad_rounds(tmp_path, capsys):
    with pytest.raises(InputError, match="--media"):
        _cli(["validate", "--rounds", "1", "--media", "Milk?", "--out", tmp_path,
              "--scheduler", "serial"])
    with pytest.raises(SystemExit) as exc:
        _cli(["validate", "--rounds", "0", "--media", "Espresso", "--out", tmp_path])
    assert exc.value.code == 2
    assert "--rounds" in capsys.readouterr().err


def test_coverage_summary_criteria():
    """Scores of a calibrated posterior pass, scores biased by half a standard deviation fail
    (criteria of docs/validation.md).  Posterior N(median, 1): PIT = Phi(truth - median)."""
    from scipy.stats import norm

    from fitmedia.validate import Score, coverage_summary

    z = np.random.default_rng(1).standard_normal(400)
    good = [Score("m", (8.0,), "R", "kappa_s", 1.0, 1.0 + e, 1.0, float(norm.cdf(-e))) for e in z]
    bad = [Score("m", (8.0,), "R", "kappa_s", 1.0, 1.5 + e, 1.0, float(norm.cdf(-e - 0.5)))
           for e in z]
    cg = coverage_summary(good)
    assert cg["passed"], cg["quantities"]
    assert abs(cg["quantities"]["kappa_s"]["coverage"]["90"] - 0.9) < 0.05
    cb = coverage_summary(bad)
    assert not cb["passed"] and not cb["criteria"]["kappa_s"]["bias_ok"]
    # the trusted block: the calibrated scores' coverage when the biased ones said "exit 1"
    mixed = good + [replace(s, trusted=False) for s in bad]
    cm = coverage_summary(mixed)
    assert cm["n_untrusted_scores"] == len(bad)
    assert cm["trusted"]["kappa_s"] == cg["quantities"]["kappa_s"]
    assert cm["quantities"]["kappa_s"]["n"] == len(mixed)


def test_z_is_the_pit_normal_score():
    """z against its definitions: for a normal posterior N(median, sd) it equals
    (median - truth) / sd (analytic); a second, light mode of g that inflates the posterior's
    sd (0.0076 -> 0.33 in a measured Head & Shoulders round) leaves it unchanged, because it
    depends on the PIT only; a truth outside every sample gives |z| = 3.72, not infinity."""
    from scipy.stats import norm

    from fitmedia.validate import Score

    for truth, median, sd in ((0.9, 0.88, 0.0076), (1.0, 1.3, 0.2), (5.0, 4.0, 2.0)):
        pit = float(norm.cdf((truth - median) / sd))
        s = Score("m", (8.0,), "R", "g", truth, median, sd, pit)
        assert s.z == pytest.approx((median - truth) / sd, abs=1e-9)
        wide = Score("m", (8.0,), "R", "g", truth, median, 0.33, pit)
        assert wide.z == s.z
    assert Score("m", (8.0,), "R", "g", 1.0, 2.0, 0.1, 0.0).z == pytest.approx(3.719, abs=1e-3)
    assert Score("m", (8.0,), "R", "g", 1.0, 0.0, 0.1, 1.0).z == pytest.approx(-3.719, abs=1e-3)


def test_optical_depth_regimes():
    """The optical depth that sorts scores into regimes, against a hand computation: the
    canonical tank is 300 mm deep and the bulb sits at z = 30 mm, so the light-to-wall distance
    is 150 - 30 = 120 mm; the tank's kappa_t is the liquid's times ml / tank ml plus the water's
    absorption.  Boundaries: 'thin' and 'dense' only when every image is."""
    from conftest import make_spec

    from fitmedia.medium import medium_by_name
    from fitmedia.spec import parse_spec
    from fitmedia.validate import INFORMATIVE_OPTICAL_DEPTH, Score, coverage_summary, optical_depths

    med = medium_by_name("Espresso")
    d = geometry_dict(width=16, height=12)
    d["medium"]["water_kappa_a"] = [1e-3, 0.0, 0.0]
    d["images"] = [{"path": "a.tiff", "exposure_s": 1.0, "concentration": 8 / 23000},
                   {"path": "b.tiff", "exposure_s": 1.0, "concentration": 240 / 23000}]
    spec = parse_spec(d, require_images=False)
    kt_r = med.as_dict()["kappa_t"]["R"]
    tau = optical_depths(spec, med, "R")
    assert tau == pytest.approx([(kt_r * 8 / 23000 + 1e-3) * 120, (kt_r * 240 / 23000 + 1e-3) * 120])
    assert make_spec().tank.half[2] == 150.0
    lo, hi = INFORMATIVE_OPTICAL_DEPTH

    def score(t):
        return Score("m", (8.0,), "R", "g", 0.9, 0.9, 0.01, 0.5, t)

    assert score((0.5 * lo,)).regime == "thin"
    assert score((0.5 * lo, 2 * lo)).regime == "informative"
    assert score((2 * hi,)).regime == "dense"
    assert score(None).regime is None
    summary = coverage_summary([score((0.5 * lo,)), score((1.0,)), score((1.0,)), score(None)])
    assert {r: b["g"]["n"] for r, b in summary["regimes"].items()} == {"thin": 1, "informative": 2}


def test_black_round_is_skipped_not_failed(geometry, tmp_path):
    """A round whose synthetic capture is black in every channel (Regular Milk 240 ml: the
    single-scattering glow never reaches the front wall) is refused by the image checks
    before any fitting (errors.BlackImageError); validate records it as skipped with that
    reason, scores nothing for it, and says so in coverage.txt (not as a failed fit)."""
    res = validate(["Regular Milk"], 1, tmp_path, ml=[240.0], geometry=geometry, seed=3,
                   scheduler="serial", options=OPTIONS)
    (rec,) = res.rounds
    assert rec["status"] == "skipped" and "a black image" in rec["error"], rec
    assert res.scores == []
    text = (tmp_path / "coverage.txt").read_text()
    assert "0 failed, 1 skipped" in text and "a black image" in text


def test_hybrid_captures_trace_more_paths_than_the_fits_last_term():
    """validate's default hybrid captures carry at most half the term noise (sd) of the fit's
    last term: at equal paths the capture's realisation put an Espresso 29 ml fit 4-7 % low at
    the truth (docs/validation.md), so the capture traces at least 4x the fit's final paths."""
    from fitmedia.batch import HYBRID_SPP, synth_choice
    from fitmedia.forward.multiple import DEFAULT_PATHS
    from fitmedia.inference.full import FINAL_PATHS_FACTOR

    assert synth_choice("full", None, None) == ("hybrid", HYBRID_SPP)
    assert synth_choice("auto", None, 5000) == ("hybrid", 5000)
    assert synth_choice("single", None, None) == ("single", 256)
    assert HYBRID_SPP >= 4 * FINAL_PATHS_FACTOR * DEFAULT_PATHS

"""Faults: output folders that cannot be written, runs that fail or are killed (issue 17).

The output-folder rules (:func:`fitmedia.util.staged_output_dir`): a bad ``--out`` is refused
with one line and exit code 2 before any work, a run that fails leaves nothing, a finished run
is moved into place whole.  The kill test: a `kill -9` of the main process of a 2-worker fit
leaves no worker alive, and ``--resume`` gives the uninterrupted run's results bit for bit.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import assert_only_the_sampler_doubted, geometry_dict


def _run(argv, capsys):
    from fitmedia.cli import main

    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's own refusal: usage line, then the error line
        code = exc.code
    err = capsys.readouterr().err
    return code, err if code != 2 or not err.startswith("usage:") else err.splitlines()[-1]


def _one_line_error(code, err, *words):
    assert code == 2, err
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], lines[0]


@pytest.fixture(scope="module")
def geo(tmp_path_factory):
    path = tmp_path_factory.mktemp("geo") / "geo.yaml"
    path.write_text(yaml.safe_dump(geometry_dict(width=16, height=12)))
    return path


def _commands(geo, out):
    """Each command that writes an output folder, with ``out`` as that folder."""
    return {
        "synth": ["synth", geo, "--medium", "Espresso", "--ml", "16", "--out", out],
        "fit": ["fit", geo, "--out", out, "--no-mcmc"],
        "validate": ["validate", "--rounds", "1", "--media", "Espresso", "--spec", geo,
                     "--scheduler", "serial", "--quiet", "--out", out],
        "fit-many": ["fit-many", geo, "--scheduler", "serial", "--quiet", "--out", out],
    }


@pytest.mark.parametrize("command", ["synth", "fit", "validate", "fit-many"])
@pytest.mark.parametrize("case", ["empty", "a file", "under a file"])
def test_bad_out_is_refused_before_any_work(geo, tmp_path, capsys, monkeypatch, command, case):
    """--out "", an existing file, or a path below a file: one line naming --out, exit code 2,
    nothing created, and no work done (the work itself is replaced by a failure here;
    formerly: tracebacks, one after the whole fit, and "" wrote into the current folder)."""
    a_file = tmp_path / "a_file"
    a_file.write_text("keep\n")
    out = {"empty": "", "a file": a_file, "under a file": a_file / "sub"}[case]
    monkeypatch.chdir(tmp_path)

    def no_work(*args, **kw):
        raise AssertionError("work started before --out was checked")
    work = {"synth": "fitmedia.synth._write_capture", "fit": "fitmedia.pipeline.load_spec",
            "validate": "fitmedia.spec.load_spec", "fit-many": "fitmedia.batch.run_tasks"}
    monkeypatch.setattr(work[command], no_work)
    code, err = _run(_commands(geo, out)[command], capsys)
    _one_line_error(code, err, "--out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]
    assert a_file.read_text() == "keep\n"


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_out_is_refused(geo, tmp_path, capsys):
    """A folder without write permission: exit 2 naming --out and the folder."""
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        code, err = _run(_commands(geo, ro / "x")["synth"], capsys)
    finally:
        ro.chmod(0o755)
    _one_line_error(code, err, "--out", "cannot write")
    assert list(ro.iterdir()) == []


def test_a_failed_run_leaves_nothing(geo, tmp_path, capsys, monkeypatch):
    """synth failing after its first image is written (the write replaced by a failure on the
    second call): exit 2, no --out folder, no temporary folder left; the same into an existing
    folder leaves that folder's files as they were."""
    from fitmedia.errors import ImageError
    import fitmedia.synth as synth

    real, calls = synth.write_float_tiff, []

    def fail_second(path, data):
        calls.append(path)
        if len(calls) == 2:
            raise ImageError(f"{path}: disk full (simulated)")
        real(path, data)
    monkeypatch.setattr(synth, "write_float_tiff", fail_second)
    code, err = _run(_commands(geo, tmp_path / "new")["synth"], capsys)
    _one_line_error(code, err, "disk full")
    assert list(tmp_path.iterdir()) == [] and len(calls) == 2
    old = tmp_path / "old"
    old.mkdir()
    (old / "capture.yaml").write_text("old\n")
    calls.clear()
    code, err = _run(_commands(geo, old)["synth"], capsys)
    assert code == 2 and [p.name for p in tmp_path.iterdir()] == ["old"]
    assert [p.name for p in old.iterdir()] == ["capture.yaml"]
    assert (old / "capture.yaml").read_text() == "old\n"


def test_staged_output_dir_moves_into_place(tmp_path):
    """A new folder appears whole (one rename); into an existing one, each file is replaced
    and other files are kept; a temporary folder of a killed run of this host (a pid that is
    not running) is removed by the next run, one of a running process is not."""
    import socket

    from fitmedia.util import PARTIAL, staged_output_dir

    out = tmp_path / "a" / "out"
    with staged_output_dir(out) as stage:
        assert stage.parent == tmp_path and not (tmp_path / "a").exists()
        (stage / "sub").mkdir()
        (stage / "sub" / "x.txt").write_text("1")
        (stage / "r.json").write_text("1")
    (out / "mine.txt").write_text("user's")
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True).stdout.strip()
    host = socket.gethostname()
    stale = out.parent / f".out{PARTIAL}{host}-{dead}-abc"
    live = out.parent / f".out{PARTIAL}{host}-{os.getpid()}-abc"
    stale.mkdir()
    live.mkdir()
    with staged_output_dir(out) as stage:
        (stage / "sub").mkdir()
        (stage / "sub" / "y.txt").write_text("2")
        (stage / "r.json").write_text("2")
    assert not stale.exists() and live.exists()
    live.rmdir()
    files = {str(p.relative_to(tmp_path)): p.read_text() for p in tmp_path.rglob("*")
             if p.is_file()}
    assert files == {"a/out/sub/x.txt": "1", "a/out/sub/y.txt": "2", "a/out/r.json": "2",
                     "a/out/mine.txt": "user's"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]


# ---------------------------------------------------------------------------------------------
# kill -9 of a 2-worker fit, then --resume


MAX_STEPS = 200


def _fit_cmd(spec, out, *extra):
    return [sys.executable, "-m", "fitmedia.cli", "fit", str(spec), "--out", str(out),
            "--seed", "4", "--quiet", "--no-report", "--workers", "2", "--n-tau", "1e6",
            "--max-steps", str(MAX_STEPS), *extra]


@pytest.fixture(scope="module")
def two_channel_capture(tmp_path_factory):
    """Espresso 16 ml at 16 x 12 pixels, channels R and G (one worker process each), and the
    output of an uninterrupted fit of it."""
    from fitmedia.medium import medium_by_name
    from fitmedia.synth import synthesize
    from conftest import make_spec

    d = tmp_path_factory.mktemp("kill")
    spec = synthesize(make_spec(width=16, height=12), d / "cap", medium_by_name("Espresso"),
                      [16], seed=2)
    spec.write_text(spec.read_text() + "channels: [R, G]\n")
    res = subprocess.run(_fit_cmd(spec, d / "whole"), capture_output=True, text=True,
                         timeout=900)
    assert_only_the_sampler_doubted(res)
    return spec, d / "whole"


def _iterations(out: Path) -> list[int]:
    """Steps in each channel's checkpoint so far (0 where none is readable yet)."""
    steps = []
    for ch in "RG":
        try:
            with np.load(out / f"checkpoint_{ch}.npz") as z:
                steps.append(int(z["iteration"]))
        except (OSError, ValueError, KeyError, EOFError):
            steps.append(0)
    return steps


#: When to kill: after this condition on the checkpoints' steps holds, plus a random delay (s).
#: Mid-chain: a channel's steps 100 -> 200 take 0.4 s at 16 x 12 on an idle 2-core machine
#: (measured 2026-12-06), so the delay stays well inside that; a delay up to 1 s killed after
#: both chains had ended in 1 CI run of many (the premise check at the end failed).
KILL_POINTS = {
    "during the MAP": (lambda steps: True, 3.0),
    "mid-chain": (lambda steps: 100 <= max(steps) < MAX_STEPS, 0.1),
    "one channel done": (lambda steps: max(steps) >= MAX_STEPS, 0.5),
}


def _alive(procs) -> list:
    import psutil

    left = []
    for p in procs:
        try:
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                left.append(p)
        except psutil.NoSuchProcess:
            pass
    return left


def _kill_main_process(spec, out, point: str, rng) -> None:
    """Start a 2-worker fit into ``out``, `kill -9` its main process at ``point`` (after the
    workers started, plus a random delay from ``rng``) and check that no worker outlives it."""
    import psutil

    ready, delay = KILL_POINTS[point]
    proc = subprocess.Popen(_fit_cmd(spec, out), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    main = psutil.Process(proc.pid)
    deadline = time.time() + 600
    while not (len(main.children()) >= 2 and ready(_iterations(out))):
        assert proc.poll() is None, f"the fit ended before the kill point ({point})"
        assert time.time() < deadline, f"kill point {point!r} not reached in 600 s"
        time.sleep(0.05)
    time.sleep(float(rng.uniform(0.0, delay)))
    workers = main.children(recursive=True)
    assert proc.poll() is None, f"the fit ended before the kill point ({point})"
    assert len(workers) >= 2
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    deadline = time.time() + 10
    while _alive(workers) and time.time() < deadline:
        time.sleep(0.05)
    left = _alive(workers)
    for p in left:  # do not leave them running after a failure
        p.kill()
    assert not left, f"{len(left)} worker process(es) outlived the killed main process"
    assert not (out / "results.json").exists()
    assert all(s < MAX_STEPS for s in _iterations(out)) or point == "one channel done"


def _same_results(a: Path, b: Path) -> None:
    """Every array of samples.npz and each checkpoint's chain bit for bit, and results.json
    equal but for the wall time and date."""
    with np.load(a / "samples.npz") as x, np.load(b / "samples.npz") as y:
        assert sorted(x.files) == sorted(y.files)
        for k in x.files:
            np.testing.assert_array_equal(x[k], y[k], err_msg=k)
    for ch in "RG":
        with np.load(a / f"checkpoint_{ch}.npz") as x, np.load(b / f"checkpoint_{ch}.npz") as y:
            assert len(x["chain"]) == MAX_STEPS
            np.testing.assert_array_equal(x["chain"], y["chain"])
    ra, rb = (json.loads((d / "results.json").read_text()) for d in (a, b))
    for r in (ra, rb):
        r.pop("wall_time_s")
        r.pop("date")
    assert ra == rb


@pytest.mark.slow
@pytest.mark.parametrize("point", list(KILL_POINTS))
def test_kill_9_of_a_2_worker_fit_then_resume(two_channel_capture, tmp_path, seed, point):
    """`kill -9` of the main process of a fit whose channels run in 2 worker processes, at 3
    points (each after a random delay, seeded): no worker survives it (they kept running and
    writing checkpoints for >= 15 s before die_with_parent), and `--resume` gives results
    equal bit for bit to an uninterrupted run's (the reference: samples, checkpoints' chains,
    results.json), with no temporary folder left beside --out."""
    spec, whole = two_channel_capture
    out = tmp_path / "killed"
    rng = np.random.default_rng([seed, list(KILL_POINTS).index(point)])
    _kill_main_process(spec, out, point, rng)
    res = subprocess.run(_fit_cmd(spec, out, "--resume"), capture_output=True, text=True,
                         timeout=900)
    assert_only_the_sampler_doubted(res)
    _same_results(out, whole)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["killed"]


# ---------------------------------------------------------------------------------------------
# validate on Dask: a worker process killed mid-round


def _validate_cmd(geo, out, *extra):
    # Lowfat Milk (Espresso until 2026-12-01): each round still samples a second mode of g (R,
    # 7 log-posterior units below the MAP), but not in 4 of 6 channels, so a round fits in
    # 31-37 s of CPU instead of 42-43 s (docs/testing.md, "Test costs")
    return [sys.executable, "-m", "fitmedia.cli", "validate", "--rounds", "2", "--media",
            "Lowfat Milk", "--spec", str(geo), "--out", str(out), "--seed", "3", "--quiet",
            "--max-steps", "100", "--n-tau", "1e6", *extra]


def _round_records(out: Path) -> list[dict]:
    recs = [json.loads((d / "round.json").read_text()) for d in sorted(out.glob("round_*"))]
    for r in recs:
        r.pop("wall_time_s")
    return recs


@pytest.mark.slow
def test_validate_survives_a_killed_dask_worker(geo, tmp_path, seed):
    """`kill -9` of one of the 2 Dask worker processes (chosen at random, seeded) while both
    rounds are being fitted: the command finishes (Dask reruns the round), the rerun of the
    command redoes nothing, no round is lost or duplicated, and the coverage table and the
    rounds' records equal those of an uninterrupted run with the same seed (the reference,
    run without Dask: ``--scheduler serial``)."""
    import psutil

    rng = np.random.default_rng(seed)
    ref = subprocess.run(_validate_cmd(geo, tmp_path / "ref", "--scheduler", "serial"),
                         capture_output=True, text=True, timeout=1200)
    assert ref.returncode in (0, 1), ref.stderr
    out = tmp_path / "killed"
    proc = subprocess.Popen(_validate_cmd(geo, out, "--workers", "2"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    started = [out / f"round_000{i}" / "capture" / "capture.yaml" for i in (0, 1)]
    deadline = time.time() + 600
    while not all(p.exists() for p in started):
        assert proc.poll() is None and time.time() < deadline, "the rounds did not start"
        time.sleep(0.05)
    time.sleep(float(rng.uniform(0.0, 2.0)))
    workers = [p for p in psutil.Process(proc.pid).children(recursive=True)
               if "multiprocessing.spawn" in " ".join(p.cmdline())]
    assert len(workers) == 2 and not list(out.glob("round_*/round.json")), \
        "not both rounds in progress at the kill"
    workers[int(rng.integers(2))].kill()
    assert proc.wait(timeout=1200) in (0, 1)
    again = subprocess.run(_validate_cmd(geo, out, "--workers", "2"), capture_output=True,
                           text=True, timeout=600)
    assert again.returncode == ref.returncode, again.stderr
    assert sorted(p.name for p in out.iterdir() if p.name.startswith("round")) == \
        ["round_0000", "round_0001"]
    assert [r["index"] for r in json.loads((out / "coverage.json").read_text())["rounds"]] \
        == [0, 1]
    for a, b in zip(_round_records(out), _round_records(tmp_path / "ref"), strict=True):
        assert a == b, [k for k in a.keys() | b.keys() if a.get(k) != b.get(k)]
    assert (out / "coverage.txt").read_text() == (tmp_path / "ref" / "coverage.txt").read_text()
    assert not [p for p in out.rglob(".*partial-*")]

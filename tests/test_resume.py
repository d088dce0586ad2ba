"""Kill and resume: a fit killed with SIGKILL mid-chain continues from its checkpoint."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from conftest import assert_only_the_sampler_doubted, geometry_dict


def _fit_cmd(spec, out, *extra):
    return [sys.executable, "-m", "fitmedia.cli", "fit", str(spec), "--out", str(out), "--seed", "4",
            "--quiet", "--no-report", "--workers", "1", "--n-tau", "1e6", "--max-steps", "300",
            *extra]


def _start_and_kill(spec, out, checkpoint_name):
    """Start a fit into ``out`` and `kill -9` it once its ``checkpoint_name`` holds 100 steps
    (the run must have stopped before its 300 steps, without a results.json)."""
    proc = subprocess.Popen(_fit_cmd(spec, out), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    ckpt = out / checkpoint_name
    deadline = time.time() + 300
    while time.time() < deadline:
        if ckpt.exists():
            try:
                if int(np.load(ckpt)["iteration"]) >= 100:
                    break
            except (OSError, ValueError, KeyError):  # being replaced right now
                pass
        time.sleep(0.05)
    else:
        proc.kill()
        pytest.fail(f"no {checkpoint_name} with 100 steps within 300 s")
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "results.json").exists()
    assert 100 <= int(np.load(ckpt)["iteration"]) < 300


@pytest.mark.slow
def test_kill_9_and_resume_gives_the_uninterrupted_chain(tmp_path):
    """A real `kill -9` of the fitting process while channel R samples; `--resume` completes
    every channel to exactly the requested 300 steps, and each chain equals, step for step, the
    chain of an uninterrupted run with the same seed (no step lost or repeated)."""
    from fitmedia.cli import main

    geo = tmp_path / "geo.yaml"
    geo.write_text(yaml.safe_dump(geometry_dict(width=40, height=30)))
    assert main(["synth", str(geo), "--medium", "Regular Milk", "--ml", "16", "--out",
                 str(tmp_path / "cap"), "--seed", "2"]) == 0
    spec = tmp_path / "cap" / "capture.yaml"

    _start_and_kill(spec, tmp_path / "killed", "checkpoint_R.npz")

    res = subprocess.run(_fit_cmd(spec, tmp_path / "killed", "--resume"), capture_output=True,
                         text=True, timeout=600)
    assert_only_the_sampler_doubted(res)
    res = subprocess.run(_fit_cmd(spec, tmp_path / "whole"), capture_output=True, text=True,
                         timeout=600)
    assert_only_the_sampler_doubted(res)
    for ch in "RGB":
        a = np.load(tmp_path / "killed" / f"checkpoint_{ch}.npz")["chain"]
        b = np.load(tmp_path / "whole" / f"checkpoint_{ch}.npz")["chain"]
        assert a.shape[0] == 300
        np.testing.assert_array_equal(a, b)


@pytest.fixture(scope="module")
def two_mode_capture(tmp_path_factory):
    """White Grapefruit Juice 9 ml at 64 x 48, channel R only, and the output of one
    uninterrupted fit of it (``whole``): the reference of both kill points below, computed
    once (it was run by each of them until 2026-12-01; docs/testing.md "Test costs")."""
    from fitmedia.medium import medium_by_name
    from fitmedia.spec import load_spec
    from fitmedia.synth import synthesize
    from conftest import ROOT

    d = tmp_path_factory.mktemp("two_mode")
    geo = load_spec(ROOT / "capture_specs" / "bulb_64x48.yaml", require_images=False)
    spec = synthesize(geo, d / "cap", medium_by_name("White Grapefruit Juice"), [9],
                      seed=1174215102)
    spec.write_text(spec.read_text() + "channels: [R]\n")
    res = subprocess.run(_fit_cmd(spec, d / "whole"), capture_output=True, text=True,
                         timeout=600)
    assert_only_the_sampler_doubted(res)
    return spec, d / "whole"


@pytest.mark.slow
@pytest.mark.parametrize("watched", ["checkpoint_R.npz", "checkpoint_R_mode2.npz"])
def test_kill_during_either_mode_and_resume(two_mode_capture, tmp_path, watched):
    """Both modes of g sampled (White Grapefruit Juice 9 ml, R only: the other mode 1.6
    log-posterior units below the MAP, tests/test_roundtrip.py): a `kill -9` while the first
    or the second mode's chain samples, then `--resume`, gives both chains step for step as an
    uninterrupted run (``two_mode_capture``'s, shared by both kill points), and the same mixed
    posterior samples and mode weights.  Failed before the second chain and the bridge had
    random streams of their own: a resumed first chain skips its initial draws, which shifted
    every later draw (809 vs 804 mixed samples)."""
    import json

    spec, whole = two_mode_capture
    _start_and_kill(spec, tmp_path / "killed", watched)
    res = subprocess.run(_fit_cmd(spec, tmp_path / "killed", "--resume"), capture_output=True,
                         text=True, timeout=600)
    assert_only_the_sampler_doubted(res)
    killed = tmp_path / "killed"
    for name in ("checkpoint_R.npz", "checkpoint_R_mode2.npz"):
        a = np.load(killed / name)["chain"]
        b = np.load(whole / name)["chain"]
        assert a.shape[0] == 300
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(np.load(killed / "samples.npz")["R/g"],
                                  np.load(whole / "samples.npz")["R/g"])
    modes = [json.loads((d / "results.json").read_text())["diagnostics"]["channels"]
             ["R"]["g_modes"] for d in (killed, whole)]
    assert [m["weight"] for m in modes[0]] == [m["weight"] for m in modes[1]]


# ---------------------------------------------------------------------------------------------
# what --resume refuses, before any fitting (issue 17)


@pytest.fixture(scope="module")
def two_captures(tmp_path_factory):
    """Espresso and Lowfat Milk, 16 ml, at 24 x 18 pixels (the issue's A and B)."""
    from fitmedia.medium import medium_by_name
    from fitmedia.synth import synthesize
    from conftest import make_spec

    d = tmp_path_factory.mktemp("ab")
    geo = make_spec(width=24, height=18)
    return (synthesize(geo, d / "A", medium_by_name("Espresso"), [16], seed=2),
            synthesize(geo, d / "B", medium_by_name("Lowfat Milk"), [16], seed=3))


def _identity(spec_path, **options):
    """The run identity `fitmedia fit SPEC --seed 4` computes (built from its parts here)."""
    from fitmedia.inference.fit import FitOptions, prepare
    from fitmedia.inference.identity import run_identity
    from fitmedia.spec import load_spec

    prep = prepare(load_spec(spec_path))
    return run_identity(prep.spec, prep.images, prep.clear, FitOptions(seed=4, **options))


def _write_checkpoint(path, identity, n_steps=3, n_walkers=16, ndim=4):
    """A checkpoint of a short chain, as the sampler writes it, stamped with ``identity``."""
    import json

    import emcee

    from fitmedia.inference.sample import save_checkpoint

    backend = emcee.backends.Backend()
    backend.reset(n_walkers, ndim)
    backend.grow(n_steps, None)
    backend.chain[:] = np.random.default_rng(0).normal(size=backend.chain.shape)
    backend.log_prob[:] = -1.0
    backend.iteration = n_steps
    backend.random_state = np.random.RandomState(0).get_state()
    save_checkpoint(path, backend, json.dumps(identity))


def _resume(spec, out, capsys, monkeypatch, *extra):
    """`fitmedia fit SPEC --out OUT --resume` in this process, with the fitting itself replaced
    by a failure: a refusal must come before it.  Returns (exit code, stderr)."""
    from fitmedia.cli import main

    def no_fitting(*args, **kw):
        raise AssertionError("fitting started before the checkpoints were checked")
    monkeypatch.setattr("fitmedia.pipeline.run_channels", no_fitting)
    code = main(["fit", str(spec), "--out", str(out), "--seed", "4", "--quiet", "--no-report",
                 "--resume", *extra])
    return code, capsys.readouterr().err


def _one_line(err, *words):
    lines = [ln for ln in err.strip().splitlines() if ln]
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], lines[0]


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_resume_refuses_the_checkpoint_of_another_capture(two_captures, tmp_path, capsys,
                                                          monkeypatch):
    """The issue's case: Espresso's checkpoint in --out, Lowfat Milk resumed into it.  Refused
    with exit 2 before any fitting, naming the file and what differs (the images; the two
    specs are equal, as synthesized here: known by construction), the folder left as it was.
    The same capture with another option or seed names those; a checkpoint of the same run is
    accepted (the check passes and the fitting is reached)."""
    a, b = two_captures
    out = tmp_path / "F"
    out.mkdir()
    _write_checkpoint(out / "checkpoint_R.npz", _identity(a))
    before = _snapshot(out)
    code, err = _resume(b, out, capsys, monkeypatch)
    assert code == 2
    _one_line(err, "checkpoint_R.npz", "another run", "image 0", "clear-water image")
    assert "spec" not in err.split("checkpoint_R.npz")[1]
    assert _snapshot(out) == before
    code, err = _resume(a, out, capsys, monkeypatch, "--robust", "--seed", "5")
    assert code == 2
    _one_line(err, "option robust (False, now True)", "option seed (4, now 5)")
    assert "image" not in err and "spec" not in err.split("checkpoint_R.npz")[1]
    with pytest.raises(AssertionError, match="fitting started"):
        _resume(a, out, capsys, monkeypatch, "--max-steps", "7", "--workers", "2")


def _truncated(path):
    _write_checkpoint(path, None)
    path.write_bytes(path.read_bytes()[:200])


def _wrong_shape(path):
    np.savez(path, **{k: np.zeros(3) for k in ("chain", "log_prob", "accepted", "iteration",
                                                 "rs_name", "rs_keys", "rs_pos",
                                                 "rs_has_gauss", "rs_gauss")})


@pytest.mark.parametrize("make, words", [
    (lambda p: p.write_bytes(b""), "empty file"),
    (_truncated, "not a usable checkpoint"),
    (_wrong_shape, "chain of shape (3,)"),
    (lambda p: p.write_text("not a checkpoint\n"), "not a usable checkpoint"),
    (lambda p: _write_checkpoint(p, None), "no run identity recorded"),
], ids=["empty", "truncated", "wrong-shaped", "text", "no-identity"])
def test_resume_refuses_an_unusable_checkpoint_up_front(two_captures, tmp_path, capsys,
                                                        monkeypatch, make, words):
    """An empty, truncated, wrong-shaped, foreign or identity-less checkpoint_G.npz beside a
    good checkpoint_R.npz: exit 2 before any fitting, one line naming the file, and neither
    file touched (formerly a traceback after the whole MAP, issue 17)."""
    a, _ = two_captures
    out = tmp_path / "F"
    out.mkdir()
    _write_checkpoint(out / "checkpoint_R.npz", _identity(a))
    make(out / "checkpoint_G.npz")
    before = _snapshot(out)
    code, err = _resume(a, out, capsys, monkeypatch)
    assert code == 2
    _one_line(err, "checkpoint_G.npz", words)
    assert _snapshot(out) == before


def test_fit_many_reuses_only_a_fit_of_the_same_run(two_channel_free_capture, tmp_path):
    """fit-many skips a capture whose folder holds its results.json only when the run identity
    matches: the same options give "done earlier" with the same estimates (and the identity
    in the record); another seed is refused before any fitting naming the option, and so is
    the folder of capture A given for capture B (formerly reported as B's)."""
    from dataclasses import replace

    from fitmedia.batch import fit_many
    from fitmedia.errors import InputError
    from fitmedia.inference.fit import FitOptions

    a, b = two_channel_free_capture
    opts = FitOptions(mcmc=False, global_evals=50, progress=False)
    first = fit_many([a], tmp_path / "o", scheduler="serial", options=opts, report=False)
    again = fit_many([a], tmp_path / "o", scheduler="serial", options=opts, report=False)
    assert [r["status"] for r in first] == ["done"] and [r["status"] for r in again] == \
        ["done earlier"]
    assert again[0]["estimates"] == first[0]["estimates"]
    assert again[0]["run_identity"] == first[0]["run_identity"] is not None
    with pytest.raises(InputError, match=r"option seed \(0, now 1\)"):
        fit_many([a], tmp_path / "o", scheduler="serial", options=replace(opts, seed=1),
                 report=False)
    (tmp_path / "B").mkdir()
    b_as_a = tmp_path / "B" / "capture_R.yaml"  # same stem, so the same folder in --out
    b_as_a.write_text(b.read_text().replace("images/", str(b.parent / "images") + "/"))
    with pytest.raises(InputError, match="image 0"):
        fit_many([b_as_a], tmp_path / "o", scheduler="serial", options=opts, report=False)


@pytest.fixture(scope="module")
def two_channel_free_capture(two_captures, tmp_path_factory):
    """The A and B captures with channel R only (a MAP-only fit in a few seconds)."""
    out = []
    for spec in two_captures:
        one = spec.parent / "capture_R.yaml"
        one.write_text(spec.read_text() + "channels: [R]\n")
        out.append(one)
    return out


def test_resume_without_the_sampler_is_refused(two_captures, tmp_path, capsys, monkeypatch):
    """`--resume --no-mcmc` asks to continue chains that this run would not sample: one line
    naming the option, exit 2, before any fitting (it used to fit the MAP and leave the
    checkpoints of an earlier run beside results they do not belong to)."""
    out = tmp_path / "out"
    out.mkdir()
    _write_checkpoint(out / "checkpoint_R.npz", _identity(two_captures[0]))
    before = _snapshot(out)
    code, err = _resume(two_captures[0], out, capsys, monkeypatch, "--no-mcmc")
    assert code == 2
    _one_line(err, "resume", "no-mcmc")
    assert _snapshot(out) == before

"""Mutation testing of fitmedia's physics core: hand-made physics mutants against the fast tests.

Each mutant is one exact text replacement in one file (an operator swap, a dropped
factor, a sign flip, kappa_a for kappa_t...).  The harness copies ``fitmedia/``,
``tests/`` and ``pyproject.toml`` as committed (HEAD) to a scratch folder (never touching the
checkout),
checks that the unmutated copy passes, then applies one mutant at a time, runs its
tests (``pytest -x``, one process; the fast tests of its area: physics, inference or
slab) and restores the file.  A mutant is *killed* when a
test fails (or the run times out), *survived* when every test passes.  The score and the
survivors go to docs/testing.md, "Mutation testing", with a triage of each survivor.

Usage::

    python tools/mutation.py                  # all mutants, all their tests
    python tools/mutation.py --before         # without the tests added for issue 14
    python tools/mutation.py --only S1 G1     # some mutants
    python tools/mutation.py --list

Runtime, measured on the shared 2-core machine: all 30 mutants 34 min (a survivor 64-160 s,
its area's whole fast set; a killed one 4-329 s, up to its first failing test);
``make mutation`` runs it all, after a baseline run of each area's tests.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# Each mutant runs the fast tests of its area (the older tests first, the issue-14 ones last:
# with ``-x`` the first failing test is recorded, and a mutant first killed by a new test
# survived the older ones of its area)
PHYSICS = ["tests/test_physics.py", "tests/test_forward_inputs.py",
           "tests/test_physics_references.py"]
INFERENCE = ["tests/test_priors.py", "tests/test_nuisance.py",
             "tests/test_sampler.py::test_optimizer_objective_is_the_sampler_log_probability",
             "tests/test_fit_objective.py"]
SLAB = ["tests/test_slab.py"]
#: tests written for issue 14; ``--before`` leaves them out (and the slab rows with n != 1, g = 0.9)
NEW_FILES = ("tests/test_physics_references.py", "tests/test_fit_objective.py",
             "tests/test_forward_inputs.py")
NEW_SLAB_ROWS = "iad_g09"

# (id, file, text, replacement, what it breaks)
MUTANTS = [
    ("G1", "fitmedia/geometry.py", "factor = factor * fresnel_transmittance(-dg[:, 2], n_g, water_ior)",
     "factor = factor", "glass->water Fresnel transmittance dropped"),
    ("G2", "fitmedia/geometry.py", "factor / water_ior**2, 0.0)", "factor, 0.0)",
     "radiance not divided by n_water^2"),
    ("G3", "fitmedia/geometry.py", "    eta = n1 / n2\n", "    eta = n2 / n1\n",
     "Snell's law inverted"),
    ("G4", "fitmedia/geometry.py", "1.0 - 0.5 * (rs + rp)", "1.0 - (rs + rp)",
     "Fresnel: polarisations summed, not averaged"),
    ("G5", "fitmedia/geometry.py", "off = (np.arange(sub) + 0.5) / sub", "off = np.arange(sub) / sub",
     "pixel samples at the corner, not the centre"),
    ("G6", "fitmedia/geometry.py", "         - ((np.asarray(y) - camera.cy)",
     "         + ((np.asarray(y) - camera.cy)", "image y axis flipped"),
    ("M1", "fitmedia/medium.py", "denom = (1.0 - g) ** 2 + 4.0 * g * sin2_half",
     "denom = (1.0 + g) ** 2 - 4.0 * g * sin2_half", "HG phase function: g sign flipped"),
    ("M2", "fitmedia/medium.py", "(1.0 - g * g) / (4.0 * np.pi) / (denom",
     "(1.0 - g * g) / (2.0 * np.pi) / (denom", "HG normalisation 2 pi"),
    ("M5", "fitmedia/medium.py", "0.5 * (1.0 - np.asarray(cos_theta, dtype=float))",
     "0.5 * (1.0 + np.asarray(cos_theta, dtype=float))", "hg_phase: scattering angle reversed"),
    ("M3", "fitmedia/medium.py", "return self.kappa_a + self.kappa_s", "return self.kappa_s",
     "Medium.kappa_t without kappa_a"),
    ("M4", "fitmedia/medium.py", "self.kappa_s * concentration, self.g",
     "self.kappa_s, self.g", "dilution does not scale kappa_s"),
    ("S1", "fitmedia/forward/single.py", "br[k] * np.exp(-kt[k] * self._s_hit)",
     "br[k] * np.exp(-ka[k] * self._s_hit)", "direct bulb attenuated by kappa_a, not kappa_t"),
    ("S2", "fitmedia/forward/single.py", "        kt = ka + ks\n", "        kt = ks + 0 * ka\n",
     "extinction without absorption"),
    ("S3", "fitmedia/forward/single.py", "hg_phase_half_angle(1.0 - sin2 if upper else sin2, gk)",
     "hg_phase_half_angle(sin2, gk)", "line integral's HG: wrong angle on the upper half"),
    ("S4", "fitmedia/forward/single.py", "np.divide(2.0, cos_alpha, out=cos_alpha)",
     "np.divide(1.0, cos_alpha, out=cos_alpha)", "bulb solid angle halved"),
    ("S5", "fitmedia/forward/single.py",
     "return img + np.where(self._smooth[..., None], self._lap_scale * lap, 0.0)",
     "return img - np.where(self._smooth[..., None], self._lap_scale * lap, 0.0)",
     "box filter: footprint correction with the wrong sign"),
    ("S6", "fitmedia/forward/single.py", "intensity = np.pi * r * r * br[k] * e_cap",
     "intensity = r * r * br[k] * e_cap", "bulb intensity without pi"),
    ("S7", "fitmedia/forward/single.py", "rad = intensity * ks[k] / self._h * lines[:, k]",
     "rad = intensity * kt[k] / self._h * lines[:, k]", "glow scales with kappa_t, not kappa_s"),
    ("S8", "fitmedia/forward/bulb_cap.py", "return float(a + np.log(2 * ((a - 1) + np.exp(-a)) / (a * a)))",
     "return float(a + np.log(2 * ((a - 1) - np.exp(-a)) / (a * a)))", "cap attenuation E(a) sign"),
    ("L1", "fitmedia/slab.py", '"ext_ior": 1.0}', '"ext_ior": n * n}',
     "slab's dielectric boundary reversed (relative index 1/n)"),
    ("L2", "fitmedia/slab.py", '"albedo": float(albedo), "scale"', '"albedo": float(albedo) ** 2, "scale"',
     "slab albedo squared"),
    ("L3", "fitmedia/slab.py", "ks * (1.0 - g)", "ks * (1.0 + g)",
     "diffusion length with 1 + g (semi-infinite thickness only)"),
    ("K1", "fitmedia/inference/likelihood.py", "return lp + ll if", "return ll if",
     "log posterior without the prior"),
    ("K2", "fitmedia/inference/likelihood.py", "o.concentration * p.kappa_s, p.g", "p.kappa_s, p.g",
     "kappa_s not scaled by the concentration"),
    ("K3", "fitmedia/inference/likelihood.py", "-0.5 * np.sum(r2 + np.log(var))",
     "-0.5 * np.sum(r2)", "Gaussian likelihood without its log-variance term"),
    ("P1", "fitmedia/inference/params.py", "lp -= 2.0 * np.log(np.cosh(u[2]))",
     "lp += 2.0 * np.log(np.cosh(u[2]))", "g prior's Jacobian with the wrong sign"),
    ("P2", "fitmedia/inference/params.py", "return self.kappa_t * (1.0 - self.albedo)",
     "return self.kappa_t * self.albedo", "ChannelParams.kappa_a = kappa_s"),
    ("P3", "fitmedia/inference/params.py", '"kappa_a": kt * expit(-u[..., 1])',
     '"kappa_a": kt * expit(u[..., 1])', "kappa_a samples = kappa_s samples"),
    ("P4", "fitmedia/inference/params.py", "lp -= 0.5 * ((u[3] - self.log_b0) / self.b_sd) ** 2",
     "lp += 0.5 * ((u[3] - self.log_b0) / self.b_sd) ** 2", "brightness prior inverted"),
    ("F1", "fitmedia/inference/fit.py", "res = find_map(problem.log_posterior, best.x,",
     "res = find_map(problem.log_likelihood, best.x,", "final MAP polish maximises the likelihood"),
]


def _tests_for(path: str) -> list[str]:
    if path.endswith("slab.py"):
        return SLAB
    return INFERENCE if "/inference/" in path else PHYSICS


def _copy_tree(dest: Path, worktree: bool) -> None:
    """The committed tree (HEAD: a consistent state while others edit the checkout), or with
    ``worktree`` the files as they are now."""
    names = ["fitmedia", "tests", "pyproject.toml"]
    if not worktree:
        archive = subprocess.run(["git", "archive", "--format=tar", "HEAD", *names], cwd=ROOT,
                                 capture_output=True, check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
        return
    for name in names[:2]:
        shutil.copytree(ROOT / name, dest / name,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info"))
    shutil.copy2(ROOT / "pyproject.toml", dest / "pyproject.toml")


def _run(tree: Path, tests: list[str], before: bool, timeout: float
         ) -> tuple[str, float, str | None]:
    """pytest on ``tests`` in ``tree``: ('pass' | 'fail' | 'timeout', seconds, first failure)."""
    if before:
        tests = [t for t in tests if t.split("::")[0] not in NEW_FILES]
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:xdist", "-p", "no:cacheprovider",
           "-m", "not slow", *tests]
    if before:
        cmd += ["-k", f"not {NEW_SLAB_ROWS}"]
    env = {**os.environ, "PYTHONPATH": str(tree), "PYTHONDONTWRITEBYTECODE": "1"}
    t0 = time.perf_counter()
    try:
        res = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True,
                             timeout=timeout)
    except subprocess.TimeoutExpired:
        return "timeout", time.perf_counter() - t0, None
    failed = [ln.split()[1] for ln in res.stdout.splitlines() if ln.startswith(("FAILED", "ERROR"))]
    return (("pass" if res.returncode == 0 else "fail"), time.perf_counter() - t0,
            failed[0] if failed else None)


def run(ids: list[str] | None, before: bool, timeout: float, out: Path | None,
        worktree: bool = False, baseline: bool = True) -> int:
    chosen = [m for m in MUTANTS if ids is None or m[0] in ids]
    with tempfile.TemporaryDirectory(prefix="fitmedia-mutation-") as tmp:
        tree = Path(tmp)
        _copy_tree(tree, worktree)
        for files in sorted({tuple(_tests_for(m[1])) for m in chosen}) if baseline else []:
            status, secs, _ = _run(tree, list(files), before, timeout)
            print(f"baseline {' '.join(files)}: {status} ({secs:.0f} s)", flush=True)
            if status != "pass":
                print("the unmutated tree fails its tests: fix that first", file=sys.stderr)
                return 2
        rows = []
        for mid, path, old, new, what in chosen:
            target = tree / path
            text = target.read_text()
            if text.count(old) != 1:
                rows.append({"id": mid, "status": "stale", "what": what})
                print(f"{mid:3} STALE ({text.count(old)} matches of its text in {path})", flush=True)
                continue
            target.write_text(text.replace(old, new))
            try:
                status, secs, killer = _run(tree, _tests_for(path), before, timeout)
            finally:
                target.write_text(text)
            state = "survived" if status == "pass" else "killed"
            rows.append({"id": mid, "file": path, "status": state, "seconds": round(secs, 1),
                         "what": what, "killed_by": killer or (status if state == "killed" else None)})
            print(f"{mid:3} {state:8} {secs:6.0f} s  {path}: {what}"
                  + (f"  <- {rows[-1]['killed_by']}" if state == "killed" else ""), flush=True)
    scored = [r for r in rows if r["status"] != "stale"]
    killed = sum(r["status"] == "killed" for r in scored)
    print(f"score: {killed} of {len(scored)} killed"
          + (f" ({100 * killed / len(scored):.0f} %)" if scored else "")
          + (" [without the issue-14 tests]" if before else ""))
    if out is not None:
        out.write_text(json.dumps({"before": before, "mutants": rows}, indent=1))
    return 1 if any(r["status"] == "stale" for r in rows) else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", metavar="ID", help="mutant ids (default: all)")
    ap.add_argument("--before", action="store_true", help="leave out the issue-14 tests")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per test run")
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--worktree", action="store_true",
                    help="mutate a copy of the working tree (default: of the last commit, HEAD)")
    ap.add_argument("--no-baseline", action="store_true",
                    help="skip the run of the unmutated tree (when its tests are known to pass)")
    ap.add_argument("--list", action="store_true", help="list the mutants and exit")
    a = ap.parse_args(argv)
    if a.list:
        for mid, path, _, _, what in MUTANTS:
            print(f"{mid:3} {path}: {what}")
        return 0
    return run(a.only, a.before, a.timeout, a.json, a.worktree, not a.no_baseline)


if __name__ == "__main__":
    sys.exit(main())

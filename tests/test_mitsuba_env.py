"""Choice of the Mitsuba variant: it works, and bad libraries are rejected by the
subprocess probe without taking the test process down."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fitmedia import mitsuba_env
from fitmedia.mitsuba_env import (MitsubaVariantError, choose_variant, doctor_report, find_libllvm,
                                  import_mitsuba, probe_variant)

pytestmark = pytest.mark.mitsuba

# Debian's libLLVM 15 aborts the process on AVX-512 CPUs (DESIGN.md, runtime facts).
DEBIAN_LLVM15 = "/usr/lib/x86_64-linux-gnu/libLLVM-15.so"


def test_importing_the_modules_has_no_side_effects():
    code = ("import sys, fitmedia.mitsuba_env, fitmedia.forward.mitsuba, fitmedia.slab; "
            "print('mitsuba' in sys.modules, 'drjit' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_choose_variant_gives_a_working_variant():
    choice = choose_variant()
    assert choice.variant.endswith(("_mono", "_rgb"))
    assert choice.reasons, "the choice must say why"
    if choice.variant.startswith("llvm"):
        assert choice.libllvm is not None and os.path.isfile(choice.libllvm)
    assert choose_variant() == choice  # cached for the process
    mi = import_mitsuba()
    assert mi.variant() == choice.variant
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path"},
                          "sensor": {"type": "perspective", "fov": 20,
                                     "film": {"type": "hdrfilm", "width": 3, "height": 2,
                                              "pixel_format": "luminance"}},
                          "sky": {"type": "constant", "radiance": 2.0}})
    img = np.asarray(mi.render(scene, spp=2))
    assert np.allclose(img, 2.0)


def test_llvm_candidates_put_the_environment_variable_first(monkeypatch, tmp_path):
    fake = tmp_path / "libLLVM-99.so"
    fake.write_text("not a library")
    monkeypatch.setenv(mitsuba_env.ENV_LIBLLVM, str(fake))
    cands = find_libllvm()
    assert cands[0] == str(fake)
    assert len(cands) == len(set(os.path.realpath(c) for c in cands))


def test_probe_rejects_a_file_that_is_not_libllvm(tmp_path):
    fake = tmp_path / "libLLVM-99.so"
    fake.write_text("not a library")
    res = probe_variant("llvm_ad_mono", str(fake))
    assert not res.ok
    assert "exited with status" in res.reason or "killed" in res.reason


@pytest.fixture(scope="module")
def aborting_library(tmp_path_factory) -> Path:
    """A shared library whose constructor calls abort(): loading it kills the process."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler to build a library that aborts")
    d = tmp_path_factory.mktemp("abort")
    src = d / "abort.c"
    src.write_text("#include <stdlib.h>\n__attribute__((constructor)) static void die(void) "
                   "{ abort(); }\n")
    lib = d / "libLLVM-98.so"
    subprocess.run([cc, "-shared", "-fPIC", "-o", str(lib), str(src)], check=True)
    return lib


def test_probe_survives_a_library_that_aborts(aborting_library):
    res = probe_variant("llvm_ad_mono", str(aborting_library))
    assert not res.ok
    assert "SIGABRT" in res.reason
    # ... and this process is still here to check it
    assert choose_variant().variant


@pytest.mark.skipif(not os.path.isfile(DEBIAN_LLVM15), reason="no Debian libLLVM 15 here")
def test_probe_of_debian_llvm15_does_not_kill_the_caller():
    res = probe_variant("llvm_ad_mono", DEBIAN_LLVM15)
    # it aborts on AVX-512 CPUs and may work elsewhere: either way we get an answer
    assert res.ok or ("SIGABRT" in res.reason or "status" in res.reason)


def test_an_unavailable_variant_is_refused_explicitly():
    with pytest.raises(MitsubaVariantError, match="no_such_variant"):
        import_mitsuba("no_such_variant")
    # as a preference it is only a wish: the usual order follows, and the reasons say why
    choice = choose_variant(prefer="no_such_variant")
    assert any("no_such_variant" in r and "not in this Mitsuba build" in r for r in choice.reasons)


def test_doctor_report_names_the_choice():
    text = doctor_report()
    assert "chosen:" in text
    assert choose_variant().variant in text.split("chosen:")[1]
    assert "libLLVM candidates" in text

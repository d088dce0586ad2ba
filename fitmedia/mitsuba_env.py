"""Choose a Mitsuba 3 variant that works on this machine, without crashing.

Mitsuba's ``llvm_ad_*`` variants load a shared libLLVM at run time (the
``DRJIT_LIBLLVM_PATH`` environment variable names it).  Some libraries abort
the whole process the first time a kernel is compiled (Debian's libLLVM 15 on
AVX-512 CPUs: ``LLVM ERROR: Cannot select ... fminimum``), others are refused
by Dr.Jit (LLVM < 15).  An abort cannot be caught in Python, so every
candidate is tried in a *subprocess* first: import mitsuba, set the variant,
render a tiny scene and check the pixel value.  The first candidate that works
is used in this process; the result is cached for the life of the process.

Order of preference (a ``prefer`` variant, if given, is tried first):

1. ``cuda_ad_mono`` where a CUDA driver is found and a GPU renders;
2. ``llvm_ad_mono`` with the first working libLLVM among
   ``$DRJIT_LIBLLVM_PATH`` (if set), then libLLVM 19, 18, 17 ... found in
   ``/usr/lib/x86_64-linux-gnu`` and ``/usr/lib/llvm-*/lib``;
3. ``scalar_mono`` if the installed wheel has it, else ``scalar_rgb`` (the pip
   wheel of Mitsuba 3.9 ships no ``scalar_mono``; fitmedia renders grey
   scenes, so the three RGB components are equal and the first one is used).

Set ``FITMEDIA_MITSUBA_VARIANT`` to prefer a variant without code changes.
Importing this module does nothing: no probe runs and Mitsuba is not imported
until :func:`choose_variant` or :func:`import_mitsuba` is called.
"""

from __future__ import annotations

import functools
import glob
import logging
import os
import re
import signal
import subprocess
import sys
from dataclasses import dataclass, field
from types import ModuleType

from .errors import FitmediaError

log = logging.getLogger(__name__)

ENV_LIBLLVM = "DRJIT_LIBLLVM_PATH"
ENV_PREFER = "FITMEDIA_MITSUBA_VARIANT"
#: Folders searched for libLLVM, in order (``/usr/lib/llvm-*/lib`` is a glob).
LLVM_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/llvm-*/lib", "/usr/lib64", "/usr/local/lib")
#: Dr.Jit 1.5 refuses LLVM older than this (it needs opaque pointers).
MIN_LLVM_VERSION = 15
PROBE_TIMEOUT_S = 120.0

# Run in a fresh interpreter: argv[1] = variant.  Renders a 4x4 image of a
# constant environment of radiance 1 and prints the mean pixel value.
_PROBE_CODE = r"""
import sys
import mitsuba as mi
mi.set_variant(sys.argv[1])
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "volpath", "max_depth": 2},
    "sensor": {"type": "perspective", "fov": 30,
               "film": {"type": "hdrfilm", "width": 4, "height": 4,
                        "rfilter": {"type": "box"},
                        "pixel_format": "luminance" if "mono" in sys.argv[1] else "rgb"}},
    "env": {"type": "constant", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}
            if "rgb" in sys.argv[1] else 1.0},
})
import numpy as np
img = np.asarray(mi.render(scene, spp=4))
print("FITMEDIA_PROBE_OK", float(img.mean()), flush=True)
"""


class MitsubaVariantError(FitmediaError, RuntimeError):
    """A requested Mitsuba variant cannot run on this machine."""


@dataclass(frozen=True)
class ProbeResult:
    """Outcome of trying one (variant, libLLVM) pair in a subprocess."""

    variant: str
    libllvm: str | None
    ok: bool
    reason: str


@dataclass(frozen=True)
class VariantChoice:
    """The variant fitmedia uses, the libLLVM it needs (llvm variants) and why."""

    variant: str
    libllvm: str | None
    reasons: list[str] = field(default_factory=list)


def _backend(variant: str) -> str:
    return variant.split("_", 1)[0]


def _llvm_version(path: str) -> int | None:
    m = re.search(r"libLLVM(?:-(\d+)|\.so\.(\d+))", os.path.basename(path))
    if m is None:
        m = re.search(r"llvm-(\d+)", path)
        return int(m.group(1)) if m else None
    return int(m.group(1) or m.group(2))


def find_libllvm() -> list[str]:
    """Candidate shared libLLVM files, best first.

    ``$DRJIT_LIBLLVM_PATH`` (if set) comes first whatever it is; then the
    libraries found in :data:`LLVM_DIRS`, newest major version first, one file
    per real library (symlinks to the same file are merged).
    """
    out: list[str] = []
    env = os.environ.get(ENV_LIBLLVM)
    if env:
        out.append(env)
    found: dict[str, tuple[int, str]] = {}
    for pattern in LLVM_DIRS:
        for folder in sorted(glob.glob(pattern)):
            for path in sorted(glob.glob(os.path.join(folder, "libLLVM*.so*"))):
                if not os.path.isfile(path):
                    continue
                version = _llvm_version(path)
                if version is None:
                    continue
                real = os.path.realpath(path)
                # keep the shortest name per real file (libLLVM-19.so over libLLVM.so.19.1)
                if real not in found or len(path) < len(found[real][1]):
                    found[real] = (version, path)
    seen = {os.path.realpath(p) for p in out}
    for version, path in sorted(found.values(), key=lambda vp: (-vp[0], vp[1])):
        if os.path.realpath(path) not in seen:
            out.append(path)
    return out


def _describe_failure(proc: subprocess.CompletedProcess) -> str:
    lines = [ln.strip() for ln in (proc.stderr or "").splitlines() if ln.strip()]
    # the most telling line: an LLVM/Dr.Jit error if there is one, else the last one
    key = next((ln for ln in lines if "LLVM ERROR" in ln or "too old" in ln
                or "could not be found" in ln or "Unable to load" in ln), None)
    detail = key or (lines[-1] if lines else "no output")
    if proc.returncode < 0:
        try:
            name = signal.Signals(-proc.returncode).name
        except ValueError:
            name = f"signal {-proc.returncode}"
        return f"the probe process was killed by {name} (crash): {detail[:200]}"
    return f"the probe exited with status {proc.returncode}: {detail[:200]}"


def probe_variant(variant: str, libllvm: str | None = None, *,
                  timeout: float = PROBE_TIMEOUT_S) -> ProbeResult:
    """Try ``variant`` (with ``libllvm`` for llvm variants) in a subprocess.

    The subprocess imports mitsuba, sets the variant and renders a 4x4 image
    of a constant environment of radiance 1; the probe succeeds when it exits
    normally and the mean pixel is 1.  A crash (e.g. a libLLVM that aborts)
    only ends the subprocess.
    """
    env = dict(os.environ)
    if libllvm is not None:
        env[ENV_LIBLLVM] = libllvm
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE_CODE, variant], env=env,
                              capture_output=True, text=True, timeout=timeout, check=False)
    except subprocess.TimeoutExpired:
        return ProbeResult(variant, libllvm, False, f"the probe timed out after {timeout:g} s")
    except OSError as exc:
        return ProbeResult(variant, libllvm, False, f"could not start the probe: {exc}")
    if proc.returncode != 0:
        return ProbeResult(variant, libllvm, False, _describe_failure(proc))
    m = re.search(r"FITMEDIA_PROBE_OK (\S+)", proc.stdout)
    if m is None:
        return ProbeResult(variant, libllvm, False, "the probe printed no result")
    value = float(m.group(1))
    if not abs(value - 1.0) < 1e-3:
        return ProbeResult(variant, libllvm, False,
                           f"the probe rendered {value!r} where 1.0 was expected")
    return ProbeResult(variant, libllvm, True, "renders correctly")


def _installed_variants() -> list[str]:
    """Variants compiled into the installed wheel, without importing mitsuba."""
    proc = subprocess.run([sys.executable, "-c", "import mitsuba; print(' '.join(mitsuba.variants()))"],
                          capture_output=True, text=True, timeout=PROBE_TIMEOUT_S, check=False)
    if proc.returncode != 0:
        raise MitsubaVariantError(f"mitsuba cannot be imported: {_describe_failure(proc)}")
    return proc.stdout.split()


def _has_cuda_driver() -> bool:
    import ctypes.util

    return ctypes.util.find_library("cuda") is not None or bool(glob.glob("/dev/nvidia[0-9]*"))


def _scalar_variant(installed: list[str]) -> str | None:
    return next((v for v in ("scalar_mono", "scalar_rgb") if v in installed), None)


def _try(variant: str, installed: list[str], reasons: list[str],
         probes: list[ProbeResult], *, exhaustive: bool = False) -> VariantChoice | None:
    """Probe one variant (every libLLVM candidate for llvm); first success wins."""
    if variant not in installed:
        reasons.append(f"{variant}: not in this Mitsuba build ({', '.join(installed)})")
        return None
    backend = _backend(variant)
    if backend == "scalar":
        reasons.append(f"{variant}: needs no JIT backend")
        return VariantChoice(variant, None, reasons)
    if backend == "cuda":
        if not _has_cuda_driver():
            reasons.append(f"{variant}: no CUDA driver (libcuda) found")
            return None
        res = probe_variant(variant)
        probes.append(res)
        reasons.append(f"{variant}: {res.reason}")
        return VariantChoice(variant, None, reasons) if res.ok else None
    candidates = find_libllvm()
    if not candidates:
        reasons.append(f"{variant}: no libLLVM found in ${ENV_LIBLLVM} or {', '.join(LLVM_DIRS)}")
        return None
    choice = None
    for lib in candidates:
        version = _llvm_version(lib)
        if version is not None and version < MIN_LLVM_VERSION:
            reasons.append(f"{variant} with {lib}: skipped, LLVM {version} < {MIN_LLVM_VERSION} "
                           f"(Dr.Jit refuses it)")
            continue
        if not os.path.isfile(lib):
            reasons.append(f"{variant} with {lib}: no such file")
            continue
        res = probe_variant(variant, lib)
        probes.append(res)
        reasons.append(f"{variant} with {lib}: {res.reason}")
        if res.ok and choice is None:
            choice = VariantChoice(variant, lib, reasons)
            if not exhaustive:
                break
    return choice


def _search(prefer: str | None, *, exhaustive: bool = False
            ) -> tuple[VariantChoice, list[ProbeResult]]:
    installed = _installed_variants()
    reasons: list[str] = []
    probes: list[ProbeResult] = []
    order = ["cuda_ad_mono", "llvm_ad_mono"]
    if prefer:
        order = [prefer] + [v for v in order if v != prefer]
    choice = None
    for variant in order:
        got = _try(variant, installed, reasons, probes, exhaustive=exhaustive)
        if got is not None and choice is None:
            choice = got
            if not exhaustive:
                break
    if choice is None:
        scalar = _scalar_variant(installed)
        if scalar is None:
            raise MitsubaVariantError("no usable Mitsuba variant: " + "; ".join(reasons))
        reasons.append(f"{scalar}: last resort (slow: no JIT, one core)")
        choice = VariantChoice(scalar, None, reasons)
    return VariantChoice(choice.variant, choice.libllvm, list(reasons)), probes


@functools.lru_cache(maxsize=None)
def _cached_choice(prefer: str | None) -> VariantChoice:
    choice, _ = _search(prefer)
    log.info("Mitsuba variant %s%s (%s)", choice.variant,
             f" with {choice.libllvm}" if choice.libllvm else "", "; ".join(choice.reasons))
    return choice


def choose_variant(*, prefer: str | None = None) -> VariantChoice:
    """The Mitsuba variant to use on this machine (cached for the process).

    Parameters
    ----------
    prefer : str, optional
        A variant name (e.g. ``"llvm_ad_mono"``, ``"scalar_rgb"``) tried first;
        default ``$FITMEDIA_MITSUBA_VARIANT`` if set.  If it does not work the
        usual order follows, and ``reasons`` says why.

    Returns
    -------
    VariantChoice
        ``variant``, ``libllvm`` (the path to export as ``DRJIT_LIBLLVM_PATH``
        for llvm variants, else None) and ``reasons`` (one line per candidate
        tried).
    """
    prefer = prefer or os.environ.get(ENV_PREFER) or None
    c = _cached_choice(prefer)
    return VariantChoice(c.variant, c.libllvm, list(c.reasons))


def import_mitsuba(variant: str | None = None) -> ModuleType:
    """Import mitsuba with a working variant set, and return the module.

    With ``variant`` None the variant of :func:`choose_variant` is used.  An
    explicit ``variant`` that cannot run here raises
    :class:`MitsubaVariantError` instead of silently falling back.
    ``DRJIT_LIBLLVM_PATH`` is set before the LLVM backend starts.
    """
    choice = choose_variant(prefer=variant)
    if variant is not None and choice.variant != variant:
        raise MitsubaVariantError(f"Mitsuba variant {variant!r} does not work here: "
                                  + "; ".join(choice.reasons))
    if choice.libllvm is not None:
        current = os.environ.get(ENV_LIBLLVM)
        if current != choice.libllvm:
            if "mitsuba" in sys.modules and current:
                log.warning("mitsuba was imported with %s=%s; using %s may not take effect",
                            ENV_LIBLLVM, current, choice.libllvm)
            os.environ[ENV_LIBLLVM] = choice.libllvm
    import mitsuba as mi

    if mi.variant() != choice.variant:
        mi.set_variant(choice.variant)
    return mi


def doctor_report() -> str:
    """A human-readable account of the Mitsuba set-up (for ``fitmedia doctor``).

    Probes every candidate (this takes a second or two per candidate) rather
    than stopping at the first that works, and names the one fitmedia uses.
    """
    lines = ["Mitsuba 3 set-up"]
    try:
        installed = _installed_variants()
    except MitsubaVariantError as exc:
        return "\n".join(lines + [f"  mitsuba: NOT USABLE: {exc}"])
    proc = subprocess.run([sys.executable, "-c", "import mitsuba, drjit; "
                           "print(mitsuba.__version__, drjit.__version__)"],
                          capture_output=True, text=True, timeout=PROBE_TIMEOUT_S, check=False)
    versions = proc.stdout.split()
    if len(versions) == 2:
        lines.append(f"  mitsuba {versions[0]}, drjit {versions[1]} ({sys.executable})")
    lines.append(f"  variants in this build: {', '.join(installed)}")
    lines.append(f"  ${ENV_LIBLLVM} = {os.environ.get(ENV_LIBLLVM, '(not set)')}")
    lines.append(f"  ${ENV_PREFER} = {os.environ.get(ENV_PREFER, '(not set)')}")
    libs = find_libllvm()
    lines.append("  libLLVM candidates: " + (", ".join(libs) if libs else "none found"))
    lines.append(f"  CUDA driver: {'found' if _has_cuda_driver() else 'not found'}")
    prefer = os.environ.get(ENV_PREFER) or None
    choice, _ = _search(prefer, exhaustive=True)
    lines.append("  candidates:")
    lines.extend(f"    - {r}" for r in choice.reasons)
    lines.append(f"  chosen: {choice.variant}"
                 + (f" with {ENV_LIBLLVM}={choice.libllvm}" if choice.libllvm else ""))
    return "\n".join(lines)

"""Peak memory of `synth` and `fit`, estimated from the spec before anything is allocated,
and refused up front when it exceeds the limit (issue 17: a 1e9-pixel camera made `synth`
allocate without limit and `fit` allocate 3 x 22 GiB before checking the image size).

The coefficients were measured with ``/usr/bin/time -v`` (peak resident set size) on the
canonical capture at 64 x 48, 200 x 150 and 400 x 300 pixels, two images plus the clear
water (docs/testing.md, "Bad-input corpus", gives the runs):

* synth: 156, 321 and 863 MB -> 137 MB + 6.1 kB per pixel (one image rendered at a time,
  supersampled 2 x 2); the 400 x 300 run was predicted to 1 %.  ``synth --model full``
  (Mitsuba, 256 spp) at 200 x 150: 284004 kB (canonical bulb) and 287912 kB (canonical spot),
  below the estimate's 312 MiB (2026-12-02, stop 25).
* fit: 262 MB for the whole 64 x 48 MAP fit; the images and one channel's forward models
  (prepare, then a channel's problem evaluated) grow by 0.24 kB per pixel and file loaded
  and 1.4 kB per pixel, image and channel fitted at once (parallel worker processes each
  hold their own models).  The chains add at most 2 x 20000 steps x 24 walkers x 7 values.
* the multiple-scattering tracer (since 2026-12-02 in every fit of a bulb, since stop 25 of
  a spot too: ``--model single``'s check and ``auto``'s share trace it, ``full`` refreshes
  it; ``synth --model hybrid``): about 1 GB per process that traces, as it traces in chunks
  of 2^20 paths and keeps its freed memory (ms_paths.TRACE_CHUNK, util.keep_freed_memory).  Measured at 64 x 48
  (Lowfat Milk 16 ml, one worker, maximum resident set): ``fit --model single --no-mcmc``
  1.20 GiB against 0.30 GiB estimated without it; ``synth --model hybrid`` 1.09 GiB against
  0.15 GiB; ``fit --model full
  --no-mcmc`` (Espresso 8 ml at 60 x 45, one channel) 1.7 GB.  ``TRACER_MB`` (1400 MiB) is
  above the largest of those excesses (about 1.7 - 0.3 GB), so the estimate holds for the full
  model too, and overstates a single fit's peak by about 0.4 GiB.
* the sampler's table of the multiple-scattering term (since 2026-12-07; forward/ms_table.py:
  ``TermTable``): 3 x ``TERM_TABLE_POINTS`` camera-sized images per image and process that
  traces, 0.38 kB per pixel (counted, not measured: added to the tracer's share).
"""

from __future__ import annotations

import os

from .errors import InputError
from .forward.ms_table import TERM_TABLE_POINTS
from .spec import Spec

ENV_LIMIT = "FITMEDIA_MAX_MEMORY_GB"
_MB = 2.0**20
SYNTH_BASE_MB, SYNTH_PER_PIXEL = 137.0, 6.1e3
FIT_BASE_MB, FIT_PER_PIXEL_FILE, FIT_PER_PIXEL_MODEL = 250.0, 0.24e3, 1.4e3
CHAIN_BYTES = 2 * 20000 * 24 * 7 * 8
TRACER_MB = 1400.0  # per process that traces the multiple-scattering term (see above)
TERM_TABLE_BYTES_PER_PIXEL = 3 * TERM_TABLE_POINTS * 8  # the term's table (see above)


def physical_memory() -> float | None:
    """The machine's physical memory in bytes (None where the OS does not say)."""
    try:
        return float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def memory_limit() -> float | None:
    """The limit in bytes: $FITMEDIA_MAX_MEMORY_GB (GiB; 0 or 'none' turns the check off)
    or else half the physical memory."""
    text = os.environ.get(ENV_LIMIT)
    if text is None:
        phys = physical_memory()
        return None if phys is None else 0.5 * phys
    if text.strip().lower() in ("0", "none", "off"):
        return None
    try:
        gb = float(text)
    except ValueError:
        gb = float("nan")
    if not gb > 0 or gb == float("inf"):
        raise InputError(f"{ENV_LIMIT}: got {text!r}; expected a positive number of GiB, or 0 "
                         "to turn the memory check off")
    return gb * 2.0**30


def default_workers(n_channels: int, spec: Spec | None = None) -> int:
    """Channels fitted at once by default: every channel in its own process where there are
    fewer channels than twice the cores, else one per core.  Where the channels do not divide
    evenly over the cores (3 on 2), one per core leaves the last channel alone on one core while
    the others idle; all at once, time-sliced, keeps every core busy to the end.  Measured on
    the bench's full fit (200 x 150 x 3 on 2 cores): at stop 38, 737 s wall against 767 s with
    2 processes (5 % more CPU, 1.5 x the memory); on 2026-12-06, when the last channel ran
    alone for about 400 of 1110 s, 1055 s against 1110 s (2083 s CPU against 1950 s;
    docs/inference.md, "Speed").  With ``spec``: more processes than cores only where the
    fit's memory estimate for them is within :func:`memory_limit` (each process holds its own
    models and tracer), so that a machine that fits one process per core is not refused."""
    cores = os.cpu_count() or 1
    base = max(1, min(n_channels, cores))
    over = max(1, n_channels if n_channels < 2 * cores else cores)
    if over > base and spec is not None:
        limit = memory_limit()
        if limit is not None and estimate_peak(spec, "fit", workers=over) > limit:
            return base
    return over


def estimate_peak(spec: Spec, command: str, *, workers: int | None = None,
                  tracer: bool | None = None) -> float:
    """Estimated peak memory in bytes of ``command`` ('synth' or 'fit') on ``spec``.

    synth renders one image at a time (its peak does not grow with the images); fit counts
    the spec's images, each with its own camera size.  ``workers``: channels fitted at once
    (``--workers``; at most the spec's channels; default: :func:`default_workers`).
    ``tracer``: whether the multiple-scattering tracer runs (``TRACER_MB`` per process);
    default: for ``fit``, yes (bulb or spot); for ``synth``, no (pass True for ``--model
    hybrid``)."""
    if tracer is None:
        tracer = command == "fit"
    trace = TRACER_MB * _MB if tracer else 0.0
    if command == "synth":
        px = spec.camera.width * spec.camera.height
        return SYNTH_BASE_MB * _MB + SYNTH_PER_PIXEL * float(px) + trace
    sizes = [spec.camera_for(i).width * spec.camera_for(i).height for i in range(len(spec.images))]
    files = sum(len(e.paths) * p for e, p in zip(spec.images, sizes))
    if spec.clear_water is not None:
        files += len(spec.clear_water.paths) * spec.camera.width * spec.camera.height
    # more workers than channels do not run: one process per channel at most
    par = min(workers, len(spec.channels)) if workers else default_workers(len(spec.channels), spec)
    per_pixel = FIT_PER_PIXEL_MODEL + (TERM_TABLE_BYTES_PER_PIXEL if tracer else 0.0)
    return (FIT_BASE_MB * _MB + FIT_PER_PIXEL_FILE * float(files)
            + per_pixel * float(sum(sizes)) * par + (CHAIN_BYTES + trace) * par)


def check_memory(spec: Spec, command: str, **kw) -> None:
    """Refuse (InputError, exit 2) when :func:`estimate_peak` exceeds :func:`memory_limit`,
    giving both figures and how to change the limit."""
    limit = memory_limit()
    need = estimate_peak(spec, command, **kw)
    if limit is not None and need > limit:
        whose = f"${ENV_LIMIT}" if ENV_LIMIT in os.environ else "half the physical memory"
        par = kw.get("workers")
        fewer = (f"fewer --workers than {par}, " if command == "fit" and par and par > 1
                 and len(spec.channels) > 1 else "")
        raise InputError(f"{spec.source}: camera.size {spec.camera.width} x {spec.camera.height}: "
                         f"`{command}` would need about {need / 2**30:.3g} GiB of memory, more "
                         f"than the limit of {limit / 2**30:.3g} GiB ({whose}); use a smaller "
                         f"camera.size, {fewer}or set {ENV_LIMIT} (GiB; 0: no check)")

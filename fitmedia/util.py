"""Small helpers shared across the package: atomic writes, output folders, seeds, JSON."""

from __future__ import annotations

import glob
import json
import os
import shutil
import socket
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable

import numpy as np


def atomic_write(path: str | Path, write: Callable[[Path], None]) -> None:
    """Call ``write(tmp_path)`` then rename the temporary file onto ``path``.

    A killed process leaves either the old file or the new one, never half of one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; results are meant to be shared
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write(path, lambda p: p.write_text(text))


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    return x


def write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as indented JSON atomically (numpy types converted, non-finite -> null)."""
    atomic_write_text(path, json.dumps(_jsonable(obj), indent=2) + "\n")


def make_rng(seed: int | np.random.Generator | None) -> np.random.Generator:
    """A numpy Generator from a seed or an existing Generator (never the global state)."""
    if isinstance(seed, np.random.Generator):
        return seed
    return np.random.default_rng(seed)


def save_npz(path: str | Path, arrays: dict[str, np.ndarray]) -> None:
    """Write a compressed .npz atomically."""
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)

    atomic_write(path, write)


#: Infix of the temporary sibling folder a run writes into (:func:`staged_output_dir`)
PARTIAL = ".partial-"


def _existing_ancestor(path: Path) -> Path:
    """``path`` or its nearest ancestor that exists."""
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_output_dir(path: str | Path, flag: str = "--out") -> Path:
    """The output folder ``path`` as an absolute Path, once it is known that a run can write
    it; else an :class:`~fitmedia.errors.InputError` naming ``flag`` (exit code 2), before any
    work.  Refused: an empty path, an existing file, a path under a file, a folder this
    process cannot create files in (tried, not guessed from permission bits: root may write
    a read-only folder).  Creates nothing; a missing folder is created when the run writes."""
    from .errors import InputError

    text = os.fspath(path) if isinstance(path, (str, os.PathLike)) else None
    if not text or not text.strip():
        raise InputError(f"{flag}: empty path; name the folder to write into")
    target = Path(os.path.abspath(Path(text).expanduser()))
    if target.exists() and not target.is_dir():
        raise InputError(f"{flag}: {text} is an existing file, not a folder")
    base = _existing_ancestor(target)
    if not base.is_dir():
        raise InputError(f"{flag}: {text}: {base} is a file, not a folder")
    try:
        os.rmdir(tempfile.mkdtemp(dir=base, prefix=".fitmedia-write-test-"))
    except OSError as exc:
        raise InputError(f"{flag}: {text}: cannot write in {base} "
                         f"({exc.strerror or type(exc).__name__})") from None
    return target


def _remove_stale_partials(parent: Path, name: str) -> None:
    """Remove temporary folders of ``name`` left by runs of this host that were killed."""
    host = socket.gethostname()
    for p in parent.glob(glob.escape(f".{name}{PARTIAL}{host}-") + "*"):
        try:
            pid = int(p.name.removeprefix(f".{name}{PARTIAL}{host}-").split("-")[0])
            os.kill(pid, 0)
        except (ValueError, ProcessLookupError):
            shutil.rmtree(p, ignore_errors=True)
        except PermissionError:  # alive, another user's
            pass


def _move_into(src: Path, dst: Path) -> None:
    """Move the folder ``src`` to ``dst``: one rename when ``dst`` does not exist, else each
    file renamed over its namesake (sub-folders merged), other files in ``dst`` kept."""
    if not dst.exists():
        os.rename(src, dst)
        return
    for entry in src.iterdir():
        there = dst / entry.name
        if entry.is_dir() and there.is_dir() and not there.is_symlink():
            _move_into(entry, there)
        else:
            os.replace(entry, there)
    src.rmdir()


@contextmanager
def staged_output_dir(path: str | Path, flag: str = "--out") -> Iterator[Path]:
    """Write a run's outputs atomically: yields a new temporary folder beside ``path``
    (``.<name>.partial-<host>-<pid>-*``) to write into; on success its contents are moved
    into ``path`` (created with its parents if missing; one rename when it did not exist,
    else file by file, each file replaced whole, files of other names kept); on an
    exception the temporary folder is removed and ``path`` is left as it was.

    ``path`` is checked first with :func:`check_output_dir`.  A run killed with SIGKILL leaves
    only its hidden temporary folder, which the next run into ``path`` on this host removes.
    Checkpoints that ``--resume`` must find are not written here but into ``path`` itself
    (docs/inference.md, "Faults and resume")."""
    target = check_output_dir(path, flag)
    base = target.parent if target.parent.exists() else _existing_ancestor(target)
    _remove_stale_partials(base, target.name)
    stage = Path(tempfile.mkdtemp(dir=base, prefix=f".{target.name}{PARTIAL}"
                                  f"{socket.gethostname()}-{os.getpid()}-"))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(stage, 0o777 & ~umask)  # mkdtemp makes 0700; it becomes the output folder
    try:
        yield stage
        target.parent.mkdir(parents=True, exist_ok=True)
        _move_into(stage, target)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise


#: glibc's malloc: blocks up to this size come from the heap, not from fresh mmap pages
MALLOC_MMAP_THRESHOLD = 1 << 30
#: and up to this much freed memory at the heap's top is kept for the next allocation
MALLOC_TRIM_THRESHOLD = 1 << 30
_MALLOC_TUNED = False


def keep_freed_memory() -> bool:
    """Let glibc's malloc keep freed memory for reuse (``mallopt`` M_MMAP_THRESHOLD and
    M_TRIM_THRESHOLD, ``MALLOC_*`` above), once per process; False where that is not glibc.

    The multiple-scattering tracer allocates and frees arrays of hundreds of MB per trace;
    by default each comes from fresh mmap pages whose first touch the kernel zero-fills.
    Measured (bench/trace_malloc.py, 2026-12-02, idle 2 cores, one trace at 48 x 64 sample
    pixels and 256 paths): 1.91 s wall (0.77 s system) by default, 1.42 s (0.09 s) with the
    freed memory kept; peak RSS 943 -> 1064 MB.
    """
    global _MALLOC_TUNED
    if _MALLOC_TUNED:
        return True
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(-3, MALLOC_MMAP_THRESHOLD) == 1 and \
            libc.mallopt(-1, MALLOC_TRIM_THRESHOLD) == 1  # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        return False
    _MALLOC_TUNED = bool(ok)
    return _MALLOC_TUNED

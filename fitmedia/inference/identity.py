"""What a run's posterior depends on, as one record (the *run identity*).

A checkpoint continued by ``--resume`` must belong to the same problem as the run that
resumes it: the same spec, the same image contents, the same model, the same options that
change the chain's past and the same fitmedia.  :func:`run_identity` records those;
:func:`identity_differences` says, in words, which of them differ.  Every checkpoint holds
the identity of the run that wrote it (``fitmedia.inference.sample.save_checkpoint``), and so
do results.json, validate's round.json and fit-many's summary records.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    from ..images import LoadedImage
    from ..spec import Spec
    from .fit import FitOptions

#: Options that do not change the chain's past: how many workers, progress bars, whether
#: resuming, and when to stop (``n_tau``, ``max_steps``: a longer run continues the same chain).
#: Every other field of FitOptions, present or future, is part of the identity.
FREE_OPTIONS = ("workers", "progress", "resume", "n_tau", "max_steps")

#: Version of this record's layout (a change makes old checkpoints differ, named as such).
IDENTITY_FORMAT = 1


def _sha256_json(obj: Any) -> str:
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def array_sha256(*arrays: np.ndarray) -> str:
    """SHA-256 of arrays' shapes, dtypes and contents (C order)."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def run_identity(spec: Spec, images: list[LoadedImage], clear: LoadedImage | None,
                 options: FitOptions) -> dict:
    """The identity of a fit of ``spec`` with the loaded ``images`` (and clear-water photo).

    Parameters
    ----------
    spec : Spec
        Its parsed content (``spec.raw``, keys sorted) is hashed, not the file's bytes:
        comments and key order do not matter, every value does.
    images, clear : LoadedImage
        The loaded, exposure-normalised data and validity masks are hashed (what the fit
        sees), one hash per image entry so a message can name the image (its path
        relative to the spec's folder; only the hashes are compared).
    options : FitOptions
        Every field except :data:`FREE_OPTIONS`.

    Returns
    -------
    dict
        JSON-ready: ``format``, ``fitmedia_version``, ``spec_sha256``, ``images`` (list of
        ``{"path", "sha256"}``), ``clear_water_sha256`` (or None), ``model``, ``options``.
    """
    from ..version import __version__

    opts = {k: v for k, v in asdict(options).items() if k not in FREE_OPTIONS and k != "model"}
    return {
        "format": IDENTITY_FORMAT,
        "fitmedia_version": __version__,
        "spec_sha256": _sha256_json(spec.raw),
        "images": [{"path": ", ".join(_relative(p, spec.source) for p in e.paths),
                    "sha256": array_sha256(im.data, im.valid)}
                   for e, im in zip(spec.images, images)],
        "clear_water_sha256": None if clear is None else array_sha256(clear.data, clear.valid),
        "model": options.model,
        "options": json.loads(json.dumps(opts)),
    }


def _relative(path, spec_source: str) -> str:
    """``path`` relative to the spec's folder (as a spec names it: the identity of a capture
    does not depend on where its folder is), or as it is when it is elsewhere."""
    import os
    from pathlib import Path

    rel = os.path.relpath(Path(path).absolute(), Path(spec_source).absolute().parent)
    return str(path) if rel.startswith("..") else rel


def identity_differences(stored: Any, current: dict) -> list[str]:
    """What differs between a stored identity and the current one, in words (empty: the same).

    A stored identity that is missing or not a dict (a checkpoint written before fitmedia
    recorded identities) differs in everything, said as such."""
    if not isinstance(stored, dict) or stored.get("format") != current["format"]:
        return ["no run identity recorded (written by an older fitmedia)"]
    out = []
    if stored.get("fitmedia_version") != current["fitmedia_version"]:
        out.append(f"fitmedia version ({stored.get('fitmedia_version')}, now "
                   f"{current['fitmedia_version']})")
    if stored.get("spec_sha256") != current["spec_sha256"]:
        out.append("the spec's content")
    old = stored.get("images") or []
    for i, new in enumerate(current["images"]):
        if i >= len(old) or old[i].get("sha256") != new["sha256"]:
            out.append(f"image {i} ({new['path']})")
    if len(old) > len(current["images"]):
        out.append(f"the number of images ({len(old)}, now {len(current['images'])})")
    if stored.get("clear_water_sha256") != current["clear_water_sha256"]:
        out.append("the clear-water image")
    if stored.get("model") != current["model"]:
        out.append(f"the model ({stored.get('model')}, now {current['model']})")
    so, co = stored.get("options") or {}, current["options"]
    for k in sorted(set(so) | set(co)):
        if so.get(k) != co.get(k):
            out.append(f"option {k} ({so.get(k)!r}, now {co.get(k)!r})")
    return out


def identity_json(identity: dict) -> str:
    """The identity as one JSON line (how checkpoints store it)."""
    return json.dumps(identity, sort_keys=True)

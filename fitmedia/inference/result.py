"""The fitter's two public types: :class:`FitOptions` (how to fit) and :class:`FitResult`
(what a fit found), the one result type that results.json is written from and read back into.

``fitmedia.fit(capture, model=..., options=FitOptions(...))`` returns a :class:`FitResult`;
``fitmedia fit`` writes ``FitResult.to_json()`` as results.json; ``validate``, ``fit-many``
and ``export`` read a results.json with :meth:`FitResult.from_json`.  The flat parameter
vector (log kappa_t, logit albedo, atanh g, ...) exists only inside the fitter, at the
nlopt / emcee boundary: a FitResult holds named physical quantities per channel.

This module imports only the standard library at import time (``fitmedia --help`` reads
FitOptions' defaults from it without loading numpy).
"""

from __future__ import annotations

import copy
import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field, fields
from functools import cached_property
from pathlib import Path
from typing import Any

#: The physical quantities of every channel in ``FitResult.parameters`` (1/mm, g unitless);
#: ``kappa_s_reduced`` (kappa_s (1 - g)) is there too, with its own fields (docs/results.md)
QUANTITIES = ("kappa_a", "kappa_s", "g", "kappa_t", "albedo")
#: results.json's top-level keys in the order a fit writes them (docs/results.md)
JSON_KEYS = ("fitmedia_spec", "model", "model_used", "trust", "units", "channels", "parameters",
             "diagnostics", "fitmedia_version", "date", "options", "priors", "spec", "name",
             "seed", "calibration", "noise", "images", "notes", "run_identity", "wall_time_s")
#: keys written only when known (a FitResult built in memory before the pipeline adds them)
_OPTIONAL_KEYS = ("run_identity", "wall_time_s")
#: central credible levels and the summary fields that bound them
INTERVALS = {0.68: ("q16", "q84"), 0.90: ("q05", "q95")}


@dataclass(frozen=True, kw_only=True)
class FitOptions:
    """How to fit (every field keyword-only; frozen: use ``dataclasses.replace`` to vary).

    The CLI's defaults are these (``fitmedia fit --help``).  Every field except ``workers``,
    ``progress``, ``resume``, ``n_tau`` and ``max_steps`` is part of the run identity
    (:mod:`fitmedia.inference.identity`).
    """

    model: str = "auto"  # single, full or auto (inference/full.py: auto_stays_single)
    seed: int = 0
    mcmc: bool = True  # False: MAP and Laplace approximation only
    robust: bool = False  # Student-t likelihood (nu = 4)
    n_tau: float = 50.0  # chain length in autocorrelation times
    max_steps: int = 20000
    n_walkers: int | None = None
    global_evals: int = 400
    background: bool = False  # fit an additive background offset per channel (nuisance)
    workers: int | None = None
    resume: bool = False
    progress: bool = True


@dataclass(frozen=True, kw_only=True)
class FitResult(Mapping):
    """What a fit found: per-channel values and intervals, samples, diagnostics, provenance,
    the model used and the trust verdict (docs/results.md describes every field).

    The fields are results.json's top-level entries under the same names; ``samples`` (the
    posterior's physical samples, ``"G/kappa_s"`` etc. as in samples.npz) is not part of
    results.json.  Read values with :meth:`value` and :meth:`interval`.  As a read-only
    ``Mapping`` a FitResult also answers ``result["parameters"]`` like the results.json dict
    it is written as (:meth:`to_json`), so code written against that dict keeps working.
    """

    channels: tuple[str, ...]
    #: ``parameters[quantity][channel]``: ``map``, and with samples ``median``, ``mean``,
    #: ``std``, ``q05``, ``q16``, ``q84``, ``q95`` (undiluted liquid, 1/mm)
    parameters: dict
    #: ``diagnostics``: the sampler's convergence and ``channels.<ch>`` (chi2, modes, ...)
    diagnostics: dict
    #: the verdict: ``ok``, ``model``, ``reasons``, ``notes``, ``misfit`` (fitmedia.trust)
    trust: dict
    model: str = "single"
    model_used: str = "single"
    units: dict = field(default_factory=lambda: {"length": "mm", "kappa": "1/mm"})
    fitmedia_spec: int = 1
    fitmedia_version: str | None = None
    date: str | None = None
    options: dict = field(default_factory=dict)
    priors: dict = field(default_factory=dict)
    spec: str | None = None
    name: str | None = None
    seed: int | None = None
    calibration: dict = field(default_factory=dict)
    noise: dict = field(default_factory=dict)
    images: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    run_identity: dict | None = None
    wall_time_s: float | None = None
    #: top-level keys of a results.json that this version does not know (kept by to_json)
    extra: dict = field(default_factory=dict)
    samples: Mapping | None = field(default=None, repr=False, compare=False)

    # ------------------------------------------------------------------ results.json
    def to_json(self) -> dict:
        """results.json's content: a new JSON-ready dict (numpy values converted, non-finite
        numbers None), keys in :data:`JSON_KEYS` order, then ``extra``."""
        from ..util import _jsonable

        out = {}
        for k in JSON_KEYS:
            v = getattr(self, k)
            if k in _OPTIONAL_KEYS and v is None:
                continue
            out[k] = list(v) if k == "channels" else v
        out.update(self.extra)
        return _jsonable(copy.deepcopy(out))

    @classmethod
    def from_dict(cls, data: Mapping, *, samples: Mapping | None = None) -> FitResult:
        """A FitResult from a results.json dict (missing optional entries take their defaults;
        unknown ones go to ``extra``)."""
        known = {f.name for f in fields(cls)} - {"extra", "samples"}
        kw = {k: copy.deepcopy(v) for k, v in data.items() if k in known}
        kw["channels"] = tuple(data.get("channels") or ())
        for k in ("parameters", "diagnostics", "trust"):
            kw.setdefault(k, {})
        extra = {k: copy.deepcopy(v) for k, v in data.items() if k not in known}
        return cls(**kw, extra=extra, samples=samples)

    @classmethod
    def from_json(cls, path: str | Path, *, samples: bool = False) -> FitResult:
        """Read a results.json (``path`` the file or the fit's folder).  ``samples``: also read
        the posterior's physical samples from samples.npz beside it (when there is one).
        A missing, unreadable or non-object file is an InputError naming it."""
        from ..errors import InputError

        path = Path(path)
        if path.is_dir():
            path = path / "results.json"
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise InputError(f"{path}: file not found; run fitmedia fit first") from None
        except (OSError, UnicodeDecodeError, ValueError) as exc:
            raise InputError(f"{path}: not a readable JSON file ({type(exc).__name__})") from None
        if not isinstance(data, dict):
            raise InputError(f"{path}: expected a JSON object")
        return cls.from_dict(data, samples=read_samples(path.parent / "samples.npz",
                                                        data.get("channels") or ())
                             if samples else None)

    # ------------------------------------------------------------------ reading values
    @property
    def statistic(self) -> str:
        """``"median"`` when a sampler ran (every channel's kappa_s has one), else ``"map"``."""
        ks = self.parameters.get("kappa_s", {})
        return "median" if self.channels and all("median" in ks.get(c, {})
                                                 for c in self.channels) else "map"

    def value(self, quantity: str, channel: str, statistic: str | None = None) -> float:
        """One number: ``quantity`` (kappa_a, kappa_s, g, kappa_t, albedo, kappa_s_reduced) of
        ``channel``, the posterior median (the MAP without a sampler) or ``statistic``."""
        entry = self._entry(quantity, channel)
        key = statistic or ("median" if "median" in entry else "map")
        if key not in entry:
            raise KeyError(f"{quantity}.{channel} has no {key!r}")
        return float(entry[key])

    def interval(self, quantity: str, channel: str, level: float = 0.90
                 ) -> tuple[float, float] | None:
        """The central ``level`` (0.68 or 0.90) credible interval of ``quantity`` in
        ``channel``; None where there is none (MAP only)."""
        if level not in INTERVALS:
            raise ValueError(f"level: {level}: one of {sorted(INTERVALS)}")
        lo, hi = INTERVALS[level]
        entry = self._entry(quantity, channel)
        return (float(entry[lo]), float(entry[hi])) if lo in entry and hi in entry else None

    def point_values(self, statistic: str | None = None) -> dict[str, dict[str, float]]:
        """``{quantity: {channel: value}}`` for :data:`QUANTITIES` (see :meth:`value`)."""
        return {q: {c: self.value(q, c, statistic) for c in self.channels} for q in QUANTITIES}

    def _entry(self, quantity: str, channel: str) -> dict:
        try:
            return self.parameters[quantity][channel]
        except KeyError:
            raise KeyError(f"no {quantity} for channel {channel!r} in this result") from None

    @property
    def ok(self) -> bool:
        """The trust verdict: False when the misfit guard or the transport checks fired."""
        return bool((self.trust or {}).get("ok", True))

    @property
    def converged(self) -> bool | None:
        """Whether every chain converged; None without a sampler."""
        return self.diagnostics.get("converged")

    # ------------------------------------------------------------------ Mapping (results.json)
    @cached_property
    def _json(self) -> dict:
        return self.to_json()

    def __getitem__(self, key: str) -> Any:
        return self._json[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._json)

    def __len__(self) -> int:
        return len(self._json)

    __hash__ = None  # mutable containers inside: not hashable


def read_result(path: str | Path) -> FitResult | None:
    """The fit in results.json ``path`` (:meth:`FitResult.from_json`), or None when it is
    missing, unreadable (half-written) or holds no fitted values (fit-many and validate
    reuse a finished fit only)."""
    from ..errors import InputError

    try:
        result = FitResult.from_json(path)
    except InputError:
        return None
    return result if result.parameters and result.channels else None


def read_samples(path: Path, channels) -> dict | None:
    """The physical posterior samples (``"<ch>/<quantity>"``) of a samples.npz, or None when
    there is none or it holds no samples (MAP only)."""
    if not Path(path).is_file():
        return None
    import numpy as np

    with np.load(path) as z:
        out = {k: z[k] for k in z.files if "/" in k and k.split("/", 1)[1] in
               (*QUANTITIES, "brightness", "background") and k.split("/", 1)[0] in channels}
    return out or None

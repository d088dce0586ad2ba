"""The main jobs as library functions (the CLI only parses arguments and calls these).

:func:`fit_capture` (``fitmedia.fit``) is the fitter's one entry point: a capture (a parsed
spec or its path), a forward model (a name or any ``ForwardModel``) and :class:`FitOptions`
in, one :class:`FitResult` out, written into a folder when one is given.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from .errors import InputError
from .inference.fit import MODELS, prepare, run_channels
from .inference.identity import run_identity
from .inference.result import FitOptions, FitResult
from .inference.results import build_results, write_outputs
from .spec import Spec, load_spec
from .util import check_output_dir, staged_output_dir

#: The chains' checkpoints in a fit's output folder (one per channel, ``_mode2`` for a second
#: mode of g); ``--resume`` continues them
CHECKPOINT_GLOB = "checkpoint_*.npz"


def check_resumable(out: Path, identity: dict) -> None:
    """Refuse, before any work, every checkpoint in ``out`` that ``--resume`` cannot continue:
    empty, truncated, wrong-shaped, or written by a run of another identity (another spec,
    other images, model, options or fitmedia version).  An InputError names the file and
    what differs; nothing is removed."""
    from .inference.sample import check_checkpoint

    for path in sorted(out.glob(CHECKPOINT_GLOB)) if out.is_dir() else []:
        check_checkpoint(path, identity)


def _load(capture: Spec | str | Path) -> Spec:
    """A capture given as a parsed spec or as the path of its YAML."""
    return capture if isinstance(capture, Spec) else load_spec(capture)


def capture_identity(spec_path: Spec | str | Path, options: FitOptions) -> dict:
    """The run identity a fit of ``spec_path`` with ``options`` has (the spec parsed and the
    images loaded, no fitting): to tell whether an earlier fit's results.json is this one's."""
    spec = _load(spec_path)
    prep = prepare(spec)
    return run_identity(spec, prep.images, prep.clear, options)


def _remove_other_checkpoints(out: Path, fits: dict[str, dict]) -> None:
    """Remove checkpoints in ``out`` that this finished run did not write (e.g. a second mode
    of g an earlier run into the same folder sampled): each checkpoint left belongs to the
    results beside it."""
    mine = {f"checkpoint_{ch}.npz" for ch in fits}
    mine |= {f"checkpoint_{ch}_mode2.npz" for ch, f in fits.items() if "chain_mode2" in f}
    for path in out.glob(CHECKPOINT_GLOB):
        if path.name not in mine:
            path.unlink(missing_ok=True)


class _OneInstance:
    """A forward-model factory from one model instance (a capture of one image): each
    channel's model is a view of it (:class:`ChannelView`)."""

    def __init__(self, model: Any):
        self.model = model
        self.name = model_name(model)

    def __call__(self, spec, image_index, channels):
        return ChannelView(self.model, channels[0])


class ChannelView:
    """One channel of a forward model that renders several: ``render`` takes that channel's
    values (scalars or arrays of shape (1,)), gives every channel of ``model`` the same
    values and returns the image of that one channel, shape (H, W, 1)."""

    def __init__(self, model: Any, channel: str):
        if channel not in tuple(model.channels):
            raise InputError(f"model: renders channels {tuple(model.channels)}, not {channel}")
        self.model, self.channels = model, (channel,)
        self.index = tuple(model.channels).index(channel)
        self.shape, self.support = model.shape, model.support

    def render(self, kappa_a, kappa_s, g, brightness):
        import numpy as np

        n = len(self.model.channels)
        args = [np.full(n, float(np.ravel(v)[0])) for v in (kappa_a, kappa_s, g, brightness)]
        return self.model.render(*args)[..., self.index:self.index + 1]


def model_name(model: Any) -> str:
    """The name results.json gives a forward model passed to :func:`fit_capture`: its ``name``
    attribute, else its class's (or the factory's) qualified name."""
    name = getattr(model, "name", None)
    if isinstance(name, str) and name:
        return name
    target = model if isinstance(model, type) or not hasattr(model, "render") else type(model)
    return getattr(target, "__qualname__", type(model).__qualname__)


def forward_factory(model: Any, spec: Spec, options: FitOptions) -> tuple[Any, FitOptions]:
    """``fit_capture``'s ``model`` as (forward-model factory or None, options): a name (single,
    full, auto) sets ``options.model``; a ForwardModel instance (one image) or a factory
    ``factory(spec, image_index, channels=(ch,)) -> ForwardModel`` is fitted as it is."""
    from dataclasses import replace

    if model is None:
        return None, options
    if isinstance(model, str):
        return None, replace(options, model=model)
    if options.model == "full":
        raise InputError(f"options.model: {options.model!r} with a forward model of your own: "
                         "the multiple-scattering term wraps fitmedia's own model only; "
                         "use 'single' or 'auto' (the default)")
    # auto (the default) has no term to add to a model of your own: it is fitted as it is
    options = replace(options, model="single")
    if hasattr(model, "render") and not isinstance(model, type):  # an instance, not a class
        if len(spec.images) != 1:
            raise InputError(f"model: one {model_name(model)} instance renders one image, the "
                             f"capture has {len(spec.images)}; pass a factory "
                             "(spec, image_index, channels) -> model instead")
        return _OneInstance(model), options
    if callable(model):
        return model, options
    raise InputError(f"model: got {model!r}: expected 'single', 'full', 'auto', a ForwardModel "
                     "or a factory (spec, image_index, channels) -> ForwardModel")


def fit_capture(capture: Spec | str | Path, *, model: Any = None,
                options: FitOptions | None = None, out: str | Path | None = None,
                report: bool | None = None) -> FitResult:
    """Fit a capture with any forward model; the one entry point (``fitmedia.fit``).

    Parameters
    ----------
    capture : Spec, str or Path
        A parsed capture spec (:func:`fitmedia.spec.load_spec`) or the path of its YAML.
    model : str, ForwardModel, factory or None
        ``"single"``, ``"full"`` or ``"auto"`` (replaces ``options.model``); a ForwardModel
        instance (:mod:`fitmedia.forward.base`; a capture of one image); or a factory called as
        ``model(spec, image_index, channels=(channel,))`` returning one, such as
        ``fitmedia.forward.single.SingleScattering``.  None: ``options.model``.
    options : FitOptions, optional
        Defaults: ``FitOptions()`` (those of ``fitmedia fit``).
    out : str or Path, optional
        Write results.json (``FitResult.to_json()``), samples.npz, fit_images.npz, the
        chains' checkpoints and (``report``, default True with ``out``) report.html there, as
        ``fitmedia fit --out`` does; None: write nothing.

    Returns
    -------
    FitResult
        Values, intervals, samples, diagnostics, provenance and the trust verdict.
    """
    t0 = time.perf_counter()
    options = options if options is not None else FitOptions()
    if out is None and options.resume:
        raise InputError("options.resume: needs out, the folder holding the checkpoints")
    if options.resume and not options.mcmc:
        raise InputError("options.resume: continues the sampler's chains, and options.mcmc is "
                         "off (--no-mcmc): there is nothing to resume")
    dest = check_output_dir(out) if out is not None else None
    spec = _load(capture)
    forward, options = forward_factory(model, spec, options)
    if options.model not in MODELS:
        raise InputError(f"model: {options.model!r} is not one of {', '.join(MODELS)}, a "
                         "ForwardModel or a factory of them")
    prep = prepare(spec, options.workers)
    identity = run_identity(spec, prep.images, prep.clear, options)
    name = None if forward is None else model_name(forward)
    if name is not None:
        identity["model"] = name
    if dest is not None and options.mcmc and options.resume:
        check_resumable(dest, identity)
    fits = run_channels(prep, options, dest if options.mcmc else None, identity, forward)
    result = _finish(build_results(prep, fits, options, model=name), identity, t0)
    if dest is not None:
        _write(dest, out, prep, fits, result, options, report if report is not None else True)
    return result


def _finish(result: FitResult, identity: dict, t0: float) -> FitResult:
    from dataclasses import replace

    return replace(result, run_identity=identity, wall_time_s=time.perf_counter() - t0)


def _write(dest: Path, out_dir, prep, fits: dict, result: FitResult, options: FitOptions,
           report: bool) -> None:
    """The fit's files into ``out_dir``: staged, moved into place at the end."""
    with staged_output_dir(out_dir) as stage:
        write_outputs(stage, prep, fits, result)
        if report:
            from .report import write_report

            write_report(stage, folder=Path(out_dir))  # the folder it ends in
    if options.mcmc:
        _remove_other_checkpoints(dest, fits)


def fit(spec_path: Spec | str | Path, out_dir: str | Path, options: FitOptions = FitOptions(),
        *, report: bool = True, model: Any = None) -> FitResult:
    """Fit a capture spec and write results.json (and report.html) into ``out_dir``
    (:func:`fit_capture` with ``out``).

    ``out_dir`` is checked first (:func:`fitmedia.util.check_output_dir`); with
    ``options.resume`` its checkpoints are checked against this run's identity after the
    images are loaded and before any fitting (:func:`check_resumable`).  The chains'
    checkpoints are written into ``out_dir`` as the sampler runs (a killed fit leaves only
    them, for ``--resume``); the results are written into a temporary folder and moved into
    ``out_dir`` at the end (:func:`fitmedia.util.staged_output_dir`).
    """
    return fit_capture(spec_path, model=model, options=options, out=out_dir, report=report)

"""fitmedia: absorption, scattering and anisotropy of liquids from photographs of a lit tank.

Internal units: millimetres and 1/mm.  Importing the package has no side
effects; Mitsuba and matplotlib are imported only by the functions that need them.

The library's entry point is :func:`fit` (docs/api.md)::

    import fitmedia
    result = fitmedia.fit("capture.yaml", model="single",
                          options=fitmedia.FitOptions(seed=1, mcmc=False))
    result.value("kappa_s", "G"), result.interval("kappa_s", "G"), result.ok
"""

from .version import __version__

__all__ = ["FitOptions", "FitResult", "__version__", "fit"]


def fit(capture, *, model=None, options=None, out=None, report=None):
    """Fit a capture (a parsed spec or the path of its YAML) with a forward model (``"single"``,
    ``"full"``, ``"auto"``, a ForwardModel or a factory of them) and :class:`FitOptions`;
    returns one :class:`FitResult`.  With ``out``, also writes results.json and the files
    beside it there, as ``fitmedia fit --out`` does.  See
    :func:`fitmedia.pipeline.fit_capture`."""
    from .pipeline import fit_capture

    return fit_capture(capture, model=model, options=options, out=out, report=report)


def __getattr__(name: str):
    """``fitmedia.FitOptions`` and ``fitmedia.FitResult``, imported on first use (they need no
    numpy, but importing the package stays free of side effects)."""
    if name in ("FitOptions", "FitResult"):
        from .inference import result

        return getattr(result, name)
    raise AttributeError(f"module 'fitmedia' has no attribute {name!r}")

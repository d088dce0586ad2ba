"""fitmedia's version, in a module of its own: modules that record it (results.json, the run
identity, the report) import it from here, not from the package, so that ``fitmedia.fit``
(in ``fitmedia/__init__.py``) can import the fitter without an import cycle."""

__version__ = "0.1.0"

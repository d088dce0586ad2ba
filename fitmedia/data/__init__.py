"""Data shipped inside the package (read with importlib.resources, so an installed wheel has them).

* ``narasimhan2006_undiluted.csv``: the published table of undiluted liquids.
* ``capture_specs/*.yaml``: the canonical geometry specs (``validate``'s default geometry).
* ``synthetic/default/``: the demo capture that ``fitmedia demo`` fits.

The repository's top-level ``capture_specs/`` and ``synthetic/default/`` are the source of
truth (``make synthetic`` regenerates the latter); ``make package-data`` copies them here, and
tests/test_package_data.py fails while the two differ.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path


def bundled_path(*parts: str) -> Path:
    """Filesystem path of a bundled file, e.g. ``bundled_path("capture_specs", "bulb.yaml")``.

    The package is installed as plain files (setuptools wheels are not zip-safe here), so the
    resource is a real path that specs' relative image paths resolve against.
    """
    return Path(str(resources.files(__name__).joinpath(*parts)))

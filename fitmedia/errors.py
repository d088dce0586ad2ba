"""Exception types.  Every error a user can cause by bad input is an
:class:`InputError`; the CLI prints its message on one line and exits with 2."""

from __future__ import annotations


class FitmediaError(Exception):
    """Base class of fitmedia's own errors."""


class InputError(FitmediaError, ValueError):
    """Bad user input: a spec field, an image file, a command-line value.

    The message names the field or file, the value and what was expected.
    """


class SpecError(InputError):
    """A capture spec that does not follow CAPTURE_SPEC.md."""

    def __init__(self, where: str, field: str, message: str):
        self.where = where
        self.field = field
        self.message = message
        super().__init__(f"{where}: {field}: {message}" if field else f"{where}: {message}")

    def __reduce__(self):  # picklable across process pools (Dask, multiprocessing)
        return (type(self), (self.where, self.field, self.message))


class ImageError(InputError):
    """An image file that cannot be used (missing, broken, wrong size, saturated, NaN)."""


class BlackImageError(ImageError):
    """An image with no glow above the noise in any channel (images/checks.check_lit): a lens
    cap, the light off, or a liquid so dense that nothing reaches the front wall.  ``validate``
    skips such a synthetic round instead of failing it (it carries nothing to score)."""

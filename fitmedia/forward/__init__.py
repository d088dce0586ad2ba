"""Forward models: the analytic single-scattering model and Mitsuba 3 full transport.

Both implement :class:`fitmedia.forward.base.ForwardModel`, so fitters, reports
and tests can swap them.
"""

from .base import ForwardModel

__all__ = ["ForwardModel"]

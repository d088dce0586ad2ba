"""HTML report (imports matplotlib lazily; the core never imports this package)."""

from .html import write_report

__all__ = ["write_report"]

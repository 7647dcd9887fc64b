"""Config errors: one line each, naming the file or key and what was expected."""

from __future__ import annotations

from occplug.errors import ConfigError

__all__ = ["ConfigError"]
